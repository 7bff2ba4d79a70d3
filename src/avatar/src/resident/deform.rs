//! The avatar's deformation of one frame on the device, recorded into a caller's encoder: the
//! pose refiner and the pose path, the motion inputs, the non-rigid network, the LBS offsets,
//! the nearest template vertices and skinning (the maths of [`crate::avatar::deform`], the
//! oracle). The training step records it before its losses and backward; the resident
//! renderer before the splatting. One place for the order of the forward phases, so training
//! and rendering deform alike.

use std::sync::Arc;

use anyhow::Context as _;
use seqavatar_compute::backend::{GpuBuffer, GpuContext};
use seqavatar_compute::splat::gpu::DeviceGaussians;
use seqavatar_core::body::BodyParams;
use seqavatar_schema::motion::MotionTrack;

use super::motion::{MotionSetup, ResidentMotion};
use super::pose::ResidentPose;
use super::skinning::{GaussianColumns, ResidentSkinning, SkinInputs, SkinningSetup};
use crate::config::AvatarConfig;
use crate::model::gpu::{GpuNetworks, NonRigidDeviceInputs};
use crate::model::{HEAD_WIDTH, NetworkGroup};
use crate::rig::BodyRig;

/// Which motion-history inputs (skeleton motion window, vertex velocities) a frame's
/// deformation reads. Eval's context probes replace them; the body pose is always the
/// frame's own.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum History {
    /// The frame's own history.
    #[default]
    Own,
    /// Skeleton motion and vertex velocities set to zero.
    Zeroed,
    /// The history of another frame of the same sequence.
    Frame(usize),
}

impl History {
    /// The frame whose history frame `frame` reads.
    pub fn frame_for(self, frame: usize) -> usize {
        match self {
            History::Frame(donor) => donor,
            History::Own | History::Zeroed => frame,
        }
    }
}

/// What a device deformation is built from, fixed for a run.
#[derive(Clone, Copy)]
pub struct DeformerSetup<'a> {
    pub config: &'a AvatarConfig,
    pub rig: &'a BodyRig,
    /// The sequence's unrefined body parameters, one per frame.
    pub frames: &'a [BodyParams],
    /// The motion track, required when the motion context has history inputs.
    pub motion: Option<&'a MotionTrack>,
    /// Raw temporal scales the networks read, largest first.
    pub scales: &'a [u32],
    /// Gaussians the workspaces are first sized for.
    pub gaussians: usize,
}

/// The device pieces of the deformation and the last forward's network outputs (the
/// backward's inputs).
pub struct ResidentDeformer {
    context: Arc<GpuContext>,
    pub pose: ResidentPose,
    pub motion: ResidentMotion,
    pub networks: Option<GpuNetworks>,
    pub skinning: ResidentSkinning,
    has_non_rigid: bool,
    has_lbs: bool,
    has_refiner: bool,
    skeleton_motion: bool,
    joints: usize,
    /// Gaussians of the current frame ([`ResidentDeformer::set_frame`]).
    count: usize,
    /// The non-rigid heads `N x 10` and LBS weight offsets `N x J` of the last forward
    /// (second handles on the networks' output buffers).
    heads: Option<GpuBuffer>,
    weight_offsets: Option<GpuBuffer>,
}

/// A second handle on the first `len` values of a network's output buffer.
fn device_view(buffer: &wgpu::Buffer, len: usize) -> GpuBuffer {
    GpuBuffer {
        buffer: buffer.clone(),
        len,
    }
}

impl ResidentDeformer {
    /// Uploads the sequence's poses and motion arrays once and allocates the workspaces;
    /// `networks` are the avatar's networks already on `context` (their Adam moments too,
    /// when training).
    pub fn new(
        context: Arc<GpuContext>,
        setup: &DeformerSetup<'_>,
        networks: Option<GpuNetworks>,
    ) -> anyhow::Result<Self> {
        let DeformerSetup {
            config,
            rig,
            frames,
            motion,
            scales,
            gaussians,
        } = *setup;
        let context_kind = config.motion_context;
        let pose = ResidentPose::new(context.clone(), rig, frames).context("resident pose path")?;
        let has_non_rigid = networks.is_some() && context_kind.has_non_rigid();
        let has_lbs = networks.is_some() && config.lbs_offsets;
        let has_refiner = networks.is_some() && config.pose_refiner;
        let skeleton_motion = has_non_rigid && context_kind.has_skeleton_motion();
        let motion = ResidentMotion::new(
            &context,
            &MotionSetup {
                track: motion,
                scales,
                length: config.sequence_length,
                template: &rig.canonical_vertices,
                tau: if has_non_rigid && context_kind.has_velocity() {
                    config.tau
                } else {
                    0
                },
                skeleton_motion,
            },
            gaussians,
        )
        .context("resident motion inputs")?;
        let skinning = ResidentSkinning::new(
            &context,
            &SkinningSetup {
                canonical_joints: &rig.canonical_joints,
                template_weights: &rig.template_weights,
                scale_min: config.scale_min,
                scale_max: config.scale_max,
                heads: has_non_rigid,
                weight_offsets: has_lbs,
                atomic_add: None,
            },
            gaussians,
        )
        .context("resident skinning")?;
        Ok(Self {
            context,
            pose,
            motion,
            networks,
            skinning,
            has_non_rigid,
            has_lbs,
            has_refiner,
            skeleton_motion,
            joints: rig.joint_count(),
            count: 0,
            heads: None,
            weight_offsets: None,
        })
    }

