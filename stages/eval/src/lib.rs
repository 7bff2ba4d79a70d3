//! The `eval` stage: scores a trained avatar's renders of the ingest entry's test images with
//! the protocol of `seqavatar-evaluation` and writes the scores, renders, error maps and the
//! contact sheet ([`stage`] documents the entry).

pub mod stage;

/// Adds the `eval` stage kind to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(stage::EvalStage));
}
