//! The composition root: every stage kind of the product in one registry, as the `pipeline`
//! binary runs them. Stage crates never know each other; whatever runs a whole pipeline (the
//! binary, the integration tests, the train bench) takes its stages from here.

use seqavatar_engine::Registry;

/// A registry holding the `ingest`, `fit`, `motion`, `train` and `eval` stage kinds.
pub fn registry() -> Registry {
    let mut registry = Registry::new();
    seqavatar_ingest::register(&mut registry);
    seqavatar_fit::register(&mut registry);
    seqavatar_motion::register(&mut registry);
    seqavatar_train::register(&mut registry);
    seqavatar_eval::register(&mut registry);
    registry
}
