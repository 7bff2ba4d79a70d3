//! The device-resident training step of the `gpu` backend (docs/resident-step.md).

pub mod log;
