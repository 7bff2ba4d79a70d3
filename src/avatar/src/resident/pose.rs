//! The pose path on the device: from the pose refiner's matrices to the skinning's target
//! joints and vertex offsets, and back (`shaders/avatar_pose.wgsl`).
//!
//! The maths is [`BodyRig::pose_with_chain`] and [`BodyRig::pose_backward`] followed by the
//! refiner product of [`crate::avatar::deform_backward`], in f32:
//! - refined local rotations `R'_j = R_j R_ref_j` for `j >= 1` (`R_j` the frame's own, the
//!   root unrefined), or `R'_j = R_j` without the refiner;
//! - forward kinematics `M_j = M_p R'_j`, `g_j = M_p (J_j - J_p) + g_p` (root `(R'_0, J_0)`);
//! - target joints `W [M_j | g_j - M_j J_j] + T` (`W = R(Rh)`, `T = Th`), `J x 12`;
//! - vertex offsets `shape_v - P_v f(big) + P_v f(R')`, `f(R) = vec(R_j - I)` row-major over
//!   `j >= 1`, `V x 3`: the per-shape part (`shape_v - P_v f(big)`, exactly what
//!   [`BodyRig::pose`] subtracts and adds) is computed once on the host in f64, the pose
//!   blend `P f(R')` per iteration on the device as a matrix-vector product;
//! - backward: `dL/dR_ref_j = R_j^T dL/dR'_j`, `(J - 1) x 9`.
//!
//! Everything a sequence needs is uploaded once by [`ResidentPose::new`]: the kinematic tree,
//! per frame the local rotation matrices, the local pose (the refiner's input) and the world
//! transform, per distinct body shape
//! (`betas`, `expression`) the rest joints and the base offsets, and `posedirs`. An
//! iteration writes one 16-byte record ([`ResidentPose::forward`]) and reads nothing back.
//!
//! Order within an iteration (one submission): [`ResidentPose::record_refiner_input`] (the
//! frame's local pose into [`ResidentPose::refiner_input`]), the refiner's forward,
//! [`ResidentPose::forward`], the skinning's forward and backward, then
//! [`ResidentPose::backward`] (before the refiner's backward). The backward reads the chain
//! the forward of the same iteration left in the workspace.

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::Arc;

use glam::DVec3;
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};
use seqavatar_core::body::BodyParams;
use seqavatar_core::rotation::axis_angle_to_matrix;

use crate::avatar::local_pose;
use crate::rig::BodyRig;

const POSE_WGSL: &str = include_str!("../../../../shaders/avatar_pose.wgsl");

/// Threads of `pose_offsets` (one per vertex coordinate).
const OFFSET_GROUP: usize = 256;
/// Rows of `posedirs` one workgroup of `pose_blend_backward` sums over.
const BLEND_ROWS: usize = 128;
/// `NO_PARENT` in the shader.
const NO_PARENT: u32 = u32::MAX;

/// Counters of non-finite values the kernels found, in the status buffer
/// ([`ResidentPose::status`]), `u32` each: they accumulate (a run stops at the first).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PoseStatus {
    /// Non-finite values written to the target joints.
    pub target_joints: u32,
    /// Non-finite values written to the vertex offsets.
    pub vertex_offsets: u32,
    /// Non-finite values written to the refiner's gradient.
    pub refinement_gradients: u32,
}

impl PoseStatus {
    /// Whether every value was finite.
    pub fn is_clean(&self) -> bool {
        *self == PoseStatus::default()
    }
}

/// The per-iteration record, the shader's `record` uniform (`vec4u`):
/// `[frame, shape, refine, 0]`.
type PoseRecord = [u32; 4];

struct PoseKernels {
    forward: Arc<Kernel>,
    offsets: Arc<Kernel>,
    blend_backward: Arc<Kernel>,
    backward: Arc<Kernel>,
}

impl PoseKernels {
    fn new(context: &GpuContext) -> anyhow::Result<Self> {
        let kernel = |name: &'static str, entry_point: &'static str| {
            context.kernel(&KernelSource {
                name,
                wgsl: Cow::Borrowed(POSE_WGSL),
                entry_point,
            })
        };
        Ok(Self {
            forward: kernel("avatar_pose_forward", "pose_forward")?,
            offsets: kernel("avatar_pose_offsets", "pose_offsets")?,
            blend_backward: kernel("avatar_pose_blend_backward", "pose_blend_backward")?,
            backward: kernel("avatar_pose_backward", "pose_backward")?,
        })
    }
}

