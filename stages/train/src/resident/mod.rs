//! The device-resident training step's pieces on the `gpu` backend (docs/resident-step.md).

pub mod adam;
pub mod aiap;
pub mod densify;
pub mod state;

#[cfg(test)]
mod tests;
