//! The motion entry's layout, both sides of it: [`write_entry`] writes the arrays the stage
//! computed, [`MotionTrack::read`] reads back what a training window gathers.
//!
//! Arrays (per-frame arrays are chunked one frame per chunk, so a run reads only the frames
//! its windows touch; scale slots are ordered largest scale first):
//! - `posed_vertices` f32 `(frame, vertex, xyz)`: world-space posed template.
//! - `joint_rotations` f32 `(frame, joint, row, col)`: root world orientation, then local
//!   joint rotations.
//! - `skeleton_motion` f32 `(frame, scale, joint, xyz)`: axis-angle of `R_t R_{t-s}^-1`.
//! - `vertex_velocity` f32 `(frame, scale, vertex, xyz)`.
//! - `scales` u32 `(scale)` raw frames; `scale_steps` u32 `(scale)` frames on the frame axis.
//! - `skeleton_motion_scale`, `vertex_velocity_scale` f64 `(scale)`: the factor each scale's
//!   block was multiplied by after the `velocity` normalisation (`input_scaling: rms`: one
//!   over the block's RMS over the whole sequence, so every block has RMS 1 on the dataset;
//!   1 for `authors` and `none`); [`read_input_scales`] reads them back.
//! - `frame_source_id` i64 `(frame)` (copied from ingest).
//! - `garment_oracle` f32 `(frame, scale, row, xyz)` and `garment_oracle_scale` f64
//!   `(component)`, only with the stage's `garment_oracle`: the ingest entry's `garment_state`
//!   normalised ([`write_garment_oracle`]), read as extra rows of every skeleton-motion block.
//! - `canonical_vertices` f32 `(vertex, xyz)`; `canonical_knn` u32 and
//!   `canonical_knn_distance` f32 `(vertex, neighbour)`, nearest first, self first.
//! - `camera_K`, `camera_R` f64 `(view, row, col)`, `camera_t` f64 `(view, xyz)`,
//!   `camera_image_size` u32 `(view, hw)` (copied from ingest, for pictures).
//!
//! Attributes: `frame_interval`, `velocity` (the normalisation applied: `authors` is the
//! reference quirk with `multi` 300), `input_scaling`, and the ingest entry's frame
//! axis ([`FrameAxis`]): `past_frames` (copied) and `starts_recording`.
//!
//! A training window `(t, L, S)` is [`window`]`(t, L, scale_steps)`: a gather of rows of
//! `skeleton_motion` and `vertex_velocity` ([`MotionTrack::gather`]). Row `u` of scale step
//! `k` is the delta between frames `u` and `u - k`, so a window reaches `L k` frames back.
//! As in the authors' code, frame indices before the recording's first frame clamp to it;
//! a window that reaches before position 0 of a frame axis that does not start the recording
//! (ingest kept too few `past_frames`) is an error, never a clamp at the edge of what ingest
//! kept.

use anyhow::Context;
use seqavatar_engine::{EntryReader, EntryWriter};

use seqavatar_knn::KnnGraph;
use serde::{Deserialize, Serialize};

/// Why motion-context inputs were rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ContextError {
    #[error("`scales` is empty: at least one sampling scale is needed")]
    NoScales,
    #[error("`sampling_interval` must be at least 1")]
    ZeroInterval,
    #[error("scale {scale} is not a positive multiple of the sampling interval {interval}")]
    ScaleNotMultiple { scale: u32, interval: u32 },
    #[error("scale {scale} is listed twice in `scales`")]
    DuplicateScale { scale: u32 },
    #[error("{what}: expected {expected} values, got {got}")]
    Shape {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("{what} is not finite at frame {frame}")]
    NotFinite { what: &'static str, frame: usize },
}

/// How vertex displacements become velocities.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum VelocityNormalisation {
    /// The paper: `(T[t] - T[t - s]) / s`, `s` in raw video frames (metres per raw frame).
    PerScale,
    /// The reference code: every scale's displacement is multiplied by `multi` and divided by
    /// the smallest scale in sampled frames (`min(S) / interval`), whatever its own scale.
    /// `multi` is 300 for I3D-Human and DNA-Rendering, 1 for ZJU-MoCap.
    Reference { multi: f64 },
}

