//! The device-resident training step on the `gpu` backend (`docs/resident-step.md`): its
//! pieces record into one encoder per iteration and read nothing back in the steady state.

pub mod adam;
pub mod aiap;
pub mod densify;
pub mod image_loss;
pub mod log;
pub mod state;
pub mod step;

#[cfg(test)]
mod tests;
