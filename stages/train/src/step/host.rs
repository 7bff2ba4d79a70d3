//! The host training step of the `cpu` backend: every phase of an iteration in plain Rust on
//! the run's host state, through the avatar's [`AvatarBackend`] (networks and splatting).
//! Its phases: `deform` (a seeded choice of training image(s) of one frame and the avatar's
//! forward pass, [`seqavatar_avatar::avatar::deform`]), `splat` (onto the iteration's
//! background, [`crate::config::Background`]), `losses` (photometric and, when configured,
//! LPIPS against the ground truth composited with its mask onto that same background,
//! [`crate::data::ImageRecord::colour_on`], and the as-isometric-as-possible loss,
//! [`crate::losses::aiap_gaussians`]), `backward` (splatting, skinning, networks),
//! `optimiser` (Adam with the docs/method.md schedules) and `densify` (density statistics and
//! control).

use anyhow::Context;
use seqavatar_avatar::avatar::{
    AvatarGaussians, Deformed, PosedFrame, deform, deform_backward, frame_pose,
    gather_frame_inputs, template_grid,
};
use seqavatar_avatar::device::{AvatarBackend, avatar_backend};
use seqavatar_avatar::rig::{FramePose, PoseChain};
use seqavatar_avatar::skinning::skin_backward;
use seqavatar_avatar::splatting::SplatPass;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::nn::adam::{AdamConfig, AdamState, adam_update};
use seqavatar_compute::splat::{RasterOptions, sh_coefficient_count};
use seqavatar_core::camera::Camera;
use seqavatar_knn::{KnnGrid, MovingKnn};

use crate::densify::{DensifyReport, names};
use crate::gaussians::{SH, SH_STORED, exponential_lr, psnr};
use crate::losses::{
    AiapGaussianGrads, AiapGaussians, AiapWeights, ColourPair, ImageLossWeights, ImagePair,
    aiap_gaussians, image_loss,
};
use crate::run::{Divergence, IterationStats, Phase, PhaseClock, Run, TrainingStep, sh_degree_at};

/// What the deform phase hands to the rest of the iteration.
struct Forward {
    /// The iteration's training images (one frame).
    chosen: Vec<usize>,
    frame: usize,
    sh_degree: u32,
    posed: PosedFrame,
    gaussians: AvatarGaussians,
    deformed: Deformed,
}

/// What the splat phase hands on.
struct Rendered {
    cameras: Vec<Camera>,
    background: [f64; 3],
    pass: SplatPass,
}

/// What the loss phase hands on: the statistics, the image gradients per camera (already
/// scaled by the camera average) and the AIAP gradients when that loss is on.
struct Losses {
    stats: IterationStats,
    upstream_colour: Vec<Vec<f64>>,
    upstream_alpha: Vec<Vec<f64>>,
    aiap: Option<AiapGaussianGrads>,
}

/// The gradients of the Gaussians' trainable columns and the densification statistics'
/// inputs.
struct Gradients {
    xyz: Vec<f64>,
    sh: Vec<f64>,
    opacity_logit: Vec<f64>,
    log_scale: Vec<f64>,
    rotation: Vec<f64>,
    /// Per Gaussian, the norm of the gradient of its projected centre (pixels).
    mean_2d_norm: Vec<f64>,
    /// Half the largest side of the iteration's cameras, in pixels.
    half_size: f64,
}