/// How the motion-context input blocks (skeleton motion at each scale, vertex velocity at
/// each scale) are scaled before the networks see them (`input_scaling` in the motion
/// config).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InputScaling {
    /// Each block divided by its RMS over the whole sequence (every frame, joint or vertex
    /// and coordinate), after the `velocity` normalisation: every block has RMS 1 on the
    /// dataset. The factors are recorded in the motion entry (`skeleton_motion_scale`,
    /// `vertex_velocity_scale`) and applied unchanged to other pose sequences
    /// (`pipeline render`).
    #[default]
    Rms,
    /// The authors' code: velocities are displacements times [`AUTHORS_MULTI`] divided by
    /// the smallest scale in sampled frames ([`VelocityNormalisation::Reference`]), skeleton
    /// motion as computed.
    Authors,
    /// The blocks as the `velocity` normalisation leaves them.
    None,
}

/// The authors' velocity multiplier (I3D-Human and DNA-Rendering configs).
pub const AUTHORS_MULTI: f64 = 300.0;

/// Per scale slot, the RMS of a `(frame, scale, items, 3)` array over frames, items and
/// coordinates (f64 sums).
pub fn block_rms(values: &[f32], n_scales: usize, items: usize) -> Vec<f64> {
    let row = n_scales * items * 3;
    let frames = values.len().checked_div(row).unwrap_or(0);
    (0..n_scales)
        .map(|slot| {
            let mut sum = 0.0;
            for frame in 0..frames {
                let at = (frame * n_scales + slot) * items * 3;
                sum += values[at..at + items * 3]
                    .iter()
                    .map(|&x| f64::from(x) * f64::from(x))
                    .sum::<f64>();
            }
            let count = frames * items * 3;
            if count == 0 {
                0.0
            } else {
                (sum / count as f64).sqrt()
            }
        })
        .collect()
}

/// Multiplies every `(frame, scale)` block of a `(frame, scale, items, 3)` array by
/// `factors[scale]`.
pub fn scale_blocks(values: &mut [f32], items: usize, factors: &[f64]) {
    let block = items * 3;
    if block == 0 || factors.is_empty() {
        return;
    }
    for (index, chunk) in values.chunks_exact_mut(block).enumerate() {
        let factor = factors[index % factors.len()];
        for x in chunk {
            *x = (f64::from(*x) * factor) as f32;
        }
    }
}

/// Validated sampling scales: raw scales (largest first, the reference flatten order) and
/// their steps in sampled frames.
#[derive(Clone, Debug, PartialEq)]
pub struct Scales {
    /// Scales in raw video frames, largest first.
    pub raw: Vec<u32>,
    /// The same scales in sampled frames (`raw / interval`).
    pub steps: Vec<usize>,
    /// The sampling interval (raw frames between consecutive body fits).
    pub interval: u32,
}

impl Scales {
    /// Validates `raw` scales against the sampling interval and sorts them largest first.
    pub fn new(raw: &[u32], interval: u32) -> Result<Self, ContextError> {
        if interval == 0 {
            return Err(ContextError::ZeroInterval);
        }
        if raw.is_empty() {
            return Err(ContextError::NoScales);
        }
        let mut sorted = raw.to_vec();
        sorted.sort_unstable_by(|a, b| b.cmp(a));
        for pair in sorted.windows(2) {
            if pair[0] == pair[1] {
                return Err(ContextError::DuplicateScale { scale: pair[0] });
            }
        }
        for &scale in &sorted {
            if scale == 0 || scale % interval != 0 {
                return Err(ContextError::ScaleNotMultiple { scale, interval });
            }
        }
        let steps = sorted.iter().map(|&s| (s / interval) as usize).collect();
        Ok(Self {
            raw: sorted,
            steps,
            interval,
        })
    }

    pub fn len(&self) -> usize {
        self.raw.len()
    }

    /// Always false: construction rejects an empty list.
    pub fn is_empty(&self) -> bool {
        self.raw.is_empty()
    }

    /// The factor each scale's displacement is multiplied by to become a velocity.
    pub fn velocity_factors(&self, normalisation: VelocityNormalisation) -> Vec<f64> {
        match normalisation {
            VelocityNormalisation::PerScale => {
                self.raw.iter().map(|&s| 1.0 / f64::from(s)).collect()
            }
            VelocityNormalisation::Reference { multi } => {
                let smallest = *self.steps.iter().min().expect("scales are never empty");
                vec![multi / smallest as f64; self.len()]
            }
        }
    }
}

