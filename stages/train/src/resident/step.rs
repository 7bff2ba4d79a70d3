//! The device-resident training iteration of the `gpu` backend: every phase of
//! [`crate::trainer::Trainer::step`] recorded into one command encoder and submitted once, on
//! state that lives on the device (`docs/resident-step.md`). The host chooses the
//! iteration's images, frame and background with the trainer's generator (the same draws,
//! in the same order, as the `cpu` path), writes the pieces' small per-iteration records, and
//! submits; it reads back only the log ring (every [`ResidentStep::log_capacity`] iterations
//! at most) and, when densification runs, the Gaussians.
//!
//! Phases, in recording order: the deformation ([`ResidentDeformer`], shared with rendering:
//! pose with the refiner's forward, forward kinematics and pose blend shapes, motion inputs,
//! the non-rigid network, the heads applied, the LBS offsets, the nearest template vertices,
//! skinning and activations), splatting, the image losses with their image gradients, AIAP,
//! then the backward in reverse (splatting, skinning, LBS offsets, non-rigid network, pose,
//! pose refiner), Adam on the Gaussians and on the networks, and the densification
//! statistics.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use anyhow::Context;
use seqavatar_avatar::model::gpu::GpuNetworks;
use seqavatar_avatar::model::{NetworkGroup, Networks};
use seqavatar_avatar::resident::deform::{DeformerSetup, History, ResidentDeformer};
use seqavatar_avatar::resident::skinning::GaussianColumns;
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource, PhaseTimer};
use seqavatar_compute::lpips::gpu::{
    Crop, CropPair, DeviceImage as LpipsImage, GpuLpips, ResidentLpips,
};
use seqavatar_compute::nn::adam::AdamState;
use seqavatar_compute::splat::RasterOptions;
use seqavatar_compute::splat::gpu::{DeviceImageGradient, GpuOptions, SplatWorkspace};
use seqavatar_core::camera::Camera;

use super::adam::{GaussianAdam, GaussianGradients};
use super::aiap::ResidentAiap;
use super::densify::GradientStats;
use super::image_loss::{DeviceImages, GroundTruth, ImageLoss, LossCamera};
use super::log::{LogField, LogRing};
use super::state::{GaussianRates, OptimiserStep, ResidentGaussians};
use crate::config::TrainConfig;
use crate::data::TrainingData;
use crate::densify::{GaussianState, names};
use crate::gaussians::SH;
use crate::losses::{AiapWeights, ImageLossWeights, LpipsLoss};
use crate::run::{Divergence, IterationStats, Run};

const STEP_WGSL: &str = include_str!("../../../../shaders/train_step.wgsl");

/// Iterations submitted ahead of the device at most.
const IN_FLIGHT: usize = 2;

/// Iterations the log ring holds: the most iterations between two reads of the logged
/// scalars.
pub const LOG_CAPACITY: usize = 64;

/// What the host decided for one iteration.
#[derive(Clone, Debug)]
pub struct IterationPlan<'a> {
    /// 1-based.
    pub iteration: u64,
    /// The frame of the chosen images.
    pub frame: usize,
    /// The chosen training images (indices into `TrainingData::images`).
    pub images: &'a [usize],
    pub background: [f64; 3],
    pub sh_degree: u32,
    /// The Gaussians' Adam update count including this iteration's.
    pub adam_step: u64,
    /// Whether this iteration accumulates densification statistics.
    pub density_statistics: bool,
}

/// The device state and workspaces of a resident training run.
pub struct ResidentStep {
    context: Arc<GpuContext>,
    config: TrainConfig,
    /// Pose, motion inputs, networks and skinning: the deformation's forward.
    deformer: ResidentDeformer,
    splat: SplatWorkspace,
    truth: GroundTruth,
    losses: ImageLoss,
    /// The LPIPS trunk on the device with its workspace, when the loss is on.
    lpips: Option<ResidentLpips>,
    gaussians: ResidentGaussians,
    adam: GaussianAdam,
    aiap: ResidentAiap,
    statistics: GradientStats,
    log: LogRing,
    /// Per camera slot, the image gradients the losses write and the splatting reads.
    image_gradients: Vec<(GpuBuffer, GpuBuffer)>,
    add: Arc<Kernel>,
    /// Device timestamps between the phases of each iteration, when timing is on
    /// ([`ResidentStep::time_phases`]), and the seconds they add up to per phase.
    timer: Option<PhaseTimer>,
    device_seconds: [f64; TIMED_PHASES],
    device_iterations: u64,
    /// Submissions the device may not have run yet, oldest first.
    in_flight: std::collections::VecDeque<wgpu::SubmissionIndex>,
    /// Iterations recorded since the log was last read, and the first one's slot.
    unread: usize,
    first_unread: usize,
}

