//! Pipeline engine: YAML pipelines, content-addressed Zarr cache, staging and publishing,
//! the runner, and the `status`, `inspect` and `gc` commands.
//!
//! Stages see only [`StageKind`], [`StageContext`], [`EntryReader`], [`EntryWriter`] and
//! [`NdArray`]; everything about where and how entries are stored stays behind [`Store`].

mod array;
#[cfg(any(test, feature = "test-stages"))]
mod builtin;
pub mod commands;
mod config;
mod entry;
mod erased;
pub mod files;
pub mod key;
mod local;
mod matrix;
pub mod picture;
mod pipeline;
#[cfg(feature = "remote")]
pub mod remote;
mod runner;
mod store;
pub mod test_support;
mod timefmt;
mod yaml_lines;

use std::collections::BTreeMap;

/// Version of this tool, recorded in every manifest.
pub const TOOL_VERSION: &str = env!("CARGO_PKG_VERSION");
use std::path::{Path, PathBuf};

pub use array::{Element, NdArray};
#[cfg(any(test, feature = "test-stages"))]
pub use builtin::TestArrays;
pub use config::{
    ConfigError, ConfigPathSegment, MEMORY_BUDGET_VAR, check_memory_budget, machine_memory_bytes,
    memory_budget_bytes, parse_config, parse_size,
};
pub use entry::{ArrayWriter, EntryReader, EntryWriter, Manifest, ManifestArray, ReadLease};
pub use local::LocalStore;
pub use pipeline::{Pipeline, PipelineError, StageSpec};
pub use runner::{
    BACKEND_LOG_PREFIX, Outcome, RunOptions, StageContext, StageKey, StageReport, backend_of,
    compute_keys, entry_problems, open_leased_verified, open_verified, run, selected_stages,
};
pub use store::{EntryId, EntryState, KeyLock, Staging, Store};

/// Opens the cache `cache`: a local folder, or `s3://bucket/prefix` fronted by the local
/// folder `$SEQAVATAR_LOCAL_CACHE` (default `cache`).
pub fn open_store(cache: &Path) -> anyhow::Result<Box<dyn Store>> {
    let text = cache.to_string_lossy();
    if !text.starts_with("s3://") {
        return Ok(Box::new(LocalStore::open(cache)?));
    }
    #[cfg(feature = "remote")]
    {
        let url = crate::remote::S3Url::parse(&text)?;
        let local = std::env::var_os("SEQAVATAR_LOCAL_CACHE")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("cache"));
        Ok(Box::new(crate::remote::RemoteStore::open(&url, &local)?))
    }
    #[cfg(not(feature = "remote"))]
    anyhow::bail!(
        "cache {text}: this binary was built without the \"remote\" feature of seqavatar-engine"
    )
}

/// One kind of stage (`kind:` in the pipeline YAML): its identity, its configuration schema
/// and the computation it performs.
pub trait StageKind: Send + Sync + 'static {
    /// The `config:` mapping, typed; resolved once, when the pipeline loads, and handed to
    /// every hook. Its serialization (defaults explicit) is the config that keys hold.
    type Config: serde::de::DeserializeOwned + serde::Serialize + Send + Sync + 'static;
    /// The name used as `kind:` in the pipeline YAML and as the cache folder name.
    fn kind(&self) -> &'static str;
    /// Implementation version; bump whenever the code changes the result.
    fn version(&self) -> u32;
    /// Kinds of stages accepted as inputs.
    fn input_kinds(&self) -> &'static [&'static str];
    /// Validates the raw config and returns it typed, in its canonical form. The default
    /// deserializes it ([`parse_config`]); kinds with further checks call that first.
    fn resolve_config(&self, raw: &serde_json::Value) -> Result<Self::Config, ConfigError> {
        parse_config(raw)
    }
    /// Checks, when the pipeline loads, that the inputs give this stage everything its run
    /// will need (before any upstream stage runs). `inputs` are the input stages with their
    /// effective configs, in order; the error text is shown with the stage's name. The
    /// default accepts any inputs of [`StageKind::input_kinds`].
    fn check_inputs(
        &self,
        _config: &Self::Config,
        _inputs: &[StageInput<'_>],
    ) -> Result<(), String> {
        Ok(())
    }
    /// What an entry of this stage will hold, as far as its effective config alone
    /// determines it, for the stages downstream to check when the pipeline loads (their
    /// [`StageKind::check_inputs`] sees it as [`StageInput::planned`]). A value of one of
    /// `seqavatar_schema`'s `Planned*` types, where a downstream stage reads it; `Null`
    /// (the default) when nothing is known before the run.
    fn planned(&self, _config: &Self::Config) -> serde_json::Value {
        serde_json::Value::Null
    }
    /// External files (raw dataset files) whose content the result depends on.
    fn external_files(&self, _config: &Self::Config) -> anyhow::Result<Vec<PathBuf>> {
        Ok(vec![])
    }
    /// Computes the entry: reads inputs from `ctx`, writes arrays to `ctx.output()`.
    fn run(&self, config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()>;
    /// Pictures `pipeline inspect --picture NAME` can draw from an entry of this kind.
    fn pictures(&self) -> Vec<PictureKind> {
        vec![]
    }
    /// Draws one of [`StageKind::pictures`].
    fn draw_picture(
        &self,
        _entry: &EntryReader,
        picture: &str,
        _options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        Err(unknown_picture(self, picture))
    }
}

/// An input stage as [`StageKind::check_inputs`] sees it.
#[derive(Clone, Copy, Debug)]
pub struct StageInput<'a> {
    pub name: &'a str,
    pub kind: &'a str,
    /// What the input stage's entry will hold, as far as its config says
    /// ([`StageKind::planned`]): a stage knows its inputs by their entries, not by their
    /// configs.
    pub planned: &'a serde_json::Value,
}

