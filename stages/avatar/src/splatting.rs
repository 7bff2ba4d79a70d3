//! Splatting with f64 at the boundary, one pair of functions per backend (called through
//! [`crate::device::AvatarBackend`]): the `cpu` backend runs in f64, the `gpu` backend in f32
//! (inputs rounded once, outputs widened), so the loss and everything around the splatting
//! stays in f64 on both.

use std::sync::Arc;

use anyhow::Context;
use seqavatar_compute::backend::GpuContext;
use seqavatar_compute::splat::{
    self, GaussianSet, ImageGradient, RasterOptions, RenderedImage, SplatGradients,
};
use seqavatar_core::camera::Camera;

/// One frame's Gaussians in world space, f64.
pub struct WorldGaussians {
    pub means: Vec<f64>,
    pub covariances: Vec<f64>,
    pub opacities: Vec<f64>,
    /// `N x K x 3` for the active degree.
    pub sh: Vec<f64>,
    pub sh_degree: u32,
}

impl WorldGaussians {
    pub fn set(&self) -> GaussianSet<'_, f64> {
        GaussianSet {
            means: &self.means,
            covariances: &self.covariances,
            opacities: &self.opacities,
            sh: &self.sh,
            sh_degree: self.sh_degree,
        }
    }
}

struct F32Gaussians {
    means: Vec<f32>,
    covariances: Vec<f32>,
    opacities: Vec<f32>,
    sh: Vec<f32>,
    sh_degree: u32,
}

impl F32Gaussians {
    fn new(g: &WorldGaussians) -> Self {
        let narrow = |v: &[f64]| v.iter().map(|x| *x as f32).collect::<Vec<f32>>();
        Self {
            means: narrow(&g.means),
            covariances: narrow(&g.covariances),
            opacities: narrow(&g.opacities),
            sh: narrow(&g.sh),
            sh_degree: g.sh_degree,
        }
    }

    fn set(&self) -> GaussianSet<'_, f32> {
        GaussianSet {
            means: &self.means,
            covariances: &self.covariances,
            opacities: &self.opacities,
            sh: &self.sh,
            sh_degree: self.sh_degree,
        }
    }
}

enum State {
    Cpu(splat::cpu::CpuForward<f64>),
    Gpu(Box<splat::gpu::GpuForward>, F32Gaussians),
}

/// A forward pass kept for its backward.
pub struct SplatPass {
    pub images: Vec<RenderedImage<f64>>,
    state: State,
}

fn widen(image: &RenderedImage<f32>) -> RenderedImage<f64> {
    let w = |v: &[f32]| v.iter().map(|x| f64::from(*x)).collect::<Vec<f64>>();
    RenderedImage {
        width: image.width,
        height: image.height,
        colour: w(&image.colour),
        alpha: w(&image.alpha),
        depth: w(&image.depth),
    }
}

/// Renders `gaussians` from `cameras` on `cpu` in f64 (the `cpu` backend's
/// [`crate::device::AvatarBackend::splat_forward`]).
pub fn forward_cpu(
    gaussians: &WorldGaussians,
    cameras: &[Camera],
    options: &RasterOptions,
) -> anyhow::Result<SplatPass> {
    let f = splat::cpu::forward(&gaussians.set(), cameras, options)
        .context("splatting forward (cpu)")?;
    Ok(SplatPass {
        images: f.images.clone(),
        state: State::Cpu(f),
    })
}

/// Renders `gaussians` from `cameras` on the gpu of `context` in f32 (the `gpu` backend's
/// [`crate::device::AvatarBackend::splat_forward`]).
pub fn forward_gpu(
    context: &Arc<GpuContext>,
    gaussians: &WorldGaussians,
    cameras: &[Camera],
    options: &RasterOptions,
) -> anyhow::Result<SplatPass> {
    let narrow = F32Gaussians::new(gaussians);
    let f = splat::gpu::forward(context, &narrow.set(), cameras, options)
        .context("splatting forward (gpu)")?;
    Ok(SplatPass {
        images: f.images.iter().map(widen).collect(),
        state: State::Gpu(Box::new(f), narrow),
    })
}

/// Gradients with respect to `gaussians` (the set given to [`forward_cpu`]).
pub fn backward_cpu(
    pass: &SplatPass,
    gaussians: &WorldGaussians,
    colour: &[Vec<f64>],
    alpha: &[Vec<f64>],
) -> anyhow::Result<SplatGradients<f64>> {
    let State::Cpu(f) = &pass.state else {
        anyhow::bail!("splatting backward: a gpu forward pass needs the gpu backend");
    };
    let upstream: Vec<ImageGradient<'_, f64>> = colour
        .iter()
        .zip(alpha)
        .map(|(c, a)| ImageGradient {
            colour: c,
            alpha: Some(a),
            depth: None,
        })
        .collect();
    splat::cpu::backward(f, &gaussians.set(), &upstream).context("splatting backward (cpu)")
}

/// Gradients with respect to the Gaussians given to [`forward_gpu`] (the pass keeps their
/// f32 copy).
pub fn backward_gpu(
    context: &Arc<GpuContext>,
    pass: &SplatPass,
    colour: &[Vec<f64>],
    alpha: &[Vec<f64>],
) -> anyhow::Result<SplatGradients<f64>> {
    let State::Gpu(f, narrow) = &pass.state else {
        anyhow::bail!("splatting backward: a cpu forward pass needs the cpu backend");
    };
    let c32: Vec<Vec<f32>> = colour
        .iter()
        .map(|c| c.iter().map(|x| *x as f32).collect())
        .collect();
    let a32: Vec<Vec<f32>> = alpha
        .iter()
        .map(|c| c.iter().map(|x| *x as f32).collect())
        .collect();
    let upstream: Vec<ImageGradient<'_, f32>> = c32
        .iter()
        .zip(&a32)
        .map(|(c, a)| ImageGradient {
            colour: c,
            alpha: Some(a),
            depth: None,
        })
        .collect();
    let g = splat::gpu::backward(context, f, &narrow.set(), &upstream)
        .context("splatting backward (gpu)")?;
    let w = |v: Vec<f32>| v.into_iter().map(f64::from).collect::<Vec<f64>>();
    Ok(SplatGradients {
        means: w(g.means),
        covariances: w(g.covariances),
        opacities: w(g.opacities),
        sh: w(g.sh),
        mean_2d_norm: w(g.mean_2d_norm),
        non_finite_gradients: g.non_finite_gradients,
    })
}
