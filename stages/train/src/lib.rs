//! The `train` stage: the SeqAvatar model (canonical Gaussians, motion-conditioned non-rigid
//! networks, skinning) and its training.
//!
//! - [`config`]: presets and the validated configuration.
//! - [`losses`]: L1, mask MSE, SSIM and as-isometric-as-possible losses with backward passes.
//! - [`skinning`]: Gaussian skinning (non-rigid offsets, blended LBS, covariance transform).
//! - [`knn`]: exact grid k-nearest neighbours (and the brute-force reference).
//! - [`densify`]: per-Gaussian state and clone/split/prune.
//! - [`gaussians`]: trainable Gaussian columns and one optimisation step through splatting.
//! - [`checkpoint`]: checkpoints as Zarr arrays, RNG state included.
//! - [`model`]: the SeqAvatar networks (non-rigid with motion context, pose refiner, LBS
//!   offsets) on `cpu` and `gpu`.
//! - [`rng`]: the deterministic generator whose state checkpoints store.

// Numeric kernels index several parallel arrays with one loop variable; iterator chains
// would hide the maths.
#![allow(clippy::needless_range_loop)]

pub mod checkpoint;
pub mod config;
pub mod densify;
pub mod gaussians;
pub mod knn;
pub mod losses;
pub mod model;
pub mod rng;
pub mod skinning;

/// Adds this crate's stage kinds to the registry.
pub fn register(_registry: &mut seqavatar_engine::Registry) {}
