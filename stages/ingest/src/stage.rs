//! The reader interface every dataset implements, the stage configuration, and the
//! split / frame-axis logic shared by all datasets.
//!
//! A dataset reader only answers questions about its capture at full resolution (cameras
//! with their distortion, images, masks, body fits). The stage decides which views and frames
//! to read, undistorts and rescales every image the same way, and writes the arrays
//! documented in the crate docs (`lib.rs`).

use std::path::PathBuf;

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};

use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;

/// One camera of a capture as the dataset calibrates it: full resolution, OpenCV
/// distortion, continuous pixel convention (built with [`Camera::from_opencv`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SourceCamera {
    /// The dataset's own camera id (ZJU `Camera_B<id>`, DNA `"<id>"`, I3D `view_<id>`).
    pub id: i64,
    pub camera: Camera,
}

/// One captured image and its foreground mask, both at the camera's full resolution.
#[derive(Clone, Debug, PartialEq)]
pub struct SourceImage {
    pub rgb: image::RgbImage,
    /// 0 = background, 255 = foreground; soft values allowed.
    pub mask: image::GrayImage,
}

/// Which body model a dataset's fits use (written as the `body_model_kind` attribute).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BodyModelKind {
    Smpl,
    Smplx,
    Procedural,
}

impl BodyModelKind {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Smpl => "smpl",
            Self::Smplx => "smplx",
            Self::Procedural => "procedural",
        }
    }
}

/// 3D keypoints of every frame of a dataset's frame list (`frame`-major), in world space,
/// metres. A keypoint whose position is not finite is missing: [`write_keypoints_3d`] stores
/// it with confidence 0.
#[derive(Clone, Debug, PartialEq)]
pub struct Keypoints3d {
    /// Per keypoint, the body joint it measures; `None` where the dataset does not document
    /// the correspondence.
    pub joints: Vec<Option<usize>>,
    /// `(frame, keypoint)` positions.
    pub positions: Vec<seqavatar_core::glam::DVec3>,
    /// `(frame, keypoint)` confidence, finite and non-negative; 0 = missing.
    pub confidence: Vec<f64>,
}

impl Keypoints3d {
    /// Number of keypoints per frame.
    pub fn num_keypoints(&self) -> usize {
        self.joints.len()
    }

    /// Number of frames (rows).
    pub fn num_frames(&self) -> usize {
        self.positions.len() / self.num_keypoints().max(1)
    }
}

/// A selection of frame-list indices: `start, start + step, ...` below `end`
/// (`end: None` = up to the last frame).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameRange {
    pub start: usize,
    pub end: Option<usize>,
    pub step: usize,
}

impl FrameRange {
    pub fn all() -> Self {
        Self {
            start: 0,
            end: None,
            step: 1,
        }
    }

    /// The selected indices among `num_frames` frames.
    pub fn indices(&self, num_frames: usize, field: &str) -> anyhow::Result<Vec<usize>> {
        if self.step == 0 {
            bail!("{field}.step must be at least 1");
        }
        let end = self.end.unwrap_or(num_frames);
        if end > num_frames {
            bail!("{field}.end = {end} but the dataset has only {num_frames} frames");
        }
        let indices: Vec<usize> = (self.start..end).step_by(self.step).collect();
        if indices.is_empty() {
            bail!(
                "{field} selects no frame (start {}, end {end}, step {})",
                self.start,
                self.step
            );
        }
        Ok(indices)
    }
}

/// Training and test views and frames. Views are indices into [`DatasetReader::cameras`];
/// frames are indices into the dataset's frame list (0..[`DatasetReader::num_frames`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Split {
    pub train_views: Vec<usize>,
    pub test_views: Vec<usize>,
    pub train_frames: FrameRange,
    pub test_frames: FrameRange,
    /// Sampling interval of the motion frame axis (I3D-Human's `interval`: 1 or 3).
    pub frame_interval: usize,
}

/// A dataset: what the stage asks of each reader. Everything is at full resolution, in the
/// project's conventions (ARCHITECTURE.md): continuous pixels, world-to-camera extrinsics in
/// metres, body parameters as [`BodyParams`] (world rotation/translation = `Rh`/`Th`).
///
/// Readers are shared across rayon threads: `read_image` must be callable concurrently and
/// must not keep decoded images around (memory stays bounded by the images in flight).
pub trait DatasetReader: Send + Sync {
    /// A short description for messages, e.g. `ZJU-MoCap /data/CoreView_377`.
    fn describe(&self) -> String;
    /// Every camera of the capture, in a fixed documented order (split views index this).
    fn cameras(&self) -> &[SourceCamera];
    /// Number of frames in the dataset's frame list.
    fn num_frames(&self) -> usize;
    /// The dataset's own number for frame-list index `frame` (file name number).
    fn frame_id(&self, frame: usize) -> i64;
    /// The split method.md prescribes for this sequence.
    fn default_split(&self) -> Split;
    /// The body model the fits refer to, and its kind.
    fn body_model(&self) -> anyhow::Result<(BodyModel, BodyModelKind)>;
    /// The dataset's body fit for a frame (for synthetic data: the jittered copy).
    fn body_params(&self, frame: usize) -> anyhow::Result<BodyParams>;
    /// Exact body parameters where known (synthetic data only).
    fn ground_truth_body_params(&self, _frame: usize) -> anyhow::Result<Option<BodyParams>> {
        Ok(None)
    }
    /// 3D keypoints of every frame of the frame list, where the dataset has them.
    fn keypoints_3d(&self) -> anyhow::Result<Option<Keypoints3d>> {
        Ok(None)
    }
    /// Image and mask of camera `view` at frame-list index `frame`, full resolution.
    fn read_image(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage>;
}

/// Split overrides from the stage config: any field left out keeps the dataset's default.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SplitOverrides {
    pub train_views: Option<Vec<usize>>,
    pub test_views: Option<Vec<usize>>,
    pub train_frames: Option<FrameRange>,
    pub test_frames: Option<FrameRange>,
    pub frame_interval: Option<usize>,
}

impl SplitOverrides {
    pub fn apply(&self, default: Split) -> Split {
        Split {
            train_views: self.train_views.clone().unwrap_or(default.train_views),
            test_views: self.test_views.clone().unwrap_or(default.test_views),
            train_frames: self.train_frames.clone().unwrap_or(default.train_frames),
            test_frames: self.test_frames.clone().unwrap_or(default.test_frames),
            frame_interval: self.frame_interval.unwrap_or(default.frame_interval),
        }
    }
}

/// ZJU-MoCap sequence (`CoreView_XXX/`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZjuMocapConfig {
    /// The `CoreView_XXX` folder.
    pub root: PathBuf,
}

/// I3D-Human sequence (`<root>/<ID>-train/` ...).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct I3dHumanConfig {
    pub root: PathBuf,
    /// Subject and sequence id, e.g. `ID1_1`.
    pub sequence: String,
}

