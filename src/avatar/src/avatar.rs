//! The trained avatar: canonical Gaussians, the body rig and (with a motion context) the
//! networks, as stored in a `train` entry, and its render path, which is exactly the
//! training forward pass (networks, skinning, splatting) without gradients.
//!
//! Its entry arrays and attributes ([`TrainedAvatar::write`], [`TrainedAvatar::load`]) are
//! listed in `seqavatar_schema::train` (docs/schema.md).

use anyhow::Context;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::nn::NnScalar;
use seqavatar_compute::splat::{RasterOptions, RenderedImage, sh_coefficient_count};
use seqavatar_core::body::BodyParams;
use seqavatar_core::camera::Camera;
use seqavatar_engine::{EntryReader, EntryWriter};
use seqavatar_schema::ingest::write_body_model;
use seqavatar_schema::train::{AvatarAttributes, read_network_parameter, write_network_parameter};

use seqavatar_knn::{KnnGrid, as_points};
use seqavatar_schema::motion::MotionTrack;

use crate::config::AvatarConfig;
use crate::device::{
    AvatarBackend, NonRigidInputs, NonRigidOffsets, avatar_backend, to_f64, to_scalar,
};
use crate::model::{LbsOffsetsCache, NetworkConfig, Networks, NonRigidCache, PoseRefinerCache};
use crate::rig::{BodyRig, FramePose, PoseChain, refine_pose};
use crate::skinning::{GaussianParams, Skinned, SkinningGrads, skin_forward};
use crate::splatting::WorldGaussians;

/// Spherical-harmonics DC constant (3DGS `C0`).
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
pub use seqavatar_schema::train::{AvatarGaussians, SH_STORED};

/// One frame's inputs: body parameters and (for motion contexts that use them) the gathered
/// motion window.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameInputs {
    pub params: BodyParams,
    /// `(L, S, J, 3)` skeleton motion, empty when unused.
    pub skeleton_motion: Vec<f32>,
    /// `(L, S, V, 3)` template-vertex velocities, empty when unused.
    pub vertex_velocity: Vec<f32>,
}

/// The inputs of frame `frame`: its body parameters and, as the motion context needs, the
/// window gathered at the raw `scales` (largest first).
pub fn gather_frame_inputs(
    config: &AvatarConfig,
    scales: &[u32],
    motion: &MotionTrack,
    params: &BodyParams,
    frame: usize,
) -> anyhow::Result<FrameInputs> {
    anyhow::ensure!(
        frame < motion.num_frames,
        "frame {frame} is outside the motion track ({} frames)",
        motion.num_frames
    );
    let context = config.motion_context;
    let (skeleton_motion, vertex_velocity) = if context.has_skeleton_motion() {
        let slots = motion.slots(scales)?;
        let (s, v) = motion.gather(frame, config.sequence_length, &slots)?;
        (
            s,
            if context.has_velocity() {
                v
            } else {
                Vec::new()
            },
        )
    } else {
        (Vec::new(), Vec::new())
    };
    Ok(FrameInputs {
        params: params.clone(),
        skeleton_motion,
        vertex_velocity,
    })
}

/// One frame's (possibly refined) skinning target and what its backward needs; `S` is the
/// networks' scalar (f32 in production, f64 as the oracle in tests).
pub struct PosedFrame<S = f32> {
    pub pose: FramePose,
    pub chain: PoseChain,
    /// The refiner's cache and its `(J - 1) x 9` matrices, when the pose refiner is on.
    pub refiner: Option<(PoseRefinerCache<S>, Vec<S>)>,
}

/// The local pose without the root joint, `3 (J - 1)` values.
pub fn local_pose(params: &BodyParams) -> Vec<f64> {
    params.pose[1..].iter().flat_map(|v| v.to_array()).collect()
}