/// Phases timed on the device: deform, splat, losses (with AIAP), backward, optimiser (with
/// the densification statistics).
pub const TIMED_PHASES: usize = 5;

/// The networks on the device with their Adam moments (`network_adam`, empty for a fresh
/// run).
fn upload_networks(
    context: &Arc<GpuContext>,
    config: &TrainConfig,
    networks: Option<&Networks<f32>>,
    network_adam: &BTreeMap<String, AdamState<f32>>,
) -> anyhow::Result<Option<GpuNetworks>> {
    let Some(net) = networks else {
        return Ok(None);
    };
    let mut gpu = GpuNetworks::upload(context.clone(), net, config.networks_precision())
        .context("uploading the networks")?;
    if !network_adam.is_empty() {
        let states: HashMap<String, AdamState<f32>> = network_adam
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        gpu.upload_adam(&config.adam(), &states)
            .context("uploading the networks' Adam moments")?;
    }
    Ok(Some(gpu))
}

/// The LPIPS trunk uploaded to `context` with its device workspace for the run's largest
/// camera.
fn lpips_workspace(
    context: &Arc<GpuContext>,
    config: &TrainConfig,
    data: &TrainingData,
    loss: &LpipsLoss,
) -> anyhow::Result<ResidentLpips> {
    let trunk = GpuLpips::new(context.clone(), loss.lpips().weights()).context("LPIPS loss")?;
    let (max_height, max_width) = data
        .cameras
        .iter()
        .map(|c| (c.height as usize, c.width as usize))
        .fold((1, 1), |(h, w), (ch, cw)| (h.max(ch), w.max(cw)));
    trunk
        .resident(
            config.lpips_input(),
            max_height,
            max_width,
            config.cameras_per_step,
        )
        .context("LPIPS on the device")
}

/// The canonical Gaussians' columns the deformation reads, from the optimiser's buffers.
fn gaussian_columns(gaussians: &ResidentGaussians) -> anyhow::Result<GaussianColumns<'_>> {
    let column = |name: &str| -> anyhow::Result<&GpuBuffer> { Ok(&gaussians.column(name)?.values) };
    Ok(GaussianColumns {
        xyz: column(names::POSITION)?,
        log_scale: column(names::LOG_SCALE)?,
        rotation: column(names::ROTATION)?,
        opacity_logit: column(names::OPACITY_LOGIT)?,
        sh: column(SH)?,
    })
}

/// Records timestamp `index` of the iteration in log slot `slot` when timing is on.
fn mark(timer: &Option<PhaseTimer>, encoder: &mut wgpu::CommandEncoder, slot: usize, index: usize) {
    if let Some(timer) = timer {
        timer.mark(encoder, slot, index);
    }
}

/// Records `destination += source` over `len` values (`train_step.wgsl`'s `add_into`,
/// compiled as `add`).
fn record_add(
    context: &GpuContext,
    add: &Kernel,
    encoder: &mut wgpu::CommandEncoder,
    destination: &wgpu::Buffer,
    source: &wgpu::Buffer,
    len: usize,
) {
    context.call(
        encoder,
        add,
        &[len as u32, 0, 0, 0],
        &[(1, source), (2, destination)],
        len.div_ceil(256) as u32,
    );
}

