//! The `ingest` stage: reads a multi-view capture (or generates the built-in synthetic scene)
//! and writes cameras, the frame axis and split, undistorted and rescaled images with masks,
//! per-frame body-model parameters and the body model itself.
//!
//! The entry's arrays and attributes are `seqavatar_schema::ingest`'s (docs/schema.md).

pub mod config;
pub mod contact_sheet;
pub mod plan;
pub mod stage;
pub mod world;

pub use config::IngestConfig;
pub use stage::Ingest;

/// Adds the `ingest` stage kind to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(stage::Ingest));
}
