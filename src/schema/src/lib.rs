//! What the stages exchange: the arrays and attributes of each cache entry, with their typed
//! readers and writers. A stage knows the arrays its inputs wrote through this crate, never
//! the crate that wrote them. `docs/schema.md` lists every entry's arrays for readers
//! outside Rust (a test holds it against [`ENTRIES`]).
//!
//! - [`ingest`]: cameras, images and masks, the garment region, body parameters and the body
//!   model, 3D keypoints, the garment history of the synthetic scene.
//! - [`body`], [`fit`]: body sequences (ingest and fit entries alike), the fit's diagnostics.
//! - [`train`]: what a train entry will hold (the avatar's arrays are `seqavatar_avatar`'s).
//! - [`eval`]: the eval entry's per-image columns, summary attributes and its images as PNGs.
//! - [`motion`]: motion templates and the vocabulary of the motion context (scales,
//!   normalisations, windows).

pub mod body;
pub mod eval;
pub mod fit;
pub mod ingest;
pub mod motion;
pub mod train;

use seqavatar_engine::EntryReader;

/// The entry's attribute `key`; an error naming the entry and the attribute when it is missing.
fn attribute(entry: &EntryReader, key: &str) -> anyhow::Result<serde_json::Value> {
    entry
        .attribute(key)
        .ok_or_else(|| anyhow::anyhow!("entry {}: attribute `{key}` is missing", entry.location()))
}

/// The entry's attribute `key` as a count; errors name the entry and the attribute.
fn count_attribute(entry: &EntryReader, key: &str) -> anyhow::Result<u64> {
    attribute(entry, key)?.as_u64().ok_or_else(|| {
        anyhow::anyhow!(
            "entry {}: attribute `{key}` is not a count",
            entry.location()
        )
    })
}

#[cfg(test)]
mod testing {
    //! A one-stage pipeline whose stage writes its entry with a test's function.

    use seqavatar_engine::{
        EntryId, EntryReader, EntryWriter, LocalStore, Pipeline, Registry, RunOptions,
        StageContext, StageKind, Store, run,
    };

    type Write = fn(&EntryWriter, &str) -> anyhow::Result<()>;

    struct Writes(Write);

    impl StageKind for Writes {
        type Config = serde_json::Value;
        fn kind(&self) -> &'static str {
            "schema_test"
        }
        fn version(&self) -> u32 {
            1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            &[]
        }
        fn run(&self, config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
            (self.0)(ctx.output(), config["case"].as_str().unwrap())
        }
    }

    /// The entry that `write` makes for `case` in `store`.
    pub(crate) fn entry(store: &LocalStore, write: Write, case: &str) -> EntryReader {
        let text =
            format!("stages:\n  - {{name: a, kind: schema_test, config: {{case: {case}}}}}\n");
        let mut registry = Registry::new();
        registry.add(Box::new(Writes(write)));
        let pipeline =
            Pipeline::parse(&text, std::path::Path::new("t.yaml"), &registry, &[]).unwrap();
        let reports = run(&pipeline, &registry, store, &RunOptions::default()).unwrap();
        store
            .open_entry(&EntryId::new("schema_test", &reports[0].key))
            .unwrap()
    }
}