/// The pose path of one sequence on the device: its uploaded body data, its workspace and
/// its output buffers. Buffers are `f32`, row-major (3 x 3 as `[r00 r01 r02 r10 ... r22]`,
/// 3 x 4 as `[r00 r01 r02 t0 r10 ... t2]`).
pub struct ResidentPose {
    context: Arc<GpuContext>,
    kernels: PoseKernels,
    joints: usize,
    vertices: usize,
    features: usize,
    blend_groups: usize,
    /// Index into the per-shape tables of each frame.
    frame_shapes: Vec<u32>,
    shape_count: usize,
    rotations_at: usize,
    d_rotations_at: usize,
    /// Sizes and offsets (uniform, 16 `u32`), fixed per sequence.
    params: wgpu::Buffer,
    /// [`PoseRecord`] (uniform, 4 `u32`), written once per iteration by the forward.
    record: wgpu::Buffer,
    /// Per frame `J x 9` local rotations, per frame `12` world `(R(Rh) row-major, Th)`, per
    /// shape `J x 3` rest joints, at the offsets in `params`.
    sequence: GpuBuffer,
    /// `J` parent indices (`u32`, `NO_PARENT` for the root).
    parents: GpuBuffer,
    /// Per shape `V x 3`: `shape_v - P_v f(big)`.
    base_offsets: GpuBuffer,
    /// `posedirs`, `(V x 3) x 9 (J - 1)`, or empty.
    pose_dirs: GpuBuffer,
    /// Workspace: `R'` `J x 9`, global frames `J x 12` (`M_j` row-major then `g_j`), the
    /// pose feature `9 (J - 1)` (when there are pose blend shapes), the frames' gradients
    /// `J x 12`, `dL/dR'` `J x 9`.
    chain: GpuBuffer,
    /// `blend_groups x features` partial sums of `P^T dL/d offsets`.
    partials: GpuBuffer,
    /// `J x 12`.
    target_joints: GpuBuffer,
    /// `V x 3`.
    vertex_offsets: GpuBuffer,
    /// `(J - 1) x 9`.
    refinement_gradients: GpuBuffer,
    /// 4 `u32` counters ([`PoseStatus`]).
    status: GpuBuffer,
    /// Per frame the local pose without the root, `3 (J - 1)` axis-angle values.
    local_poses: GpuBuffer,
    /// The refiner's input of the current frame, `3 (J - 1)`.
    refiner_input: GpuBuffer,
    /// Bound in place of the refiner's matrices when a forward runs without them.
    no_refinements: GpuBuffer,
}

/// Bit pattern of one body shape (`betas`, `expression`), for grouping frames by shape.
fn shape_key(params: &BodyParams) -> (Vec<u64>, Vec<u64>) {
    let bits = |values: &[f64]| values.iter().map(|x| x.to_bits()).collect();
    (bits(&params.betas), bits(&params.expression))
}

/// Row-major f32 of a 3 x 3.
fn rows_f32(m: glam::DMat3) -> [f32; 9] {
    let mut out = [0.0; 9];
    for r in 0..3 {
        out[3 * r] = m.x_axis[r] as f32;
        out[3 * r + 1] = m.y_axis[r] as f32;
        out[3 * r + 2] = m.z_axis[r] as f32;
    }
    out
}

fn u32_len(what: &str, value: usize) -> anyhow::Result<u32> {
    u32::try_from(value).map_err(|_| anyhow::anyhow!("{what}: {value} does not fit 32 bits"))
}

