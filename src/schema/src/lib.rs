//! What the stages exchange: the arrays and attributes of each cache entry, with their typed
//! readers and writers. A stage knows the arrays its inputs wrote through this crate, never
//! the crate that wrote them. `docs/schema.md` lists every entry's arrays for readers
//! outside Rust (a test holds it against [`ENTRIES`]).
//!
//! - [`ingest`]: cameras, images and masks, the garment region, body parameters and the body
//!   model, 3D keypoints, the garment history of the synthetic scene.
//! - [`body`], [`fit`]: body sequences (ingest and fit entries alike), the fit's diagnostics.
//! - [`train`]: what a train entry will hold (the avatar's arrays are `seqavatar_avatar`'s).
//! - [`eval`]: the eval entry's summary attributes and its images as PNGs.
//! - [`motion`]: motion templates and the vocabulary of the motion context (scales,
//!   normalisations, windows).

pub mod body;
pub mod eval;
pub mod fit;
pub mod ingest;
pub mod motion;
pub mod train;
