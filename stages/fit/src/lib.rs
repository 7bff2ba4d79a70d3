//! The `fit` stage: refines per-frame body-model fits (pose, translation, shared shape) with a
//! data term and a temporal term measured in rotation space, before anything differentiates
//! them.

pub mod banded;
pub mod evidence;
pub mod keypoints;
pub mod refine;
pub mod smooth;
pub mod stage;

pub use stage::{FitConfig, FitMode, FitStage};

/// Adds this crate's stage kinds to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(FitStage));
}