/// DNA-Rendering take (main `.smc`; the annotation file is found next to it).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DnaRenderingConfig {
    pub main_file: PathBuf,
    /// Explicit annotation file; default: derived from `main_file` (datasets.md).
    pub annotations_file: Option<PathBuf>,
}

/// Which dataset to ingest (`dataset: {kind: synthetic, ...}` in the YAML).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum DatasetConfig {
    Synthetic(crate::synthetic::SyntheticConfig),
    ZjuMocap(ZjuMocapConfig),
    I3dHuman(I3dHumanConfig),
    DnaRendering(DnaRenderingConfig),
}

impl Default for DatasetConfig {
    fn default() -> Self {
        Self::Synthetic(crate::synthetic::SyntheticConfig::default())
    }
}

/// The `ingest` stage configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct IngestConfig {
    pub dataset: DatasetConfig,
    /// Image rescale factor applied after undistortion (ZJU 0.5, DNA 0.25 in method.md).
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

/// What the stage will ingest: resolved from a reader's default split and the overrides.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct IngestPlan {
    /// Dataset camera indices written as the `view` axis, sorted.
    pub views: Vec<usize>,
    /// Dataset frame-list indices written as the `frame` axis: an arithmetic sequence with
    /// step `frame_interval` that reaches `past_frames` steps before the first used frame.
    pub frames: Vec<usize>,
    pub frame_interval: usize,
    /// Per frame of `frames`: bit 0 = a training image uses it, bit 1 = a test image does.
    pub frame_split: Vec<u8>,
    /// Images to write: (position in `views`, position in `frames`, split 0 train / 1 test).
    pub images: Vec<(usize, usize, u8)>,
}

impl IngestPlan {
    /// Resolves the split against a dataset with `num_cameras` cameras and `num_frames`
    /// frames. Errors name the config field at fault.
    pub fn new(
        split: &Split,
        num_cameras: usize,
        num_frames: usize,
        past_frames: usize,
    ) -> anyhow::Result<Self> {
        let interval = split.frame_interval;
        if interval == 0 {
            bail!("split.frame_interval must be at least 1");
        }
        for (field, views) in [
            ("split.train_views", &split.train_views),
            ("split.test_views", &split.test_views),
        ] {
            if let Some(bad) = views.iter().find(|&&v| v >= num_cameras) {
                bail!(
                    "{field} names view {bad} but the dataset has {num_cameras} cameras (0..{num_cameras})"
                );
            }
        }
        if split.train_views.is_empty() && split.test_views.is_empty() {
            bail!("split.train_views and split.test_views are both empty");
        }
        let train_frames = if split.train_views.is_empty() {
            Vec::new()
        } else {
            split
                .train_frames
                .indices(num_frames, "split.train_frames")?
        };
        let test_frames = if split.test_views.is_empty() {
            Vec::new()
        } else {
            split.test_frames.indices(num_frames, "split.test_frames")?
        };
        let used: Vec<usize> = train_frames.iter().chain(&test_frames).copied().collect();
        let first = *used.iter().min().expect("at least one split is non-empty");
        let last = *used.iter().max().expect("at least one split is non-empty");
        if let Some(bad) = used
            .iter()
            .find(|&&f| !(f - first).is_multiple_of(interval))
        {
            bail!(
                "frame {bad} is not on the frame axis {first} + k * {interval}: the split's frame steps must be multiples of split.frame_interval"
            );
        }
        let start = first - (first / interval).min(past_frames) * interval;
        let frames: Vec<usize> = (start..=last).step_by(interval).collect();
        let position = |f: usize| (f - start) / interval;
        let mut frame_split = vec![0u8; frames.len()];
        for &f in &train_frames {
            frame_split[position(f)] |= 1;
        }
        for &f in &test_frames {
            frame_split[position(f)] |= 2;
        }
        let mut views: Vec<usize> = split
            .train_views
            .iter()
            .chain(&split.test_views)
            .copied()
            .collect();
        views.sort_unstable();
        views.dedup();
        let view_position = |v: usize| views.binary_search(&v).expect("view comes from the split");
        let mut images = Vec::new();
        for &v in &split.train_views {
            for &f in &train_frames {
                images.push((view_position(v), position(f), 0u8));
            }
        }
        for &v in &split.test_views {
            for &f in &test_frames {
                images.push((view_position(v), position(f), 1u8));
            }
        }
        // The same (view, frame) in both splits is stored once, as training data.
        let mut seen = std::collections::HashSet::new();
        images.retain(|&(v, f, _)| seen.insert((v, f)));
        Ok(Self {
            views,
            frames,
            frame_interval: interval,
            frame_split,
            images,
        })
    }
}

