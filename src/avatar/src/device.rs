//! The backend an avatar's numeric work runs on, chosen once.
//!
//! [`AvatarBackend`] is everything the host render and training paths ask of a backend: the
//! per-Gaussian networks (non-rigid and LBS offsets) forward and backward, and splatting
//! forward and backward. [`avatar_backend`] is the one place that looks at which backend a
//! [`Backend`] is (itself resolved once from a `device:` setting by [`Backend::select`]): it
//! builds the `cpu` implementation, or the `gpu` one, which owns its context and its f32
//! copy of the per-Gaussian networks. The trainer's host step, `pipeline export` and the
//! host render path build one when they are built and call through it; none of them
//! asks which backend it is (as Brush picks its backend once and never asks again).
//!
//! On this host path the pose refiner is not a backend operation: it runs on `cpu` (one row
//! per frame). How a whole sequence is rendered (this host path, or entirely on the device)
//! is chosen once as well, by the sequence renderer.

use std::sync::Arc;

use anyhow::Context;
use seqavatar_compute::backend::{Backend, GpuContext};
use seqavatar_compute::nn::{NnScalar, Precision};
use seqavatar_compute::splat::{RasterOptions, SplatGradients};
use seqavatar_core::camera::Camera;
use seqavatar_motion::knn::{KnnGrid, as_points};

use crate::model::gpu::{GpuLbsOffsetsCache, GpuNetworks, GpuNonRigidCache};
use crate::model::{
    FrameInputs, GaussianInputs, LbsOffsetsCache, NetworkConfig, NetworkGroup, Networks,
    NonRigidCache,
};
use crate::skinning::SkinningGrads;
use crate::splatting::{self, SplatPass, WorldGaussians};

/// The activations of the non-rigid network's forward pass, where it ran.
pub enum NonRigidPass<S = f32> {
    /// On `cpu`, in the networks' scalar.
    Cpu(NonRigidCache<S>),
    /// On the gpu, in f32 ([`GpuNetworks`], a copy of the master's parameters).
    Gpu(GpuNonRigidCache),
}

/// The activations of the LBS-offset network's forward pass, where it ran.
pub enum LbsOffsetsPass<S = f32> {
    /// On `cpu`, in the networks' scalar.
    Cpu(LbsOffsetsCache<S>),
    /// On the gpu, in f32 ([`GpuNetworks`], a copy of the master's parameters).
    Gpu(GpuLbsOffsetsCache),
}

/// The non-rigid network's inputs of one frame, as the render path holds them (f64 pose and
/// centres, f32 motion windows); each backend rounds them to its scalar once.
pub struct NonRigidInputs<'a> {
    /// The local pose without the root joint, `3 (J - 1)` values.
    pub local_pose: &'a [f64],
    /// The skeleton-motion window `(L, S, J, 3)`, for motion contexts with skeleton motion.
    pub skeleton_motion: Option<&'a [f32]>,
    /// Canonical centres, `N x 3`.
    pub xyz: &'a [f64],
    /// For motion contexts with velocity: the grid over the canonical template vertices and
    /// the window `(L, S, V, 3)` of their velocities, gathered per Gaussian by
    /// [`knn_velocity`] in the backend's scalar.
    pub vertex_velocity: Option<(&'a KnnGrid, &'a [f32])>,
}

impl NonRigidInputs<'_> {
    fn knn_velocity<T: NnScalar>(&self, config: &NetworkConfig) -> Option<Vec<T>> {
        self.vertex_velocity.map(|(grid, window)| {
            knn_velocity(
                grid,
                self.xyz,
                window,
                config.sequence_length,
                config.n_scales,
                config.tau,
            )
        })
    }
}

/// f64 values in the networks' scalar (rounded once for f32).
pub(crate) fn to_scalar<S: NnScalar>(values: &[f64]) -> Vec<S> {
    values.iter().map(|&v| S::from_f64(v)).collect()
}