/// For [`StageKind::check_inputs`]: an error unless exactly one input has each of `kinds`.
pub fn require_one_input_of_each(inputs: &[StageInput<'_>], kinds: &[&str]) -> Result<(), String> {
    for kind in kinds {
        let matching: Vec<&str> = inputs
            .iter()
            .filter(|input| input.kind == *kind)
            .map(|input| input.name)
            .collect();
        match matching.len() {
            1 => {}
            0 => {
                return Err(format!(
                    "needs an input of kind {kind}; {}",
                    describe(inputs)
                ));
            }
            _ => {
                return Err(format!(
                    "has several inputs of kind {kind} ({}); expected one",
                    matching.join(", ")
                ));
            }
        }
    }
    Ok(())
}

fn describe(inputs: &[StageInput<'_>]) -> String {
    if inputs.is_empty() {
        "it has no inputs".to_owned()
    } else {
        let list: Vec<String> = inputs
            .iter()
            .map(|input| format!("{} ({})", input.name, input.kind))
            .collect();
        format!("its inputs are: {}", list.join(", "))
    }
}

/// The error for a picture name a stage kind does not draw, listing the ones it does (taken
/// from [`StageKind::pictures`], so the list cannot drift from the stage).
pub fn unknown_picture<K: StageKind + ?Sized>(kind: &K, picture: &str) -> anyhow::Error {
    let names: Vec<&str> = kind.pictures().iter().map(|p| p.name).collect();
    let known = if names.is_empty() {
        "it draws none".to_owned()
    } else {
        format!("it has: {}", names.join(", "))
    };
    anyhow::anyhow!(
        "stage kind \"{}\" has no picture named \"{picture}\" ({known})",
        kind.kind()
    )
}

/// A picture a stage kind can draw for `inspect`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PictureKind {
    pub name: &'static str,
    pub description: &'static str,
}

/// `--opt key=value` options given to [`StageKind::draw_picture`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PictureOptions {
    pub values: BTreeMap<String, String>,
}

impl PictureOptions {
    /// Parses `key=value` strings.
    pub fn parse(pairs: &[String]) -> anyhow::Result<Self> {
        let mut values = BTreeMap::new();
        for pair in pairs {
            let (key, value) = pair
                .split_once('=')
                .ok_or_else(|| anyhow::anyhow!("--opt \"{pair}\": expected key=value"))?;
            values.insert(key.trim().to_string(), value.trim().to_string());
        }
        Ok(Self { values })
    }

    /// An unsigned integer option, or `default` when absent.
    pub fn get_u64(&self, name: &str, default: u64) -> anyhow::Result<u64> {
        match self.values.get(name) {
            None => Ok(default),
            Some(text) => text.parse::<u64>().map_err(|_| {
                anyhow::anyhow!("picture option {name}={text}: expected an unsigned integer")
            }),
        }
    }

    /// A floating-point option, or `default` when absent.
    pub fn get_f64(&self, name: &str, default: f64) -> anyhow::Result<f64> {
        match self.values.get(name) {
            None => Ok(default),
            Some(text) => match text.parse::<f64>() {
                Ok(value) if value.is_finite() => Ok(value),
                _ => anyhow::bail!("picture option {name}={text}: expected a finite number"),
            },
        }
    }

    /// A string option, or `default` when absent.
    pub fn get_str(&self, name: &str, default: &str) -> anyhow::Result<String> {
        Ok(self
            .values
            .get(name)
            .cloned()
            .unwrap_or_else(|| default.to_string()))
    }

    /// Names of options that are not in `known`, so callers can reject typos.
    pub fn unknown_keys(&self, known: &[&str]) -> Vec<String> {
        self.values
            .keys()
            .filter(|key| !known.contains(&key.as_str()))
            .cloned()
            .collect()
    }
}

/// All stage kinds known to the binary.
pub struct Registry {
    kinds: BTreeMap<&'static str, Box<dyn erased::ErasedStage>>,
}

impl Default for Registry {
    fn default() -> Self {
        Self::new()
    }
}

impl Registry {
    /// An empty registry; in test builds (feature `test-stages`) it holds the built-in
    /// `test_arrays` kind.
    pub fn new() -> Self {
        #[allow(unused_mut)]
        let mut registry = Self {
            kinds: BTreeMap::new(),
        };
        #[cfg(any(test, feature = "test-stages"))]
        registry.add(Box::new(TestArrays));
        registry
    }

    /// Adds a stage kind; a later kind with the same name replaces the earlier one.
    pub fn add<S: StageKind>(&mut self, stage: Box<S>) {
        self.kinds.insert(StageKind::kind(stage.as_ref()), stage);
    }

    /// The stage kind named `kind`.
    pub(crate) fn get(&self, kind: &str) -> Option<&dyn erased::ErasedStage> {
        self.kinds.get(kind).map(|boxed| boxed.as_ref())
    }

    /// Names of all registered kinds, sorted.
    pub fn kind_names(&self) -> Vec<&'static str> {
        self.kinds.keys().copied().collect()
    }
}