/// The skinning target of a frame, through the pose refiner when the networks have one.
pub fn frame_pose<S: NnScalar>(
    rig: &BodyRig,
    networks: Option<&Networks<S>>,
    params: &BodyParams,
) -> anyhow::Result<PosedFrame<S>> {
    let mut refiner = None;
    let refined;
    let params = match networks.filter(|n| n.has_pose_refiner()) {
        Some(net) => {
            let (matrices, cache) = net.pose_refiner_forward(&to_scalar(&local_pose(params)))?;
            // Row-major matrices.
            let refinements: Vec<seqavatar_core::glam::DMat3> = to_f64(&matrices)
                .chunks_exact(9)
                .map(|m| seqavatar_core::glam::DMat3::from_cols_slice(m).transpose())
                .collect();
            refined = refine_pose(params, &refinements);
            refiner = Some((cache, matrices));
            &refined
        }
        None => params,
    };
    let (pose, chain) = rig.pose_with_chain(params)?;
    Ok(PosedFrame {
        pose,
        chain,
        refiner,
    })
}

/// The deformed Gaussians of one frame and the intermediates the backward needs; `S` is the
/// `cpu` networks' scalar.
pub struct Deformed<S = f32> {
    /// Nearest template vertex of each (post-non-rigid) centre.
    pub nearest: Vec<u32>,
    pub non_rigid: Option<NonRigidCache<S>>,
    /// LBS weight offsets `N x J` and the activations of the pass that made them.
    pub weight_offsets: Option<(Vec<f64>, LbsOffsetsCache<S>)>,
    /// Centres after the non-rigid offset (canonical space).
    pub positions: Vec<f64>,
    /// Linear scale offsets `N x 3` and rotation offsets `N x 4`.
    pub d_scales: Vec<f64>,
    pub d_rotations: Vec<f64>,
    pub skinned: Skinned,
    pub world: WorldGaussians,
}

impl<S> Deformed<S> {
    /// The skinning inputs of these Gaussians: their deformed centres and offsets with the
    /// canonical `gaussians` they were deformed from (what the skinning backward reads).
    pub fn skin_params<'a>(&'a self, gaussians: &'a AvatarGaussians) -> GaussianParams<'a> {
        GaussianParams {
            positions: &self.positions,
            log_scales: &gaussians.log_scale,
            d_scales: &self.d_scales,
            rotations: &gaussians.rotation,
            d_rotations: &self.d_rotations,
            weight_offsets: self.weight_offsets.as_ref().map(|(w, _)| w.as_slice()),
            nearest: &self.nearest,
        }
    }
}

/// Splats one frame's deformed Gaussians from `camera` on `background`, as every render
/// of a trained avatar does (no smoothed opacity cut-off).
pub fn splat_on(
    world: &WorldGaussians,
    camera: &Camera,
    device: &AvatarBackend,
    background: [f64; 3],
) -> anyhow::Result<RenderedImage<f64>> {
    let options = RasterOptions {
        background,
        smooth_cutoff: false,
    };
    let mut pass = device.splat_forward(world, std::slice::from_ref(camera), &options)?;
    Ok(pass.images.swap_remove(0))
}