/// Opens the reader for a dataset config.
pub fn open_reader(config: &IngestConfig) -> anyhow::Result<Box<dyn DatasetReader>> {
    match &config.dataset {
        DatasetConfig::Synthetic(synthetic) => {
            let scene = crate::synthetic::SyntheticScene::generate(synthetic)
                .context("generating the synthetic scene")?;
            Ok(Box::new(scene))
        }
        // ZJU-MoCap, I3D-Human and DNA-Rendering (crate::datasets).
        _ => crate::datasets::open_dataset_reader(config),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn split(
        train: &[usize],
        test: &[usize],
        train_frames: FrameRange,
        test_frames: FrameRange,
        interval: usize,
    ) -> Split {
        Split {
            train_views: train.to_vec(),
            test_views: test.to_vec(),
            train_frames,
            test_frames,
            frame_interval: interval,
        }
    }

    #[test]
    fn zju_style_split_ingests_only_used_images_and_past_frames() {
        // Train view 0 on frames 10..20; test views 1, 2 every 5th frame from 10.
        let s = split(
            &[0],
            &[2, 1],
            FrameRange {
                start: 10,
                end: Some(20),
                step: 1,
            },
            FrameRange {
                start: 10,
                end: Some(20),
                step: 5,
            },
            1,
        );
        let plan = IngestPlan::new(&s, 4, 100, 3).unwrap();
        assert_eq!(plan.views, vec![0, 1, 2]);
        assert_eq!(plan.frames, (7..20).collect::<Vec<_>>());
        assert_eq!(plan.frame_split[..3], [0, 0, 0]);
        assert_eq!(plan.frame_split[3], 3);
        assert_eq!(plan.frame_split[4], 1);
        assert_eq!(plan.images.len(), 10 + 2 * 2);
        assert!(plan.images.contains(&(2, 8, 1)));
        // Past frames clamp at the start of the sequence.
        let plan = IngestPlan::new(&s, 4, 100, 50).unwrap();
        assert_eq!(plan.frames[0], 0);
    }

    #[test]
    fn interval_and_errors() {
        let s = split(
            &[0],
            &[],
            FrameRange {
                start: 4,
                end: None,
                step: 3,
            },
            FrameRange::all(),
            3,
        );
        let plan = IngestPlan::new(&s, 1, 12, 1).unwrap();
        assert_eq!(plan.frames, vec![1, 4, 7, 10]);
        let bad = split(
            &[0],
            &[],
            FrameRange {
                start: 4,
                end: None,
                step: 2,
            },
            FrameRange::all(),
            3,
        );
        let err = IngestPlan::new(&bad, 1, 12, 1).unwrap_err().to_string();
        assert!(err.contains("frame_interval"), "{err}");
        let bad = split(&[5], &[], FrameRange::all(), FrameRange::all(), 1);
        let err = IngestPlan::new(&bad, 2, 12, 0).unwrap_err().to_string();
        assert!(err.contains("split.train_views"), "{err}");
        let bad = split(
            &[0],
            &[],
            FrameRange {
                start: 0,
                end: Some(40),
                step: 1,
            },
            FrameRange::all(),
            1,
        );
        let err = IngestPlan::new(&bad, 2, 12, 0).unwrap_err().to_string();
        assert!(err.contains("split.train_frames.end"), "{err}");
    }

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
}

// ---------------------------------------------------------------------------------------
// The stage: writes the arrays documented in lib.rs.
// ---------------------------------------------------------------------------------------

use rayon::prelude::*;
use seqavatar_core::body::BodyModelArrays;
use seqavatar_core::glam::{DVec2, DVec3};
use seqavatar_engine::{
    ConfigError, ConfigPathSegment, EntryReader, EntryWriter, PictureKind, PictureOptions,
    StageContext, StageKind,
};

/// The `ingest` stage kind.
pub struct Ingest;

/// Implementation version: bump whenever the written arrays change for the same config.
/// 3: images and masks decode strictly (a truncated JPEG was accepted with grey rows), so
/// entries made by the lenient decoder are not served again.
/// 4: attribute `first_frame_index` (where the frame axis starts in the recording).
pub const INGEST_VERSION: u32 = 4;

impl StageKind for Ingest {
    fn kind(&self) -> &'static str {
        "ingest"
    }

    fn version(&self) -> u32 {
        INGEST_VERSION
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &[]
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<serde_json::Value, ConfigError> {
        let resolved = seqavatar_engine::resolve_typed::<IngestConfig>(raw)?;
        let config: IngestConfig = serde_json::from_value(resolved.clone())
            .map_err(|e| ConfigError::new(vec![], e.to_string()))?;
        config.validate()?;
        Ok(resolved)
    }

    fn external_files(&self, config: &serde_json::Value) -> anyhow::Result<Vec<PathBuf>> {
        let config: IngestConfig = serde_json::from_value(config.clone())?;
        let mut files: Vec<PathBuf> = config.body_model.iter().cloned().collect();
        files.extend(crate::datasets::source_files(&config));
        Ok(files)
    }

    fn run(&self, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        let config: IngestConfig = ctx.config()?;
        // Ranges were checked when the pipeline loaded (resolve_config).
        let reader = open_reader(&config)?;
        ctx.log(&format!("reading {}", reader.describe()));
        let split = config.split.apply(reader.default_split());
        let plan = IngestPlan::new(
            &split,
            reader.cameras().len(),
            reader.num_frames(),
            config.past_frames,
        )?;
        ctx.log(&format!(
            "{} views, {} frames ({} with images), {} images",
            plan.views.len(),
            plan.frames.len(),
            plan.frame_split.iter().filter(|s| **s != 0).count(),
            plan.images.len()
        ));
        let out = ctx.output();
        let cameras = write_cameras(out, reader.as_ref(), &plan, config.resolution_scale)?;
        let (model, kind) = reader.body_model()?;
        write_body_model(out, &model)?;
        write_frames(out, reader.as_ref(), &plan, &model)?;

        // Images, in parallel, one chunk each; nothing but the images in flight is held.
        let max_h = cameras.iter().map(|c| c.height).max().unwrap_or(1) as u64;
        let max_w = cameras.iter().map(|c| c.width).max().unwrap_or(1) as u64;
        let n = plan.images.len() as u64;
        let images = out.create_array::<u8>(
            "images",
            &["image", "height", "width", "rgb"],
            &[n, max_h, max_w, 3],
            &[1, max_h, max_w, 3],
        )?;
        let masks = out.create_array::<u8>(
            "masks",
            &["image", "height", "width"],
            &[n, max_h, max_w],
            &[1, max_h, max_w],
        )?;
        let bar = ctx.progress_bar(n, "images");
        plan.images.par_iter().enumerate().try_for_each(
            |(index, &(view, frame, _))| -> anyhow::Result<()> {
                let source_view = plan.views[view];
                let source_frame = plan.frames[frame];
                let source = reader
                    .read_image(source_view, source_frame)
                    .with_context(|| {
                        format!(
                            "{}: camera {} frame {}",
                            reader.describe(),
                            reader.cameras()[source_view].id,
                            reader.frame_id(source_frame)
                        )
                    })?;
                let source_camera = &reader.cameras()[source_view].camera;
                let (rgb, mask) =
                    resample(&source, source_camera, &cameras[view]).with_context(|| {
                        format!(
                            "{}: camera {} frame {}",
                            reader.describe(),
                            reader.cameras()[source_view].id,
                            reader.frame_id(source_frame)
                        )
                    })?;
                let (w, h) = (cameras[view].width as usize, cameras[view].height as usize);
                let (mw, mh) = (max_w as usize, max_h as usize);
                let mut rgb_chunk = vec![0u8; mh * mw * 3];
                let mut mask_chunk = vec![0u8; mh * mw];
                for row in 0..h {
                    rgb_chunk[row * mw * 3..row * mw * 3 + w * 3]
                        .copy_from_slice(&rgb[row * w * 3..(row + 1) * w * 3]);
                    mask_chunk[row * mw..row * mw + w]
                        .copy_from_slice(&mask[row * w..(row + 1) * w]);
                }
                images.write_chunk(&[index as u64, 0, 0, 0], &rgb_chunk)?;
                masks.write_chunk(&[index as u64, 0, 0], &mask_chunk)?;
                bar.inc(1);
                Ok(())
            },
        )?;
        bar.finish_and_clear();
        let image_view: Vec<u32> = plan.images.iter().map(|i| i.0 as u32).collect();
        let image_frame: Vec<u32> = plan.images.iter().map(|i| i.1 as u32).collect();
        let image_split: Vec<u8> = plan.images.iter().map(|i| i.2).collect();
        let chunk = [n.max(1)];
        out.write_array("image_view", &["image"], &[n], &chunk, &image_view)?;
        out.write_array("image_frame", &["image"], &[n], &chunk, &image_frame)?;
        out.write_array("image_split", &["image"], &[n], &chunk, &image_split)?;

        let dataset = serde_json::to_value(&config.dataset)?
            .get("kind")
            .cloned()
            .unwrap_or(serde_json::Value::Null);
        out.set_attribute("dataset", dataset)?;
        out.set_attribute("body_model_kind", kind.as_str().into())?;
        out.set_attribute("frame_interval", plan.frame_interval.into())?;
        out.set_attribute("resolution_scale", config.resolution_scale.into())?;
        out.set_attribute("past_frames", config.past_frames.into())?;
        // Where the frame axis starts in the recording, so that motion windows clamp only at
        // the recording's true start (`seqavatar_motion::schema::FrameAxis`).
        out.set_attribute("first_frame_index", plan.frames[0].into())?;
        let train = image_split.iter().filter(|s| **s == 0).count();
        out.set_attribute("num_train_images", train.into())?;
        out.set_attribute("num_test_images", (image_split.len() - train).into())?;
        out.set_attribute("background", serde_json::json!([0, 0, 0]))?;
        Ok(())
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![PictureKind {
            name: "contact_sheet",
            description: "grid of ingested images with their masks overlaid in green (options: split=train|test|all, max=N images, columns=N)",
        }]
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        if picture != "contact_sheet" {
            return Err(seqavatar_engine::unknown_picture(self, picture));
        }
        contact_sheet(entry, options)
    }
}

/// Writes the camera arrays; returns the rescaled, distortion-free cameras per view.
fn write_cameras(
    out: &EntryWriter,
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    scale: f64,
) -> anyhow::Result<Vec<Camera>> {
    let mut cameras = Vec::with_capacity(plan.views.len());
    let mut k: Vec<f64> = Vec::new();
    let mut r: Vec<f64> = Vec::new();
    let mut t: Vec<f64> = Vec::new();
    let mut size: Vec<u32> = Vec::new();
    let mut distortion: Vec<f64> = Vec::new();
    let mut ids: Vec<i64> = Vec::new();
    for &view in &plan.views {
        let source = &reader.cameras()[view];
        source
            .camera
            .validate()
            .with_context(|| format!("{}: camera {}", reader.describe(), source.id))?;
        let mut camera = source.camera.rescaled(scale);
        camera.distortion = [0.0; 5];
        k.extend(camera.k_matrix().iter().flatten().copied());
        let rt = camera.rotation.transpose();
        // Row-major R: rows of R are the columns of R^T.
        r.extend(
            rt.x_axis
                .to_array()
                .into_iter()
                .chain(rt.y_axis.to_array())
                .chain(rt.z_axis.to_array()),
        );
        t.extend(camera.translation.to_array());
        size.extend([camera.height, camera.width]);
        distortion.extend(source.camera.distortion);
        ids.push(source.id);
        cameras.push(camera);
    }
    let v = plan.views.len() as u64;
    out.write_array(
        "camera_K",
        &["view", "row", "col"],
        &[v, 3, 3],
        &[v, 3, 3],
        &k,
    )?;
    out.write_array(
        "camera_R",
        &["view", "row", "col"],
        &[v, 3, 3],
        &[v, 3, 3],
        &r,
    )?;
    out.write_array("camera_t", &["view", "xyz"], &[v, 3], &[v, 3], &t)?;
    out.write_array(
        "camera_image_size",
        &["view", "hw"],
        &[v, 2],
        &[v, 2],
        &size,
    )?;
    out.write_array(
        "camera_source_distortion",
        &["view", "coeff"],
        &[v, 5],
        &[v, 5],
        &distortion,
    )?;
    out.write_array("camera_source_id", &["view"], &[v], &[v], &ids)?;
    Ok(cameras)
}

/// Writes the frame axis and the per-frame body parameters (fits and, where known, truth).
fn write_frames(
    out: &EntryWriter,
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    model: &BodyModel,
) -> anyhow::Result<()> {
    let n = plan.frames.len() as u64;
    let ids: Vec<i64> = plan.frames.iter().map(|&f| reader.frame_id(f)).collect();
    out.write_array("frame_source_id", &["frame"], &[n], &[n], &ids)?;
    out.write_array("frame_split", &["frame"], &[n], &[n], &plan.frame_split)?;
    let fits = plan
        .frames
        .par_iter()
        .map(|&f| {
            let params = reader.body_params(f).with_context(|| {
                format!(
                    "{}: body fit of frame {}",
                    reader.describe(),
                    reader.frame_id(f)
                )
            })?;
            model.check_params(&params).with_context(|| {
                format!(
                    "{}: body fit of frame {}",
                    reader.describe(),
                    reader.frame_id(f)
                )
            })?;
            Ok(params)
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    write_body_params(out, "body", &fits, model)?;
    let truth = plan
        .frames
        .iter()
        .map(|&f| reader.ground_truth_body_params(f))
        .collect::<anyhow::Result<Vec<_>>>()?;
    if truth.iter().all(Option::is_some) {
        let truth: Vec<BodyParams> = truth.into_iter().flatten().collect();
        write_body_params(out, "gt_body", &truth, model)?;
    }
    if let Some(keypoints) = reader.keypoints_3d()? {
        let describe = reader.describe();
        let rows = keypoints.num_frames();
        let k = keypoints.num_keypoints();
        anyhow::ensure!(
            keypoints.positions.len() == rows * k
                && keypoints.confidence.len() == rows * k
                && rows >= reader.num_frames(),
            "{describe}: 3D keypoints have {} positions and {} confidences for {k} keypoints; expected {} frames x {k}",
            keypoints.positions.len(),
            keypoints.confidence.len(),
            reader.num_frames()
        );
        let selected = Keypoints3d {
            joints: keypoints.joints.clone(),
            positions: plan
                .frames
                .iter()
                .flat_map(|&f| keypoints.positions[f * k..(f + 1) * k].iter().copied())
                .collect(),
            confidence: plan
                .frames
                .iter()
                .flat_map(|&f| keypoints.confidence[f * k..(f + 1) * k].iter().copied())
                .collect(),
        };
        write_keypoints_3d(out, &selected, model)
            .with_context(|| format!("{describe}: 3D keypoints"))?;
    }
    Ok(())
}

/// Writes `keypoints_3d`, `keypoints_3d_confidence` and the `keypoints_3d_joints` attribute
/// (lib.rs schema). A keypoint with a non-finite position gets confidence 0; a negative or
/// non-finite confidence, or a joint the model does not have, is an error naming the frame
/// (row) and keypoint.
pub fn write_keypoints_3d(
    out: &EntryWriter,
    keypoints: &Keypoints3d,
    model: &BodyModel,
) -> anyhow::Result<()> {
    let k = keypoints.num_keypoints();
    let n = keypoints.num_frames();
    anyhow::ensure!(k > 0, "no keypoints");
    for (i, joint) in keypoints.joints.iter().enumerate() {
        if let Some(j) = joint {
            anyhow::ensure!(
                *j < model.num_joints(),
                "keypoint {i} names joint {j}; the body model has {} joints",
                model.num_joints()
            );
        }
    }
    let mut confidence = keypoints.confidence.clone();
    for (i, (c, p)) in confidence.iter_mut().zip(&keypoints.positions).enumerate() {
        anyhow::ensure!(
            c.is_finite() && *c >= 0.0,
            "confidence {c} of frame {} keypoint {} is not a finite non-negative number",
            i / k,
            i % k
        );
        if !p.is_finite() {
            *c = 0.0;
        }
    }
    let positions: Vec<f64> = keypoints
        .positions
        .iter()
        .flat_map(|p| p.to_array())
        .collect();
    let (n64, k64) = (n as u64, k as u64);
    let chunk = n64.clamp(1, 1024);
    out.write_array(
        "keypoints_3d",
        &["frame", "keypoint", "xyz"],
        &[n64, k64, 3],
        &[chunk, k64, 3],
        &positions,
    )?;
    out.write_array(
        "keypoints_3d_confidence",
        &["frame", "keypoint"],
        &[n64, k64],
        &[chunk, k64],
        &confidence,
    )?;
    let joints: Vec<i64> = keypoints
        .joints
        .iter()
        .map(|j| j.map_or(-1, |j| j as i64))
        .collect();
    out.set_attribute("keypoints_3d_joints", serde_json::to_value(joints)?)?;
    Ok(())
}

/// Reads the arrays written by [`write_keypoints_3d`]; `None` when the entry has none.
/// Errors name the entry and the array or attribute.
pub fn read_keypoints_3d(entry: &EntryReader) -> anyhow::Result<Option<Keypoints3d>> {
    let names = entry.array_names();
    if !names.iter().any(|n| n == "keypoints_3d") {
        return Ok(None);
    }
    let location = entry.location();
    let positions = entry.read::<f64>("keypoints_3d")?;
    anyhow::ensure!(
        positions.shape.len() == 3 && positions.shape[2] == 3,
        "entry {location}: array keypoints_3d has shape {:?}, expected (frame, keypoint, 3)",
        positions.shape
    );
    let (n, k) = (positions.shape[0], positions.shape[1]);
    let confidence = entry.read::<f64>("keypoints_3d_confidence")?;
    anyhow::ensure!(
        confidence.shape == [n, k],
        "entry {location}: array keypoints_3d_confidence has shape {:?}, expected ({n}, {k})",
        confidence.shape
    );
    let joints = entry.attribute("keypoints_3d_joints").ok_or_else(|| {
        anyhow::anyhow!("entry {location}: attribute keypoints_3d_joints is missing")
    })?;
    let joints: Vec<i64> = serde_json::from_value(joints).map_err(|e| {
        anyhow::anyhow!(
            "entry {location}: attribute keypoints_3d_joints is not a list of integers: {e}"
        )
    })?;
    anyhow::ensure!(
        joints.len() == k,
        "entry {location}: attribute keypoints_3d_joints has {} entries for {k} keypoints",
        joints.len()
    );
    let joints = joints
        .into_iter()
        .enumerate()
        .map(|(i, j)| match j {
            -1 => Ok(None),
            j if j >= 0 => Ok(Some(j as usize)),
            j => Err(anyhow::anyhow!(
                "entry {location}: attribute keypoints_3d_joints[{i}] is {j} (a joint index or -1)"
            )),
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Some(Keypoints3d {
        joints,
        positions: positions
            .data
            .chunks_exact(3)
            .map(|c| DVec3::new(c[0], c[1], c[2]))
            .collect(),
        confidence: confidence.data,
    }))
}

/// Writes `<prefix>_pose`, `_world_rotation`, `_world_translation`, `_betas` and (when the
/// model has them) `_expression`, zero-padding coefficients to the model's counts.
pub fn write_body_params(
    out: &EntryWriter,
    prefix: &str,
    params: &[BodyParams],
    model: &BodyModel,
) -> anyhow::Result<()> {
    let n = params.len() as u64;
    let j = model.num_joints() as u64;
    let pose: Vec<f64> = params
        .iter()
        .flat_map(|p| p.pose.iter().flat_map(|v| v.to_array()))
        .collect();
    out.write_array(
        &format!("{prefix}_pose"),
        &["frame", "joint", "xyz"],
        &[n, j, 3],
        &[n, j, 3],
        &pose,
    )?;
    let rotation: Vec<f64> = params
        .iter()
        .flat_map(|p| p.world_rotation.to_array())
        .collect();
    out.write_array(
        &format!("{prefix}_world_rotation"),
        &["frame", "xyz"],
        &[n, 3],
        &[n, 3],
        &rotation,
    )?;
    let translation: Vec<f64> = params
        .iter()
        .flat_map(|p| p.world_translation.to_array())
        .collect();
    out.write_array(
        &format!("{prefix}_world_translation"),
        &["frame", "xyz"],
        &[n, 3],
        &[n, 3],
        &translation,
    )?;
    let padded = |values: &[f64], count: usize| {
        let mut row = values.to_vec();
        row.resize(count, 0.0);
        row
    };
    let b = model.num_betas();
    if b > 0 {
        let betas: Vec<f64> = params.iter().flat_map(|p| padded(&p.betas, b)).collect();
        out.write_array(
            &format!("{prefix}_betas"),
            &["frame", "beta"],
            &[n, b as u64],
            &[n, b as u64],
            &betas,
        )?;
    }
    let e = model.num_expression();
    if e > 0 {
        let expression: Vec<f64> = params
            .iter()
            .flat_map(|p| padded(&p.expression, e))
            .collect();
        out.write_array(
            &format!("{prefix}_expression"),
            &["frame", "expression"],
            &[n, e as u64],
            &[n, e as u64],
            &expression,
        )?;
    }
    Ok(())
}

/// Reads per-frame body parameters written by [`write_body_params`] (`prefix` = `body` or
/// `gt_body`).
pub fn read_body_params(entry: &EntryReader, prefix: &str) -> anyhow::Result<Vec<BodyParams>> {
    let pose = entry.read::<f64>(&format!("{prefix}_pose"))?;
    anyhow::ensure!(
        pose.shape.len() == 3 && pose.shape[2] == 3,
        "array {prefix}_pose has shape {:?}, expected (frame, joint, 3)",
        pose.shape
    );
    let (n, j) = (pose.shape[0], pose.shape[1]);
    let rotation = entry.read::<f64>(&format!("{prefix}_world_rotation"))?;
    let translation = entry.read::<f64>(&format!("{prefix}_world_translation"))?;
    for (name, array) in [
        ("world_rotation", &rotation),
        ("world_translation", &translation),
    ] {
        anyhow::ensure!(
            array.shape == [n, 3],
            "array {prefix}_{name} has shape {:?}, expected ({n}, 3)",
            array.shape
        );
    }
    let optional = |name: &str| -> anyhow::Result<(usize, Vec<f64>)> {
        let full = format!("{prefix}_{name}");
        if !entry.array_names().contains(&full) {
            return Ok((0, Vec::new()));
        }
        let array = entry.read::<f64>(&full)?;
        anyhow::ensure!(
            array.shape.len() == 2 && array.shape[0] == n,
            "array {full} has shape {:?}, expected ({n}, K)",
            array.shape
        );
        Ok((array.shape[1], array.data))
    };
    let (b, betas) = optional("betas")?;
    let (e, expression) = optional("expression")?;
    let v3 = |data: &[f64], i: usize| DVec3::new(data[3 * i], data[3 * i + 1], data[3 * i + 2]);
    Ok((0..n)
        .map(|f| BodyParams {
            pose: (0..j).map(|k| v3(&pose.data, f * j + k)).collect(),
            betas: betas[f * b..(f + 1) * b].to_vec(),
            expression: expression[f * e..(f + 1) * e].to_vec(),
            world_rotation: v3(&rotation.data, f),
            world_translation: v3(&translation.data, f),
        })
        .collect())
}

/// Writes the `body_model_*` arrays.
pub fn write_body_model(out: &EntryWriter, model: &BodyModel) -> anyhow::Result<()> {
    let a = model.arrays();
    let v = model.num_vertices() as u64;
    let j = model.num_joints() as u64;
    let f = a.faces.len() as u64;
    let template: Vec<f64> = a.template.iter().flatten().copied().collect();
    out.write_array(
        "body_model_template",
        &["vertex", "xyz"],
        &[v, 3],
        &[v, 3],
        &template,
    )?;
    let faces: Vec<u32> = a.faces.iter().flatten().copied().collect();
    out.write_array(
        "body_model_faces",
        &["face", "corner"],
        &[f, 3],
        &[f.max(1), 3],
        &faces,
    )?;
    out.write_array("body_model_parents", &["joint"], &[j], &[j], &a.parents)?;
    out.write_array(
        "body_model_weights",
        &["vertex", "joint"],
        &[v, j],
        &[v, j],
        &a.weights,
    )?;
    out.write_array(
        "body_model_joint_regressor",
        &["joint", "vertex"],
        &[j, v],
        &[j, v],
        &a.joint_regressor,
    )?;
    if a.num_betas > 0 {
        let b = a.num_betas as u64;
        out.write_array(
            "body_model_shape_dirs",
            &["vertex", "xyz", "beta"],
            &[v, 3, b],
            &[v, 3, b],
            &a.shape_dirs,
        )?;
    }
    if a.num_expression > 0 {
        let e = a.num_expression as u64;
        out.write_array(
            "body_model_expression_dirs",
            &["vertex", "xyz", "expression"],
            &[v, 3, e],
            &[v, 3, e],
            &a.expression_dirs,
        )?;
    }
    if !a.pose_dirs.is_empty() {
        let p = 9 * (j - 1);
        // Chunked by vertex blocks: SMPL-X's pose_dirs are 60 MB.
        let block = v.min(2048);
        out.write_array(
            "body_model_pose_dirs",
            &["vertex", "xyz", "pose_feature"],
            &[v, 3, p],
            &[block, 3, p],
            &a.pose_dirs,
        )?;
    }
    Ok(())
}

/// Reads the body model written by [`write_body_model`] and validates it.
pub fn read_body_model(entry: &EntryReader) -> anyhow::Result<BodyModel> {
    let names = entry.array_names();
    let has = |name: &str| names.iter().any(|n| n == name);
    let template = entry.read::<f64>("body_model_template")?;
    anyhow::ensure!(
        template.shape.len() == 2 && template.shape[1] == 3,
        "array body_model_template has shape {:?}, expected (vertex, 3)",
        template.shape
    );
    let faces = entry.read::<u32>("body_model_faces")?;
    let parents = entry.read::<i64>("body_model_parents")?;
    let last_dim = |name: &str, shape: &[usize]| -> anyhow::Result<usize> {
        shape
            .last()
            .copied()
            .ok_or_else(|| anyhow::anyhow!("array {name} is zero-dimensional"))
    };
    let (shape_dirs, num_betas) = if has("body_model_shape_dirs") {
        let a = entry.read::<f64>("body_model_shape_dirs")?;
        let b = last_dim("body_model_shape_dirs", &a.shape)?;
        (a.data, b)
    } else {
        (Vec::new(), 0)
    };
    let (expression_dirs, num_expression) = if has("body_model_expression_dirs") {
        let a = entry.read::<f64>("body_model_expression_dirs")?;
        let e = last_dim("body_model_expression_dirs", &a.shape)?;
        (a.data, e)
    } else {
        (Vec::new(), 0)
    };
    let pose_dirs = if has("body_model_pose_dirs") {
        entry.read::<f32>("body_model_pose_dirs")?.data
    } else {
        Vec::new()
    };
    anyhow::ensure!(
        faces.data.len() % 3 == 0,
        "array body_model_faces is not (face, 3)"
    );
    let arrays = BodyModelArrays {
        template: template
            .data
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        faces: faces
            .data
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        parents: parents.data,
        weights: entry.read::<f64>("body_model_weights")?.data,
        joint_regressor: entry.read::<f64>("body_model_joint_regressor")?.data,
        shape_dirs,
        num_betas,
        expression_dirs,
        num_expression,
        pose_dirs,
    };
    BodyModel::new(arrays)
        .with_context(|| format!("body model arrays of entry {}", entry.location()))
}

/// Undistorts and rescales one image and mask onto `target` (a distortion-free camera with
/// the same pose as `source`, its intrinsics scaled). Each output pixel averages `n x n`
/// bilinear samples (`n = ceil(1 / scale)`), so downscaling does not alias.
pub fn resample(
    image: &SourceImage,
    source: &Camera,
    target: &Camera,
) -> anyhow::Result<(Vec<u8>, Vec<u8>)> {
    let (sw, sh) = (image.rgb.width(), image.rgb.height());
    anyhow::ensure!(
        (sw, sh) == (source.width, source.height),
        "image is {sw}x{sh} but the camera calibration says {}x{}",
        source.width,
        source.height
    );
    anyhow::ensure!(
        image.mask.dimensions() == (sw, sh),
        "mask is {}x{} but the image is {sw}x{sh}",
        image.mask.width(),
        image.mask.height()
    );
    let (tw, th) = (target.width as usize, target.height as usize);
    let identity =
        (tw, th) == (sw as usize, sh as usize) && source.distortion.iter().all(|d| *d == 0.0);
    if identity {
        return Ok((image.rgb.as_raw().clone(), image.mask.as_raw().clone()));
    }
    let ratio = DVec2::new(sw as f64 / tw as f64, sh as f64 / th as f64);
    let n = ratio.max_element().ceil().max(1.0) as usize;
    let rgb = image.rgb.as_raw();
    let mask = image.mask.as_raw();
    let (sw, sh) = (sw as usize, sh as usize);
    // Bilinear sample of 4 channels (r, g, b, mask) at a continuous pixel position; outside
    // the image counts as black background.
    let sample = |q: DVec2| -> [f64; 4] {
        let x = q.x - 0.5;
        let y = q.y - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (tx, ty) = (x - x0, y - y0);
        let mut out = [0.0; 4];
        for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
            for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                let (xi, yi) = (x0 as i64 + dx, y0 as i64 + dy);
                if xi < 0 || yi < 0 || xi >= sw as i64 || yi >= sh as i64 {
                    continue;
                }
                let p = yi as usize * sw + xi as usize;
                let w = wx * wy;
                out[0] += w * rgb[3 * p] as f64;
                out[1] += w * rgb[3 * p + 1] as f64;
                out[2] += w * rgb[3 * p + 2] as f64;
                out[3] += w * mask[p] as f64;
            }
        }
        out
    };
    let mut out_rgb = vec![0u8; tw * th * 3];
    let mut out_mask = vec![0u8; tw * th];
    out_rgb
        .par_chunks_mut(tw * 3)
        .zip(out_mask.par_chunks_mut(tw))
        .enumerate()
        .for_each(|(row, (rgb_row, mask_row))| {
            for col in 0..tw {
                let mut acc = [0.0; 4];
                for sy in 0..n {
                    for sx in 0..n {
                        let target_pixel = DVec2::new(
                            col as f64 + (sx as f64 + 0.5) / n as f64,
                            row as f64 + (sy as f64 + 0.5) / n as f64,
                        );
                        // Undistorted full-resolution pixel, then where the lens put it.
                        let undistorted = target_pixel * ratio;
                        let captured = source.undistort_source_pixel(undistorted);
                        let s = sample(captured);
                        for c in 0..4 {
                            acc[c] += s[c];
                        }
                    }
                }
                let scale = 1.0 / (n * n) as f64;
                for c in 0..3 {
                    rgb_row[3 * col + c] = (acc[c] * scale).round().clamp(0.0, 255.0) as u8;
                }
                mask_row[col] = (acc[3] * scale).round().clamp(0.0, 255.0) as u8;
            }
        });
    Ok((out_rgb, out_mask))
}

/// A grid of ingested images with the mask overlaid in green at the foreground boundary
/// and tinted outside.
fn contact_sheet(entry: &EntryReader, options: &PictureOptions) -> anyhow::Result<image::RgbImage> {
    let which = options.get_str("split", "all")?;
    let wanted: Option<u8> = match which.as_str() {
        "train" => Some(0),
        "test" => Some(1),
        "all" => None,
        other => anyhow::bail!("picture option split={other}: expected train, test or all"),
    };
    let max = options.get_u64("max", 16)?.max(1) as usize;
    let split = entry.read::<u8>("image_split")?;
    let chosen: Vec<usize> = (0..split.data.len())
        .filter(|&i| wanted.is_none_or(|w| split.data[i] == w))
        .collect();
    anyhow::ensure!(!chosen.is_empty(), "the entry has no {which} images");
    // Spread the picks over the whole list.
    let picks: Vec<usize> = (0..max.min(chosen.len()))
        .map(|k| chosen[k * chosen.len() / max.min(chosen.len())])
        .collect();
    let shape = entry.shape("images")?;
    anyhow::ensure!(
        shape.len() == 4,
        "array images has shape {shape:?}, expected (image, height, width, 3)"
    );
    let (h, w) = (shape[1] as usize, shape[2] as usize);
    let columns = (options.get_u64("columns", 4)?.max(1) as usize).min(picks.len());
    let rows = picks.len().div_ceil(columns);
    let mut sheet = image::RgbImage::new((columns * w) as u32, (rows * h) as u32);
    for (k, &index) in picks.iter().enumerate() {
        let rgb = entry.read_region::<u8>(
            "images",
            &[index as u64, 0, 0, 0],
            &[1, h as u64, w as u64, 3],
        )?;
        let mask =
            entry.read_region::<u8>("masks", &[index as u64, 0, 0], &[1, h as u64, w as u64])?;
        let (ox, oy) = ((k % columns) * w, (k / columns) * h);
        for y in 0..h {
            for x in 0..w {
                let m = mask.data[y * w + x];
                let p = (y * w + x) * 3;
                let mut c = [rgb.data[p], rgb.data[p + 1], rgb.data[p + 2]];
                let boundary = m >= 128
                    && [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)]
                        .iter()
                        .any(|(dx, dy)| {
                            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                            nx < 0
                                || ny < 0
                                || nx >= w as i64
                                || ny >= h as i64
                                || mask.data[ny as usize * w + nx as usize] < 128
                        });
                if boundary {
                    c = [0, 255, 0];
                } else if m < 128 {
                    // Background: dark blue tint so the mask's extent is visible.
                    c = [c[0] / 2, c[1] / 2, c[2] / 2 + 60];
                }
                sheet.put_pixel((ox + x) as u32, (oy + y) as u32, image::Rgb(c));
            }
        }
    }
    Ok(sheet)
}

#[cfg(test)]
mod stage_tests {
    use super::*;
    use seqavatar_engine::{EntryId, LocalStore, Pipeline, Registry, RunOptions, Store};

    const TINY: &str = "stages:\n  - name: ingest\n    kind: ingest\n    config:\n      dataset: {kind: synthetic, cameras: 3, frames: 4, width: 48, height: 40, supersample: 1, body_grid_spacing: 0.04}\n      past_frames: 2\n";

    fn run_pipeline(text: &str) -> (tempfile::TempDir, EntryReader) {
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::new();
        crate::register(&mut registry);
        let file = dir.path().join("p.yaml");
        std::fs::write(&file, text).unwrap();
        let pipeline = Pipeline::load(&file, &registry, &[]).unwrap();
        let store = LocalStore::open(&dir.path().join("cache")).unwrap();
        let reports =
            seqavatar_engine::run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
        let entry = store
            .open_entry(&EntryId::new("ingest", &reports[0].key))
            .unwrap();
        (dir, entry)
    }

    #[test]
    fn synthetic_ingest_writes_the_documented_schema() {
        let (_dir, entry) = run_pipeline(TINY);
        // 3 cameras: view 1 tests, views 0 and 2 train on all 4 frames; test every 2nd frame.
        assert_eq!(entry.shape("images").unwrap(), vec![10, 40, 48, 3]);
        assert_eq!(entry.shape("masks").unwrap(), vec![10, 40, 48]);
        let split = entry.read::<u8>("image_split").unwrap().data;
        assert_eq!(split.iter().filter(|s| **s == 0).count(), 8);
        assert_eq!(
            entry.read::<i64>("frame_source_id").unwrap().data,
            vec![0, 1, 2, 3]
        );
        assert_eq!(
            entry.attribute("body_model_kind"),
            Some("procedural".into())
        );
        assert_eq!(entry.attribute("num_test_images"), Some(2.into()));

        let model = read_body_model(&entry).unwrap();
        assert_eq!(model.num_joints(), 24);
        let fits = read_body_params(&entry, "body").unwrap();
        let truth = read_body_params(&entry, "gt_body").unwrap();
        assert_eq!(fits.len(), 4);
        assert_eq!(truth.len(), 4);
        assert!(fits[0].pose != truth[0].pose, "the fits are jittered");
        let pose_error: f64 = fits[2]
            .pose
            .iter()
            .zip(&truth[2].pose)
            .map(|(a, b)| (*a - *b).length())
            .sum::<f64>()
            / 24.0;
        assert!(pose_error > 0.01 && pose_error < 0.2, "{pose_error}");

        // 3D keypoints: keypoint j is joint j, the true joint position plus ~1 cm noise.
        let keypoints = read_keypoints_3d(&entry)
            .unwrap()
            .expect("synthetic keypoints");
        assert_eq!(entry.shape("keypoints_3d").unwrap(), vec![4, 24, 3]);
        assert_eq!(keypoints.joints, (0..24).map(Some).collect::<Vec<_>>());
        assert!(keypoints.confidence.iter().all(|c| *c == 1.0));
        let mut squared = 0.0;
        for (f, params) in truth.iter().enumerate() {
            let joints = model.forward(params).unwrap().joints;
            for (j, joint) in joints.iter().enumerate() {
                squared += (keypoints.positions[f * 24 + j] - *joint).length_squared();
            }
        }
        // Mean squared distance of 3 coordinates with sigma 1 cm: 3e-4 m^2.
        let mean_squared = squared / 96.0;
        assert!(
            mean_squared > 1.5e-4 && mean_squared < 5e-4,
            "{mean_squared}"
        );

        // Camera convention: the true pelvis and a point on the torso surface project onto
        // the foreground of every image through the stored K, R, t.
        let k = entry.read::<f64>("camera_K").unwrap().data;
        let r = entry.read::<f64>("camera_R").unwrap().data;
        let t = entry.read::<f64>("camera_t").unwrap().data;
        let views = entry.read::<u32>("image_view").unwrap().data;
        let frames = entry.read::<u32>("image_frame").unwrap().data;
        for image in 0..views.len() {
            let (v, f) = (views[image] as usize, frames[image] as usize);
            let posed = model.forward(&truth[f]).unwrap();
            let x = posed.joints[3];
            let cam: Vec<f64> = (0..3)
                .map(|row| {
                    (0..3)
                        .map(|col| r[v * 9 + row * 3 + col] * x[col])
                        .sum::<f64>()
                        + t[v * 3 + row]
                })
                .collect();
            let u = k[v * 9] * cam[0] / cam[2] + k[v * 9 + 2];
            let w = k[v * 9 + 4] * cam[1] / cam[2] + k[v * 9 + 5];
            let mask = entry
                .read_region::<u8>("masks", &[image as u64, 0, 0], &[1, 40, 48])
                .unwrap();
            let (col, row) = (u.floor() as usize, w.floor() as usize);
            assert!(
                mask.data[row * 48 + col] > 128,
                "image {image}: spine1 at ({u}, {w}) is background"
            );
            // The image border is background (the focal length keeps 4 % margins).
            assert_eq!(mask.data[0], 0);
        }
        // Contact sheet.
        let options =
            PictureOptions::parse(&["split=train".to_string(), "max=3".to_string()]).unwrap();
        let sheet = Ingest
            .draw_picture(&entry, "contact_sheet", &options)
            .unwrap();
        assert_eq!(sheet.dimensions(), (3 * 48, 40));
        assert!(Ingest.draw_picture(&entry, "nope", &options).is_err());
    }

    #[test]
    fn config_errors_name_the_field() {
        let raw = serde_json::json!({"dataset": {"kind": "synthetic", "cameras": 2, "colour": 1}});
        let err = Ingest.resolve_config(&raw).unwrap_err().to_string();
        assert!(err.contains("colour"), "{err}");
        let resolved = Ingest.resolve_config(&serde_json::json!({})).unwrap();
        assert_eq!(resolved["dataset"]["kind"], "synthetic");
        assert_eq!(resolved["dataset"]["cameras"], 8);
        let bad = IngestConfig {
            dataset: DatasetConfig::Synthetic(crate::synthetic::SyntheticConfig {
                frames: 0,
                ..Default::default()
            }),
            ..Default::default()
        };
        let err = format!("{:#}", open_reader(&bad).err().unwrap());
        assert!(err.contains("dataset.frames"), "{err}");
    }

    #[test]
    fn resampling_undistorts_and_rescales_a_known_point() {
        let source = Camera::from_opencv(
            200,
            160,
            [[180.0, 0.0, 101.3], [0.0, 182.0, 78.6], [0.0, 0.0, 1.0]],
            seqavatar_core::rotation::axis_angle_to_matrix(DVec3::new(0.05, -0.1, 0.02)),
            DVec3::new(0.1, 0.0, 2.0),
            [-0.25, 0.08, 0.002, -0.001, 0.0],
        )
        .unwrap();
        let point = DVec3::new(0.8, -0.5, 0.3);
        let captured = source.project_distorted(point).unwrap();
        // A bright 4x4 block centred on the captured (distorted) position.
        let mut rgb = image::RgbImage::new(200, 160);
        let mut mask = image::GrayImage::new(200, 160);
        for y in 0..160u32 {
            for x in 0..200u32 {
                let d = DVec2::new(x as f64 + 0.5, y as f64 + 0.5) - captured;
                if d.x.abs() < 2.0 && d.y.abs() < 2.0 {
                    rgb.put_pixel(x, y, image::Rgb([255, 200, 100]));
                    mask.put_pixel(x, y, image::Luma([255]));
                }
            }
        }
        let mut target = source.rescaled(0.5);
        target.distortion = [0.0; 5];
        let (out_rgb, out_mask) = resample(&SourceImage { rgb, mask }, &source, &target).unwrap();
        // Centroid of the mask in the output lands where the ideal camera projects the point.
        let (mut sum, mut total) = (DVec2::ZERO, 0.0);
        for y in 0..80 {
            for x in 0..100 {
                let m = out_mask[y * 100 + x] as f64;
                sum += DVec2::new(x as f64 + 0.5, y as f64 + 0.5) * m;
                total += m;
            }
        }
        let centroid = sum / total;
        let expected = target.project(point).unwrap();
        assert!(
            (centroid - expected).length() < 0.15,
            "{centroid:?} vs {expected:?}"
        );
        // Distortion moved the point by pixels: the test would notice a missing undistortion.
        assert!((captured * 0.5 - expected).length() > 1.0);
        assert!(out_rgb.iter().any(|&c| c > 0));
        // A mask of the wrong size is an error naming the mask.
        let bad = SourceImage {
            rgb: image::RgbImage::new(200, 160),
            mask: image::GrayImage::new(10, 10),
        };
        assert!(
            resample(&bad, &source, &target)
                .unwrap_err()
                .to_string()
                .contains("mask")
        );
    }
}
