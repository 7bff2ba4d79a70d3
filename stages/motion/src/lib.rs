//! The `motion` stage.
