//! The `train` stage: training the SeqAvatar model (canonical Gaussians, motion-conditioned
//! non-rigid networks, skinning), whose render path, networks and rig live in
//! `seqavatar-avatar`.
//!
//! - [`config`]: presets and the validated configuration ([`config::TrainConfig::avatar`]
//!   is the part the avatar keeps).
//! - [`losses`]: L1, mask MSE, SSIM and as-isometric-as-possible losses with backward passes.
//! - [`densify`]: per-Gaussian state and clone/split/prune.
//! - [`diagnostics`]: input RMS and first-layer weight norms per input block of the non-rigid
//!   network.
//! - [`gaussians`]: the trainable Gaussian columns, their initial state and schedules.
//! - [`checkpoint`]: checkpoints as Zarr arrays, RNG state included.
//! - [`resident`]: the device-resident training step's pieces (`gpu` backend).
//! - [`rng`]: the deterministic generator whose state checkpoints store.
//! - [`data`]: what a run reads from its input entries.
//! - [`trainer`]: the training loop; [`run`]: its resumable state and the [`run::TrainingStep`]
//!   that advances it, host (`cpu`) or device-resident (`gpu`), built once by `step`.
//! - [`resident`]: pieces of the device-resident training step (`gpu` backend).
//! - [`stage`]: the `train` stage kind.

// Numeric kernels index several parallel arrays with one loop variable; iterator chains
// would hide the maths.
#![allow(clippy::needless_range_loop)]

pub mod checkpoint;
pub mod config;
pub mod data;
pub mod densify;
pub mod diagnostics;
pub mod gaussians;
pub mod hull;
pub mod losses;
pub mod resident;
pub mod rng;
pub mod run;
pub mod stage;
mod step;
pub mod trainer;

pub use stage::TrainStage;

/// Adds this crate's stage kinds to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(stage::TrainStage));
}
