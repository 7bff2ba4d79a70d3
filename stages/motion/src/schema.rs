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
//! - `frame_source_id` i64 `(frame)` (copied from ingest).
//! - `canonical_vertices` f32 `(vertex, xyz)`; `canonical_knn` u32 and
//!   `canonical_knn_distance` f32 `(vertex, neighbour)`, nearest first, self first.
//! - `camera_K`, `camera_R` f64 `(view, row, col)`, `camera_t` f64 `(view, xyz)`,
//!   `camera_image_size` u32 `(view, hw)` (copied from ingest, for pictures).
//!
//! Attributes: `frame_interval`, `velocity` (the normalisation).
//!
//! A training window `(t, L, S)` is [`crate::window`]`(t, L, scale_steps)`: a gather of rows of
//! `skeleton_motion` and `vertex_velocity` ([`MotionTrack::gather`]).

use seqavatar_engine::{EntryReader, EntryWriter};

use crate::compute::MotionArrays;
use crate::context::{Scales, VelocityNormalisation};
use crate::knn::KnnGraph;

/// What the motion stage computed, to be written by [`write_entry`].
#[derive(Clone, Copy)]
pub struct MotionEntry<'a> {
    pub motion: &'a MotionArrays,
    pub scales: &'a Scales,
    pub canonical: &'a [[f32; 3]],
    pub graph: &'a KnnGraph,
    /// The ingest entry's `frame_interval` (raw frames per sampled frame).
    pub frame_interval: u32,
    pub velocity: VelocityNormalisation,
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
    out.set_attribute("velocity", serde_json::to_value(velocity)?)?;
    Ok(())
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
    pub fn gather(&self, frame: usize, length: usize, slots: &[usize]) -> (Vec<f32>, Vec<f32>) {
        let steps: Vec<usize> = slots.iter().map(|&s| self.scale_steps[s]).collect();
        let window = crate::window(frame, length, &steps);
        let (s_all, j, v) = (self.scales.len(), self.num_joints, self.num_vertices);
        let mut skeleton = Vec::with_capacity(length * slots.len() * j * 3);
        let mut velocity = Vec::with_capacity(length * slots.len() * v * 3);
        for l in 0..length {
            for (k, &slot) in slots.iter().enumerate() {
                let row = window.frame(l, k).min(self.num_frames.saturating_sub(1));
                let at = (row * s_all + slot) * j * 3;
                skeleton.extend_from_slice(&self.skeleton_motion[at..at + j * 3]);
                let at = (row * s_all + slot) * v * 3;
                velocity.extend_from_slice(&self.vertex_velocity[at..at + v * 3]);
            }
        }
        (skeleton, velocity)
    }
}