impl Gradients {
    /// The trainable columns' gradients by column name, in the optimiser's order.
    fn columns(&self) -> [(&'static str, &Vec<f64>); 5] {
        [
            (names::POSITION, &self.xyz),
            (SH, &self.sh),
            (names::OPACITY_LOGIT, &self.opacity_logit),
            (names::LOG_SCALE, &self.log_scale),
            (names::ROTATION, &self.rotation),
        ]
    }
}

/// The `cpu` step: the avatar's backend, built once for the run's networks, and what the host
/// phases keep between iterations.
pub(crate) struct HostStep {
    /// The backend every phase runs on.
    device: AvatarBackend,
    template_grid: KnnGrid,
    /// The AIAP loss's canonical neighbour lists, kept between iterations (exact every
    /// iteration; not checkpointed: a resumed run rebuilds them on its first step).
    aiap_knn: MovingKnn,
    /// Unrefined skinning targets per frame, computed once.
    poses: Vec<Option<(FramePose, PoseChain)>>,
}

impl TrainingStep for HostStep {
    fn step(&mut self, run: &mut Run<'_>) -> anyhow::Result<IterationStats> {
        let iteration = run.iteration + 1;
        let mut clock = PhaseClock::start();
        let forward = self.deform_phase(run, iteration)?;
        clock.lap(&mut run.phase_times, Phase::Deform);
        let rendered = self.splat_phase(run, &forward)?;
        clock.lap(&mut run.phase_times, Phase::Splat);
        let losses = self.loss_phase(run, iteration, &forward, &rendered)?;
        clock.lap(&mut run.phase_times, Phase::Losses);
        let mut stats = losses.stats;
        let gradients = self.backward_phase(run, iteration, &forward, rendered, losses)?;
        clock.lap(&mut run.phase_times, Phase::Backward);
        self.optimiser_phase(run, iteration, &gradients)?;
        clock.lap(&mut run.phase_times, Phase::Optimiser);
        stats.densified = self.densify_phase(run, iteration, &gradients)?;
        clock.lap(&mut run.phase_times, Phase::Densify);
        run.phase_times.iterations += 1;
        run.iteration = iteration;
        stats.gaussians = run.state.len();
        run.curve.push(&stats);
        Ok(stats)
    }

    fn aiap_neighbour_searches(&self) -> anyhow::Result<(u64, u64)> {
        Ok((self.aiap_knn.rebuilds(), self.aiap_knn.calls()))
    }
}

impl HostStep {
    /// The step of `run` on `backend` (`cpu`), which the avatar's backend is built from once
    /// ([`avatar_backend`]).
    pub(crate) fn new(backend: Backend, run: &Run<'_>) -> anyhow::Result<Self> {
        Ok(Self {
            device: avatar_backend(backend)?,
            template_grid: template_grid(&run.data.rig),
            aiap_knn: MovingKnn::default(),
            poses: vec![None; run.data.params.len()],
        })
    }

    /// The frame's skinning target: refined every iteration when the pose refiner is on,
    /// else computed once per frame.
    fn posed_frame(&mut self, run: &Run<'_>, frame: usize) -> anyhow::Result<PosedFrame> {
        let params = &run.data.params[frame];
        if run.networks.as_ref().is_some_and(|n| n.has_pose_refiner()) {
            return frame_pose(&run.data.rig, run.networks.as_ref(), params)
                .with_context(|| format!("frame {frame}"));
        }
        if self.poses[frame].is_none() {
            let posed = run
                .data
                .rig
                .pose_with_chain(params)
                .with_context(|| format!("frame {frame}"))?;
            self.poses[frame] = Some(posed);
        }
        let (pose, chain) = self.poses[frame].clone().expect("just set");
        Ok(PosedFrame {
            pose,
            chain,
            refiner: None,
        })
    }

    /// Deform: the iteration's images and frame, the (refined) pose, the networks' forward,
    /// skinning and activations.
    fn deform_phase(&mut self, run: &mut Run<'_>, iteration: u64) -> anyhow::Result<Forward> {
        let sh_degree = sh_degree_at(&run.config, iteration);
        let chosen = run.pick_images();
        let frame = run.data.images[chosen[0]].frame;
        if let Some(net) = run.networks.as_mut() {
            net.zero_grad();
        }
        let posed = self.posed_frame(run, frame)?;
        let avatar_config = run.config.avatar();
        let inputs = gather_frame_inputs(
            &avatar_config,
            &run.scales,
            &run.data.motion,
            &run.data.params[frame],
            frame,
        )?;
        let gaussians = run.avatar_gaussians()?;
        let deformed = deform(
            &run.data.rig,
            &self.template_grid,
            run.networks.as_ref(),
            &self.device,
            &gaussians,
            &inputs,
            &posed.pose,
            &avatar_config,
            sh_degree,
        )?;
        Ok(Forward {
            chosen,
            frame,
            sh_degree,
            posed,
            gaussians,
            deformed,
        })
    }

