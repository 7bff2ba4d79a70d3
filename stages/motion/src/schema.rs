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
//! - `canonical_vertices` f32 `(vertex, xyz)`; `canonical_knn` u32 and
//!   `canonical_knn_distance` f32 `(vertex, neighbour)`, nearest first, self first.
//! - `camera_K`, `camera_R` f64 `(view, row, col)`, `camera_t` f64 `(view, xyz)`,
//!   `camera_image_size` u32 `(view, hw)` (copied from ingest, for pictures).
//!
//! Attributes: `frame_interval`, `velocity` (the normalisation applied: `authors` is the
//! reference quirk with `multi` 300), `input_scaling`, and the ingest entry's frame
//! axis ([`FrameAxis`]): `past_frames` (copied) and `starts_recording`.
//!
//! A training window `(t, L, S)` is [`crate::window`]`(t, L, scale_steps)`: a gather of rows of
//! `skeleton_motion` and `vertex_velocity` ([`MotionTrack::gather`]). Row `u` of scale step
//! `k` is the delta between frames `u` and `u - k`, so a window reaches `L k` frames back.
//! As in the authors' code, frame indices before the recording's first frame clamp to it;
//! a window that reaches before position 0 of a frame axis that does not start the recording
//! (ingest kept too few `past_frames`) is an error, never a clamp at the edge of what ingest
//! kept.

use anyhow::Context;
use seqavatar_engine::{EntryReader, EntryWriter};

use crate::compute::{InputScales, MotionArrays};
use crate::context::{InputScaling, Scales, VelocityNormalisation};
use seqavatar_knn::KnnGraph;

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
        let count = |key: &str| -> anyhow::Result<u64> {
            ingest
                .attribute(key)
                .ok_or_else(|| {
                    anyhow::anyhow!("entry {}: attribute `{key}` is missing", ingest.location())
                })?
                .as_u64()
                .ok_or_else(|| {
                    anyhow::anyhow!(
                        "entry {}: attribute `{key}` is not a count",
                        ingest.location()
                    )
                })
        };
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
        let attribute = |key: &str| {
            entry
                .attribute(key)
                .ok_or_else(|| anyhow::anyhow!("entry {location}: attribute `{key}` is missing"))
        };
        let past_frames = attribute("past_frames")?.as_u64().ok_or_else(|| {
            anyhow::anyhow!("entry {location}: attribute `past_frames` is not a count")
        })?;
        let starts_recording = attribute("starts_recording")?.as_bool().ok_or_else(|| {
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
    out.write_array("scales", &["scale"], &[s], &[s], &scales.raw)?;
    let steps: Vec<u32> = scales.steps.iter().map(|&k| k as u32).collect();
    out.write_array("scale_steps", &["scale"], &[s], &[s], &steps)?;
    let flat: Vec<f32> = canonical.iter().flatten().copied().collect();
    out.write_array(
        "canonical_vertices",
        &["vertex", "xyz"],
        &[v, 3],
        &[v, 3],
        &flat,
    )?;
    let k = graph.k as u64;
    out.write_array(
        "canonical_knn",
        &["vertex", "neighbour"],
        &[v, k],
        &[v, k],
        &graph.indices,
    )?;
    out.write_array(
        "canonical_knn_distance",
        &["vertex", "neighbour"],
        &[v, k],
        &[v, k],
        &graph.distances,
    )?;
    let names = ingest.array_names();
    if names.iter().any(|n| n == "frame_source_id") {
        let ids = ingest.read::<i64>("frame_source_id")?;
        anyhow::ensure!(
            ids.len() as u64 == f,
            "entry {}: `frame_source_id` has {} frames, the body parameters {f}",
            ingest.location(),
            ids.len()
        );
        out.write_array("frame_source_id", &["frame"], &[f], &[f.max(1)], &ids.data)?;
    }
    for (name, dims) in [
        ("camera_K", &["view", "row", "col"][..]),
        ("camera_R", &["view", "row", "col"][..]),
        ("camera_t", &["view", "xyz"][..]),
    ] {
        if names.iter().any(|n| n == name) {
            let a = ingest.read::<f64>(name)?;
            let shape: Vec<u64> = a.shape.iter().map(|&x| x as u64).collect();
            out.write_array(
                name,
                dims,
                &shape,
                &shape.iter().map(|&x| x.max(1)).collect::<Vec<_>>(),
                &a.data,
            )?;
        }
    }
    if names.iter().any(|n| n == "camera_image_size") {
        let a = ingest.read::<u32>("camera_image_size")?;
        let shape: Vec<u64> = a.shape.iter().map(|&x| x as u64).collect();
        out.write_array(
            "camera_image_size",
            &["view", "hw"],
            &shape,
            &shape.iter().map(|&x| x.max(1)).collect::<Vec<_>>(),
            &a.data,
        )?;
    }
    out.set_attribute("frame_interval", frame_interval.into())?;
    out.write_array(
        "skeleton_motion_scale",
        &["scale"],
        &[s],
        &[s],
        &input_scales.skeleton_motion,
    )?;
    out.write_array(
        "vertex_velocity_scale",
        &["scale"],
        &[s],
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
    let names = entry.array_names();
    let read = |name: &str| -> anyhow::Result<Vec<f64>> {
        if !names.iter().any(|a| a == name) {
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

/// The motion entry's arrays a window gathers from.
#[derive(Clone, Debug)]
pub struct MotionTrack {
    pub num_frames: usize,
    pub num_joints: usize,
    pub num_vertices: usize,
    /// Raw scales, largest first.
    pub scales: Vec<u32>,
    /// The same scales in steps on the frame axis.
    pub scale_steps: Vec<usize>,
    /// `(frame, scale, joint, 3)`.
    pub skeleton_motion: Vec<f32>,
    /// `(frame, scale, vertex, 3)`.
    pub vertex_velocity: Vec<f32>,
    /// Where the frame axis sits in its recording.
    pub axis: FrameAxis,
}

impl MotionTrack {
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
        for (name, data) in [
            ("skeleton_motion", &skeleton.data),
            ("vertex_velocity", &velocity.data),
        ] {
            if let Some(bad) = data.iter().position(|v| !v.is_finite()) {
                anyhow::bail!("entry {location}: array `{name}` has a non-finite value at {bad}");
            }
        }
        Ok(Self {
            num_frames: f,
            num_joints: j,
            num_vertices: velocity.shape[2],
            scales,
            scale_steps: steps.iter().map(|&k| k as usize).collect(),
            skeleton_motion: skeleton.data,
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
        let window = crate::window(frame, length, &steps);
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