/// The networks' values in f64 (exact).
pub(crate) fn to_f64<S: NnScalar>(values: &[S]) -> Vec<f64> {
    values.iter().map(|&v| v.to_f64()).collect()
}

/// Per Gaussian the velocities of its `tau` nearest template vertices (of its canonical
/// centre), `N x L x tau x S x 3`, from a window `(L, S, V, 3)`.
pub fn knn_velocity<S: NnScalar>(
    template_grid: &KnnGrid,
    xyz: &[f64],
    window: &[f32],
    length: usize,
    n_scales: usize,
    tau: usize,
) -> Vec<S> {
    let n = xyz.len() / 3;
    let v = window.len() / (length * n_scales * 3).max(1);
    // The canonical centres move by at most an optimiser step per iteration (and not at all
    // between rendered frames): the grid's candidate lists answer most calls.
    let neighbours = template_grid.query_all_tracked(&as_points(xyz), tau);
    let mut out = Vec::with_capacity(n * length * tau * n_scales * 3);
    for i in 0..n {
        for l in 0..length {
            for &vertex in &neighbours[i * tau..(i + 1) * tau] {
                for s in 0..n_scales {
                    let at = ((l * n_scales + s) * v + vertex as usize) * 3;
                    out.extend(
                        window[at..at + 3]
                            .iter()
                            .map(|&x| S::from_f64(f64::from(x))),
                    );
                }
            }
        }
    }
    out
}

/// The non-rigid network's outputs, widened to f64.
pub struct NonRigidOffsets {
    /// Position offsets, `N x 3`.
    pub d_xyz: Vec<f64>,
    /// Rotation offsets (unnormalised `wxyz` quaternions), `N x 4`.
    pub d_rot: Vec<f64>,
    /// Linear scale offsets, `N x 3`.
    pub d_scale: Vec<f64>,
}

/// What the render and training paths ask of a backend; `S` is the scalar of the `cpu`
/// networks (the parameter master: f32 in production, f64 the oracle in tests). Built by
/// [`avatar_backend`] for one set of networks.
pub trait AvatarBackend<S: NnScalar = f32>: Send + Sync {
    /// The compute backend, for the compute operations that take one (LPIPS).
    fn compute(&self) -> &Backend;

    /// One line for run summaries: which backend runs, and on which adapter.
    fn describe(&self) -> String {
        self.compute().describe()
    }

    /// Whether the per-Gaussian networks run on a gpu copy (`gpu` backend built with
    /// per-Gaussian networks).
    fn networks_on_gpu(&self) -> bool;

    /// Makes the backend's copy of the per-Gaussian networks equal to `networks` (the
    /// master, changed by every optimiser step); nothing to do on `cpu`.
    fn refresh_networks(&self, networks: &Networks<S>) -> anyhow::Result<()>;

    /// The non-rigid network's forward pass.
    fn non_rigid_forward(
        &self,
        networks: &Networks<S>,
        inputs: &NonRigidInputs<'_>,
    ) -> anyhow::Result<(NonRigidOffsets, NonRigidPass<S>)>;

    /// The LBS-offset network's forward pass: offsets `N x J` of the centres `positions`.
    fn lbs_offsets_forward(
        &self,
        networks: &Networks<S>,
        positions: &[f64],
    ) -> anyhow::Result<(Vec<f64>, LbsOffsetsPass<S>)>;

    /// Backward of the per-Gaussian networks' forward passes (`non_rigid`, `lbs_offsets`:
    /// those that ran) from the skinning's gradients: their parameter gradients accumulate
    /// into `networks`' (the master), and the gradient of the canonical centres through the
    /// non-rigid network is returned (zeros without one).
    fn networks_backward(
        &self,
        networks: &mut Networks<S>,
        non_rigid: Option<&NonRigidPass<S>>,
        lbs_offsets: Option<&LbsOffsetsPass<S>>,
        skin: &SkinningGrads,
    ) -> anyhow::Result<Vec<f64>>;