/// The frames a `(t, L, scales)` window reads, as a gather.
///
/// `frames[l * n_scales + s]` is the row of the per-(frame, scale) arrays to read for
/// element `l` (0 = the most recent delta) of scale slot `s`: `max(t - l * step_s, 0)`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Window {
    pub length: usize,
    pub n_scales: usize,
    pub frames: Vec<usize>,
}

impl Window {
    /// The frame to read for window element `l` and scale slot `s`.
    pub fn frame(&self, l: usize, s: usize) -> usize {
        self.frames[l * self.n_scales + s]
    }
}

/// The gather indices of the paper's window at frame `frame`, length `length`, for scales
/// given as steps in sampled frames (as stored in the motion entry, largest first).
pub fn window(frame: usize, length: usize, steps: &[usize]) -> Window {
    let mut frames = Vec::with_capacity(length * steps.len());
    for l in 0..length {
        for &step in steps {
            frames.push(frame.saturating_sub(l.saturating_mul(step)));
        }
    }
    Window {
        length,
        n_scales: steps.len(),
        frames,
    }
}

/// Per-frame motion arrays, row-major, frame-major.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionArrays {
    pub num_frames: usize,
    pub num_vertices: usize,
    pub num_joints: usize,
    /// `(frame, vertex, 3)` posed world-space template vertices.
    pub posed_vertices: Vec<f32>,
    /// `(frame, joint, 3, 3)` rotation matrices, row-major: joint 0 is the root's world
    /// orientation `R(Rh) R(pose_0)`, the others are local joint rotations.
    pub joint_rotations: Vec<f32>,
    /// `(frame, scale, joint, 3)` axis-angle of `R_t R_{t-s}^-1`.
    pub skeleton_motion: Vec<f32>,
    /// `(frame, scale, vertex, 3)` vertex velocity.
    pub vertex_velocity: Vec<f32>,
}

/// The factors each motion-context input block is multiplied by, per scale slot (largest
/// scale first), on top of the velocity normalisation.
#[derive(Clone, Debug, PartialEq)]
pub struct InputScales {
    pub skeleton_motion: Vec<f64>,
    pub vertex_velocity: Vec<f64>,
}

impl InputScales {
    /// No scaling.
    pub fn ones(n_scales: usize) -> Self {
        Self {
            skeleton_motion: vec![1.0; n_scales],
            vertex_velocity: vec![1.0; n_scales],
        }
    }

    /// `1 / RMS` of every block of `motion` ([`InputScaling::Rms`]); 1 for a block that is
    /// zero throughout (a still sequence, or one frame).
    pub fn rms_of(motion: &MotionArrays, n_scales: usize) -> Self {
        let inverse =
            |rms: Vec<f64>| -> Vec<f64> { rms.into_iter().map(unit_rms_factor).collect() };
        Self {
            skeleton_motion: inverse(block_rms(
                &motion.skeleton_motion,
                n_scales,
                motion.num_joints,
            )),
            vertex_velocity: inverse(block_rms(
                &motion.vertex_velocity,
                n_scales,
                motion.num_vertices,
            )),
        }
    }

    /// The scales of `scaling` for `motion`: RMS factors, or ones.
    pub fn for_scaling(scaling: InputScaling, motion: &MotionArrays, n_scales: usize) -> Self {
        match scaling {
            InputScaling::Rms => Self::rms_of(motion, n_scales),
            InputScaling::Authors | InputScaling::None => Self::ones(n_scales),
        }
    }
}

impl MotionArrays {
    /// Multiplies the skeleton-motion and vertex-velocity blocks by `scales`.
    pub fn scale_inputs(&mut self, scales: &InputScales) {
        scale_blocks(
            &mut self.skeleton_motion,
            self.num_joints,
            &scales.skeleton_motion,
        );
        scale_blocks(
            &mut self.vertex_velocity,
            self.num_vertices,
            &scales.vertex_velocity,
        );
    }
}

/// Where a frame axis sits in its recording, from the ingest entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameAxis {
    /// Frames (axis steps) ingest was asked to keep before its first used frame.
    pub past_frames: usize,
    /// Whether position 0 is the recording's first frame on this axis (ingest reached the
    /// start), so that windows clamp to it; otherwise the recording has frames before
    /// position 0 that are not in the entry.
    pub starts_recording: bool,
}

