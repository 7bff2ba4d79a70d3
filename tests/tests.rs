//! Integration tests: run the real `pipeline` binary in fresh temporary directories.

mod datasets;
mod engine;
mod eval;
mod fit;
mod motion;
mod remote;
mod support;
mod tidy;
mod train;
mod viewer;