/// The forward pass shared by training and rendering: non-rigid offsets from the networks
/// (zeros without them), nearest template vertex of the moved centre, LBS weight offsets,
/// skinning, activations. The per-Gaussian networks, non-rigid and LBS offsets, run on
/// `device` (in the networks' scalar `S`; inputs rounded once, outputs widened to f64);
/// everything else runs in f64.
///
/// The pose refiner ([`frame_pose`]) stays on `cpu` on every backend on purpose: it is one
/// row per frame (`69 -> 128 -> 128 -> 69` for SMPL, about 35k multiply-adds), and its
/// output must be on the host before anything per Gaussian can start (it moves the joints),
/// so a gpu pass would be a blocking round trip of its own (two with the backward). Measured
/// with `benches/networks.rs` (forward + backward, paper widths): 0.054 ms on `cpu` in f64
/// against 9.3 ms on lavapipe; on a hardware gpu the two submit-wait-download round trips
/// alone (typically 0.1 ms or more each) exceed the whole `cpu` time.
#[allow(clippy::too_many_arguments)]
pub fn deform<S: NnScalar>(
    rig: &BodyRig,
    template_grid: &KnnGrid,
    networks: Option<&Networks<S>>,
    device: &AvatarBackend,
    gaussians: &AvatarGaussians,
    inputs: &FrameInputs,
    pose: &FramePose,
    config: &AvatarConfig,
    sh_degree: u32,
) -> anyhow::Result<Deformed<S>> {
    let n = gaussians.len();
    if let Some(bad) = gaussians.xyz.iter().position(|v| !v.is_finite()) {
        anyhow::bail!("Gaussian {} has a non-finite centre", bad / 3);
    }
    let (positions, d_scales, d_rotations, non_rigid) =
        match networks.filter(|net| net.has_non_rigid()) {
            Some(net) => {
                let has_skeleton = config.motion_context.has_skeleton_motion();
                let has_velocity = config.motion_context.has_velocity();
                let (offsets, cache) = device.non_rigid_forward(
                    net,
                    &NonRigidInputs {
                        local_pose: &local_pose(&inputs.params),
                        skeleton_motion: has_skeleton.then_some(inputs.skeleton_motion.as_slice()),
                        xyz: &gaussians.xyz,
                        vertex_velocity: has_velocity
                            .then_some((template_grid, inputs.vertex_velocity.as_slice())),
                    },
                )?;
                let NonRigidOffsets {
                    d_xyz,
                    d_rot,
                    d_scale,
                } = offsets;
                let positions: Vec<f64> = gaussians
                    .xyz
                    .iter()
                    .zip(&d_xyz)
                    .map(|(a, b)| a + b)
                    .collect();
                (positions, d_scale, d_rot, Some(cache))
            }
            None => (
                gaussians.xyz.clone(),
                vec![0.0; 3 * n],
                [1.0, 0.0, 0.0, 0.0].repeat(n),
                None,
            ),
        };
    if let Some(bad) = positions.iter().position(|v| !v.is_finite()) {
        anyhow::bail!("Gaussian {} has a non-finite deformed centre", bad / 3);
    }
    let weight_offsets = match networks.filter(|net| net.has_lbs_offsets()) {
        None => None,
        Some(net) => Some(device.lbs_offsets_forward(net, &positions)?),
    };
    let nearest = template_grid.query_all(&as_points(&positions), 1);
    anyhow::ensure!(
        nearest.len() == n,
        "nearest template vertex: {} results for {n} Gaussians",
        nearest.len()
    );
    let frame = rig.frame(pose, config.scale_min, config.scale_max);
    let skinned = skin_forward(
        &frame,
        &GaussianParams {
            positions: &positions,
            log_scales: &gaussians.log_scale,
            d_scales: &d_scales,
            rotations: &gaussians.rotation,
            d_rotations: &d_rotations,
            weight_offsets: weight_offsets.as_ref().map(|(w, _)| w.as_slice()),
            nearest: &nearest,
        },
    );
    let k = sh_coefficient_count(sh_degree);
    let sh: Vec<f64> = (0..n)
        .flat_map(|i| {
            gaussians.sh[i * 3 * SH_STORED..i * 3 * SH_STORED + 3 * k]
                .iter()
                .copied()
        })
        .collect();
    let opacities = gaussians
        .opacity_logit
        .iter()
        .map(|l| 1.0 / (1.0 + (-l).exp()))
        .collect();
    let world = WorldGaussians {
        means: skinned.positions.clone(),
        covariances: skinned.covariances.clone(),
        opacities,
        sh,
        sh_degree,
    };
    Ok(Deformed {
        nearest,
        non_rigid,
        weight_offsets,
        positions,
        d_scales,
        d_rotations,
        skinned,
        world,
    })
}