impl FrameAxis {
    /// A recording read from its first frame (a pose file): windows clamp at position 0.
    pub const FROM_START: FrameAxis = FrameAxis {
        past_frames: 0,
        starts_recording: true,
    };

    /// The frame axis of an ingest entry (attributes `past_frames`, `frame_interval`,
    /// `first_frame_index`); errors name the entry and the attribute.
    pub fn of_ingest(ingest: &EntryReader) -> anyhow::Result<Self> {
        let count = |key: &str| crate::count_attribute(ingest, key);
        let interval = count("frame_interval")?;
        anyhow::ensure!(
            interval >= 1,
            "entry {}: attribute `frame_interval` is 0",
            ingest.location()
        );
        Ok(Self {
            past_frames: usize::try_from(count("past_frames")?)?,
            starts_recording: count("first_frame_index")? < interval,
        })
    }

    /// The frame axis stored in a motion entry (attributes `past_frames`, `starts_recording`).
    pub fn of_motion(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        let past_frames = crate::count_attribute(entry, "past_frames")?;
        let starts_recording = crate::attribute(entry, "starts_recording")?
            .as_bool()
            .ok_or_else(|| {
                anyhow::anyhow!("entry {location}: attribute `starts_recording` is not a boolean")
            })?;
        Ok(Self {
            past_frames: usize::try_from(past_frames)?,
            starts_recording,
        })
    }
}

/// What the motion stage computed, to be written by [`write_entry`].
#[derive(Clone, Copy)]
pub struct MotionEntry<'a> {
    pub motion: &'a MotionArrays,
    pub scales: &'a Scales,
    pub canonical: &'a [[f32; 3]],
    pub graph: &'a KnnGraph,
    /// The ingest entry's `frame_interval` (raw frames per sampled frame).
    pub frame_interval: u32,
    /// The velocity normalisation applied (after `input_scaling: authors` chose it).
    pub velocity: VelocityNormalisation,
    pub input_scaling: InputScaling,
    /// The factors each scale's blocks were multiplied by.
    pub input_scales: &'a InputScales,
    /// The ingest entry's frame axis.
    pub axis: FrameAxis,
}

/// Writes the motion entry's arrays and attributes; `ingest` provides the arrays copied
/// from it (`frame_source_id`, cameras).
pub fn write_entry(
    out: &EntryWriter,
    ingest: &EntryReader,
    entry: &MotionEntry<'_>,
) -> anyhow::Result<()> {
    let MotionEntry {
        motion,
        scales,
        canonical,
        graph,
        frame_interval,
        velocity,
        input_scaling,
        input_scales,
        axis,
    } = *entry;
    let (f, v, j, s) = (
        motion.num_frames as u64,
        motion.num_vertices as u64,
        motion.num_joints as u64,
        scales.len() as u64,
    );
    out.write_array(
        "posed_vertices",
        &["frame", "vertex", "xyz"],
        &[f, v, 3],
        &[1, v, 3],
        &motion.posed_vertices,
    )?;
    out.write_array(
        "joint_rotations",
        &["frame", "joint", "row", "col"],
        &[f, j, 3, 3],
        &[1, j, 3, 3],
        &motion.joint_rotations,
    )?;
    out.write_array(
        "skeleton_motion",
        &["frame", "scale", "joint", "xyz"],
        &[f, s, j, 3],
        &[1, s, j, 3],
        &motion.skeleton_motion,
    )?;
    out.write_array(
        "vertex_velocity",
        &["frame", "scale", "vertex", "xyz"],
        &[f, s, v, 3],
        &[1, s, v, 3],
        &motion.vertex_velocity,
    )?;
    out.write_whole("scales", &["scale"], &[s], &scales.raw)?;
    let steps: Vec<u32> = scales.steps.iter().map(|&k| k as u32).collect();
    out.write_whole("scale_steps", &["scale"], &[s], &steps)?;
    let flat: Vec<f32> = canonical.iter().flatten().copied().collect();
    out.write_whole("canonical_vertices", &["vertex", "xyz"], &[v, 3], &flat)?;
    let k = graph.k as u64;
    out.write_whole(
        "canonical_knn",
        &["vertex", "neighbour"],
        &[v, k],
        &graph.indices,
    )?;
    out.write_whole(
        "canonical_knn_distance",
        &["vertex", "neighbour"],
        &[v, k],
        &graph.distances,
    )?;
    if ingest.has_array("frame_source_id") {
        let ids = ingest.read::<i64>("frame_source_id")?;
        anyhow::ensure!(
            ids.len() as u64 == f,
            "entry {}: `frame_source_id` has {} frames, the body parameters {f}",
            ingest.location(),
            ids.len()
        );
        out.write_array("frame_source_id", &["frame"], &[f], &[f.max(1)], &ids.data)?;
    }
    crate::ingest::copy_cameras(out, ingest, true)?;
    out.set_attribute("frame_interval", frame_interval.into())?;
    out.write_whole(
        "skeleton_motion_scale",
        &["scale"],
        &[s],
        &input_scales.skeleton_motion,
    )?;
    out.write_whole(
        "vertex_velocity_scale",
        &["scale"],
        &[s],
        &input_scales.vertex_velocity,
    )?;
    out.set_attribute("velocity", serde_json::to_value(velocity)?)?;
    out.set_attribute("input_scaling", serde_json::to_value(input_scaling)?)?;
    out.set_attribute("past_frames", axis.past_frames.into())?;
    out.set_attribute("starts_recording", axis.starts_recording.into())?;
    Ok(())
}

