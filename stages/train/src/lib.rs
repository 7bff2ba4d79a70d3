//! The `train` stage: the SeqAvatar model (canonical Gaussians, motion-conditioned non-rigid
//! networks, skinning) and its training.
//!
//! - [`config`]: presets and the validated configuration.
//! - [`losses`]: L1, mask MSE, SSIM and as-isometric-as-possible losses with backward passes.
//! - [`skinning`]: Gaussian skinning (non-rigid offsets, blended LBS, covariance transform).
//! - [`knn`]: exact grid k-nearest neighbours (and the brute-force reference).
//! - [`densify`]: per-Gaussian state and clone/split/prune.
//! - [`gaussians`]: the trainable Gaussian columns, their initial state and schedules.
//! - [`checkpoint`]: checkpoints as Zarr arrays, RNG state included.
//! - [`model`]: the SeqAvatar networks (non-rigid with motion context, pose refiner, LBS
//!   offsets) on `cpu` and `gpu`.
//! - [`rng`]: the deterministic generator whose state checkpoints store.
//! - [`rig`]: canonical and per-frame skinning targets from the body model.
//! - [`data`]: what a run reads from its input entries.
//! - [`splatting`]: splatting on the `cpu` or `gpu` backend with f64 at the boundary.
//! - [`avatar`]: the trained avatar, its entry arrays and its render path.
//! - [`trainer`]: the training loop and its resumable state.
//! - [`stage`]: the `train` stage kind.

// Numeric kernels index several parallel arrays with one loop variable; iterator chains
// would hide the maths.
#![allow(clippy::needless_range_loop)]

pub mod avatar;
pub mod checkpoint;
pub mod config;
pub mod data;
pub mod densify;
pub mod gaussians;
pub mod knn;
pub mod losses;
pub mod model;
pub mod rig;
pub mod rng;
pub mod skinning;
pub mod splatting;
pub mod stage;
pub mod trainer;

pub use avatar::{FrameInputs, TrainedAvatar};
pub use stage::TrainStage;

/// Adds this crate's stage kinds to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(stage::TrainStage));
}
