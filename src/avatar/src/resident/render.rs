//! Rendering a trained avatar on the device: the canonical Gaussians, the networks, the
//! sequence's poses and motion arrays are uploaded once; each frame records the deformation
//! ([`super::deform::ResidentDeformer`], the training step's forward) and the splatting into
//! one submission and reads back only the finished image (its splatting status in the same
//! read-back). Eval, `pipeline render`, the held-out PSNR and `pipeline view` render through
//! it on the `gpu` backend ([`crate::sequence::SequenceRenderer`]).

use std::sync::Arc;

use anyhow::Context as _;
use seqavatar_compute::backend::{GpuBuffer, GpuContext};
use seqavatar_compute::splat::gpu::{GpuOptions, SplatWorkspace};
use seqavatar_compute::splat::{RasterOptions, RenderedImage};
use seqavatar_core::body::BodyParams;
use seqavatar_core::camera::Camera;
use seqavatar_schema::motion::MotionTrack;

use super::deform::{DeformerSetup, History, ResidentDeformer};
use super::skinning::GaussianColumns;
use crate::avatar::TrainedAvatar;
use crate::model::gpu::GpuNetworks;
use crate::splatting::WorldGaussians;

/// Renders beyond this many tries mean the pair capacity cannot settle.
const MAX_TRIES: usize = 8;

/// The canonical Gaussians' columns on the device, f32.
struct CanonicalColumns {
    xyz: GpuBuffer,
    log_scale: GpuBuffer,
    rotation: GpuBuffer,
    opacity_logit: GpuBuffer,
    sh: GpuBuffer,
}

impl CanonicalColumns {
    fn view(&self) -> GaussianColumns<'_> {
        GaussianColumns {
            xyz: &self.xyz,
            log_scale: &self.log_scale,
            rotation: &self.rotation,
            opacity_logit: &self.opacity_logit,
            sh: &self.sh,
        }
    }
}

/// A trained avatar on the device with the frames of one sequence; its networks' dense layers
/// take the path the avatar's `precision` chooses, once, when it is built.
pub struct ResidentRenderer {
    context: Arc<GpuContext>,
    deformer: ResidentDeformer,
    columns: CanonicalColumns,
    count: usize,
    sh_degree: u32,
    splat: SplatWorkspace,
}

impl ResidentRenderer {
    /// Uploads `avatar` (a snapshot: later changes to it are not seen), its networks, and the
    /// body parameters `frames` and motion track `motion` of the sequence it renders.
    pub fn new(
        context: Arc<GpuContext>,
        avatar: &TrainedAvatar,
        frames: &[BodyParams],
        motion: Option<&MotionTrack>,
    ) -> anyhow::Result<Self> {
        let gaussians = &avatar.gaussians;
        let count = gaussians.len();
        anyhow::ensure!(count > 0, "the avatar has no Gaussians");
        let f32s = |values: &[f64]| values.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let upload = |what: &str, values: &[f64]| context.upload(what, &f32s(values));
        let columns = CanonicalColumns {
            xyz: upload("canonical centres", &gaussians.xyz)?,
            log_scale: upload("log scales", &gaussians.log_scale)?,
            rotation: upload("rotations", &gaussians.rotation)?,
            opacity_logit: upload("opacity logits", &gaussians.opacity_logit)?,
            sh: upload("SH coefficients", &gaussians.sh)?,
        };
        let networks = avatar
            .networks
            .as_ref()
            .map(|networks| {
                GpuNetworks::upload(
                    context.clone(),
                    networks,
                    avatar.config.networks_precision(),
                )
            })
            .transpose()
            .context("uploading the avatar's networks")?;
        let deformer = ResidentDeformer::new(
            context.clone(),
            &DeformerSetup {
                config: &avatar.config,
                rig: &avatar.rig,
                frames,
                motion,
                scales: &avatar.scales,
                gaussians: count,
            },
            networks,
        )?;
        let splat = SplatWorkspace::new(&context, GpuOptions::default(), None)
            .map_err(|e| anyhow::anyhow!("{e}"))
            .context("splatting workspace")?;
        Ok(Self {
            context,
            deformer,
            columns,
            count,
            sh_degree: avatar.sh_degree,
            splat,
        })
    }

    pub fn frames(&self) -> usize {
        self.deformer.pose.frame_count()
    }

    fn record_deform(
        &mut self,
        frame: usize,
        history: History,
    ) -> anyhow::Result<wgpu::CommandEncoder> {
        self.deformer
            .set_frame(frame, history, self.count, self.sh_degree)?;
        let mut encoder = self.context.encoder();
        self.deformer
            .record_forward(&mut encoder, frame, history, &self.columns.view())?;
        Ok(encoder)
    }

    /// Renders frame `frame` from `camera` on `background`: colour and alpha (depth too).
    /// One submission and one read-back, again only when the splatting's pair capacity had
    /// to grow.
    pub fn render(
        &mut self,
        frame: usize,
        history: History,
        camera: &Camera,
        background: [f64; 3],
    ) -> anyhow::Result<RenderedImage<f32>> {
        let options = RasterOptions {
            background,
            smooth_cutoff: false,
        };
        let cameras = std::slice::from_ref(camera);
        for _ in 0..MAX_TRIES {
            let mut encoder = self.record_deform(frame, history)?;
            let world = self.deformer.world(self.sh_degree);
            self.splat
                .forward(&self.context, &mut encoder, world, cameras, &options)
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            self.context.queue().submit([encoder.finish()]);
            if let Some((mut images, _)) = self
                .splat
                .download_checked_images(&self.context)
                .map_err(|e| anyhow::anyhow!("{e}"))?
            {
                return Ok(images.swap_remove(0));
            }
        }
        anyhow::bail!(
            "frame {frame}: the splatting's pair capacity did not settle in {MAX_TRIES} tries"
        )
    }

    /// The deformed Gaussians of frame `frame` as the splatting reads them, read back (what
    /// `pipeline export` writes).
    pub fn deform(&mut self, frame: usize, history: History) -> anyhow::Result<WorldGaussians> {
        let encoder = self.record_deform(frame, history)?;
        self.context.queue().submit([encoder.finish()]);
        let n = self.count;
        let k = ((self.sh_degree + 1) * (self.sh_degree + 1)) as usize;
        let skinning = &self.deformer.skinning;
        let mut columns = self
            .context
            .download_all::<f32>(
                self.context.encoder(),
                &[
                    (&skinning.means.buffer, 3 * n),
                    (&skinning.covariances.buffer, 6 * n),
                    (&skinning.opacities.buffer, n),
                    (&skinning.sh.buffer, 3 * k * n),
                ],
            )?
            .into_iter()
            .map(|values| values.into_iter().map(f64::from).collect::<Vec<f64>>());
        let mut next = || columns.next().unwrap_or_default();
        Ok(WorldGaussians {
            means: next(),
            covariances: next(),
            opacities: next(),
            sh: next(),
            sh_degree: self.sh_degree,
        })
    }
}