impl ResidentPose {
    /// Uploads what the pose path of a sequence needs (see the module documentation; `frames`
    /// are the unrefined body parameters, indexed as [`ResidentPose::forward`] indexes them)
    /// and allocates the workspace and outputs.
    pub fn new(
        context: Arc<GpuContext>,
        rig: &BodyRig,
        frames: &[BodyParams],
    ) -> anyhow::Result<Self> {
        let model = &rig.model;
        let joints = model.num_joints();
        let vertices = model.num_vertices();
        let features = if model.has_pose_dirs() {
            9 * (joints - 1)
        } else {
            0
        };
        anyhow::ensure!(
            !frames.is_empty(),
            "resident pose: the sequence has no frames"
        );

        // Per frame: local rotations and world transform; per shape: rest joints and base.
        let mut frame_rotations = Vec::with_capacity(frames.len() * joints * 9);
        let mut frame_world = Vec::with_capacity(frames.len() * 12);
        let mut local_poses = Vec::with_capacity(frames.len() * 3 * (joints - 1));
        let mut shapes: HashMap<(Vec<u64>, Vec<u64>), u32> = HashMap::new();
        let mut frame_shapes = Vec::with_capacity(frames.len());
        let mut rest_joints: Vec<f32> = Vec::new();
        let mut base_offsets: Vec<f32> = Vec::new();
        let canonical_rest = rig.canonical_rest();
        for (index, params) in frames.iter().enumerate() {
            model
                .check_params(params)
                .map_err(|e| anyhow::anyhow!("resident pose: frame {index}: {e}"))?;
            for v in &params.pose {
                frame_rotations.extend(rows_f32(axis_angle_to_matrix(*v)));
            }
            local_poses.extend(local_pose(params).iter().map(|x| *x as f32));
            frame_world.extend(rows_f32(axis_angle_to_matrix(params.world_rotation)));
            frame_world.extend(params.world_translation.to_array().map(|x| x as f32));
            let next = shapes.len() as u32;
            let shape = *shapes.entry(shape_key(params)).or_insert_with(|| {
                let shaped = model.shaped_vertices(params);
                for joint in model.regress_joints(&shaped) {
                    rest_joints.extend(joint.to_array().map(|x| x as f32));
                }
                for (s, c) in shaped.iter().zip(canonical_rest) {
                    let base: DVec3 = *s - *c;
                    base_offsets.extend(base.to_array().map(|x| x as f32));
                }
                next
            });
            frame_shapes.push(shape);
        }
        let shape_count = shapes.len();

        let mut sequence = frame_rotations;
        let frame_rotations_at = 0;
        let frame_world_at = sequence.len();
        sequence.extend(frame_world);
        let rest_joints_at = sequence.len();
        sequence.extend(rest_joints);

        let parents: Vec<u32> = model
            .parents()
            .iter()
            .map(|p| p.map_or(NO_PARENT, |p| p as u32))
            .collect();

        // Workspace: rotations, global frames, feature, their gradients.
        let rotations_at = 0;
        let globals_at = rotations_at + 9 * joints;
        let feature_at = globals_at + 12 * joints;
        let d_globals_at = feature_at + features;
        let d_rotations_at = d_globals_at + 12 * joints;
        let chain_len = d_rotations_at + 9 * joints;

        let blend_groups = if features == 0 {
            0
        } else {
            (3 * vertices).div_ceil(BLEND_ROWS)
        };
        // The shader's `params` uniform (16 `u32`), in the order of its accessors
        // (`joint_count()`...): sizes, then the offsets into the sequence and the workspace.
        let sizes = [
            ("joints", joints),
            ("vertices", vertices),
            ("pose features", features),
            ("pose blend workgroups", blend_groups),
        ];
        let sequence_offsets =
            [frame_rotations_at, frame_world_at, rest_joints_at].map(|at| ("sequence size", at));
        let workspace_offsets = [
            rotations_at,
            globals_at,
            feature_at,
            d_globals_at,
            d_rotations_at,
        ]
        .map(|at| ("workspace size", at));
        let mut params = [0_u32; 16];
        for (word, (what, value)) in params.iter_mut().zip(
            sizes
                .into_iter()
                .chain(sequence_offsets)
                .chain(workspace_offsets),
        ) {
            *word = u32_len(what, value)?;
        }
        let pose_dirs = &model.arrays().pose_dirs;
        let kernels = PoseKernels::new(&context)?;
        Ok(Self {
            kernels,
            joints,
            vertices,
            features,
            blend_groups,
            frame_shapes,
            shape_count,
            rotations_at,
            d_rotations_at,
            params: context.uniform("pose params", &params),
            record: context.uniform("pose record", &PoseRecord::default()),
            sequence: context.upload("pose sequence", &sequence)?,
            parents: context.upload("pose parents", &parents)?,
            base_offsets: context.upload("pose base offsets", &base_offsets)?,
            pose_dirs: context.upload("posedirs", pose_dirs)?,
            chain: context.zeros("pose chain", chain_len, 4)?,
            partials: context.zeros("pose blend partials", blend_groups * features, 4)?,
            target_joints: context.zeros("target joints", 12 * joints, 4)?,
            vertex_offsets: context.zeros("vertex offsets", 3 * vertices, 4)?,
            refinement_gradients: context.zeros(
                "pose refinement gradients",
                9 * (joints - 1),
                4,
            )?,
            status: context.zeros("pose status", 4, 4)?,
            local_poses: context.upload("local poses", &local_poses)?,
            refiner_input: context.zeros("pose refiner input", 3 * (joints - 1), 4)?,
            no_refinements: context.zeros("no pose refinements", 0, 4)?,
            context,
        })
    }