    /// Renders `gaussians` from `cameras`, keeping what the backward needs.
    fn splat_forward(
        &self,
        gaussians: &WorldGaussians,
        cameras: &[Camera],
        options: &RasterOptions,
    ) -> anyhow::Result<SplatPass>;

    /// Gradients with respect to the Gaussians given to the forward of `pass` (the pass keeps
    /// the f32 copy both backends splat).
    fn splat_backward(
        &self,
        pass: &SplatPass,
        colour: &[Vec<f64>],
        alpha: &[Vec<f64>],
    ) -> anyhow::Result<SplatGradients<f64>>;
}

/// The backend `backend` names, for the networks `networks` (those of the avatar or the
/// trainer it serves; `None` without networks). The one place that looks at which backend
/// it is: on the gpu the per-Gaussian networks are uploaded here, once, as an f32 copy whose
/// dense layers take the path `precision` chooses ([`AvatarConfig::networks_precision`];
/// `cpu` always runs f32).
///
/// [`AvatarConfig::networks_precision`]: crate::config::AvatarConfig::networks_precision
pub fn avatar_backend<S: NnScalar>(
    backend: Backend,
    networks: Option<&Networks<S>>,
    precision: Precision,
) -> anyhow::Result<Box<dyn AvatarBackend<S>>> {
    match &backend {
        Backend::Cpu => Ok(Box::new(CpuBackend { backend })),
        Backend::Gpu(context) => {
            let context = context.clone();
            let copy = networks
                .filter(|net| net.has_non_rigid() || net.has_lbs_offsets())
                .map(|net| upload(context.clone(), net, precision))
                .transpose()
                .context("uploading the networks to the gpu")?;
            Ok(Box::new(GpuBackend {
                backend,
                context,
                networks: copy,
            }))
        }
    }
}

/// An f32 copy of `networks` on `context` (f64 values rounded once).
fn upload<S: NnScalar>(
    context: Arc<GpuContext>,
    networks: &Networks<S>,
    precision: Precision,
) -> anyhow::Result<GpuNetworks> {
    let mut narrow = Networks::<f32>::new(networks.config(), 0)?;
    narrow.load_parameters(|name| {
        networks
            .parameters()
            .into_iter()
            .find(|param| param.name == name)
            .map(|param| param.values.iter().map(|v| v.to_f64() as f32).collect())
    })?;
    Ok(GpuNetworks::upload(context, &narrow, precision)?)
}

/// Plain Rust: the networks in their scalar, splatting in f64.
struct CpuBackend {
    backend: Backend,
}

const FOREIGN_PASS: &str = "a pass that ran on another backend";

impl<S: NnScalar> AvatarBackend<S> for CpuBackend {
    fn compute(&self) -> &Backend {
        &self.backend
    }

    fn networks_on_gpu(&self) -> bool {
        false
    }

    fn refresh_networks(&self, _networks: &Networks<S>) -> anyhow::Result<()> {
        Ok(())
    }

    fn non_rigid_forward(
        &self,
        networks: &Networks<S>,
        inputs: &NonRigidInputs<'_>,
    ) -> anyhow::Result<(NonRigidOffsets, NonRigidPass<S>)> {
        let skeleton: Option<Vec<S>> = inputs
            .skeleton_motion
            .map(|window| window.iter().map(|&x| S::from_f64(f64::from(x))).collect());
        let knn: Option<Vec<S>> = inputs.knn_velocity(networks.config());
        let (out, cache) = networks.non_rigid_forward(
            &FrameInputs {
                local_pose: &to_scalar(inputs.local_pose),
                skeleton_motion: skeleton.as_deref(),
            },
            &GaussianInputs {
                xyz: &to_scalar(inputs.xyz),
                knn_velocity: knn.as_deref(),
            },
        )?;
        Ok((
            NonRigidOffsets {
                d_xyz: to_f64(&out.d_xyz),
                d_rot: to_f64(&out.d_rot),
                d_scale: to_f64(&out.d_scale),
            },
            NonRigidPass::Cpu(cache),
        ))
    }