    /// Whether the non-rigid network runs (heads reach the skinning).
    pub fn has_non_rigid(&self) -> bool {
        self.has_non_rigid
    }

    /// Whether the LBS-offset network runs.
    pub fn has_lbs_offsets(&self) -> bool {
        self.has_lbs
    }

    pub fn has_pose_refiner(&self) -> bool {
        self.has_refiner
    }

    /// Grows the per-Gaussian workspaces to hold `capacity` Gaussians.
    pub fn reserve(&mut self, capacity: usize) -> anyhow::Result<()> {
        if capacity > self.motion.capacity() {
            self.motion.reserve(capacity)?;
        }
        if capacity > self.skinning.capacity() {
            self.skinning.reserve(capacity)?;
        }
        Ok(())
    }

    /// Writes the small per-frame records (the history frame and the Gaussian count of the
    /// motion inputs, the skinning's count and SH degree) before recording
    /// [`ResidentDeformer::record_forward`] for `frame`. Host-side checks (the frame's window
    /// lies inside the motion track) fail here, naming the frame.
    pub fn set_frame(
        &mut self,
        frame: usize,
        history: History,
        gaussians: usize,
        sh_degree: u32,
    ) -> anyhow::Result<()> {
        anyhow::ensure!(
            frame < self.pose.frame_count(),
            "frame {frame}: the sequence has {} frames",
            self.pose.frame_count()
        );
        self.motion
            .set_iteration(history.frame_for(frame), gaussians)?;
        self.skinning.set_iteration(gaussians, sh_degree)?;
        self.count = gaussians;
        Ok(())
    }

    /// Records the deformation of `frame` (after [`ResidentDeformer::set_frame`]) of the
    /// canonical Gaussians `columns` into the skinning's outputs
    /// ([`ResidentSkinning::means`], `covariances`, `opacities`, `sh`). Submits nothing.
    pub fn record_forward(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        frame: usize,
        history: History,
        columns: &GaussianColumns<'_>,
    ) -> anyhow::Result<()> {
        let n = self.count;
        // Pose: the frame's unrefined local pose (the refiner's and the non-rigid network's
        // input), the refiner's forward, forward kinematics and pose blend shapes.
        self.pose.record_refiner_input(encoder, frame)?;
        let refinements = match (self.has_refiner, self.networks.as_mut()) {
            (true, Some(networks)) => Some(device_view(
                networks.record_forward(
                    encoder,
                    NetworkGroup::PoseRefiner,
                    0,
                    &[&[&self.pose.refiner_input().buffer]],
                )?,
                9 * (self.joints - 1),
            )),
            _ => None,
        };
        self.pose.forward(encoder, frame, refinements.as_ref())?;

        // Motion inputs and the non-rigid network.
        self.heads = if self.has_non_rigid {
            self.motion.record_skeleton_window(encoder)?;
            self.motion.record_canonical_knn(encoder, columns.xyz)?;
            self.motion.record_velocity(encoder)?;
            if history == History::Zeroed {
                encoder.clear_buffer(&self.motion.window.buffer, 0, None);
                for block in &self.motion.velocity {
                    encoder.clear_buffer(&block.buffer, 0, None);
                }
            }
            let velocity: Vec<&wgpu::Buffer> =
                self.motion.velocity.iter().map(|b| &b.buffer).collect();
            let networks = self.networks.as_mut().expect("has a non-rigid network");
            Some(device_view(
                networks.record_non_rigid_forward(
                    encoder,
                    n,
                    &NonRigidDeviceInputs {
                        local_pose: &self.pose.refiner_input().buffer,
                        skeleton_motion: self.skeleton_motion.then_some(&self.motion.window.buffer),
                        xyz: &columns.xyz.buffer,
                        knn_velocity: &velocity,
                    },
                )?,
                HEAD_WIDTH * n,
            ))
        } else {
            None
        };
        self.skinning
            .record_deform(encoder, columns.xyz, self.heads.as_ref())?;
        self.weight_offsets = match self.networks.as_mut() {
            Some(networks) if self.has_lbs => Some(device_view(
                networks.record_forward(
                    encoder,
                    NetworkGroup::LbsOffsets,
                    n,
                    &[&[&self.skinning.positions.buffer]],
                )?,
                self.joints * n,
            )),
            _ => None,
        };
        self.motion
            .record_nearest(encoder, &self.skinning.positions)?;
        let inputs = self.skin_inputs();
        self.skinning.record_forward(encoder, columns, &inputs)?;
        Ok(())
    }

    /// The skinning's inputs from the other pieces, as the last forward used them.
    pub fn skin_inputs(&self) -> SkinInputs<'_> {
        SkinInputs {
            nearest: &self.motion.nearest,
            weight_offsets: self.weight_offsets.as_ref(),
            target_joints: self.pose.target_joints(),
            vertex_offsets: self.pose.vertex_offsets(),
        }
    }

    /// The deformed Gaussians of the last forward, as the splatting reads them.
    pub fn world(&self, sh_degree: u32) -> DeviceGaussians<'_> {
        DeviceGaussians {
            means: &self.skinning.means,
            covariances: &self.skinning.covariances,
            opacities: &self.skinning.opacities,
            sh: &self.skinning.sh,
            count: self.count as u32,
            sh_degree,
        }
    }

    pub fn context(&self) -> &Arc<GpuContext> {
        &self.context
    }
}
