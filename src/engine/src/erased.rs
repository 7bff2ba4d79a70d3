//! The registry's object-safe view of a [`StageKind`]: the config type erased. A stage's
//! config is resolved once, when the pipeline loads, and handed back typed to the hooks of
//! the kind that resolved it.

use std::any::Any;
use std::path::PathBuf;
use std::sync::Arc;

use crate::{
    ConfigError, EntryReader, PictureKind, PictureOptions, StageContext, StageInput, StageKind,
};

/// A stage's resolved [`StageKind::Config`], type-erased; only its own kind opens it.
pub(crate) type TypedConfig = Arc<dyn Any + Send + Sync>;

fn typed<'c, S: StageKind>(stage: &S, config: &'c TypedConfig) -> &'c S::Config {
    config.downcast_ref().unwrap_or_else(|| {
        let kind = StageKind::kind(stage);
        panic!("stage kind \"{kind}\" was given a config it did not resolve")
    })
}

/// [`StageKind`] without its config type, as the [`crate::Registry`] holds it; implemented
/// for every stage kind.
pub(crate) trait ErasedStage: Send + Sync {
    fn version(&self) -> u32;
    fn input_kinds(&self) -> &'static [&'static str];
    /// The effective config (defaults explicit, the JSON that keys hash) and the typed one.
    fn resolve_config(
        &self,
        raw: &serde_json::Value,
    ) -> Result<(serde_json::Value, TypedConfig), ConfigError>;
    fn check_inputs(&self, config: &TypedConfig, inputs: &[StageInput<'_>]) -> Result<(), String>;
    fn planned(&self, config: &TypedConfig) -> serde_json::Value;
    fn external_files(&self, config: &TypedConfig) -> anyhow::Result<Vec<PathBuf>>;
    fn run(&self, config: &TypedConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()>;
    fn pictures(&self) -> Vec<PictureKind>;
    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage>;
}

impl<S: StageKind> ErasedStage for S {
    fn version(&self) -> u32 {
        StageKind::version(self)
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        StageKind::input_kinds(self)
    }

    fn resolve_config(
        &self,
        raw: &serde_json::Value,
    ) -> Result<(serde_json::Value, TypedConfig), ConfigError> {
        let config = StageKind::resolve_config(self, raw)?;
        let effective = serde_json::to_value(&config).map_err(|error| {
            ConfigError::new(vec![], format!("cannot re-serialize config: {error}"))
        })?;
        Ok((effective, Arc::new(config)))
    }

    fn check_inputs(&self, config: &TypedConfig, inputs: &[StageInput<'_>]) -> Result<(), String> {
        StageKind::check_inputs(self, typed(self, config), inputs)
    }

    fn planned(&self, config: &TypedConfig) -> serde_json::Value {
        StageKind::planned(self, typed(self, config))
    }

    fn external_files(&self, config: &TypedConfig) -> anyhow::Result<Vec<PathBuf>> {
        StageKind::external_files(self, typed(self, config))
    }

    fn run(&self, config: &TypedConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        StageKind::run(self, typed(self, config), ctx)
    }

    fn pictures(&self) -> Vec<PictureKind> {
        StageKind::pictures(self)
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        StageKind::draw_picture(self, entry, picture, options)
    }
}
