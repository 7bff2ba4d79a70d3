//! The trained avatar: canonical Gaussians, the body rig and (with a motion context) the
//! networks, as stored in a `train` entry, and its render path, which is exactly the
//! training forward pass (networks, skinning, splatting) without gradients.
//!
//! # Entry arrays written by [`TrainedAvatar::write`]
//!
//! - `gaussian_xyz` f64 `(gaussian, xyz)`: canonical (big-pose) centres, metres.
//! - `gaussian_sh` f64 `(gaussian, coeff, rgb)`: 16 SH coefficients per channel (degree 3
//!   storage; the attribute `sh_degree` says how many are active).
//! - `gaussian_opacity` f64 `(gaussian)`: opacity logits (activated with a sigmoid).
//! - `gaussian_log_scale` f64 `(gaussian, xyz)`; `gaussian_rotation` f64 `(gaussian, wxyz)`.
//! - The body model arrays of the ingest schema (`body_model_*`), so that the entry renders
//!   on its own.
//! - `network/<name>` f64: network parameters by their stable names (when the motion context
//!   or the refiners use networks).
//!
//! Attributes: `config` (the resolved train config), `sh_degree`, `scales` (raw temporal
//! scales fed to the networks, largest first), `scale_steps`, `sequence_length`,
//! `background`, `body_model_kind`, `extent`.

use anyhow::Context;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::splat::{RasterOptions, RenderedImage, sh_coefficient_count};
use seqavatar_core::body::BodyParams;
use seqavatar_core::camera::Camera;
use seqavatar_engine::{EntryReader, EntryWriter};
use seqavatar_ingest::stage::write_body_model;

use crate::config::TrainConfig;
use crate::data::MotionTrack;
use crate::densify::{GaussianState, names};
use crate::gaussians::{SH, SH_STORED};
use crate::knn::{KnnGrid, as_points};
use crate::model::gpu::{GpuNetworks, GpuNonRigidCache};
use crate::model::{
    GaussianInputs, LbsOffsetsCache, NetworkConfig, NetworkGroup, Networks, NonRigidCache,
    NonRigidOutput, PoseRefinerCache,
};
use crate::rig::{BodyRig, FramePose, PoseChain, refine_pose};
use crate::skinning::{GaussianParams, Skinned, SkinningGrads, skin_forward};
use crate::splatting::{self, WorldGaussians};

/// The per-Gaussian parameters of an avatar (flat, row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct AvatarGaussians {
    pub xyz: Vec<f64>,
    /// `N x 16 x 3`.
    pub sh: Vec<f64>,
    pub opacity_logit: Vec<f64>,
    pub log_scale: Vec<f64>,
    pub rotation: Vec<f64>,
}

impl AvatarGaussians {
    pub fn len(&self) -> usize {
        self.opacity_logit.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logit.is_empty()
    }

    /// The trainable columns of a training state.
    pub fn from_state(state: &GaussianState) -> anyhow::Result<Self> {
        Ok(Self {
            xyz: state.values(names::POSITION)?.to_vec(),
            sh: state.values(SH)?.to_vec(),
            opacity_logit: state.values(names::OPACITY_LOGIT)?.to_vec(),
            log_scale: state.values(names::LOG_SCALE)?.to_vec(),
            rotation: state.values(names::ROTATION)?.to_vec(),
        })
    }
}

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
    config: &TrainConfig,
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
        let (s, v) = motion.gather(frame, config.sequence_length, &slots);
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

/// One frame's (possibly refined) skinning target and what its backward needs.
pub struct PosedFrame {
    pub pose: FramePose,
    pub chain: PoseChain,
    /// The refiner's cache and its `(J - 1) x 9` matrices, when the pose refiner is on.
    pub refiner: Option<(PoseRefinerCache<f64>, Vec<f64>)>,
}

/// The local pose without the root joint, `3 (J - 1)` values.
pub fn local_pose(params: &BodyParams) -> Vec<f64> {
    params.pose[1..].iter().flat_map(|v| v.to_array()).collect()
}

