//! Pictures, the one place every stage draws with: the generic pictures of image-like arrays
//! that `inspect --png/--exr` writes for any entry (`arrays`), and the drawing kit the stages'
//! own pictures and eval's reports use (line plots, colour map and colour bar, point splats
//! with a depth test, the 3x5 pixel font for numbers), re-exported here from `draw`.

mod arrays;
mod draw;

pub(crate) use arrays::{array_exr, array_png};
pub use draw::*;