    /// Splat: the deformed Gaussians rendered into every chosen camera on this iteration's
    /// background (every image loss compares with the ground truth composited onto it).
    fn splat_phase(&mut self, run: &mut Run<'_>, forward: &Forward) -> anyhow::Result<Rendered> {
        let cameras: Vec<_> = forward
            .chosen
            .iter()
            .map(|&i| run.data.cameras[run.data.images[i].view].clone())
            .collect();
        let background = run.config.background.draw(&mut run.rng);
        let options = RasterOptions {
            background,
            smooth_cutoff: false,
        };
        let pass = self
            .device
            .splat_forward(&forward.deformed.world, &cameras, &options)?;
        Ok(Rendered {
            cameras,
            background,
            pass,
        })
    }

    /// Losses: the photometric (and LPIPS) losses per camera, averaged, with their image
    /// gradients, and the as-isometric-as-possible loss with its gradients.
    fn loss_phase(
        &mut self,
        run: &mut Run<'_>,
        iteration: u64,
        forward: &Forward,
        rendered: &Rendered,
    ) -> anyhow::Result<Losses> {
        let chosen = &forward.chosen;
        let weights = ImageLossWeights {
            mask: run.config.mask_weight,
            ssim: run.config.ssim_weight,
        };
        let scale = 1.0 / chosen.len() as f64;
        let mut stats = IterationStats {
            iteration,
            ..Default::default()
        };
        let mut upstream_colour = Vec::with_capacity(chosen.len());
        let mut upstream_alpha = Vec::with_capacity(chosen.len());
        for (image, &index) in rendered.pass.images.iter().zip(chosen) {
            let record = &run.data.images[index];
            let (w, h) = (image.width as usize, image.height as usize);
            let bound = run
                .data
                .padded_bound(index, run.config.bound_padding)
                .expect("training images have a foreground");
            let target_colour = record.colour_on(rendered.background);
            let target_mask = record.mask_f64();
            let (terms, mut grads) = image_loss(
                &ImagePair {
                    width: w,
                    height: h,
                    colour: &image.colour,
                    alpha: &image.alpha,
                    target_colour: &target_colour,
                    target_mask: &target_mask,
                },
                bound,
                weights,
            );
            stats.l1 += scale * terms.l1;
            stats.mask_mse += scale * terms.mask_mse;
            stats.dssim += scale * terms.dssim;
            stats.total += scale * terms.total;
            if let Some(lpips) = &run.lpips {
                // Its image gradient joins the colour gradient before the splatting backward.
                let weight = run.config.lpips_weight;
                let value = lpips
                    .add_loss(
                        ColourPair {
                            width: w,
                            height: h,
                            colour: &image.colour,
                            target: &target_colour,
                        },
                        bound,
                        weight,
                        &mut grads.colour,
                    )
                    .with_context(|| format!("iteration {iteration}: LPIPS loss"))?;
                stats.lpips += scale * value;
                stats.total += scale * weight * value;
            }
            stats.psnr += scale * psnr(&image.colour, &target_colour, w, bound);
            upstream_colour.push(grads.colour.iter().map(|g| g * scale).collect::<Vec<f64>>());
            upstream_alpha.push(grads.alpha.iter().map(|g| g * scale).collect::<Vec<f64>>());
        }
        let gaussians = &forward.gaussians;
        let aiap = aiap_gaussians(
            &AiapGaussians {
                xyz: &gaussians.xyz,
                log_scale: &gaussians.log_scale,
                rotation: &gaussians.rotation,
                deformed_centres: &forward.deformed.skinned.positions,
                deformed_covariances: &forward.deformed.skinned.covariances,
            },
            AiapWeights {
                centre: run.config.aiap_centre_weight,
                covariance: run.config.aiap_covariance_weight,
                neighbours: run.config.aiap_neighbours,
            },
            &mut self.aiap_knn,
        );
        if let Some(aiap) = &aiap {
            stats.aiap = aiap.value;
            stats.total += stats.aiap;
        }
        stats.check_finite()?;
        Ok(Losses {
            stats,
            upstream_colour,
            upstream_alpha,
            aiap,
        })
    }