/// Backward of [`frame_pose`] and [`deform`] through the networks, from the skinning's
/// gradients: accumulates the networks' parameter gradients and returns the gradient of the
/// canonical centres through the non-rigid network (zeros without one; the direct path
/// `x' = x + d_xyz` is the caller's). `params` are the frame's unrefined body parameters.
/// The per-Gaussian networks' backward runs on `device`, the backend their forward ran on
/// ([`AvatarBackend::networks_backward`]); the pose refiner's on `cpu`.
#[allow(clippy::too_many_arguments)]
pub fn deform_backward<S: NnScalar>(
    networks: &mut Networks<S>,
    device: &AvatarBackend,
    rig: &BodyRig,
    posed: &PosedFrame<S>,
    deformed: &Deformed<S>,
    params: &BodyParams,
    skin: &SkinningGrads,
) -> anyhow::Result<Vec<f64>> {
    let through = device.networks_backward(
        networks,
        deformed.non_rigid.as_ref(),
        deformed.weight_offsets.as_ref().map(|(_, pass)| pass),
        skin,
    )?;
    if let Some((cache, _)) = &posed.refiner {
        let d_rotations =
            rig.pose_backward(&posed.chain, &skin.target_joints, &skin.vertex_offsets);
        // R'_j = R_j R_ref_j, so dL/dR_ref_j = R_j^T dL/dR'_j (non-root joints).
        let mut flat = Vec::with_capacity(9 * (d_rotations.len() - 1));
        for j in 1..d_rotations.len() {
            let g = seqavatar_core::rotation::axis_angle_to_matrix(params.pose[j]).transpose()
                * d_rotations[j];
            for r in 0..3 {
                flat.extend([g.x_axis[r], g.y_axis[r], g.z_axis[r]]);
            }
        }
        networks.pose_refiner_backward(cache, &to_scalar(&flat))?;
    }
    Ok(through)
}

/// A grid over the canonical template vertices for nearest-vertex queries.
pub fn template_grid(rig: &BodyRig) -> KnnGrid {
    KnnGrid::new(&as_points(&rig.canonical_vertices), 4.0)
}

/// A trained avatar, ready to render.
pub struct TrainedAvatar {
    pub config: AvatarConfig,
    pub rig: BodyRig,
    pub gaussians: AvatarGaussians,
    /// Active SH degree.
    pub sh_degree: u32,
    /// Raw temporal scales the networks were trained with (largest first).
    pub scales: Vec<u32>,
    /// The colour [`TrainedAvatar::render`] composites behind the Gaussians: the training
    /// background's [`crate::config::Background::render_colour`] (`pipeline render` uses
    /// it); the held-out PSNR and eval render on the protocol's background instead.
    pub background: [f64; 3],
    /// The networks in f32 (absent for motion context `none` without refiners).
    pub networks: Option<Networks<f32>>,
    template_grid: KnnGrid,
}

impl TrainedAvatar {
    pub fn new(
        config: AvatarConfig,
        rig: BodyRig,
        gaussians: AvatarGaussians,
        sh_degree: u32,
        scales: Vec<u32>,
        networks: Option<Networks<f32>>,
    ) -> Self {
        let template_grid = template_grid(&rig);
        Self {
            background: config.background.render_colour(),
            networks,
            config,
            rig,
            gaussians,
            sh_degree,
            scales,
            template_grid,
        }
    }

    /// The host backend `backend` names ([`avatar_backend`]: `cpu`'s; the gpu renders a
    /// sequence on the device, `crate::sequence::SequenceRenderer`).
    pub fn backend(&self, backend: Backend) -> anyhow::Result<AvatarBackend> {
        avatar_backend(backend).context("the avatar's host backend")
    }

    /// The deformed Gaussians of one frame (pose refiner, networks, skinning), the
    /// per-Gaussian networks on `device` (built by [`TrainedAvatar::backend`]).
    pub fn deform(&self, inputs: &FrameInputs, device: &AvatarBackend) -> anyhow::Result<Deformed> {
        let posed = frame_pose(&self.rig, self.networks.as_ref(), &inputs.params)?;
        deform(
            &self.rig,
            &self.template_grid,
            self.networks.as_ref(),
            device,
            &self.gaussians,
            inputs,
            &posed.pose,
            &self.config,
            self.sh_degree,
        )
    }

    /// The inputs of frame `frame` of a motion track with its body parameters.
    pub fn frame_inputs(
        &self,
        motion: &MotionTrack,
        params: &BodyParams,
        frame: usize,
    ) -> anyhow::Result<FrameInputs> {
        gather_frame_inputs(&self.config, &self.scales, motion, params, frame)
    }