impl ResidentStep {
    /// Uploads the run's state and data once: the Gaussians (`state`) with their Adam
    /// moments, the networks with theirs (`network_adam`, empty for a fresh run), the
    /// sequence's poses and motion arrays, the ground-truth images; allocates every
    /// workspace for the current Gaussian count.
    pub fn new(context: Arc<GpuContext>, run: &Run<'_>) -> anyhow::Result<Self> {
        let (config, data, scales, state) = (&run.config, run.data, &run.scales[..], &run.state);
        let (networks, network_adam, lpips) =
            (run.networks.as_ref(), &run.network_adam, run.lpips.as_ref());
        let n = state.len();
        let avatar = config.avatar();
        let networks = upload_networks(&context, config, networks, network_adam)?;
        let deformer = ResidentDeformer::new(
            context.clone(),
            &DeformerSetup {
                config: &avatar,
                rig: &data.rig,
                frames: &data.params,
                motion: Some(&data.motion),
                scales,
                gaussians: n,
            },
            networks,
        )?;
        let splat = SplatWorkspace::new(&context, GpuOptions::default(), None)
            .map_err(|e| anyhow::anyhow!("{e}"))
            .context("splatting workspace")?;
        let truth = GroundTruth::upload_training(&context, data).context("training images")?;
        let max_pixels = data
            .cameras
            .iter()
            .map(|c| c.width as usize * c.height as usize)
            .max()
            .unwrap_or(1);
        let losses = ImageLoss::new(
            context.clone(),
            ImageLossWeights {
                mask: config.mask_weight,
                ssim: config.ssim_weight,
            },
            if config.lpips_enabled() {
                config.lpips_weight
            } else {
                0.0
            },
            config.cameras_per_step,
            max_pixels,
        )
        .context("image losses")?;
        let lpips = lpips
            .map(|loss| lpips_workspace(&context, config, data, loss))
            .transpose()?;
        let gaussians = ResidentGaussians::upload(&context, state).context("Gaussians")?;
        let adam = GaussianAdam::new(&context)?;
        let aiap = ResidentAiap::new(
            &context,
            AiapWeights {
                centre: config.aiap_centre_weight,
                covariance: config.aiap_covariance_weight,
                neighbours: config.aiap_neighbours,
            },
        )?;
        let statistics = GradientStats::new(&context)?;
        let log = LogRing::new(&context, LOG_CAPACITY)?;
        let image_gradients = (0..config.cameras_per_step)
            .map(|_| {
                Ok((
                    context.zeros("colour gradient", 3 * max_pixels, 4)?,
                    context.zeros("alpha gradient", max_pixels, 4)?,
                ))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let add = context.kernel(&KernelSource {
            name: "train_step_add_into",
            wgsl: std::borrow::Cow::Borrowed(STEP_WGSL),
            entry_point: "add_into",
        })?;
        Ok(Self {
            context,
            config: config.clone(),
            deformer,
            splat,
            truth,
            losses,
            lpips,
            gaussians,
            adam,
            aiap,
            statistics,
            log,
            image_gradients,
            add,
            timer: None,
            device_seconds: [0.0; TIMED_PHASES],
            device_iterations: 0,
            in_flight: std::collections::VecDeque::new(),
            unread: 0,
            first_unread: 0,
        })
    }

    /// Starts timing the phases of every iteration on the device from the next one (one
    /// timestamp between phases; read with the log); `false` when the adapter has no
    /// timestamps inside encoders. Clears the times so far.
    pub fn time_phases(&mut self) -> anyhow::Result<bool> {
        if self.timer.is_none() {
            self.timer = PhaseTimer::new(&self.context, TIMED_PHASES + 1, LOG_CAPACITY)?;
        }
        self.device_seconds = [0.0; TIMED_PHASES];
        self.device_iterations = 0;
        Ok(self.timer.is_some())
    }

    /// Device seconds per phase (deform, splat, losses, backward, optimiser) summed over
    /// the iterations timed and read so far, and their count; `None` when not timing.
    pub fn device_phase_seconds(&self) -> Option<([f64; TIMED_PHASES], u64)> {
        self.timer
            .as_ref()
            .map(|_| (self.device_seconds, self.device_iterations))
    }

    /// Iterations that can be recorded between two reads of the log.
    pub fn log_capacity(&self) -> usize {
        self.log.capacity()
    }

    /// Iterations recorded since the log was last read.
    pub fn unread(&self) -> usize {
        self.unread
    }

    /// Records and submits one iteration (see the module documentation). Nothing is read
    /// back.
    pub fn record(
        &mut self,
        plan: &IterationPlan<'_>,
        data: &TrainingData,
        lpips: Option<&LpipsLoss>,
    ) -> anyhow::Result<()> {
        let mut encoder = self.context.encoder();
        let slot = self.first_unread + self.unread;
        self.log.clear_slot(&mut encoder, slot);
        mark(&self.timer, &mut encoder, slot, 0);
        self.record_deformation(&mut encoder, plan, data)?;
        mark(&self.timer, &mut encoder, slot, 1);
        let cameras = self.record_splatting(&mut encoder, plan, data)?;
        mark(&self.timer, &mut encoder, slot, 2);
        self.record_losses(&mut encoder, plan, data, &cameras, lpips)?;
        mark(&self.timer, &mut encoder, slot, 3);
        let aiap_active = self.record_backward(&mut encoder, plan, cameras.len())?;
        mark(&self.timer, &mut encoder, slot, 4);
        self.record_optimisers(&mut encoder, plan, aiap_active)?;
        mark(&self.timer, &mut encoder, slot, 5);
        if let Some(timer) = self.timer.as_mut() {
            timer.finish_slot(&mut encoder, slot);
        }
        self.record_log(&mut encoder, slot);
        self.submit(encoder)
    }

    /// The iteration's host-side records (small writes, ordered before the submission) and
    /// the deformation: pose, motion inputs, networks, skinning.
    fn record_deformation(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        plan: &IterationPlan<'_>,
        data: &TrainingData,
    ) -> anyhow::Result<()> {
        let config = &self.config;
        let n = self.gaussians.len();
        self.deformer
            .set_frame(plan.frame, History::Own, n, plan.sh_degree)?;
        self.gaussians.write_step(&OptimiserStep {
            iteration: plan.iteration,
            adam_step: plan.adam_step,
            adam: config.adam(),
            rates: GaussianRates::at(&config.learning_rates, data.extent, plan.iteration),
            sh_degree: plan.sh_degree as usize,
            half_size: half_size(data, plan.images),
        })?;
        if let Some(networks) = self.deformer.networks.as_mut() {
            networks.record_zero_grad(encoder);
        }
        let columns = gaussian_columns(&self.gaussians)?;
        self.deformer
            .record_forward(encoder, plan.frame, History::Own, &columns)
    }

    /// Splatting into the chosen cameras on the iteration's background; returns the cameras.
    fn record_splatting(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        plan: &IterationPlan<'_>,
        data: &TrainingData,
    ) -> anyhow::Result<Vec<Camera>> {
        let cameras: Vec<Camera> = plan
            .images
            .iter()
            .map(|&i| data.cameras[data.images[i].view].clone())
            .collect();
        let options = RasterOptions {
            background: plan.background,
            smooth_cutoff: false,
        };
        self.splat
            .forward(
                &self.context,
                encoder,
                self.deformer.world(plan.sh_degree),
                &cameras,
                &options,
            )
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(cameras)
    }

    /// The image losses and their image gradients per camera (LPIPS's joined to the colour
    /// gradient), then AIAP.
    fn record_losses(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        plan: &IterationPlan<'_>,
        data: &TrainingData,
        cameras: &[Camera],
        lpips: Option<&LpipsLoss>,
    ) -> anyhow::Result<()> {
        let config = &self.config;
        let loss_cameras: Vec<LossCamera> = plan
            .images
            .iter()
            .map(|&i| LossCamera {
                image: i,
                pixel_offset: 0,
                rect: data
                    .padded_bound(i, config.bound_padding)
                    .expect("training images have a foreground"),
                background: plan.background,
            })
            .collect();
        self.losses
            .begin_iteration(encoder, plan.iteration, &loss_cameras, &self.truth)?;
        for (c, (camera, loss_camera)) in cameras.iter().zip(&loss_cameras).enumerate() {
            let (colour, alpha) = &self.image_gradients[c];
            let rendered = self.splat.colour(c).map_err(|e| anyhow::anyhow!("{e}"))?;
            self.losses.record_camera(
                encoder,
                c,
                &self.truth,
                DeviceImages {
                    colour: rendered,
                    alpha: self.splat.alpha(c).map_err(|e| anyhow::anyhow!("{e}"))?,
                },
                DeviceImages { colour, alpha },
            )?;
            if let (Some(workspace), Some(loss)) = (&self.lpips, lpips) {
                // Its image gradient joins the colour gradient before the splatting backward.
                let (width, height) = (camera.width as usize, camera.height as usize);
                let target = self.losses.record_target(encoder, c, &self.truth)?;
                let crop = loss.crop(loss_camera.rect, width, height)?;
                let image = |buffer| LpipsImage {
                    buffer,
                    offset: 0,
                    width,
                    height,
                };
                workspace.record(
                    encoder,
                    c,
                    CropPair {
                        render: image(rendered),
                        target: image(target),
                        crop: Crop {
                            x0: crop.x0,
                            y0: crop.y0,
                            width: crop.width(),
                            height: crop.height(),
                        },
                    },
                    (config.lpips_weight / cameras.len() as f64) as f32,
                    colour,
                )?;
                self.losses.record_lpips(encoder, c, workspace.value(c))?;
            }
        }
        self.losses.finish_iteration(encoder);
        self.aiap.record(
            encoder,
            &self.gaussians,
            &self.deformer.skinning.means,
            &self.deformer.skinning.covariances,
        )
    }

    /// The backward: splatting (AIAP's deformed-space gradients joined), skinning, the LBS
    /// offsets, the non-rigid network (its centre gradient joins the direct path), the pose
    /// path and the pose refiner. Returns whether AIAP ran.
    fn record_backward(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        plan: &IterationPlan<'_>,
        camera_count: usize,
    ) -> anyhow::Result<bool> {
        let context = &self.context;
        let n = self.gaussians.len();
        let world = self.deformer.world(plan.sh_degree);
        let upstream: Vec<DeviceImageGradient<'_>> = self.image_gradients[..camera_count]
            .iter()
            .map(|(colour, alpha)| DeviceImageGradient {
                colour,
                alpha: Some(alpha),
                depth: None,
            })
            .collect();
        self.splat
            .backward(context, encoder, world, &upstream)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let splat_grads = self.splat.gradients().map_err(|e| anyhow::anyhow!("{e}"))?;
        let aiap_active = self.aiap.active(n);
        if aiap_active {
            let grads = self.aiap.gradients().context("AIAP gradients")?;
            for (into, from, len) in [
                (splat_grads.means(), &grads.deformed_centres, 3 * n),
                (
                    splat_grads.covariances(),
                    &grads.deformed_covariances,
                    6 * n,
                ),
            ] {
                record_add(context, &self.add, encoder, &into.buffer, &from.buffer, len);
            }
        }
        let (has_non_rigid, has_lbs, has_refiner) = (
            self.deformer.has_non_rigid(),
            self.deformer.has_lbs_offsets(),
            self.deformer.has_pose_refiner(),
        );
        let columns = gaussian_columns(&self.gaussians)?;
        let deformer = &mut self.deformer;
        deformer.skinning.record_backward(
            encoder,
            &columns,
            &deformer.skin_inputs(),
            splat_grads.means(),
            splat_grads.covariances(),
        )?;
        // Networks' backward: LBS offsets, the non-rigid network (its centre gradient joins
        // the direct path), the pose path and the pose refiner.
        if let Some(networks) = deformer.networks.as_mut()
            && has_lbs
        {
            networks.record_backward(
                encoder,
                NetworkGroup::LbsOffsets,
                &deformer.skinning.grad_weight_offsets.buffer,
            )?;
        }
        if has_non_rigid {
            let networks = deformer.networks.as_mut().expect("has a non-rigid network");
            let through = networks
                .record_non_rigid_backward(encoder, &deformer.skinning.grad_heads.buffer)?;
            // The skinning writes `grad_positions` afresh every backward: the sum is this
            // iteration's total centre gradient.
            record_add(
                context,
                &self.add,
                encoder,
                &deformer.skinning.grad_positions.buffer,
                through,
                3 * n,
            );
        }
        if has_refiner {
            deformer.pose.backward(
                encoder,
                &deformer.skinning.grad_target_joints,
                &deformer.skinning.grad_vertex_offsets,
            )?;
            let networks = deformer.networks.as_mut().expect("has a pose refiner");
            networks.record_backward(
                encoder,
                NetworkGroup::PoseRefiner,
                &deformer.pose.refinement_gradients().buffer,
            )?;
        }

        Ok(aiap_active)
    }

    /// Adam on the Gaussians and on the networks, and the densification statistics.
    fn record_optimisers(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        plan: &IterationPlan<'_>,
        aiap_active: bool,
    ) -> anyhow::Result<()> {
        let config = &self.config;
        let deformer = &mut self.deformer;
        let splat_grads = self.splat.gradients().map_err(|e| anyhow::anyhow!("{e}"))?;
        let aiap_grads = if aiap_active {
            let grads = self.aiap.gradients().context("AIAP gradients")?;
            Some([&grads.xyz, &grads.log_scale, &grads.rotation])
        } else {
            None
        };
        self.adam.record(
            encoder,
            &self.gaussians,
            &GaussianGradients {
                xyz: &deformer.skinning.grad_positions,
                log_scale: &deformer.skinning.grad_log_scales,
                rotation: &deformer.skinning.grad_rotations,
                opacity: splat_grads.opacities(),
                sh: splat_grads.sh(),
                aiap: aiap_grads,
            },
            plan.sh_degree as usize,
        )?;
        if let Some(networks) = deformer.networks.as_mut() {
            networks.record_adam(encoder, &config.adam(), |group| {
                config.network_rate(group, plan.iteration)
            })?;
        }
        if plan.density_statistics {
            self.statistics
                .record(encoder, &self.gaussians, splat_grads.mean_2d_norm())?;
        }

        Ok(())
    }

    /// The iteration's logged scalars into its slot of the ring.
    fn record_log(&mut self, encoder: &mut wgpu::CommandEncoder, slot: usize) {
        let loss_log = self.losses.log_buffer();
        for (field, index) in [
            (LogField::L1, 0),
            (LogField::MaskMse, 1),
            (LogField::Dssim, 2),
            (LogField::Lpips, 3),
            (LogField::Psnr, 4),
            (LogField::ImageTotal, 5),
        ] {
            self.log
                .record(encoder, slot, field, &loss_log.buffer, index);
        }
        self.log
            .record(encoder, slot, LogField::Aiap, &self.aiap.log().buffer, 0);
    }

    /// Submits the recorded iteration.
    fn submit(&mut self, encoder: wgpu::CommandEncoder) -> anyhow::Result<()> {
        let submitted = self.context.queue().submit([encoder.finish()]);
        self.unread += 1;
        // At most `IN_FLIGHT` iterations queued ahead of the device: the host waits (no data
        // comes back) for the oldest before going on, so the queue and its staging memory
        // stay bounded when the host records faster than the device runs.
        self.in_flight.push_back(submitted);
        if self.in_flight.len() > IN_FLIGHT {
            let oldest = self.in_flight.pop_front().expect("non-empty");
            self.wait_for(Some(oldest))?;
        }
        Ok(())
    }

    /// Waits until the device has run every submitted iteration (timing; nothing is read).
    pub fn wait_idle(&mut self) -> anyhow::Result<()> {
        self.in_flight.clear();
        self.wait_for(None)
    }

    fn wait_for(&self, submission: Option<wgpu::SubmissionIndex>) -> anyhow::Result<()> {
        self.context
            .device()
            .poll(wgpu::PollType::Wait {
                submission_index: submission,
                timeout: None,
            })
            .map_err(|error| anyhow::anyhow!("waiting for the device: {error}"))?;
        Ok(())
    }

    /// Reads the statistics of the iterations recorded since the last read (one round trip,
    /// after they have run; `gaussians` is the run's count) and checks every piece's status:
    /// a non-finite value is a [`Divergence`] naming the iteration and tensor, as on `cpu`.
    pub fn read_log(
        &mut self,
        last_iteration: u64,
        gaussians: usize,
    ) -> anyhow::Result<Vec<IterationStats>> {
        let slots = self
            .log
            .read(&self.context, self.first_unread, self.unread)?;
        let first_iteration = last_iteration + 1 - self.unread as u64;
        self.first_unread = (self.first_unread + self.unread) % self.log.capacity();
        self.unread = 0;
        let logged: Vec<IterationStats> = (first_iteration..)
            .zip(&slots)
            .map(|(iteration, values)| {
                let v = |field: LogField| f64::from(values[field as usize]);
                IterationStats {
                    iteration,
                    total: v(LogField::ImageTotal) + v(LogField::Aiap),
                    l1: v(LogField::L1),
                    mask_mse: v(LogField::MaskMse),
                    dssim: v(LogField::Dssim),
                    lpips: v(LogField::Lpips),
                    aiap: v(LogField::Aiap),
                    psnr: v(LogField::Psnr),
                    gaussians,
                    densified: None,
                }
            })
            .collect();
        if let Some(timer) = self.timer.as_mut() {
            for phases in timer.read(&self.context)? {
                for (total, seconds) in self.device_seconds.iter_mut().zip(phases) {
                    *total += seconds;
                }
                self.device_iterations += 1;
            }
        }
        let status = self.context.download::<u32>(
            self.context.encoder(),
            &self.gaussians.status().buffer,
            self.gaussians.status().len,
        )?;
        if let Some(found) = ResidentGaussians::decode_status(&status) {
            return Err(Divergence {
                iteration: found.iteration,
                what: found.what,
                tensor: found.tensor,
                detail: format!(" (Gaussian {})", found.gaussian),
            }
            .into());
        }
        for stats in &logged {
            stats.check_finite()?;
        }
        if let Some(found) = self
            .deformer
            .networks
            .as_ref()
            .map(GpuNetworks::download_non_finite)
            .transpose()?
            .flatten()
        {
            return Err(Divergence {
                iteration: last_iteration,
                what: if found.gradient {
                    "gradient of"
                } else {
                    "parameter"
                },
                tensor: found.tensor,
                detail: format!(
                    " (value {}; found by iteration {last_iteration})",
                    found.index
                ),
            }
            .into());
        }
        let pose = self.deformer.pose.download_status()?;
        anyhow::ensure!(
            pose.is_clean(),
            "iterations {first_iteration}-{last_iteration}: the pose path met non-finite values ({pose:?})"
        );
        let [forward, forward_at, backward, backward_at] =
            self.deformer.skinning.download_status()?;
        anyhow::ensure!(
            forward == 0 && backward == 0,
            "iterations {first_iteration}-{last_iteration}: skinning met non-finite values \
             ({forward} in the forward, first at Gaussian {forward_at}; {backward} in the \
             backward, first at Gaussian {backward_at})"
        );
        let status = self
            .splat
            .check_status(&self.context)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        if status.overflowed_bands > 0 {
            // The bands rendered without their last pairs; the capacity has grown for the
            // next iterations. Rare (the first iterations after a large densification).
            eprintln!(
                "splatting: {} bands exceeded the pair capacity in the last {} iterations (grown to {} pairs per band)",
                status.overflowed_bands,
                slots.len(),
                self.splat.pairs_per_band()
            );
        }
        Ok(logged)
    }

    /// The AIAP neighbour searches: `(full searches, calls)` (one read-back).
    pub fn aiap_searches(&self) -> anyhow::Result<(u64, u64)> {
        self.aiap.download_searches()
    }

    /// Copies the Gaussians (values, moments, densification statistics) back into `state`.
    pub fn download_state(&self, state: &mut GaussianState) -> anyhow::Result<()> {
        self.gaussians.download_into(state)
    }

    /// Replaces the device Gaussians with `state` (after the host densified) and grows the
    /// workspaces that depend on the Gaussian count.
    pub fn upload_state(&mut self, state: &GaussianState) -> anyhow::Result<()> {
        self.gaussians.reupload(state)?;
        let n = state.len();
        self.deformer.reserve(n)?;
        Ok(())
    }

    /// Copies the networks' parameters and Adam moments back to the host.
    pub fn download_networks(
        &self,
        networks: &mut Networks<f32>,
        adam: &mut BTreeMap<String, AdamState<f32>>,
    ) -> anyhow::Result<()> {
        if let Some(gpu) = &self.deformer.networks {
            gpu.download_into(networks)?;
            adam.clear();
            adam.extend(gpu.download_adam()?);
        }
        Ok(())
    }
}

/// Half the largest side of the iteration's cameras, in pixels.
fn half_size(data: &TrainingData, images: &[usize]) -> f64 {
    images
        .iter()
        .map(|&i| {
            let camera = &data.cameras[data.images[i].view];
            camera.width.max(camera.height)
        })
        .max()
        .unwrap_or(1) as f64
        * 0.5
}