    /// Backward: the splatting backward, the AIAP gradients joined to it, the skinning
    /// backward and the networks' backward (their parameter gradients accumulate); the
    /// gradients of the Gaussians' trainable columns, checked finite.
    fn backward_phase(
        &mut self,
        run: &mut Run<'_>,
        iteration: u64,
        forward: &Forward,
        rendered: Rendered,
        losses: Losses,
    ) -> anyhow::Result<Gradients> {
        let deformed = &forward.deformed;
        let gaussians = &forward.gaussians;
        let n = gaussians.len();
        let mut splat_grads = self.device.splat_backward(
            &rendered.pass,
            &losses.upstream_colour,
            &losses.upstream_alpha,
        )?;
        drop(rendered.pass);
        let (mut d_xyz, d_log_scale_aiap, d_rotation_aiap) = match losses.aiap {
            Some(aiap) => {
                add_into(&mut splat_grads.means, &aiap.deformed_centres);
                add_into(&mut splat_grads.covariances, &aiap.deformed_covariances);
                (aiap.xyz, aiap.log_scale, aiap.rotation)
            }
            None => (vec![0.0; 3 * n], vec![0.0; 3 * n], vec![0.0; 4 * n]),
        };
        let frame_data = run.data.rig.frame(
            &forward.posed.pose,
            run.config.scale_min,
            run.config.scale_max,
        );
        let params = deformed.skin_params(gaussians);
        let skin = skin_backward(
            &frame_data,
            &params,
            &splat_grads.means,
            &splat_grads.covariances,
        );
        add_into(&mut d_xyz, &skin.positions);
        if let Some(net) = run.networks.as_mut() {
            let through = deform_backward(
                net,
                &self.device,
                &run.data.rig,
                &forward.posed,
                deformed,
                &run.data.params[forward.frame],
                &skin,
            )?;
            add_into(&mut d_xyz, &through);
        }
        let mut d_log_scale = skin.log_scales.clone();
        add_into(&mut d_log_scale, &d_log_scale_aiap);
        let mut d_rotation = skin.rotations.clone();
        add_into(&mut d_rotation, &d_rotation_aiap);
        let opacities = &deformed.world.opacities;
        let d_opacity: Vec<f64> = (0..n)
            .map(|i| splat_grads.opacities[i] * opacities[i] * (1.0 - opacities[i]))
            .collect();
        let k = sh_coefficient_count(forward.sh_degree);
        let mut d_sh = vec![0.0; n * 3 * SH_STORED];
        for i in 0..n {
            d_sh[i * 3 * SH_STORED..i * 3 * SH_STORED + 3 * k]
                .copy_from_slice(&splat_grads.sh[i * 3 * k..(i + 1) * 3 * k]);
        }
        let gradients = Gradients {
            xyz: d_xyz,
            sh: d_sh,
            opacity_logit: d_opacity,
            log_scale: d_log_scale,
            rotation: d_rotation,
            mean_2d_norm: splat_grads.mean_2d_norm,
            half_size: rendered
                .cameras
                .iter()
                .map(|c| c.width.max(c.height))
                .max()
                .unwrap_or(1) as f64
                * 0.5,
        };
        for (name, values) in gradients.columns() {
            if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                return Err(Divergence {
                    iteration,
                    what: "gradient of",
                    tensor: format!("gaussians/{name}"),
                    detail: format!(" (Gaussian {})", bad / (values.len() / n.max(1)).max(1)),
                }
                .into());
            }
        }
        Ok(gradients)
    }

    /// Optimiser: Adam on the Gaussians' columns (docs/method.md's schedules) and on the networks
    /// (per-group rates decayed by `network_decay^(step / iterations)`).
    fn optimiser_phase(
        &mut self,
        run: &mut Run<'_>,
        iteration: u64,
        gradients: &Gradients,
    ) -> anyhow::Result<()> {
        let n = gradients.opacity_logit.len();
        run.adam_step += 1;
        let lr = &run.config.learning_rates;
        let extent = run.data.extent;
        let position_lr = exponential_lr(
            lr.position_initial * extent,
            lr.position_final * extent,
            iteration,
            u64::from(lr.position_decay_steps),
        );
        let adam = run.config.adam();
        for (name, gradient) in gradients.columns() {
            let mut moments = AdamState {
                m: std::mem::take(run.state.values_mut(&format!("{name}.adam_m"))?),
                v: std::mem::take(run.state.values_mut(&format!("{name}.adam_v"))?),
                step: run.adam_step - 1,
            };
            let values = run.state.values_mut(name)?;
            if name == SH {
                update_sh(
                    &adam,
                    lr.sh_dc,
                    lr.sh_rest,
                    values,
                    gradient,
                    &mut moments,
                    n,
                )?;
            } else {
                let rate = match name {
                    names::POSITION => position_lr,
                    names::OPACITY_LOGIT => lr.opacity,
                    names::LOG_SCALE => lr.scaling,
                    _ => lr.rotation,
                };
                adam_update(&adam, rate, values, gradient, &mut moments)?;
            }
            if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                let width = values.len() / n.max(1);
                return Err(Divergence {
                    iteration,
                    what: "parameter",
                    tensor: format!("gaussians/{name}"),
                    detail: format!(" (Gaussian {})", bad / width.max(1)),
                }
                .into());
            }
            *run.state.values_mut(&format!("{name}.adam_m"))? = moments.m;
            *run.state.values_mut(&format!("{name}.adam_v"))? = moments.v;
        }

