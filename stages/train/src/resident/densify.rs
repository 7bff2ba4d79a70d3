//! Densification statistics on the device: `accumulate_gradient_stats` as
//! `Trainer::densify_phase` feeds it (the view-space gradient norm times half the image size,
//! a visibility count where the norm is > 0), from the splatting's `mean_2d_norm` buffer into
//! the `grad_accum` / `grad_count` buffers of [`ResidentGaussians`]; they reach the host's
//! `GaussianState` with [`ResidentGaussians::download_into`] when densification runs
//! (`shaders/train_densify_stats.wgsl`).

use std::borrow::Cow;
use std::sync::Arc;

use anyhow::{Context, ensure};
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};

use super::state::ResidentGaussians;

const STATS_WGSL: &str = include_str!("../../../../shaders/train_densify_stats.wgsl");

/// The compiled statistics kernel.
#[derive(Debug)]
pub struct GradientStats {
    context: Arc<GpuContext>,
    accumulate: Arc<Kernel>,
}

impl GradientStats {
    pub fn new(context: &Arc<GpuContext>) -> anyhow::Result<Self> {
        Ok(GradientStats {
            context: context.clone(),
            accumulate: context.kernel(&KernelSource {
                name: "train_densify_stats",
                wgsl: Cow::Borrowed(STATS_WGSL),
                entry_point: "accumulate",
            })?,
        })
    }

    /// Records the accumulation of one iteration's view-space gradient norms (`N` f32, the
    /// splatting's `mean_2d_norm`), scaled by the record's half size. Record it while
    /// `iteration <= densify_until`, as the `cpu` trainer accumulates.
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: &ResidentGaussians,
        mean_2d_norm: &GpuBuffer,
    ) -> anyhow::Result<()> {
        let n = gaussians.len();
        ensure!(
            mean_2d_norm.len >= n,
            "densification statistics: `mean_2d_norm` holds {} values, {n} needed",
            mean_2d_norm.len
        );
        let groups = u32::try_from(n.div_ceil(256)).context("densification statistics")?;
        self.context.dispatch(
            encoder,
            &self.accumulate,
            &[
                (0, &gaussians.record().buffer),
                (1, &mean_2d_norm.buffer),
                (2, &gaussians.grad_accum().buffer),
                (3, &gaussians.grad_count().buffer),
            ],
            groups,
        );
        Ok(())
    }
}
