//! The `ingest` stage configuration: which dataset, the split overrides, the resolution and
//! the past frames the motion windows need; ranges checked when the pipeline loads.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use seqavatar_engine::{ConfigError, ConfigPathSegment};

use crate::plan::ImageCounts;
use seqavatar_datasets::{DatasetConfig, FrameRange, Split};
use seqavatar_schema::ingest::{IngestImages, PlannedIngest};

/// Split overrides from the stage config: any field left out keeps the dataset's default.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SplitOverrides {
    pub train_views: Option<Vec<usize>>,
    pub test_views: Option<Vec<usize>>,
    pub train_frames: Option<FrameRange>,
    pub test_frames: Option<FrameRange>,
    pub frame_interval: Option<usize>,
    /// The temporal hold-out ([`Split::held_out_frames`]); left out of the resolved config
    /// when not set, so the keys of configs without one stay what they were.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub held_out_frames: Option<FrameRange>,
}

impl SplitOverrides {
    pub fn apply(&self, default: Split) -> Split {
        Split {
            train_views: self.train_views.clone().unwrap_or(default.train_views),
            test_views: self.test_views.clone().unwrap_or(default.test_views),
            train_frames: self.train_frames.clone().unwrap_or(default.train_frames),
            test_frames: self.test_frames.clone().unwrap_or(default.test_frames),
            frame_interval: self.frame_interval.unwrap_or(default.frame_interval),
            held_out_frames: self.held_out_frames.clone().or(default.held_out_frames),
        }
    }
}

/// The `ingest` stage configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IngestConfig {
    pub dataset: DatasetConfig,
    /// Image rescale factor applied after undistortion (ZJU 0.5, DNA 0.25 in docs/method.md).
    pub resolution_scale: f64,
    pub split: SplitOverrides,
    /// How many past frames (in steps of the frame interval) before each used frame the
    /// motion windows need; their body parameters are ingested (not their images). For
    /// SeqAvatar this is `L * max(scales)`.
    pub past_frames: usize,
    /// Body-model file (SMPL / SMPL-X dense `.npz`) for datasets that need one.
    pub body_model: Option<PathBuf>,
}

impl Default for IngestConfig {
    fn default() -> Self {
        Self {
            dataset: DatasetConfig::default(),
            resolution_scale: 1.0,
            split: SplitOverrides::default(),
            past_frames: 0,
            body_model: None,
        }
    }
}

/// The most cameras a synthetic scene may have (the datasets have 10 to 60).
pub const MAX_SYNTHETIC_CAMERAS: usize = 1024;
/// The most frames a synthetic scene, or `past_frames`, may ask for.
pub const MAX_FRAMES: usize = 100_000;

impl IngestConfig {
    /// Checks ranges when the pipeline loads (before any stage runs); errors name the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let key = |names: &[&str]| -> Vec<ConfigPathSegment> {
            names
                .iter()
                .map(|n| ConfigPathSegment::Key((*n).to_owned()))
                .collect()
        };
        if !(self.resolution_scale.is_finite()
            && self.resolution_scale > 0.0
            && self.resolution_scale <= 4.0)
        {
            return Err(ConfigError::at_key(
                "resolution_scale",
                format!("must be within (0, 4], got {}", self.resolution_scale),
            ));
        }
        if self.past_frames > MAX_FRAMES {
            return Err(ConfigError::at_key(
                "past_frames",
                format!("must be at most {MAX_FRAMES}, got {}", self.past_frames),
            ));
        }
        if let DatasetConfig::Synthetic(scene) = &self.dataset {
            for (name, value, max) in [
                ("cameras", scene.cameras, MAX_SYNTHETIC_CAMERAS),
                ("frames", scene.frames, MAX_FRAMES),
            ] {
                if value > max {
                    return Err(ConfigError::new(
                        key(&["dataset", name]),
                        format!("must be at most {max}, got {value}"),
                    ));
                }
            }
            scene
                .validate()
                .map_err(|e| ConfigError::new(key(&["dataset"]), e.to_string()))?;
        }
        Ok(())
    }
}