/// The velocity normalisation and input scales a motion entry's arrays were made with, to
/// compute matching arrays for other pose sequences (`pipeline render`). Entries made
/// before `input_scaling` existed have no scale arrays: ones.
pub fn read_input_scales(
    entry: &EntryReader,
) -> anyhow::Result<(VelocityNormalisation, InputScales)> {
    let location = entry.location();
    let velocity = entry
        .attribute("velocity")
        .or_else(|| entry.config().get("velocity").cloned())
        .ok_or_else(|| {
            anyhow::anyhow!("motion entry {location}: attribute `velocity` is missing")
        })?;
    let velocity: VelocityNormalisation = serde_json::from_value(velocity)
        .with_context(|| format!("motion entry {location}: attribute `velocity`"))?;
    let n = entry.read::<u32>("scales")?.data.len();
    let read = |name: &str| -> anyhow::Result<Vec<f64>> {
        if !entry.has_array(name) {
            return Ok(vec![1.0; n]);
        }
        let values = entry.read::<f64>(name)?.data;
        anyhow::ensure!(
            values.len() == n && values.iter().all(|v| v.is_finite() && *v > 0.0),
            "motion entry {location}: array `{name}` must hold {n} positive factors, got {values:?}"
        );
        Ok(values)
    };
    Ok((
        velocity,
        InputScales {
            skeleton_motion: read("skeleton_motion_scale")?,
            vertex_velocity: read("vertex_velocity_scale")?,
        },
    ))
}

/// The factor that scales values of RMS `rms` to RMS 1: `1 / rms`, or 1 where the values are
/// zero throughout (or their RMS is not finite).
fn unit_rms_factor(rms: f64) -> f64 {
    if rms > 0.0 && rms.is_finite() {
        1.0 / rms
    } else {
        1.0
    }
}

/// Whether the motion entry holds the garment oracle ([`write_garment_oracle`]).
pub fn has_garment_oracle(entry: &EntryReader) -> bool {
    entry.has_array("garment_oracle")
}

