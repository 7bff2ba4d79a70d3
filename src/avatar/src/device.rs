//! The backend of an avatar's host paths, chosen once.
//!
//! [`AvatarBackend`] is everything the host render and training paths ask of a backend: the
//! per-Gaussian networks (non-rigid and LBS offsets) forward and backward, and splatting
//! forward and backward, in plain Rust on `cpu` (the networks in their scalar, splatting in
//! f32 on the lane path). [`avatar_backend`] builds it from a [`Backend`] (itself resolved
//! once from a `device:` setting by [`Backend::select`]); on the gpu nothing runs on the host
//! path: the trainer's step and the sequence renderer run the whole frame on the device,
//! each chosen once by its own factory. The trainer's host step and the sequence renderer's
//! host path build one when they are built and call through it.
//!
//! On this host path the pose refiner is not a backend operation either: it runs on `cpu`
//! (one row per frame).

use seqavatar_compute::backend::Backend;
use seqavatar_compute::nn::NnScalar;
use seqavatar_compute::splat::{RasterOptions, SplatGradients};
use seqavatar_core::camera::Camera;
use seqavatar_knn::{KnnGrid, as_points};

use crate::model::{
    FrameInputs, GaussianInputs, LbsOffsetsCache, NetworkConfig, Networks, NonRigidCache,
};
use crate::skinning::SkinningGrads;
use crate::splatting::{self, SplatPass, WorldGaussians};

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

/// What the host render and training paths ask of a backend, in plain Rust on `cpu`: the
/// per-Gaussian networks in their scalar `S` (the parameter master: f32 in production, f64
/// the oracle in tests), splatting in f32 on the lane path. Built by [`avatar_backend`].
#[derive(Debug)]
pub struct AvatarBackend(());

/// The host backend of `backend`: `cpu`'s; the gpu has no host path (it trains and renders
/// on the device). The one place the host path looks at which backend it is.
pub fn avatar_backend(backend: Backend) -> anyhow::Result<AvatarBackend> {
    match backend {
        Backend::Cpu => Ok(AvatarBackend(())),
        Backend::Gpu(_) => {
            anyhow::bail!("the host path runs on `cpu`; on the gpu, frames run on the device")
        }
    }
}

impl AvatarBackend {
    /// The non-rigid network's forward pass.
    pub fn non_rigid_forward<S: NnScalar>(
        &self,
        networks: &Networks<S>,
        inputs: &NonRigidInputs<'_>,
    ) -> anyhow::Result<(NonRigidOffsets, NonRigidCache<S>)> {
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
            cache,
        ))
    }

    /// The LBS-offset network's forward pass: offsets `N x J` of the centres `positions`.
    pub fn lbs_offsets_forward<S: NnScalar>(
        &self,
        networks: &Networks<S>,
        positions: &[f64],
    ) -> anyhow::Result<(Vec<f64>, LbsOffsetsCache<S>)> {
        let (offsets, cache) = networks.lbs_offsets_forward(&to_scalar(positions))?;
        Ok((to_f64(&offsets), cache))
    }

    /// Backward of the per-Gaussian networks' forward passes (`non_rigid`, `lbs_offsets`:
    /// those that ran) from the skinning's gradients: their parameter gradients accumulate
    /// into `networks`' (the master), and the gradient of the canonical centres through the
    /// non-rigid network is returned (zeros without one).
    pub fn networks_backward<S: NnScalar>(
        &self,
        networks: &mut Networks<S>,
        non_rigid: Option<&NonRigidCache<S>>,
        lbs_offsets: Option<&LbsOffsetsCache<S>>,
        skin: &SkinningGrads,
    ) -> anyhow::Result<Vec<f64>> {
        let mut through = vec![0.0; skin.positions.len()];
        if let Some(cache) = non_rigid {
            through = to_f64(&networks.non_rigid_backward(
                cache,
                &to_scalar(&skin.positions),
                &to_scalar(&skin.d_rotations),
                &to_scalar(&skin.d_scales),
            )?);
        }
        if let Some(cache) = lbs_offsets {
            networks.lbs_offsets_backward(cache, &to_scalar(&skin.weight_offsets))?;
        }
        Ok(through)
    }

    /// Renders `gaussians` from `cameras`, keeping what the backward needs.
    pub fn splat_forward(
        &self,
        gaussians: &WorldGaussians,
        cameras: &[Camera],
        options: &RasterOptions,
    ) -> anyhow::Result<SplatPass> {
        splatting::forward_cpu(gaussians, cameras, options)
    }

    /// Gradients with respect to the Gaussians given to the forward of `pass` (the pass keeps
    /// the f32 copy it splatted).
    pub fn splat_backward(
        &self,
        pass: &SplatPass,
        colour: &[Vec<f64>],
        alpha: &[Vec<f64>],
    ) -> anyhow::Result<SplatGradients<f64>> {
        splatting::backward_cpu(pass, colour, alpha)
    }
}
