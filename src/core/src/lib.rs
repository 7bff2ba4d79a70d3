//! Shared math for every stage: rotations, the camera model, (in `body`) body models and
//! linear blend skinning, and the one safe matrix product (`matmul`, over `gemm`). This crate
//! does no I/O: file formats live in `seqavatar-formats`.

pub mod body;
pub mod camera;
pub mod matmul;
pub mod rng;
pub mod rotation;

pub use glam;
