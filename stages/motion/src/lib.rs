//! The `motion` stage: motion templates computed once per sequence (posed template vertices,
//! per-joint rotations, skeleton motion and vertex velocity per (frame, scale), the canonical
//! template and its KNN graph), stored chunked by frame so that any training window is a
//! gather (`seqavatar_schema::motion::window`); the computation is `seqavatar-context`'s.

pub mod stage;

pub use stage::{MotionConfig, MotionStage};

/// Adds this crate's stage kinds to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(MotionStage));
}