/// The skinning target of a frame, through the pose refiner when the networks have one.
pub fn frame_pose(
    rig: &BodyRig,
    networks: Option<&Networks<f64>>,
    params: &BodyParams,
) -> anyhow::Result<PosedFrame> {
    match networks.filter(|n| n.has_pose_refiner()) {
        Some(net) => {
            let (matrices, cache) = net.pose_refiner_forward(&local_pose(params))?;
            let refinements: Vec<seqavatar_core::glam::DMat3> = matrices
                .chunks_exact(9)
                .map(|m| {
                    seqavatar_core::glam::DMat3::from_cols_array(&[
                        m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8],
                    ])
                })
                .collect();
            let refined = refine_pose(params, &refinements);
            let (pose, chain) = rig.pose_with_chain(&refined)?;
            Ok(PosedFrame {
                pose,
                chain,
                refiner: Some((cache, matrices)),
            })
        }
        None => {
            let (pose, chain) = rig.pose_with_chain(params)?;
            Ok(PosedFrame {
                pose,
                chain,
                refiner: None,
            })
        }
    }
}

/// The deformed Gaussians of one frame and the intermediates the backward needs.
pub struct Deformed {
    /// Nearest template vertex of each (post-non-rigid) centre.
    pub nearest: Vec<u32>,
    pub non_rigid: Option<NonRigidPass>,
    /// LBS weight offsets `N x J` and their cache.
    pub weight_offsets: Option<(Vec<f64>, LbsOffsetsCache<f64>)>,
    /// Centres after the non-rigid offset (canonical space).
    pub positions: Vec<f64>,
    /// Linear scale offsets `N x 3` and rotation offsets `N x 4`.
    pub d_scales: Vec<f64>,
    pub d_rotations: Vec<f64>,
    pub skinned: Skinned,
    pub world: WorldGaussians,
}

/// The activations of the non-rigid network's forward pass, where it ran.
pub enum NonRigidPass {
    /// On `cpu`, in f64 (the parameter master).
    Cpu(NonRigidCache<f64>),
    /// On the gpu, in f32 ([`GpuNetworks`], a copy of the master's parameters).
    Gpu(GpuNonRigidCache),
}

fn narrow(values: &[f64]) -> Vec<f32> {
    values.iter().map(|&v| v as f32).collect()
}

fn widen(values: &[f32]) -> Vec<f64> {
    values.iter().map(|&v| f64::from(v)).collect()
}

/// Per Gaussian the velocities of its `tau` nearest template vertices (of its canonical
/// centre), `N x L x tau x S x 3`, from a window `(L, S, V, 3)`.
pub fn knn_velocity(
    template_grid: &KnnGrid,
    xyz: &[f64],
    window: &[f32],
    length: usize,
    n_scales: usize,
    tau: usize,
) -> Vec<f64> {
    let n = xyz.len() / 3;
    let v = window.len() / (length * n_scales * 3).max(1);
    let neighbours = template_grid.query_all(&as_points(xyz), tau);
    let mut out = Vec::with_capacity(n * length * tau * n_scales * 3);
    for i in 0..n {
        for l in 0..length {
            for &vertex in &neighbours[i * tau..(i + 1) * tau] {
                for s in 0..n_scales {
                    let at = ((l * n_scales + s) * v + vertex as usize) * 3;
                    out.extend(window[at..at + 3].iter().map(|x| f64::from(*x)));
                }
            }
        }
    }
    out
}

/// The forward pass shared by training and rendering: non-rigid offsets from the networks
/// (zeros without them), nearest template vertex of the moved centre, LBS weight offsets,
/// skinning, activations. Everything runs on `cpu` in f64 (see [`deform_on`]).
#[allow(clippy::too_many_arguments)]
pub fn deform(
    rig: &BodyRig,
    template_grid: &KnnGrid,
    networks: Option<&Networks<f64>>,
    gaussians: &AvatarGaussians,
    inputs: &FrameInputs,
    pose: &FramePose,
    config: &TrainConfig,
    sh_degree: u32,
) -> anyhow::Result<Deformed> {
    deform_on(
        rig,
        template_grid,
        networks,
        None,
        gaussians,
        inputs,
        pose,
        config,
        sh_degree,
    )
}

