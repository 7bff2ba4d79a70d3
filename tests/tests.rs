//! Integration tests: run the real `pipeline` binary in fresh temporary directories.

mod engine;
mod remote;
