//! The `motion` stage: motion templates computed once per sequence (posed template vertices,
//! per-joint rotations, skeleton motion and vertex velocity per (frame, scale), the canonical
//! template and its KNN graph), stored chunked by frame so that any training window is a
//! gather ([`window`]).

pub mod compute;
pub mod context;
pub mod pose;
pub mod schema;
pub mod stage;

pub use context::{InputScaling, Scales, VelocityNormalisation, Window, window};
pub use schema::{FrameAxis, MotionTrack, read_input_scales};
/// The grid KNN now lives in the library crate `seqavatar-knn`; this path keeps code written
/// against `seqavatar_motion::knn` compiling until it imports `seqavatar_knn` directly.
pub use seqavatar_knn as knn;
pub use stage::{MotionConfig, MotionStage};

/// Adds this crate's stage kinds to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(MotionStage));
}