    /// Joints `J` (root included).
    pub fn joint_count(&self) -> usize {
        self.joints
    }

    /// Template vertices `V`.
    pub fn vertex_count(&self) -> usize {
        self.vertices
    }

    pub fn frame_count(&self) -> usize {
        self.frame_shapes.len()
    }

    /// Distinct body shapes among the frames (one per subject when `betas` are shared).
    pub fn shape_count(&self) -> usize {
        self.shape_count
    }

    /// The pose refiner's input of the frame of the last
    /// [`ResidentPose::record_refiner_input`]: its local pose without the root, `3 (J - 1)`
    /// axis-angle values ([`crate::avatar::local_pose`] in f32).
    pub fn refiner_input(&self) -> &GpuBuffer {
        &self.refiner_input
    }

    /// Records the copy of frame `frame`'s local pose into [`ResidentPose::refiner_input`]
    /// (device to device, nothing uploaded), before the refiner's forward.
    pub fn record_refiner_input(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        frame: usize,
    ) -> anyhow::Result<()> {
        self.shape_of(frame)?;
        let values = 3 * (self.joints - 1);
        if values > 0 {
            let bytes = (4 * values) as u64;
            encoder.copy_buffer_to_buffer(
                &self.local_poses.buffer,
                bytes * frame as u64,
                &self.refiner_input.buffer,
                0,
                bytes,
            );
        }
        Ok(())
    }

    fn shape_of(&self, frame: usize) -> anyhow::Result<u32> {
        self.frame_shapes.get(frame).copied().ok_or_else(|| {
            anyhow::anyhow!(
                "resident pose: frame {frame} out of range ({} frames)",
                self.frame_shapes.len()
            )
        })
    }

    /// The target joint transforms of the last forward, `J x 12` (3 x 4 row-major, world
    /// rotation and translation included): the skinning's `target_joints`.
    pub fn target_joints(&self) -> &GpuBuffer {
        &self.target_joints
    }

    /// The vertex offsets of the last forward, `V x 3`: the skinning's `vertex_offsets`.
    pub fn vertex_offsets(&self) -> &GpuBuffer {
        &self.vertex_offsets
    }

    /// `dL/dR_ref`, `(J - 1) x 9` row-major, written by [`ResidentPose::backward`]: what the
    /// pose refiner's backward reads.
    pub fn refinement_gradients(&self) -> &GpuBuffer {
        &self.refinement_gradients
    }

    /// The status counters, 4 `u32`: non-finite target joints, vertex offsets, refinement
    /// gradients, and one reserved (see [`PoseStatus`]).
    pub fn status(&self) -> &GpuBuffer {
        &self.status
    }

    fn check_len(what: &str, buffer: &GpuBuffer, expected: usize) -> anyhow::Result<()> {
        anyhow::ensure!(
            buffer.len == expected,
            "resident pose: `{what}` holds {} values, expected {expected}",
            buffer.len
        );
        Ok(())
    }

