//! Shared math for every stage: rotations, the camera model and (in `body`) body models and
//! linear blend skinning. This crate does no I/O: file formats live in the stages.

pub mod body;
pub mod camera;
pub mod rng;
pub mod rotation;

pub use glam;