    fn lbs_offsets_forward(
        &self,
        networks: &Networks<S>,
        positions: &[f64],
    ) -> anyhow::Result<(Vec<f64>, LbsOffsetsPass<S>)> {
        let (offsets, cache) = networks.lbs_offsets_forward(&to_scalar(positions))?;
        Ok((to_f64(&offsets), LbsOffsetsPass::Cpu(cache)))
    }

    fn networks_backward(
        &self,
        networks: &mut Networks<S>,
        non_rigid: Option<&NonRigidPass<S>>,
        lbs_offsets: Option<&LbsOffsetsPass<S>>,
        skin: &SkinningGrads,
    ) -> anyhow::Result<Vec<f64>> {
        let mut through = vec![0.0; skin.positions.len()];
        if let Some(pass) = non_rigid {
            let NonRigidPass::Cpu(cache) = pass else {
                anyhow::bail!("non-rigid backward on cpu: {FOREIGN_PASS} (gpu)");
            };
            through = to_f64(&networks.non_rigid_backward(
                cache,
                &to_scalar(&skin.positions),
                &to_scalar(&skin.d_rotations),
                &to_scalar(&skin.d_scales),
            )?);
        }
        if let Some(pass) = lbs_offsets {
            let LbsOffsetsPass::Cpu(cache) = pass else {
                anyhow::bail!("LBS-offset backward on cpu: {FOREIGN_PASS} (gpu)");
            };
            networks.lbs_offsets_backward(cache, &to_scalar(&skin.weight_offsets))?;
        }
        Ok(through)
    }

    fn splat_forward(
        &self,
        gaussians: &WorldGaussians,
        cameras: &[Camera],
        options: &RasterOptions,
    ) -> anyhow::Result<SplatPass> {
        splatting::forward_cpu(gaussians, cameras, options)
    }

    fn splat_backward(
        &self,
        pass: &SplatPass,
        colour: &[Vec<f64>],
        alpha: &[Vec<f64>],
    ) -> anyhow::Result<SplatGradients<f64>> {
        splatting::backward_cpu(pass, colour, alpha)
    }
}

/// wgpu: the per-Gaussian networks on an f32 copy, splatting in f32 (inputs rounded once,
/// outputs widened).
struct GpuBackend {
    backend: Backend,
    context: Arc<GpuContext>,
    /// The f32 copy of the per-Gaussian networks; absent when the networks it was built for
    /// have none (then nothing asks for them).
    networks: Option<GpuNetworks>,
}

impl GpuBackend {
    /// The gpu copy, checked to be of `networks`' configuration.
    fn copy_of(&self, networks: &NetworkConfig) -> anyhow::Result<&GpuNetworks> {
        let copy = self.networks.as_ref().context(
            "the gpu backend was built without per-Gaussian networks, but is asked to run them",
        )?;
        anyhow::ensure!(
            copy.config() == networks,
            "the gpu backend was built for networks of another configuration"
        );
        Ok(copy)
    }
}

impl<S: NnScalar> AvatarBackend<S> for GpuBackend {
    fn compute(&self) -> &Backend {
        &self.backend
    }

    fn networks_on_gpu(&self) -> bool {
        self.networks.is_some()
    }

    fn refresh_networks(&self, networks: &Networks<S>) -> anyhow::Result<()> {
        if let Some(copy) = &self.networks {
            copy.upload_groups(networks, GpuNetworks::DEFORM_GROUPS)
                .context("uploading the networks to the gpu")?;
        }
        Ok(())
    }