/// Writes the garment oracle: `garment_oracle` f32 `(frame, scale, row, xyz)`, the ingest
/// entry's `garment_state` with each component divided by its RMS over the sequence (1 for a
/// component that is zero throughout), zero-padded to whole rows of 3 and repeated for every
/// scale slot, and the factors as `garment_oracle_scale` f64 `(component)`. [`MotionTrack::read`]
/// appends its rows to every skeleton-motion block, so the rows (c)-(e) read the garment's
/// true state through the skeleton-motion encoder: the ablation's upper bound.
pub fn write_garment_oracle(
    out: &EntryWriter,
    states: &[[f64; crate::ingest::GARMENT_STATE_COMPONENTS]],
    n_scales: usize,
) -> anyhow::Result<()> {
    const C: usize = crate::ingest::GARMENT_STATE_COMPONENTS;
    let rows = C.div_ceil(3);
    let factors: Vec<f64> = (0..C)
        .map(|c| {
            let mean_square =
                states.iter().map(|s| s[c] * s[c]).sum::<f64>() / states.len().max(1) as f64;
            unit_rms_factor(mean_square.sqrt())
        })
        .collect();
    let mut values = Vec::with_capacity(states.len() * n_scales * rows * 3);
    for state in states {
        for _ in 0..n_scales {
            values.extend((0..rows * 3).map(|c| {
                if c < C {
                    (state[c] * factors[c]) as f32
                } else {
                    0.0
                }
            }));
        }
    }
    let (f, s, r) = (states.len() as u64, n_scales as u64, rows as u64);
    out.write_array(
        "garment_oracle",
        &["frame", "scale", "row", "xyz"],
        &[f, s, r, 3],
        &[1, s, r, 3],
        &values,
    )?;
    out.write_whole(
        "garment_oracle_scale",
        &["component"],
        &[C as u64],
        &factors,
    )?;
    Ok(())
}

/// The motion entry's arrays a window gathers from.
#[derive(Clone, Debug)]
pub struct MotionTrack {
    pub num_frames: usize,
    /// Rows of every skeleton-motion block: the body's joints, then `garment_rows`.
    pub num_joints: usize,
    /// Rows of the garment oracle ([`write_garment_oracle`]) at the end of every
    /// skeleton-motion block; 0 without one.
    pub garment_rows: usize,
    pub num_vertices: usize,
    /// Raw scales, largest first.
    pub scales: Vec<u32>,
    /// The same scales in steps on the frame axis.
    pub scale_steps: Vec<usize>,
    /// `(frame, scale, joint, 3)`, the garment oracle's rows last.
    pub skeleton_motion: Vec<f32>,
    /// `(frame, scale, vertex, 3)`.
    pub vertex_velocity: Vec<f32>,
    /// Where the frame axis sits in its recording.
    pub axis: FrameAxis,
}