    /// Renders one frame from `camera` on `device` (built by [`TrainedAvatar::backend`]):
    /// colour (background included) and alpha.
    pub fn render(
        &self,
        inputs: &FrameInputs,
        camera: &Camera,
        device: &AvatarBackend,
    ) -> anyhow::Result<RenderedImage<f64>> {
        self.render_on(inputs, camera, device, self.background)
    }

    /// [`TrainedAvatar::render`] on `background` instead of the avatar's own colour.
    pub fn render_on(
        &self,
        inputs: &FrameInputs,
        camera: &Camera,
        device: &AvatarBackend,
        background: [f64; 3],
    ) -> anyhow::Result<RenderedImage<f64>> {
        let deformed = self.deform(inputs, device)?;
        splat_on(&deformed.world, camera, device, background)
    }

    /// Writes the avatar arrays and attributes into an entry.
    pub fn write(
        &self,
        out: &EntryWriter,
        extent: f64,
        body_model_kind: &str,
    ) -> anyhow::Result<()> {
        self.gaussians.write(out)?;
        for param in self.networks.iter().flat_map(Networks::parameters) {
            // Stored in f64 (exactly the f32 values), as the entry format has it.
            write_network_parameter(out, &param.name, &param.shape, &to_f64(param.values))?;
        }
        write_body_model(out, &self.rig.model)?;
        let attributes = AvatarAttributes {
            avatar: &self.config,
            sh_degree: self.sh_degree,
            scales: self.scales.clone(),
            sequence_length: self.config.sequence_length,
            background: self.background,
            body_model_kind: body_model_kind.to_owned(),
            extent,
            motion_joints: self.networks.as_ref().map(|n| n.config().motion_joints),
        };
        attributes.write(out)
    }