        // Adam on the networks: per-group rates decayed by `network_decay^(step / iterations)`.
        if let Some(net) = run.networks.as_mut() {
            for param in net.parameters() {
                if let Some(bad) = param.grads.iter().position(|v| !v.is_finite()) {
                    return Err(Divergence {
                        iteration,
                        what: "gradient of",
                        tensor: format!("network.{}", param.name),
                        detail: format!(" (value {bad})"),
                    }
                    .into());
                }
            }
            for param in net.parameters_mut() {
                let rate = run.config.network_rate(param.group, iteration);
                let moments = run
                    .network_adam
                    .entry(param.name.clone())
                    .or_insert_with(|| AdamState::new(param.values.len()));
                adam_update(&adam, rate, param.values, param.grads, moments)?;
                if let Some(bad) = param.values.iter().position(|v| !v.is_finite()) {
                    return Err(Divergence {
                        iteration,
                        what: "parameter",
                        tensor: format!("network.{}", param.name),
                        detail: format!(" (value {bad})"),
                    }
                    .into());
                }
            }
        }

        Ok(())
    }

    /// Densify: the view-space gradient statistics (in 3DGS's NDC units) while density
    /// control is on, and clone/split/prune at its iterations.
    fn densify_phase(
        &mut self,
        run: &mut Run<'_>,
        iteration: u64,
        gradients: &Gradients,
    ) -> anyhow::Result<Option<DensifyReport>> {
        let c = &run.config;
        if iteration <= u64::from(c.densify_until) {
            let norms: Vec<f64> = gradients
                .mean_2d_norm
                .iter()
                .map(|g| g * gradients.half_size)
                .collect();
            let visible: Vec<bool> = gradients.mean_2d_norm.iter().map(|g| *g > 0.0).collect();
            run.state.accumulate_gradient_stats(&norms, &visible)?;
        }
        if run.density_control_due(iteration) {
            return run.density_control(iteration).map(Some);
        }
        Ok(None)
    }
}

/// `into += from`, element by element.
fn add_into(into: &mut [f64], from: &[f64]) {
    for (a, b) in into.iter_mut().zip(from) {
        *a += b;
    }
}

/// Adam on the SH column with one rate for the DC coefficients and another for the rest.
pub(crate) fn update_sh(
    config: &AdamConfig,
    dc_rate: f64,
    rest_rate: f64,
    values: &mut [f64],
    gradient: &[f64],
    adam: &mut AdamState<f64>,
    n: usize,
) -> anyhow::Result<()> {
    let row = 3 * SH_STORED;
    let start_step = adam.step;
    for (part, lr) in [(0..3, dc_rate), (3..row, rest_rate)] {
        let gather = |v: &[f64]| -> Vec<f64> {
            (0..n)
                .flat_map(|i| v[i * row + part.start..i * row + part.end].iter().copied())
                .collect()
        };
        let mut p = gather(values);
        let mut sub = AdamState {
            m: gather(&adam.m),
            v: gather(&adam.v),
            step: start_step,
        };
        adam_update(config, lr, &mut p, &gather(gradient), &mut sub)?;
        let width = part.end - part.start;
        for i in 0..n {
            values[i * row + part.start..i * row + part.end]
                .copy_from_slice(&p[i * width..(i + 1) * width]);
            adam.m[i * row + part.start..i * row + part.end]
                .copy_from_slice(&sub.m[i * width..(i + 1) * width]);
            adam.v[i * row + part.start..i * row + part.end]
                .copy_from_slice(&sub.v[i * width..(i + 1) * width]);
        }
        adam.step = sub.step;
    }
    Ok(())
}