impl MotionTrack {
    /// The body's joints: the rows of a skeleton-motion block before the garment oracle's.
    pub fn body_joints(&self) -> usize {
        self.num_joints - self.garment_rows
    }

    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        let scales = entry.read::<u32>("scales")?.data;
        let steps = entry.read::<u32>("scale_steps")?.data;
        anyhow::ensure!(
            !scales.is_empty() && steps.len() == scales.len(),
            "entry {location}: `scales` ({}) and `scale_steps` ({}) must be non-empty and equally long",
            scales.len(),
            steps.len()
        );
        let skeleton = entry.read::<f32>("skeleton_motion")?;
        let velocity = entry.read::<f32>("vertex_velocity")?;
        let s = scales.len();
        anyhow::ensure!(
            skeleton.shape.len() == 4 && skeleton.shape[1] == s && skeleton.shape[3] == 3,
            "entry {location}: array `skeleton_motion` has shape {:?}, expected (frame, {s}, joint, 3)",
            skeleton.shape
        );
        let (f, j) = (skeleton.shape[0], skeleton.shape[2]);
        anyhow::ensure!(
            velocity.shape.len() == 4
                && velocity.shape[0] == f
                && velocity.shape[1] == s
                && velocity.shape[3] == 3,
            "entry {location}: array `vertex_velocity` has shape {:?}, expected ({f}, {s}, vertex, 3)",
            velocity.shape
        );
        let oracle = if has_garment_oracle(entry) {
            let oracle = entry.read::<f32>("garment_oracle")?;
            anyhow::ensure!(
                oracle.shape.len() == 4
                    && oracle.shape[0] == f
                    && oracle.shape[1] == s
                    && oracle.shape[2] >= 1
                    && oracle.shape[3] == 3
                    && j >= 1,
                "entry {location}: array `garment_oracle` has shape {:?}, expected ({f}, {s}, row, 3) beside {j} joints",
                oracle.shape
            );
            Some(oracle)
        } else {
            None
        };
        for (name, data) in [
            ("skeleton_motion", &skeleton.data),
            ("vertex_velocity", &velocity.data),
            (
                "garment_oracle",
                oracle.as_ref().map_or(&Vec::new(), |o| &o.data),
            ),
        ] {
            if let Some(bad) = data.iter().position(|v| !v.is_finite()) {
                anyhow::bail!("entry {location}: array `{name}` has a non-finite value at {bad}");
            }
        }
        let (garment_rows, skeleton_motion) = match oracle {
            None => (0, skeleton.data),
            Some(oracle) => {
                let r = oracle.shape[2];
                let blocks = skeleton.data.chunks_exact(j * 3);
                let joined = blocks
                    .zip(oracle.data.chunks_exact(r * 3))
                    .flat_map(|(joints, garment)| joints.iter().chain(garment).copied())
                    .collect();
                (r, joined)
            }
        };
        Ok(Self {
            num_frames: f,
            num_joints: j + garment_rows,
            garment_rows,
            num_vertices: velocity.shape[2],
            scales,
            scale_steps: steps.iter().map(|&k| k as usize).collect(),
            skeleton_motion,
            vertex_velocity: velocity.data,
            axis: FrameAxis::of_motion(entry)?,
        })
    }

    /// Slots (indices into `scales`) of the wanted raw scales, in the order given.
    pub fn slots(&self, wanted: &[u32]) -> anyhow::Result<Vec<usize>> {
        wanted
            .iter()
            .map(|w| {
                self.scales.iter().position(|s| s == w).ok_or_else(|| {
                    anyhow::anyhow!("scale {w} is not in the motion entry ({:?})", self.scales)
                })
            })
            .collect()
    }

    /// The gathered window of frame `frame`: skeleton motion `(L, S', J, 3)` and vertex
    /// velocity `(L, S', V, 3)` for the scale slots `slots`, `l = 0` the most recent delta.
    ///
    /// A window reaching before position 0 ([`MotionTrack::reach`] above `frame`) clamps
    /// there only when position 0 starts the recording; otherwise it is an error.
    pub fn gather(
        &self,
        frame: usize,
        length: usize,
        slots: &[usize],
    ) -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
        anyhow::ensure!(
            frame < self.num_frames,
            "frame {frame} is outside the motion track ({} frames)",
            self.num_frames
        );
        if let Some(&bad) = slots.iter().find(|&&s| s >= self.scale_steps.len()) {
            anyhow::bail!(
                "scale slot {bad} is not in the motion track ({} scales)",
                self.scale_steps.len()
            );
        }
        let reach = self.reach(length, slots);
        if reach > frame && !self.axis.starts_recording {
            anyhow::bail!(
                "frame {frame}: the motion window reaches {reach} frames back (sequence length \
                 {length} x largest scale step {}), before the first frame of the frame axis, \
                 and the recording starts earlier (ingest kept past_frames = {}): ingest with \
                 past_frames >= {reach} or a later first frame",
                reach / length.max(1),
                self.axis.past_frames
            );
        }
        let steps: Vec<usize> = slots.iter().map(|&s| self.scale_steps[s]).collect();
        let window = window(frame, length, &steps);
        let (s_all, j, v) = (self.scales.len(), self.num_joints, self.num_vertices);
        let mut skeleton = Vec::with_capacity(length * slots.len() * j * 3);
        let mut velocity = Vec::with_capacity(length * slots.len() * v * 3);
        for l in 0..length {
            for (k, &slot) in slots.iter().enumerate() {
                let row = window.frame(l, k);
                let at = (row * s_all + slot) * j * 3;
                skeleton.extend_from_slice(&self.skeleton_motion[at..at + j * 3]);
                let at = (row * s_all + slot) * v * 3;
                velocity.extend_from_slice(&self.vertex_velocity[at..at + v * 3]);
            }
        }
        Ok((skeleton, velocity))
    }

    /// How many frames back a window of `length` at the scale `slots` reaches: `length` x
    /// the largest step (each row is a delta against the frame one step earlier).
    pub fn reach(&self, length: usize, slots: &[usize]) -> usize {
        let largest = slots
            .iter()
            .filter_map(|&s| self.scale_steps.get(s))
            .copied()
            .max()
            .unwrap_or(0);
        length.saturating_mul(largest)
    }

    /// Checks that windows of `length` at the scale `slots` of every frame the ingest entry
    /// uses stay inside the recording as the entry holds it: their reach must not exceed the
    /// ingest `past_frames`, unless the entry starts at the recording's first frame (then
    /// windows clamp there, as the authors' code does). The error names both values.
    pub fn check_window(&self, length: usize, slots: &[usize]) -> anyhow::Result<()> {
        let reach = self.reach(length, slots);
        if reach > self.axis.past_frames && !self.axis.starts_recording {
            anyhow::bail!(
                "the motion window reaches {reach} frames back (sequence_length {length} x \
                 largest scale step {}), but the ingest entry holds past_frames = {} before its \
                 first used frame and the recording starts earlier: set the ingest \
                 `past_frames` to at least {reach}, or shorten `sequence_length` or `scales`",
                reach / length.max(1),
                self.axis.past_frames
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Six frames, one joint and one vertex, raw scales 2 and 1 (steps 2 and 1); each value
    /// encodes its row: `10 frame + scale slot` (skeleton), negated (velocity).
    fn track(axis: FrameAxis) -> MotionTrack {
        let (f, s) = (6, 2);
        let skeleton: Vec<f32> = (0..f * s)
            .flat_map(|row| [(10 * (row / s) + row % s) as f32; 3])
            .collect();
        MotionTrack {
            num_frames: f,
            num_joints: 1,
            garment_rows: 0,
            num_vertices: 1,
            scales: vec![2, 1],
            scale_steps: vec![2, 1],
            vertex_velocity: skeleton.iter().map(|v| -v).collect(),
            skeleton_motion: skeleton,
            axis,
        }
    }

    fn rows(values: &[f32]) -> Vec<f32> {
        values.iter().step_by(3).copied().collect()
    }

    /// At the first frames of a recording the window clamps to frame 0 (the authors'
    /// `max(t - l k, 0)`), with every row a gather of the stored deltas.
    #[test]
    fn windows_clamp_at_the_recording_start() {
        let t = track(FrameAxis::FROM_START);
        // Frame 1, L = 3, both scales: rows (1, 1), (0, 0), (0, 0) for steps (2, 1).
        let (skeleton, velocity) = t.gather(1, 3, &[0, 1]).unwrap();
        assert_eq!(rows(&skeleton), vec![10.0, 11.0, 0.0, 1.0, 0.0, 1.0]);
        assert_eq!(rows(&velocity), vec![-10.0, -11.0, -0.0, -1.0, -0.0, -1.0]);
        let (skeleton, _) = t.gather(0, 2, &[1]).unwrap();
        assert_eq!(rows(&skeleton), vec![1.0, 1.0]);
        // Far enough in, nothing clamps: frame 5, L = 2, step 2: rows 5 and 3.
        let (skeleton, _) = t.gather(5, 2, &[0]).unwrap();
        assert_eq!(rows(&skeleton), vec![50.0, 30.0]);
        assert_eq!(t.reach(3, &[0, 1]), 6);
        // Any window is fine when the axis starts the recording.
        t.check_window(8, &[0, 1]).unwrap();
        assert!(t.gather(6, 1, &[0]).is_err());
        assert!(t.gather(1, 1, &[2]).is_err());
    }

    /// When the recording starts before the axis, a window reaching before position 0 is an
    /// error naming the frame and the values, never a clamp at the edge of what ingest kept.
    #[test]
    fn windows_never_clamp_at_the_edge_of_what_ingest_kept() {
        let t = track(FrameAxis {
            past_frames: 2,
            starts_recording: false,
        });
        let error = t.gather(3, 2, &[0, 1]).unwrap_err().to_string();
        assert!(
            error.contains("frame 3") && error.contains("reaches 4 frames back"),
            "{error}"
        );
        assert!(error.contains("past_frames = 2"), "{error}");
        // Frame 4 reaches exactly frame 0: rows 4 and 2 at step 2, 4 and 3 at step 1.
        let (skeleton, _) = t.gather(4, 2, &[0, 1]).unwrap();
        assert_eq!(rows(&skeleton), vec![40.0, 41.0, 20.0, 31.0]);
        // The config check names both values.
        let error = t.check_window(2, &[0, 1]).unwrap_err().to_string();
        assert!(
            error.contains("reaches 4 frames back")
                && error.contains("sequence_length 2")
                && error.contains("past_frames = 2"),
            "{error}"
        );
        t.check_window(1, &[0, 1]).unwrap();
        t.check_window(2, &[1]).unwrap();
    }
}