impl IngestConfig {
    /// The split and its image counts, where the config alone determines them (a synthetic
    /// scene: its cameras and frames are config fields); `None` for file-based datasets,
    /// whose default split and counts come from their files. Counted, not listed: cheap for
    /// the largest scene the ranges allow.
    pub fn image_counts_at_load(&self) -> Option<(Split, anyhow::Result<ImageCounts>)> {
        let DatasetConfig::Synthetic(scene) = &self.dataset else {
            return None;
        };
        let split = self
            .split
            .apply(seqavatar_datasets::synthetic::scene::default_split(
                scene.cameras,
            ));
        let counts = ImageCounts::of(&split, scene.cameras, scene.frames);
        Some((split, counts))
    }

    /// What the entry will hold, as far as this config determines it: the images of a
    /// synthetic scene (its split's images at `dataset.width x dataset.height` times
    /// `resolution_scale`; none for file-based datasets or a split the plan refuses, which
    /// ingest reports), and why there will be no test image where the config says so.
    pub fn planned(&self) -> PlannedIngest {
        let images = match (&self.dataset, self.image_counts_at_load()) {
            (DatasetConfig::Synthetic(scene), Some((_, Ok(counts)))) => {
                let side = |n: u32| ((f64::from(n) * self.resolution_scale).round() as u64).max(1);
                Some(IngestImages {
                    count: (counts.train + counts.test) as u64,
                    width: side(scene.width),
                    height: side(scene.height),
                    source: format!(
                        "dataset.cameras {} x dataset.frames {} split, dataset.width x \
                         dataset.height {} x {} at resolution_scale {}",
                        scene.cameras,
                        scene.frames,
                        scene.width,
                        scene.height,
                        self.resolution_scale
                    ),
                })
            }
            _ => None,
        };
        PlannedIngest {
            images,
            no_test_images: self.check_test_images_at_load().err(),
        }
    }

    /// For a stage that evaluates on the held-out images (eval): an error, naming the split
    /// fields, when the split yields no test image, so the pipeline is refused when it loads
    /// rather than after training. Checked wherever the config decides it: the whole plan
    /// of a synthetic scene; for file-based datasets an explicit empty `split.test_views`
    /// without `split.held_out_frames`, and otherwise the split applied to the dataset's
    /// cameras and frames, read from its files (a dataset with one camera has no held-out
    /// camera for the default split). A dataset that cannot be opened is left to ingest,
    /// which reports why.
    pub fn check_test_images_at_load(&self) -> Result<(), String> {
        let advice = "set split.test_views (and split.test_frames) to views and frames not \
                      trained on, or split.held_out_frames";
        let Some((split, counts)) = self.image_counts_at_load() else {
            let no_test_views = self.split.test_views.as_ref().is_some_and(Vec::is_empty);
            if no_test_views && self.split.held_out_frames.is_none() {
                return Err(format!(
                    "the split yields no test images (split.test_views is empty and \
                     split.held_out_frames is not set): evaluation would have nothing to \
                     measure; {advice}"
                ));
            }
            let Ok(reader) = seqavatar_datasets::open_reader(&self.dataset, None) else {
                return Ok(());
            };
            let split = self.split.apply(reader.default_split());
            let (cameras, frames) = (reader.cameras().len(), reader.num_frames());
            if ImageCounts::of(&split, cameras, frames).is_ok_and(|counts| counts.test == 0) {
                let plural = if cameras == 1 { "" } else { "s" };
                return Err(format!(
                    "{} has {cameras} camera{plural} and {frames} frames: {}",
                    reader.describe(),
                    no_test_images(&split, advice)
                ));
            }
            return Ok(());
        };
        let counts = counts.map_err(|e| format!("split: {e:#}"))?;
        if counts.test > 0 {
            return Ok(());
        }
        Err(no_test_images(&split, advice))
    }
}

/// Why `split` yields no test image, naming its fields, and what to do (`advice`).
fn no_test_images(split: &Split, advice: &str) -> String {
    format!(
        "the split yields no test images (split.test_views {:?}, split.test_frames {}, \
         split.held_out_frames {}; a (view, frame) also in split.train_views x \
         split.train_frames is a training image): evaluation would have nothing to measure; \
         {advice}",
        split.test_views,
        describe_range(&split.test_frames),
        split
            .held_out_frames
            .as_ref()
            .map_or_else(|| "not set".to_owned(), describe_range),
    )
}