    fn non_rigid_forward(
        &self,
        networks: &Networks<S>,
        inputs: &NonRigidInputs<'_>,
    ) -> anyhow::Result<(NonRigidOffsets, NonRigidPass<S>)> {
        let copy = self.copy_of(networks.config())?;
        let knn: Option<Vec<f32>> = inputs.knn_velocity(networks.config());
        let (out, cache) = copy.non_rigid_forward(
            &FrameInputs {
                local_pose: &to_scalar::<f32>(inputs.local_pose),
                skeleton_motion: inputs.skeleton_motion,
            },
            &GaussianInputs {
                xyz: &to_scalar::<f32>(inputs.xyz),
                knn_velocity: knn.as_deref(),
            },
        )?;
        Ok((
            NonRigidOffsets {
                d_xyz: to_f64(&out.d_xyz),
                d_rot: to_f64(&out.d_rot),
                d_scale: to_f64(&out.d_scale),
            },
            NonRigidPass::Gpu(cache),
        ))
    }

    fn lbs_offsets_forward(
        &self,
        networks: &Networks<S>,
        positions: &[f64],
    ) -> anyhow::Result<(Vec<f64>, LbsOffsetsPass<S>)> {
        let copy = self.copy_of(networks.config())?;
        let (offsets, cache) = copy.lbs_offsets_forward(&to_scalar::<f32>(positions))?;
        Ok((to_f64(&offsets), LbsOffsetsPass::Gpu(cache)))
    }

    fn networks_backward(
        &self,
        networks: &mut Networks<S>,
        non_rigid: Option<&NonRigidPass<S>>,
        lbs_offsets: Option<&LbsOffsetsPass<S>>,
        skin: &SkinningGrads,
    ) -> anyhow::Result<Vec<f64>> {
        let mut through = vec![0.0; skin.positions.len()];
        let mut ran: Vec<NetworkGroup> = Vec::new();
        let non_rigid = match non_rigid {
            None => None,
            Some(NonRigidPass::Gpu(cache)) => {
                ran.push(NetworkGroup::NonRigid);
                Some(cache)
            }
            Some(NonRigidPass::Cpu(_)) => {
                anyhow::bail!("non-rigid backward on the gpu: {FOREIGN_PASS} (cpu)")
            }
        };
        let lbs_offsets = match lbs_offsets {
            None => None,
            Some(LbsOffsetsPass::Gpu(cache)) => {
                ran.push(NetworkGroup::LbsOffsets);
                Some(cache)
            }
            Some(LbsOffsetsPass::Cpu(_)) => {
                anyhow::bail!("LBS-offset backward on the gpu: {FOREIGN_PASS} (cpu)")
            }
        };
        if ran.is_empty() {
            return Ok(through);
        }
        let copy = self.copy_of(networks.config())?;
        // The device gradients accumulate across backwards; start from zero so the download
        // holds exactly this pass's contribution.
        copy.zero_grad()?;
        if let Some(cache) = non_rigid {
            let d_canonical = copy.non_rigid_backward(
                cache,
                &to_scalar::<f32>(&skin.positions),
                &to_scalar::<f32>(&skin.d_rotations),
                &to_scalar::<f32>(&skin.d_scales),
            )?;
            if !d_canonical.is_empty() {
                through = to_f64(&d_canonical);
            }
        }
        if let Some(cache) = lbs_offsets {
            copy.lbs_offsets_backward(cache, &to_scalar::<f32>(&skin.weight_offsets))?;
        }
        copy.add_groups_gradients_into(networks, &ran)?;
        Ok(through)
    }

    fn splat_forward(
        &self,
        gaussians: &WorldGaussians,
        cameras: &[Camera],
        options: &RasterOptions,
    ) -> anyhow::Result<SplatPass> {
        splatting::forward_gpu(&self.context, gaussians, cameras, options)
    }

    fn splat_backward(
        &self,
        pass: &SplatPass,
        colour: &[Vec<f64>],
        alpha: &[Vec<f64>],
    ) -> anyhow::Result<SplatGradients<f64>> {
        splatting::backward_gpu(&self.context, pass, colour, alpha)
    }
}