/// [`deform`] with the non-rigid network evaluated on the gpu when `gpu_networks` is given
/// (a copy of `networks`' parameters; inputs rounded to f32 once, outputs widened to f64).
/// The pose refiner and the LBS offsets stay on `cpu`: they are per-frame or cheap next to
/// the per-Gaussian non-rigid network.
#[allow(clippy::too_many_arguments)]
pub fn deform_on(
    rig: &BodyRig,
    template_grid: &KnnGrid,
    networks: Option<&Networks<f64>>,
    gpu_networks: Option<&GpuNetworks>,
    gaussians: &AvatarGaussians,
    inputs: &FrameInputs,
    pose: &FramePose,
    config: &TrainConfig,
    sh_degree: u32,
) -> anyhow::Result<Deformed> {
    let n = gaussians.len();
    if let Some(bad) = gaussians.xyz.iter().position(|v| !v.is_finite()) {
        anyhow::bail!("Gaussian {} has a non-finite centre", bad / 3);
    }
    let (positions, d_scales, d_rotations, non_rigid) =
        match networks.filter(|net| net.has_non_rigid()) {
            Some(net) => {
                let net_config = net.config();
                let skeleton: Vec<f64>;
                let skeleton_motion = if config.motion_context.has_skeleton_motion() {
                    skeleton = inputs
                        .skeleton_motion
                        .iter()
                        .map(|x| f64::from(*x))
                        .collect();
                    Some(skeleton.as_slice())
                } else {
                    None
                };
                let velocity: Vec<f64>;
                let knn = if config.motion_context.has_velocity() {
                    velocity = knn_velocity(
                        template_grid,
                        &gaussians.xyz,
                        &inputs.vertex_velocity,
                        net_config.sequence_length,
                        net_config.n_scales,
                        net_config.tau,
                    );
                    Some(velocity.as_slice())
                } else {
                    None
                };
                let pose_values = local_pose(&inputs.params);
                let (out, cache) = match gpu_networks {
                    None => {
                        let (out, cache) = net.non_rigid_forward(
                            &crate::model::FrameInputs {
                                local_pose: &pose_values,
                                skeleton_motion,
                            },
                            &GaussianInputs {
                                xyz: &gaussians.xyz,
                                knn_velocity: knn,
                            },
                        )?;
                        (out, NonRigidPass::Cpu(cache))
                    }
                    Some(gpu) => {
                        let pose32 = narrow(&pose_values);
                        let knn32 = knn.map(narrow);
                        let xyz32 = narrow(&gaussians.xyz);
                        let skeleton32 = skeleton_motion.map(|_| inputs.skeleton_motion.as_slice());
                        let (out, cache) = gpu.non_rigid_forward(
                            &crate::model::FrameInputs {
                                local_pose: &pose32,
                                skeleton_motion: skeleton32,
                            },
                            &GaussianInputs {
                                xyz: &xyz32,
                                knn_velocity: knn32.as_deref(),
                            },
                        )?;
                        let out = NonRigidOutput {
                            d_xyz: widen(&out.d_xyz),
                            d_rot: widen(&out.d_rot),
                            d_scale: widen(&out.d_scale),
                        };
                        (out, NonRigidPass::Gpu(cache))
                    }
                };
                let positions: Vec<f64> = gaussians
                    .xyz
                    .iter()
                    .zip(&out.d_xyz)
                    .map(|(a, b)| a + b)
                    .collect();
                (positions, out.d_scale, out.d_rot, Some(cache))
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
        Some(net) => Some(net.lbs_offsets_forward(&positions)?),
        None => None,
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
/// A non-rigid pass that ran on the gpu runs its backward there too (`gpu_networks`, the
/// copy it ran on): its parameter gradients are downloaded and added to `networks`'.
#[allow(clippy::too_many_arguments)]
pub fn deform_backward(
    networks: &mut Networks<f64>,
    gpu_networks: Option<&GpuNetworks>,
    rig: &BodyRig,
    posed: &PosedFrame,
    deformed: &Deformed,
    params: &BodyParams,
    skin: &SkinningGrads,
) -> anyhow::Result<Vec<f64>> {
    let mut through = vec![0.0; deformed.positions.len()];
    match &deformed.non_rigid {
        None => {}
        Some(NonRigidPass::Cpu(cache)) => {
            through = networks.non_rigid_backward(
                cache,
                &skin.positions,
                &skin.d_rotations,
                &skin.d_scales,
            )?;
        }
        Some(NonRigidPass::Gpu(cache)) => {
            let gpu = gpu_networks.context(
                "the non-rigid pass ran on the gpu, but its backward got no gpu networks",
            )?;
            // The device gradients accumulate across backwards; start from zero so the
            // download holds exactly this pass's contribution.
            gpu.zero_grad()?;
            let d_canonical = gpu.non_rigid_backward(
                cache,
                &narrow(&skin.positions),
                &narrow(&skin.d_rotations),
                &narrow(&skin.d_scales),
            )?;
            gpu.add_group_gradients_into(networks, NetworkGroup::NonRigid)?;
            if !d_canonical.is_empty() {
                through = widen(&d_canonical);
            }
        }
    }
    if let Some((_, cache)) = &deformed.weight_offsets {
        networks.lbs_offsets_backward(cache, &skin.weight_offsets)?;
    }
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
        networks.pose_refiner_backward(cache, &flat)?;
    }
    Ok(through)
}

/// Whether a configuration trains networks.
pub fn needs_networks(config: &TrainConfig) -> bool {
    config.motion_context.has_non_rigid() || config.pose_refiner || config.lbs_offsets
}

/// A grid over the canonical template vertices for nearest-vertex queries.
pub fn template_grid(rig: &BodyRig) -> KnnGrid {
    KnnGrid::new(&as_points(&rig.canonical_vertices), 4.0)
}

/// A trained avatar, ready to render.
pub struct TrainedAvatar {
    pub config: TrainConfig,
    pub rig: BodyRig,
    pub gaussians: AvatarGaussians,
    /// Active SH degree.
    pub sh_degree: u32,
    /// Raw temporal scales the networks were trained with (largest first).
    pub scales: Vec<u32>,
    pub background: [f64; 3],
    /// The networks (absent for motion context `none` without refiners).
    pub networks: Option<Networks<f64>>,
    template_grid: KnnGrid,
}

impl TrainedAvatar {
    pub fn new(
        config: TrainConfig,
        rig: BodyRig,
        gaussians: AvatarGaussians,
        sh_degree: u32,
        scales: Vec<u32>,
        networks: Option<Networks<f64>>,
    ) -> Self {
        let template_grid = template_grid(&rig);
        Self {
            background: config.background,
            networks,
            config,
            rig,
            gaussians,
            sh_degree,
            scales,
            template_grid,
        }
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

    /// Renders one frame from `camera` on `backend`: colour (background included) and alpha.
    pub fn render(
        &self,
        inputs: &FrameInputs,
        camera: &Camera,
        backend: &Backend,
    ) -> anyhow::Result<RenderedImage<f64>> {
        let posed = frame_pose(&self.rig, self.networks.as_ref(), &inputs.params)?;
        let deformed = deform(
            &self.rig,
            &self.template_grid,
            self.networks.as_ref(),
            &self.gaussians,
            inputs,
            &posed.pose,
            &self.config,
            self.sh_degree,
        )?;
        let options = RasterOptions {
            background: self.background,
            smooth_cutoff: false,
        };
        let mut pass = splatting::forward(
            backend,
            &deformed.world,
            std::slice::from_ref(camera),
            &options,
        )?;
        Ok(pass.images.swap_remove(0))
    }

    /// Writes the avatar arrays and attributes into an entry.
    pub fn write(
        &self,
        out: &EntryWriter,
        extent: f64,
        body_model_kind: &str,
    ) -> anyhow::Result<()> {
        let g = &self.gaussians;
        let n = g.len() as u64;
        let chunk = n.max(1);
        out.write_array(
            "gaussian_xyz",
            &["gaussian", "xyz"],
            &[n, 3],
            &[chunk, 3],
            &g.xyz,
        )?;
        out.write_array(
            "gaussian_sh",
            &["gaussian", "coeff", "rgb"],
            &[n, SH_STORED as u64, 3],
            &[chunk, SH_STORED as u64, 3],
            &g.sh,
        )?;
        out.write_array(
            "gaussian_opacity",
            &["gaussian"],
            &[n],
            &[chunk],
            &g.opacity_logit,
        )?;
        out.write_array(
            "gaussian_log_scale",
            &["gaussian", "xyz"],
            &[n, 3],
            &[chunk, 3],
            &g.log_scale,
        )?;
        out.write_array(
            "gaussian_rotation",
            &["gaussian", "wxyz"],
            &[n, 4],
            &[chunk, 4],
            &g.rotation,
        )?;
        if let Some(networks) = &self.networks {
            for param in networks.parameters() {
                let shape: Vec<u64> = param.shape.iter().map(|&d| d as u64).collect();
                let dims: &[&str] = if shape.len() == 2 {
                    &["input", "output"]
                } else {
                    &["output"]
                };
                let chunk: Vec<u64> = shape.iter().map(|&d| d.max(1)).collect();
                out.write_array(
                    &format!("network.{}", param.name),
                    dims,
                    &shape,
                    &chunk,
                    param.values,
                )?;
            }
        }
        write_body_model(out, &self.rig.model)?;
        out.set_attribute("config", serde_json::to_value(&self.config)?)?;
        out.set_attribute("sh_degree", self.sh_degree.into())?;
        out.set_attribute("scales", serde_json::to_value(&self.scales)?)?;
        out.set_attribute("sequence_length", self.config.sequence_length.into())?;
        out.set_attribute("background", serde_json::to_value(self.background)?)?;
        out.set_attribute("body_model_kind", body_model_kind.into())?;
        out.set_attribute("extent", extent.into())?;
        if let Some(networks) = &self.networks {
            out.set_attribute("motion_joints", networks.config().motion_joints.into())?;
        }
        Ok(())
    }

    /// Reads an avatar from a `train` entry; errors name the entry and the array or
    /// attribute.
    pub fn load(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        let attribute = |key: &str| {
            entry
                .attribute(key)
                .ok_or_else(|| anyhow::anyhow!("entry {location}: attribute `{key}` is missing"))
        };
        let config: TrainConfig = serde_json::from_value(attribute("config")?)
            .with_context(|| format!("entry {location}: attribute `config`"))?;
        config
            .validate()
            .with_context(|| format!("entry {location}: attribute `config`"))?;
        let sh_degree = attribute("sh_degree")?
            .as_u64()
            .filter(|d| *d <= 3)
            .ok_or_else(|| {
                anyhow::anyhow!("entry {location}: attribute `sh_degree` is not 0..=3")
            })? as u32;
        let scales: Vec<u32> = serde_json::from_value(attribute("scales")?)
            .with_context(|| format!("entry {location}: attribute `scales`"))?;
        let background: [f64; 3] = serde_json::from_value(attribute("background")?)
            .with_context(|| format!("entry {location}: attribute `background`"))?;
        let xyz = entry.read::<f64>("gaussian_xyz")?;
        anyhow::ensure!(
            xyz.shape.len() == 2 && xyz.shape[1] == 3,
            "entry {location}: array `gaussian_xyz` has shape {:?}, expected (gaussian, 3)",
            xyz.shape
        );
        let n = xyz.shape[0];
        let read = |name: &str, shape: &[usize]| -> anyhow::Result<Vec<f64>> {
            let a = entry.read::<f64>(name)?;
            anyhow::ensure!(
                a.shape == shape,
                "entry {location}: array `{name}` has shape {:?}, expected {shape:?}",
                a.shape
            );
            if let Some(bad) = a.data.iter().position(|v| !v.is_finite()) {
                anyhow::bail!("entry {location}: array `{name}` has a non-finite value at {bad}");
            }
            Ok(a.data)
        };
        let gaussians = AvatarGaussians {
            xyz: read("gaussian_xyz", &[n, 3])?,
            sh: read("gaussian_sh", &[n, SH_STORED, 3])?,
            opacity_logit: read("gaussian_opacity", &[n])?,
            log_scale: read("gaussian_log_scale", &[n, 3])?,
            rotation: read("gaussian_rotation", &[n, 4])?,
        };
        let model = seqavatar_ingest::read_body_model(entry)
            .with_context(|| format!("entry {location}: body model"))?;
        let rig = BodyRig::new(model)?;
        let networks = if needs_networks(&config) {
            let motion_joints = match attribute("motion_joints")?.as_u64() {
                Some(j) => j as usize,
                None => anyhow::bail!("entry {location}: attribute `motion_joints` is not a count"),
            };
            let net_config =
                NetworkConfig::from_train(&config, rig.joint_count(), motion_joints, scales.len())
                    .with_context(|| format!("entry {location}: network configuration"))?;
            let mut networks = Networks::new(&net_config, config.seed)
                .with_context(|| format!("entry {location}: network configuration"))?;
            let names = entry.array_names();
            networks
                .load_parameters(|name| {
                    let array = format!("network.{name}");
                    if !names.contains(&array) {
                        return None;
                    }
                    entry.read::<f64>(&array).ok().map(|a| a.data)
                })
                .with_context(|| format!("entry {location}: network arrays `network.*`"))?;
            Some(networks)
        } else {
            None
        };
        let mut avatar = Self::new(config, rig, gaussians, sh_degree, scales, networks);
        avatar.background = background;
        Ok(avatar)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{MotionContext, Preset};
    use crate::model::Widths;
    use crate::rng::Rng;
    use crate::skinning::skin_backward;
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_core::glam::DVec3;

    struct Setup {
        rig: BodyRig,
        grid: KnnGrid,
        config: TrainConfig,
        gaussians: AvatarGaussians,
        inputs: FrameInputs,
        a: Vec<f64>,
        b: Vec<f64>,
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

    /// The same with the LBS weight offsets. Their input is detached (method.md), so the
    /// centres and the non-rigid network, which move that input, are checked without them.
    #[test]
    fn lbs_offset_gradients_match_finite_differences() {
        check_deformation_gradients(MotionContext::None, true);
    }

    fn check_deformation_gradients(context: MotionContext, lbs_offsets: bool) {
        let model = procedural_body(0.05);
        let rig = BodyRig::new(model.clone()).unwrap();
        let grid = template_grid(&rig);
        let mut rng = Rng::new(9);
        let mut config = TrainConfig::preset(Preset::Fast);
        config.motion_context = context;
        config.lbs_offsets = lbs_offsets;
        config.trunk_width = 16;
        config.trunk_depth = 2;
        config.tau = 2;
        config.sequence_length = 2;
        let (j, v, scales) = (rig.joint_count(), rig.vertex_count(), 2);
        let n = 12;
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
        let mut net_config = NetworkConfig::from_train(&config, j, j, scales).unwrap();
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
        // Analytic gradients.
        let posed = frame_pose(&setup.rig, Some(&networks), &setup.inputs.params).unwrap();
        let deformed = deform(
            &setup.rig,
            &setup.grid,
            Some(&networks),
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
            &GaussianParams {
                positions: &deformed.positions,
                log_scales: &setup.gaussians.log_scale,
                d_scales: &deformed.d_scales,
                rotations: &setup.gaussians.rotation,
                d_rotations: &deformed.d_rotations,
                weight_offsets: deformed.weight_offsets.as_ref().map(|(w, _)| w.as_slice()),
                nearest: &deformed.nearest,
            },
            &setup.a,
            &setup.b,
        );
        networks.zero_grad();
        let through = deform_backward(
            &mut networks,
            None,
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
