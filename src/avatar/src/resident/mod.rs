//! Device-resident pieces of the training step and of rendering on the `gpu` backend
//! (`docs/resident-step.md`): buffers stay on the device, operations record into the caller's
//! command encoder.

pub mod deform;
pub mod motion;
pub mod pose;
pub mod render;
pub mod skinning;