    /// Reads an avatar from a `train` entry; errors name the entry and the array or
    /// attribute.
    pub fn load(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        let attributes = AvatarAttributes::<AvatarConfig>::read(entry)?;
        let config = attributes.avatar;
        config
            .validate()
            .with_context(|| format!("entry {location}: attribute `avatar`"))?;
        let gaussians = AvatarGaussians::read(entry)?;
        let model = seqavatar_schema::ingest::read_body_model(entry)
            .with_context(|| format!("entry {location}: body model"))?;
        let rig = config.rig(model)?;
        let scales = attributes.scales;
        let networks = if config.needs_networks() {
            let motion_joints = attributes.motion_joints.ok_or_else(|| {
                anyhow::anyhow!("entry {location}: attribute `motion_joints` is missing")
            })?;
            let net_config =
                NetworkConfig::from_avatar(&config, rig.joint_count(), motion_joints, scales.len())
                    .with_context(|| format!("entry {location}: network configuration"))?;
            // Every parameter is loaded below; the initialisation seed does not matter.
            let mut networks = Networks::new(&net_config, 0)
                .with_context(|| format!("entry {location}: network configuration"))?;
            networks
                .load_parameters(|name| {
                    read_network_parameter(entry, name).map(|values| to_scalar::<f32>(&values))
                })
                .with_context(|| format!("entry {location}: network arrays `network.*`"))?;
            Some(networks)
        } else {
            None
        };
        let mut avatar = Self::new(
            config,
            rig,
            gaussians,
            attributes.sh_degree,
            scales,
            networks,
        );
        avatar.background = attributes.background;
        Ok(avatar)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MotionContext;
    use crate::model::Widths;
    use crate::skinning::skin_backward;
    use seqavatar_compute::backend::DeviceChoice;
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_core::glam::DVec3;
    use seqavatar_core::rng::SplitMix64 as Rng;

    struct Setup {
        rig: BodyRig,
        grid: KnnGrid,
        config: AvatarConfig,
        gaussians: AvatarGaussians,
        inputs: FrameInputs,
        a: Vec<f64>,
        b: Vec<f64>,
    }

    /// The `cpu` backend, as every caller builds it.
    fn cpu() -> AvatarBackend {
        avatar_backend(Backend::select(DeviceChoice::Cpu).unwrap()).unwrap()
    }

    /// A smooth function of the skinned Gaussians: `sum a . centres + sum b . covariances`.
    fn loss(s: &Setup, networks: &Networks<f64>, xyz: &[f64]) -> f64 {
        let gaussians = AvatarGaussians {
            xyz: xyz.to_vec(),
            ..s.gaussians.clone()
        };
        let posed = frame_pose(&s.rig, Some(networks), &s.inputs.params).unwrap();
        let d = deform(
            &s.rig,
            &s.grid,
            Some(networks),
            &cpu(),
            &gaussians,
            &s.inputs,
            &posed.pose,
            &s.config,
            0,
        )
        .unwrap();
        let p: f64 = d
            .skinned
            .positions
            .iter()
            .zip(&s.a)
            .map(|(x, y)| x * y)
            .sum();
        let c: f64 = d
            .skinned
            .covariances
            .iter()
            .zip(&s.b)
            .map(|(x, y)| x * y)
            .sum();
        p + c
    }

    /// The whole deformation (pose refiner, non-rigid network with every motion input,
    /// skinning) against central differences in f64, for parameters of each network and for
    /// the canonical centres.
    #[test]
    fn deformation_gradients_match_finite_differences() {
        check_deformation_gradients(MotionContext::Multiscale, false);
    }

    /// The same with the LBS weight offsets. Their input is detached (docs/method.md), so the
    /// centres and the non-rigid network, which move that input, are checked without them.
    #[test]
    fn lbs_offset_gradients_match_finite_differences() {
        check_deformation_gradients(MotionContext::None, true);
    }

    /// A small deformation problem: `n` Gaussians near the template, a random pose, motion
    /// inputs at two scales, every enabled network with outputs large enough to matter.
    fn build(context: MotionContext, lbs_offsets: bool, n: usize) -> (Setup, Networks<f64>) {
        let model = procedural_body(0.05);
        let rig = BodyRig::new(model.clone()).unwrap();
        let grid = template_grid(&rig);
        let mut rng = Rng::new(9);
        let mut config = AvatarConfig::for_tests();
        config.motion_context = context;
        config.lbs_offsets = lbs_offsets;
        config.trunk_width = 16;
        config.trunk_depth = 2;
        config.tau = 2;
        config.sequence_length = 2;
        let (j, v, scales) = (rig.joint_count(), rig.vertex_count(), 2);
        let canonical = &rig.canonical_vertices;
        let xyz: Vec<f64> = (0..n)
            .flat_map(|i| {
                let k = (i * 37) % v;
                [canonical[3 * k], canonical[3 * k + 1], canonical[3 * k + 2]]
            })
            .map(|x| x + 0.01 * rng.normal())
            .collect();
        let gaussians = AvatarGaussians {
            xyz,
            sh: vec![0.0; n * 3 * SH_STORED],
            opacity_logit: vec![0.0; n],
            log_scale: (0..3 * n).map(|_| rng.uniform(-4.0, -3.0)).collect(),
            rotation: (0..4 * n).map(|_| rng.uniform(-1.0, 1.0)).collect(),
        };
        let mut params = model.zero_params();
        for p in params.pose.iter_mut() {
            *p = DVec3::new(
                rng.uniform(-0.3, 0.3),
                rng.uniform(-0.3, 0.3),
                rng.uniform(-0.3, 0.3),
            );
        }
        params.world_translation = DVec3::new(0.1, 0.0, 2.0);
        let inputs = FrameInputs {
            params,
            skeleton_motion: (0..2 * scales * j * 3)
                .map(|_| rng.uniform(-0.5, 0.5) as f32)
                .collect(),
            vertex_velocity: (0..2 * scales * v * 3)
                .map(|_| rng.uniform(-0.5, 0.5) as f32)
                .collect(),
        };
        let mut net_config = NetworkConfig::from_avatar(&config, j, j, scales).unwrap();
        net_config.widths = Widths {
            encoding_frequencies: 2,
            pose_encoder: 4,
            seq_pose_frame: 4,
            seq_pose: 4,
            seq_xyz_velocity: 4,
            seq_xyz_position: 4,
            seq_xyz_frame: 4,
            seq_xyz_hidden: 4,
            seq_xyz: 4,
            pose_refiner_hidden: 6,
            lbs_hidden: 6,
        };
        let mut networks = Networks::<f64>::new(&net_config, 4).unwrap();
        // Larger refiner and offset outputs than their near-zero initialisation, so that
        // every path carries a visible gradient.
        for param in networks.parameters_mut() {
            if param.name.starts_with("pose_refiner.2") || param.name.starts_with("lbs_offsets.4") {
                for x in param.values.iter_mut() {
                    *x = rng.uniform(-0.1, 0.1);
                }
            }
        }
        let setup = Setup {
            a: (0..3 * n).map(|_| rng.uniform(-1.0, 1.0)).collect(),
            b: (0..6 * n).map(|_| rng.uniform(-100.0, 100.0)).collect(),
            rig,
            grid,
            config,
            gaussians,
            inputs,
        };
        (setup, networks)
    }

    fn check_deformation_gradients(context: MotionContext, lbs_offsets: bool) {
        let n = 12;
        let (setup, mut networks) = build(context, lbs_offsets, n);
        // Analytic gradients.
        let posed = frame_pose(&setup.rig, Some(&networks), &setup.inputs.params).unwrap();
        let device = cpu();
        let deformed = deform(
            &setup.rig,
            &setup.grid,
            Some(&networks),
            &device,
            &setup.gaussians,
            &setup.inputs,
            &posed.pose,
            &setup.config,
            0,
        )
        .unwrap();
        let frame = setup
            .rig
            .frame(&posed.pose, setup.config.scale_min, setup.config.scale_max);
        let skin = skin_backward(
            &frame,
            &deformed.skin_params(&setup.gaussians),
            &setup.a,
            &setup.b,
        );
        networks.zero_grad();
        let through = deform_backward(
            &mut networks,
            &device,
            &setup.rig,
            &posed,
            &deformed,
            &setup.inputs.params,
            &skin,
        )
        .unwrap();
        let d_xyz: Vec<f64> = skin
            .positions
            .iter()
            .zip(&through)
            .map(|(x, y)| x + y)
            .collect();
        let eps = 1e-6;
        let check = |name: &str, numeric: f64, analytic: f64| {
            assert!(
                (numeric - analytic).abs() <= 1e-5 * (1.0 + analytic.abs().max(numeric.abs())),
                "{name}: numeric {numeric} analytic {analytic}"
            );
        };
        let names: Vec<(String, usize)> = networks
            .parameters()
            .iter()
            .map(|p| (p.name.clone(), p.values.len()))
            .collect();
        let mut checked = 0;
        for (name, len) in &names {
            let wanted = [
                "pose_refiner.0.weight",
                "pose_refiner.2.bias",
                "lbs_offsets.4.weight",
                "lbs_offsets.0.bias",
            ];
            let is_non_rigid =
                !name.starts_with("pose_refiner") && !name.starts_with("lbs_offsets");
            if !(wanted.contains(&name.as_str()) || is_non_rigid) {
                continue;
            }
            let analytic_all: Vec<f64> = networks
                .parameters()
                .iter()
                .find(|p| &p.name == name)
                .unwrap()
                .grads
                .to_vec();
            for k in [0, len / 2, len - 1] {
                let eval = |delta: f64| {
                    let mut moved = networks.clone();
                    for p in moved.parameters_mut() {
                        if &p.name == name {
                            p.values[k] += delta;
                        }
                    }
                    loss(&setup, &moved, &setup.gaussians.xyz)
                };
                let numeric = (eval(eps) - eval(-eps)) / (2.0 * eps);
                check(&format!("{name}[{k}]"), numeric, analytic_all[k]);
                checked += 1;
            }
        }
        assert!(checked >= 12, "checked {checked} parameters");
        if lbs_offsets {
            return;
        }
        for i in [0, 7, 3 * n - 1] {
            let eval = |delta: f64| {
                let mut x = setup.gaussians.xyz.clone();
                x[i] += delta;
                loss(&setup, &networks, &x)
            };
            let numeric = (eval(eps) - eval(-eps)) / (2.0 * eps);
            check(&format!("xyz[{i}]"), numeric, d_xyz[i]);
        }
    }
}
