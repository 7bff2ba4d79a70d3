//! Device-resident pieces of the training step on the `gpu` backend (`docs/resident-step.md`):
//! buffers stay on the device, operations record into the step's command encoder.

pub mod motion;
pub mod pose;
pub mod skinning;
