//! Adam on the Gaussians' columns on the device: the maths of `adam_update` and the
//! trainer's `update_sh` (DC and rest rates) with the rates of [`super::state::OptimiserStep`],
//! the opacity-logit chain rule and the SH scatter from the active degree into the stored
//! layout done in the kernel (`shaders/train_adam.wgsl`), non-finite gradients and values
//! flagged in the status buffer of [`ResidentGaussians`].

use std::borrow::Cow;
use std::sync::Arc;

use anyhow::{Context, ensure};
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};

use super::state::{ResidentGaussians, StepSize};
use crate::gaussians::{SH, SH_STORED, TRAINABLE};

const ADAM_WGSL: &str = include_str!("../../../../shaders/train_adam.wgsl");

fn source(entry_point: &'static str, name: &'static str) -> KernelSource {
    KernelSource {
        name,
        wgsl: Cow::Borrowed(ADAM_WGSL),
        entry_point,
    }
}

/// The gradients one Adam step of the Gaussians reads, as device buffers of at least `N`
/// rows in the layouts below.
#[derive(Clone, Copy, Debug)]
pub struct GaussianGradients<'a> {
    /// `dL/dxyz` from the skinning backward (networks included), `N x 3`.
    pub xyz: &'a GpuBuffer,
    /// `dL/dlog_scale` from the skinning backward, `N x 3`.
    pub log_scale: &'a GpuBuffer,
    /// `dL/drotation` from the skinning backward, `N x 4`.
    pub rotation: &'a GpuBuffer,
    /// `dL/dopacity` of the activated opacity from the splatting backward, `N`.
    pub opacity: &'a GpuBuffer,
    /// `dL/dsh` of the active degree `d` from the splatting backward, `N x (d + 1)^2 x 3`.
    pub sh: &'a GpuBuffer,
    /// The AIAP loss's gradients of `xyz`, `log_scale` and `rotation` (`N x 3`, `N x 3`,
    /// `N x 4`), added to the skinning ones; `None` when AIAP is off.
    pub aiap: Option<[&'a GpuBuffer; 3]>,
}

/// The compiled Adam kernels and each column's constants.
#[derive(Debug)]
pub struct GaussianAdam {
    context: Arc<GpuContext>,
    sum_of_two: Arc<Kernel>,
    single: Arc<Kernel>,
    opacity: Arc<Kernel>,
    sh: Arc<Kernel>,
    /// Per column in `TRAINABLE` order: `[id, width, step size index, 0]` (u32).
    constants: Vec<GpuBuffer>,
}

impl GaussianAdam {
    /// Compiles the kernels and uploads the columns' constants (once).
    pub fn new(context: &Arc<GpuContext>) -> anyhow::Result<Self> {
        let compile = |entry, name| context.kernel(&source(entry, name));
        let mut constants = Vec::new();
        for (id, (name, width)) in TRAINABLE.iter().enumerate() {
            let step = match *name {
                SH => StepSize::ShDc,
                crate::densify::names::POSITION => StepSize::Position,
                crate::densify::names::OPACITY_LOGIT => StepSize::Opacity,
                crate::densify::names::LOG_SCALE => StepSize::Scaling,
                _ => StepSize::Rotation,
            };
            constants.push(context.upload(
                &format!("adam constants of {name}"),
                &[id as u32, *width as u32, step as u32, 0],
            )?);
        }
        Ok(GaussianAdam {
            context: context.clone(),
            sum_of_two: compile("sum_of_two", "train_adam_sum_of_two")?,
            single: compile("single", "train_adam_single")?,
            opacity: compile("opacity", "train_adam_opacity")?,
            sh: compile("sh", "train_adam_sh")?,
            constants,
        })
    }

    /// Records one Adam update of every trainable column of `gaussians` from `gradients`,
    /// at the rates and step of the record last written with
    /// [`ResidentGaussians::write_step`]. `sh_degree` must be that record's degree (it sizes
    /// the check of the SH gradient buffer only).
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: &ResidentGaussians,
        gradients: &GaussianGradients<'_>,
        sh_degree: usize,
    ) -> anyhow::Result<()> {
        let n = gaussians.len();
        let k = (sh_degree + 1) * (sh_degree + 1);
        ensure!(k <= SH_STORED, "Adam: SH degree {sh_degree} is above 3");
        let check = |what: &str, buffer: &GpuBuffer, len: usize| {
            ensure!(
                buffer.len >= len,
                "Adam of the Gaussians: gradient `{what}` holds {} values, {len} needed",
                buffer.len
            );
            Ok(())
        };
        check("xyz", gradients.xyz, 3 * n)?;
        check("log_scale", gradients.log_scale, 3 * n)?;
        check("rotation", gradients.rotation, 4 * n)?;
        check("opacity", gradients.opacity, n)?;
        check("sh", gradients.sh, 3 * k * n)?;
        if let Some([xyz, log_scale, rotation]) = gradients.aiap {
            check("aiap xyz", xyz, 3 * n)?;
            check("aiap log_scale", log_scale, 3 * n)?;
            check("aiap rotation", rotation, 4 * n)?;
        }
        for (id, column) in gaussians.columns().iter().enumerate() {
            let name = column.name;
            // The second source is bound only where the kernel reads it (pipelines laid out
            // from the shader have no slot for an unused binding).
            let (kernel, a, b) = match name {
                SH => (&self.sh, gradients.sh, None),
                crate::densify::names::OPACITY_LOGIT => (&self.opacity, gradients.opacity, None),
                _ => {
                    let (own, slot) = match name {
                        crate::densify::names::POSITION => (gradients.xyz, 0),
                        crate::densify::names::LOG_SCALE => (gradients.log_scale, 1),
                        _ => (gradients.rotation, 2),
                    };
                    match gradients.aiap {
                        Some(aiap) => (&self.sum_of_two, own, Some(aiap[slot])),
                        None => (&self.single, own, None),
                    }
                }
            };
            let values = n * column.width;
            let groups = u32::try_from(values.div_ceil(256))
                .with_context(|| format!("Adam of `{name}`: {values} values"))?;
            let mut bindings = vec![
                (0, &gaussians.record().buffer),
                (1, &self.constants[id].buffer),
                (2, &column.values.buffer),
                (3, &column.first_moment.buffer),
                (4, &column.second_moment.buffer),
                (5, &a.buffer),
                (7, &gaussians.status().buffer),
            ];
            if let Some(b) = b {
                bindings.push((6, &b.buffer));
            }
            self.context.dispatch(encoder, kernel, &bindings, groups);
        }
        Ok(())
    }
}