fn describe_range(range: &FrameRange) -> String {
    match range.end {
        Some(end) => format!("{}..{end} step {}", range.start, range.step),
        None => format!("{}.. step {}", range.start, range.step),
    }
}

#[cfg(test)]
mod tests {
    use crate::stage::Ingest;

    /// Values that passed validation and then aborted the run (issue 16) are refused when
    /// the config resolves, naming the field.
    #[test]
    fn config_ranges_are_checked_at_load() {
        use seqavatar_engine::StageKind;
        let resolve = |raw: serde_json::Value| {
            Ingest
                .resolve_config(&raw)
                .map(|_| ())
                .map_err(|e| e.to_string())
        };
        resolve(serde_json::json!({})).unwrap();
        for (raw, field) in [
            (
                serde_json::json!({"dataset": {"kind": "synthetic", "frames": 1_000_000_000u64}}),
                "dataset.frames",
            ),
            (
                serde_json::json!({"dataset": {"kind": "synthetic", "cameras": 100_000_000u64}}),
                "dataset.cameras",
            ),
            (
                serde_json::json!({"dataset": {"kind": "synthetic", "fps": -1.0}}),
                "dataset",
            ),
            (
                serde_json::json!({"resolution_scale": 0.0}),
                "resolution_scale",
            ),
            (
                serde_json::json!({"past_frames": 1_000_000_000u64}),
                "past_frames",
            ),
        ] {
            let err = resolve(raw.clone()).unwrap_err();
            assert!(err.contains(field), "{raw} gave `{err}`");
        }
    }

    /// A split without test images is refused from the config alone (eval calls this when
    /// the pipeline loads): one synthetic camera (no test view), test images all inside the
    /// training split (stored once, as training images), an explicit empty `test_views` of a
    /// file-based dataset; a temporal hold-out or the defaults give test images.
    #[test]
    fn a_split_without_test_images_is_refused_at_load() {
        use super::IngestConfig;
        let config =
            |raw: serde_json::Value| seqavatar_engine::parse_config::<IngestConfig>(&raw).unwrap();
        let synthetic = |extra: serde_json::Value| {
            let mut raw = serde_json::json!({
                "dataset": {"kind": "synthetic", "cameras": 8, "frames": 6, "width": 16, "height": 16}
            });
            for (key, value) in extra.as_object().unwrap() {
                if key == "cameras" {
                    raw["dataset"]["cameras"] = value.clone();
                } else {
                    raw[key] = value.clone();
                }
            }
            config(raw)
        };
        // The demo's shape (8 cameras, default split) has test views.
        synthetic(serde_json::json!({}))
            .check_test_images_at_load()
            .unwrap();
        let refused = [
            synthetic(serde_json::json!({"cameras": 1})),
            synthetic(serde_json::json!({"split": {"test_views": []}})),
            // Test view 1 on frames all trained on by view 1 too: no image left for testing.
            synthetic(serde_json::json!({"split": {"train_views": [0, 1], "test_views": [1]}})),
            config(serde_json::json!({
                "dataset": {"kind": "zju_mocap", "root": "/nowhere"},
                "split": {"test_views": []}
            })),
        ];
        for (i, c) in refused.iter().enumerate() {
            let err = c.check_test_images_at_load().unwrap_err();
            assert!(
                err.contains("no test images") && err.contains("split.test_views"),
                "case {i}: {err}"
            );
        }
        // A temporal hold-out gives every view a test image at its frames.
        synthetic(serde_json::json!({
            "cameras": 1,
            "split": {"held_out_frames": {"start": 5, "end": null, "step": 10}}
        }))
        .check_test_images_at_load()
        .unwrap();
        // A file-based dataset's default split comes from its files; one that cannot be
        // opened is left to ingest, which says why.
        config(serde_json::json!({"dataset": {"kind": "zju_mocap", "root": "/nowhere"}}))
            .check_test_images_at_load()
            .unwrap();
        // A split the plan itself refuses is reported naming its field.
        let err = synthetic(serde_json::json!({"split": {"test_views": [99]}}))
            .check_test_images_at_load()
            .unwrap_err();
        assert!(err.contains("split.test_views"), "{err}");
    }
}
