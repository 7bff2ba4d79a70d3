//! The trained avatar and its render path: canonical Gaussians, the body rig, skinning, the
//! SeqAvatar networks and the splatting glue, as a `train` entry stores them. Eval and
//! `pipeline render` depend on this crate, not on the trainer.
//!
//! - [`config`]: [`AvatarConfig`], the part of the training configuration rendering needs,
//!   and the enums it shares with the train config (motion context, background).
//! - [`avatar`]: the trained avatar, its entry arrays and its render path.
//! - [`device`]: [`device::AvatarBackend`], the host render and training paths' networks and
//!   splatting on `cpu`, built once ([`device::avatar_backend`]).
//! - [`model`]: the SeqAvatar networks (non-rigid with motion context, pose refiner, LBS
//!   offsets) on `cpu` and `gpu`.
//! - [`rig`]: canonical and per-frame skinning targets from the body model.
//! - [`skinning`]: Gaussian skinning (non-rigid offsets, blended LBS, covariance transform).
//! - [`splatting`]: splatting on the `cpu` or `gpu` backend with f64 at the boundary.
//! - [`resident`]: the device-resident pieces of the `gpu` training step: motion inputs,
//!   the pose path and skinning, recorded into the step's command encoder.
//! - [`ply`]: the avatar's canonical and posed Gaussians as 3D Gaussian Splatting PLY
//!   clouds, for `pipeline export` (the file format is `seqavatar_formats::ply`).

// Numeric kernels index several parallel arrays with one loop variable; iterator chains
// would hide the maths.
#![allow(clippy::needless_range_loop)]

pub mod avatar;
pub mod config;
pub mod device;
pub mod model;
pub mod ply;
pub mod resident;
pub mod rig;
pub mod sequence;
pub mod skinning;
pub mod splatting;
pub mod test_support;

pub use avatar::{FrameInputs, TrainedAvatar};
pub use config::AvatarConfig;
