//! The `fit` stage.