    /// Records the forward of frame `frame`: refined rotations (with `refinements`, the pose
    /// refiner's `(J - 1) x 9` row-major matrices, or the frame's own pose when `None`),
    /// forward kinematics, [`ResidentPose::target_joints`] and
    /// [`ResidentPose::vertex_offsets`]. Writes the 16-byte iteration record; submits
    /// nothing. One forward per submission: the record is the iteration's.
    pub fn forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        frame: usize,
        refinements: Option<&GpuBuffer>,
    ) -> anyhow::Result<()> {
        let shape = self.shape_of(frame)?;
        if let Some(buffer) = refinements {
            Self::check_len("refinements", buffer, 9 * (self.joints - 1))?;
        }
        let record: PoseRecord = [frame as u32, shape, u32::from(refinements.is_some()), 0];
        self.context.write(&self.record, 0, &record)?;
        let refinements = refinements.unwrap_or(&self.no_refinements);
        self.context.dispatch(
            encoder,
            &self.kernels.forward,
            &[
                (0, &self.params),
                (1, &self.record),
                (2, &self.sequence.buffer),
                (3, &self.parents.buffer),
                (4, &refinements.buffer),
                (5, &self.chain.buffer),
                (6, &self.target_joints.buffer),
                (7, &self.status.buffer),
            ],
            1,
        );
        self.context.dispatch(
            encoder,
            &self.kernels.offsets,
            &[
                (0, &self.params),
                (1, &self.record),
                (5, &self.chain.buffer),
                (7, &self.status.buffer),
                (8, &self.base_offsets.buffer),
                (9, &self.pose_dirs.buffer),
                (10, &self.vertex_offsets.buffer),
            ],
            (3 * self.vertices).div_ceil(OFFSET_GROUP) as u32,
        );
        Ok(())
    }

    /// Records the backward of the last [`ResidentPose::forward`], from `d_target_joints`
    /// (`J x 12`) and `d_vertex_offsets` (`V x 3`) to
    /// [`ResidentPose::refinement_gradients`] (`dL/dR_ref_j = R_j^T dL/dR'_j`); the gradients
    /// of the refined rotations `dL/dR'_j` (`J x 9`, root included) stay in the workspace
    /// ([`ResidentPose::download_rotation_gradients`]). Submits nothing.
    pub fn backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        d_target_joints: &GpuBuffer,
        d_vertex_offsets: &GpuBuffer,
    ) -> anyhow::Result<()> {
        Self::check_len("d_target_joints", d_target_joints, 12 * self.joints)?;
        Self::check_len("d_vertex_offsets", d_vertex_offsets, 3 * self.vertices)?;
        if self.features != 0 {
            self.context.dispatch(
                encoder,
                &self.kernels.blend_backward,
                &[
                    (0, &self.params),
                    (9, &self.pose_dirs.buffer),
                    (11, &d_vertex_offsets.buffer),
                    (12, &self.partials.buffer),
                ],
                self.blend_groups as u32,
            );
        }
        self.context.dispatch(
            encoder,
            &self.kernels.backward,
            &[
                (0, &self.params),
                (1, &self.record),
                (2, &self.sequence.buffer),
                (3, &self.parents.buffer),
                (5, &self.chain.buffer),
                (7, &self.status.buffer),
                (12, &self.partials.buffer),
                (13, &d_target_joints.buffer),
                (14, &self.refinement_gradients.buffer),
            ],
            1,
        );
        Ok(())
    }

    /// Reads the refined rotations `R'_j` and their gradients `dL/dR'_j` of the last forward
    /// and backward back, `J x 9` each (tests, debugging): one round trip.
    pub fn download_rotation_gradients(&self) -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
        let chain: Vec<f32> =
            self.context
                .download(self.context.encoder(), &self.chain.buffer, self.chain.len)?;
        let rotations = chain[self.rotations_at..self.rotations_at + 9 * self.joints].to_vec();
        let gradients = chain[self.d_rotations_at..self.d_rotations_at + 9 * self.joints].to_vec();
        Ok((rotations, gradients))
    }

    /// Reads the status counters back: one round trip.
    pub fn download_status(&self) -> anyhow::Result<PoseStatus> {
        let words: Vec<u32> =
            self.context
                .download(self.context.encoder(), &self.status.buffer, self.status.len)?;
        Ok(PoseStatus {
            target_joints: words[0],
            vertex_offsets: words[1],
            refinement_gradients: words[2],
        })
    }
}

#[cfg(test)]
mod tests;
