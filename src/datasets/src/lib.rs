//! The multi-view human datasets: the reader interface every dataset implements
//! ([`DatasetReader`]), the readers (ZJU-MoCap, I3D-Human, DNA-Rendering and the SMPL /
//! SMPL-X dense `.npz` body-model loader), the built-in synthetic scene, and the one place
//! that opens a reader for a dataset config ([`open_reader`]).
//!
//! A dataset reader only answers questions about its capture at full resolution (cameras
//! with their distortion, images, masks, body fits). The ingest stage decides which views and
//! frames to read, undistorts and rescales every image the same way, and writes the arrays of
//! `seqavatar_schema::ingest`.

pub mod body_model;
pub mod common;
pub mod dna_rendering;
pub mod i3d_human;
pub mod smc;
pub mod sources;
pub mod synthetic;
pub mod zju_mocap;

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};

use seqavatar_core::body::{BodyModel, BodyParams};

pub use seqavatar_schema::ingest::{GarmentRegion, Keypoints3d, SourceCamera};

pub use seqavatar_formats::resample::SourceImage;

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

/// A garment's particles at one frame: as simulated, and its static drape under the same
/// pose (world space, metres, one position per particle in both), and the exact state of the
/// dynamics that moved it off the drape, where the generator has one.
#[derive(Clone, Debug, PartialEq)]
pub struct GarmentHistory {
    pub simulated: Vec<seqavatar_core::glam::DVec3>,
    pub drape: Vec<seqavatar_core::glam::DVec3>,
    /// The garment's dynamic state, [`GARMENT_STATE_COMPONENTS`] values (the history scene's
    /// oscillator: [`synthetic::garment::Swing::in_body_frame`]); what a perfect motion
    /// context would have to infer, the input of the ablation's oracle row.
    pub state: [f64; GARMENT_STATE_COMPONENTS],
}

pub use seqavatar_schema::ingest::GARMENT_STATE_COMPONENTS;

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
    /// The temporal hold-out: frames never trained on. They are taken out of
    /// `train_frames`, and every view of the split (training and test views) gets a test
    /// image at each of them. `None` (every dataset's default) is the paper's protocol alone:
    /// held-out cameras on training frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out_frames: Option<FrameRange>,
}

impl Split {
    /// The split of a capture sampled at every frame: training on every frame below `end`
    /// (`None` = up to the last frame), testing on every `test_step`-th of them, no hold-out.
    pub fn first_frames(
        train_views: Vec<usize>,
        test_views: Vec<usize>,
        end: Option<usize>,
        test_step: usize,
    ) -> Self {
        Self {
            train_views,
            test_views,
            train_frames: FrameRange {
                start: 0,
                end,
                step: 1,
            },
            test_frames: FrameRange {
                start: 0,
                end,
                step: test_step,
            },
            frame_interval: 1,
            held_out_frames: None,
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
    Synthetic(synthetic::SyntheticConfig),
    ZjuMocap(ZjuMocapConfig),
    I3dHuman(I3dHumanConfig),
    DnaRendering(DnaRenderingConfig),
}

impl Default for DatasetConfig {
    fn default() -> Self {
        Self::Synthetic(synthetic::SyntheticConfig::default())
    }
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
    /// The dataset's own number for frame-list index `frame` (file name number; by default
    /// the index itself).
    fn frame_id(&self, frame: usize) -> i64 {
        frame as i64
    }
    /// The split docs/method.md prescribes for this sequence.
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
    /// The garment at frame-list index `frame` as simulated and as its static drape (what the
    /// pose alone determines), particle for particle, where the dataset knows both (the
    /// synthetic history scene). Their difference is the history-only displacement the
    /// stage records per frame.
    fn garment_history(&self, _frame: usize) -> anyhow::Result<Option<GarmentHistory>> {
        Ok(None)
    }
    /// Image and mask of camera `view` at frame-list index `frame`, full resolution.
    fn read_image(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage>;
    /// Where this capture's garment region comes from; `None` (the default) when it has
    /// none. When `Some`, [`Self::read_image_with_garment`] returns a garment mask with every
    /// image.
    fn garment_region(&self) -> Option<GarmentRegion> {
        None
    }
    /// [`Self::read_image`] and, where [`Self::garment_region`] is `Some`, the garment
    /// region's mask of the same image (0 outside .. 255 inside, soft values allowed, within
    /// the foreground mask), full resolution.
    fn read_image_with_garment(
        &self,
        view: usize,
        frame: usize,
    ) -> anyhow::Result<(SourceImage, Option<image::GrayImage>)> {
        Ok((self.read_image(view, frame)?, None))
    }
}

/// Opens the reader for a dataset config: generates the synthetic scene or opens a
/// file-based dataset (ZJU-MoCap, I3D-Human, DNA-Rendering). The only place readers are opened.
pub fn open_reader(
    dataset: &DatasetConfig,
    body_model: Option<&Path>,
) -> anyhow::Result<Box<dyn DatasetReader>> {
    match dataset {
        DatasetConfig::Synthetic(synthetic) => {
            let scene = synthetic::SyntheticScene::generate(synthetic)
                .context("generating the synthetic scene")?;
            Ok(Box::new(scene))
        }
        DatasetConfig::ZjuMocap(c) => Ok(Box::new(zju_mocap::ZjuMocap::open(&c.root, body_model)?)),
        DatasetConfig::I3dHuman(c) => Ok(Box::new(i3d_human::I3dHuman::open(
            &c.root,
            &c.sequence,
            body_model,
        )?)),
        DatasetConfig::DnaRendering(c) => Ok(Box::new(dna_rendering::DnaRendering::open(
            &c.main_file,
            c.annotations_file.as_deref(),
            body_model,
        )?)),
    }
}
