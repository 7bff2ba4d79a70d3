//! The training loop. [`Trainer::step`] runs one iteration as named phases ([`Phase`], each
//! timed into [`Trainer::phase_times`]): `deform` (a seeded choice of training image(s) of
//! one frame and the avatar's forward pass, [`seqavatar_avatar::avatar::deform`]), `splat` (on the
//! chosen backend onto the iteration's background, [`crate::config::Background`]), `losses`
//! (photometric and, when configured, LPIPS against the ground truth composited with its mask
//! onto that same background, [`crate::data::ImageRecord::colour_on`], and the
//! as-isometric-as-possible loss, [`crate::losses::aiap_gaussians`]), `backward` (splatting,
//! skinning, networks), `optimiser` (Adam with the docs/method.md schedules) and `densify` (density
//! statistics and control); the SH degree follows its schedule.
//!
//! A [`Trainer`] holds the complete resumable state; [`Trainer::checkpoint`] and
//! [`Trainer::resume`] convert it to and from a [`Checkpoint`] exactly, so a resumed `cpu`
//! run reproduces an uninterrupted one bit for bit (every random draw comes from the one
//! [`Rng`] whose state the checkpoint stores, and every reduction has a fixed order).

use anyhow::Context;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::lpips::{Lpips, LpipsWeights};
use seqavatar_compute::nn::adam::{AdamConfig, AdamState, adam_update};
use seqavatar_compute::splat::{RasterOptions, sh_coefficient_count};
use seqavatar_core::camera::Camera;

use std::collections::BTreeMap;
use std::time::Instant;

use seqavatar_avatar::avatar::{
    AvatarGaussians, Deformed, PosedFrame, TrainedAvatar, deform, deform_backward, frame_pose,
    gather_frame_inputs, needs_networks, template_grid,
};
use seqavatar_avatar::device::{AvatarBackend, avatar_backend};
use seqavatar_avatar::model::{NetworkConfig, NetworkGroup, Networks};
use seqavatar_avatar::rig::{FramePose, PoseChain};
use seqavatar_knn::{KnnGrid, MovingKnn, as_points, knn_brute_force};

use crate::checkpoint::{Checkpoint, Tensor};
use crate::config::TrainConfig;
use crate::data::TrainingData;
use crate::densify::{
    DensifyReport, DensifySettings, GaussianState, Growth, densify_and_prune, names,
};
use crate::gaussians::{
    SH, SH_STORED, TRAINABLE, avatar_gaussians, exponential_lr, initial_state, psnr,
};
use crate::losses::{
    AiapGaussianGrads, AiapGaussians, AiapWeights, ColourPair, ImageLossWeights, ImagePair,
    LpipsLoss, Rect, aiap_gaussians, image_loss,
};
use crate::resident::step::{IterationPlan, LOG_CAPACITY, ResidentRun, ResidentStep};
use crate::rng::Rng;
use seqavatar_avatar::skinning::skin_backward;
use seqavatar_avatar::splatting::SplatPass;

/// Loss and statistics of one iteration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct IterationStats {
    pub iteration: u64,
    pub total: f64,
    pub l1: f64,
    pub mask_mse: f64,
    pub dssim: f64,
    /// LPIPS on the crop (unweighted; 0 when the loss is off).
    pub lpips: f64,
    pub aiap: f64,
    pub psnr: f64,
    pub gaussians: usize,
    pub densified: Option<DensifyReport>,
}

/// Per-iteration curves (one value per completed iteration).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LossCurve {
    pub total: Vec<f64>,
    pub l1: Vec<f64>,
    pub mask_mse: Vec<f64>,
    pub dssim: Vec<f64>,
    pub lpips: Vec<f64>,
    pub aiap: Vec<f64>,
    pub psnr: Vec<f64>,
    pub gaussians: Vec<f64>,
}

impl LossCurve {
    /// Names of the curves, as stored (`curve/<name>` in checkpoints, `loss_<name>` in the
    /// entry).
    pub const NAMES: [&'static str; 8] = [
        "total",
        "l1",
        "mask_mse",
        "dssim",
        "lpips",
        "aiap",
        "psnr",
        "gaussians",
    ];

    fn columns(&self) -> [&Vec<f64>; 8] {
        [
            &self.total,
            &self.l1,
            &self.mask_mse,
            &self.dssim,
            &self.lpips,
            &self.aiap,
            &self.psnr,
            &self.gaussians,
        ]
    }

    fn columns_mut(&mut self) -> [&mut Vec<f64>; 8] {
        [
            &mut self.total,
            &mut self.l1,
            &mut self.mask_mse,
            &mut self.dssim,
            &mut self.lpips,
            &mut self.aiap,
            &mut self.psnr,
            &mut self.gaussians,
        ]
    }

    /// The named curve.
    pub fn get(&self, name: &str) -> Option<&Vec<f64>> {
        Self::NAMES
            .iter()
            .position(|n| *n == name)
            .map(|i| self.columns()[i])
    }

    fn push(&mut self, s: &IterationStats) {
        let values = [
            s.total,
            s.l1,
            s.mask_mse,
            s.dssim,
            s.lpips,
            s.aiap,
            s.psnr,
            s.gaussians as f64,
        ];
        for (column, v) in self.columns_mut().into_iter().zip(values) {
            column.push(v);
        }
    }
}

/// Training diverged: a non-finite loss, gradient or parameter.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("training diverged at iteration {iteration}: {what} `{tensor}` is not finite{detail}")]
pub struct Divergence {
    pub iteration: u64,
    /// `loss`, `gradient of` or `parameter`.
    pub what: &'static str,
    pub tensor: String,
    pub detail: String,
}

/// The phases of one iteration, in the order [`Trainer::step`] runs them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Phase {
    /// Image choice, the (refined) pose, the networks' forward, skinning, activations.
    Deform,
    /// Splatting into every chosen camera.
    Splat,
    /// Photometric, LPIPS and as-isometric-as-possible losses with their gradients.
    Losses,
    /// Splatting, skinning and network backward.
    Backward,
    /// Adam on the Gaussians and the networks.
    Optimiser,
    /// Density statistics and control.
    Densify,
}

impl Phase {
    /// Every phase, in order.
    pub const ALL: [Phase; 6] = [
        Phase::Deform,
        Phase::Splat,
        Phase::Losses,
        Phase::Backward,
        Phase::Optimiser,
        Phase::Densify,
    ];

    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Phase::Deform => "deform",
            Phase::Splat => "splat",
            Phase::Losses => "losses",
            Phase::Backward => "backward",
            Phase::Optimiser => "optimiser",
            Phase::Densify => "densify",
        }
    }
}

/// Wall time per phase, accumulated over the iterations since the trainer was built or
/// [`Trainer::reset_phase_times`] was called.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PhaseTimes {
    seconds: [f64; 6],
    iterations: u64,
}

impl PhaseTimes {
    /// Seconds spent in `phase`.
    pub fn seconds(&self, phase: Phase) -> f64 {
        self.seconds[phase as usize]
    }

    /// Seconds spent in every phase together.
    pub fn total(&self) -> f64 {
        self.seconds.iter().sum()
    }

    /// Completed iterations timed.
    pub fn iterations(&self) -> u64 {
        self.iterations
    }
}

/// Times consecutive phases: each lap charges the time since the previous one.
struct PhaseClock(Instant);

impl PhaseClock {
    fn start() -> Self {
        PhaseClock(Instant::now())
    }

    fn lap(&mut self, times: &mut PhaseTimes, phase: Phase) {
        let now = Instant::now();
        times.seconds[phase as usize] += (now - self.0).as_secs_f64();
        self.0 = now;
    }
}

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

/// The complete state of a run.
pub struct Trainer<'d> {
    pub config: TrainConfig,
    data: &'d TrainingData,
    /// The backend every phase runs on, chosen once when the trainer is built (on the gpu it
    /// owns an f32 copy of the per-Gaussian networks, non-rigid and LBS offsets, refreshed
    /// from `networks`, the parameter master, before every forward pass).
    device: Box<dyn AvatarBackend>,
    pub state: GaussianState,
    /// Completed iterations.
    pub iteration: u64,
    /// Adam updates applied to the Gaussians.
    pub adam_step: u64,
    pub rng: Rng,
    pub curve: LossCurve,
    /// Raw scales fed to the networks (largest first).
    pub scales: Vec<u32>,
    /// The networks (when the configuration has any) and their Adam state by name.
    pub networks: Option<Networks<f32>>,
    network_adam: BTreeMap<String, AdamState<f32>>,
    train_images: Vec<usize>,
    /// The LPIPS loss, loaded only when `lpips_weight > 0`.
    lpips: Option<LpipsLoss>,
    template_grid: KnnGrid,
    /// The AIAP loss's canonical neighbour lists, kept between iterations (exact every
    /// iteration; not checkpointed: a resumed run rebuilds them on its first step).
    aiap_knn: MovingKnn,
    /// Unrefined skinning targets per frame, computed once.
    poses: Vec<Option<(FramePose, PoseChain)>>,
    phase_times: PhaseTimes,
    /// On the `gpu` backend: the run's state on the device and its iteration
    /// ([`ResidentStep`]); the host fields above are brought up to date by
    /// [`Trainer::sync`].
    resident: Option<ResidentStep>,
    /// On the `gpu` backend: iterations between two reads of the logged scalars.
    log_every: usize,
    /// The last iteration whose logged scalars were read (`IterationStats` of the iterations
    /// recorded since repeat them).
    last_logged: IterationStats,
}

/// Where a run stands: fresh ([`Trainer::new`]) or read from a checkpoint
/// ([`Trainer::resume`]).
struct RunState {
    state: GaussianState,
    /// Iterations done.
    iteration: u64,
    /// The Gaussians' Adam step count.
    adam_step: u64,
    rng: Rng,
    curve: LossCurve,
    networks: Option<Networks<f32>>,
    network_adam: BTreeMap<String, AdamState<f32>>,
}

/// The active SH degree at (1-based) iteration `iteration`: one more every `interval`.
pub fn sh_degree_at(config: &TrainConfig, iteration: u64) -> u32 {
    let steps = iteration / u64::from(config.sh_degree_interval.max(1));
    steps.min(u64::from(config.sh_degree)) as u32
}

/// Initial linear scales: `sqrt(mean squared distance to the 3 nearest other points)`.
pub fn initial_scales(points: &[f64]) -> Vec<f64> {
    let p = as_points(points);
    let n = p.len();
    let k = 4.min(n);
    let grid = KnnGrid::new(&p, 4.0);
    let nn = if n <= 64 {
        knn_brute_force(&p, &p, k)
    } else {
        grid.query_all(&p, k)
    };
    (0..n)
        .flat_map(|i| {
            let mut sum = 0.0;
            let mut count = 0;
            for &j in &nn[i * k..(i + 1) * k] {
                if j as usize != i {
                    let d: f64 = (0..3).map(|a| (p[i][a] - p[j as usize][a]).powi(2)).sum();
                    sum += d;
                    count += 1;
                }
            }
            let s = if count > 0 {
                (sum / count as f64).sqrt().max(1e-7)
            } else {
                0.01
            };
            [s; 3]
        })
        .collect()
}

impl<'d> Trainer<'d> {
    /// A fresh run: Gaussians at the canonical template vertices with random colours,
    /// opacity 0.1, isotropic scales from the neighbour distances, identity rotations. Every
    /// phase runs on `backend`, which the trainer builds its [`AvatarBackend`] from once
    /// ([`avatar_backend`]).
    pub fn new(
        config: TrainConfig,
        data: &'d TrainingData,
        backend: Backend,
    ) -> anyhow::Result<Self> {
        let scales = config
            .effective_scales(&data.motion.scales)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut rng = Rng::new(config.seed);
        let centres = data.rig.canonical_vertices.clone();
        // Density control never removes Gaussians to meet the cap, so a cap below the
        // starting count would be silently ignored: refuse it instead.
        let starting = centres.len() / 3;
        anyhow::ensure!(
            starting <= config.max_gaussians,
            "train config field `max_gaussians` is {}, below the {starting} Gaussians training \
             starts with (one per vertex of the body template): set it to at least {starting}",
            config.max_gaussians
        );
        let colours: Vec<f64> = (0..centres.len()).map(|_| rng.next_f64()).collect();
        let state = initial_state(&centres, &colours, 0.1, &initial_scales(&centres))?;
        let networks = build_networks(&config, data, scales.len())?;
        Self::assemble(
            config,
            data,
            backend,
            scales,
            RunState {
                state,
                iteration: 0,
                adam_step: 0,
                rng,
                curve: LossCurve::default(),
                networks,
                network_adam: BTreeMap::new(),
            },
        )
    }

    /// The trainer of `config` on `data` from `run` (fresh or a checkpoint's), checking the
    /// training images and building the device step on the gpu backend.
    fn assemble(
        config: TrainConfig,
        data: &'d TrainingData,
        backend: Backend,
        scales: Vec<u32>,
        run: RunState,
    ) -> anyhow::Result<Self> {
        let RunState {
            state,
            iteration,
            adam_step,
            rng,
            curve,
            networks,
            network_adam,
        } = run;
        let train_images: Vec<usize> = data
            .split(0)
            .into_iter()
            .filter(|&i| data.images[i].bound.is_some())
            .collect();
        anyhow::ensure!(
            !train_images.is_empty(),
            "no training image has a non-empty foreground mask"
        );
        let gpu_context = backend.gpu().cloned();
        let device = avatar_backend(backend, networks.as_ref(), config.networks_precision())?;
        let lpips = load_lpips_loss(&config, device.compute())?;
        if let Some(loss) = &lpips {
            for &index in &train_images {
                let camera = &data.cameras[data.images[index].view];
                loss.check_image(camera.width as usize, camera.height as usize)
                    .with_context(|| {
                        format!(
                            "LPIPS loss: training camera {} (after resolution_scale {})",
                            data.images[index].view, config.resolution_scale
                        )
                    })?;
            }
        }
        // On the gpu backend the whole iteration lives on the device.
        let resident = match gpu_context {
            Some(context) => Some(
                ResidentStep::new(
                    context,
                    &ResidentRun {
                        config: &config,
                        data,
                        scales: &scales,
                        state: &state,
                        networks: networks.as_ref(),
                        network_adam: &network_adam,
                        lpips: lpips.as_ref(),
                    },
                )
                .context("the device-resident training step")?,
            ),
            None => None,
        };
        Ok(Self {
            lpips,
            template_grid: template_grid(&data.rig),
            aiap_knn: MovingKnn::default(),
            poses: vec![None; data.params.len()],
            config,
            data,
            device,
            state,
            iteration,
            adam_step,
            rng,
            curve,
            scales,
            networks,
            network_adam,
            train_images,
            phase_times: PhaseTimes::default(),
            resident,
            log_every: LOG_CAPACITY,
            last_logged: IterationStats::default(),
        })
    }

    /// The frame's skinning target: refined every iteration when the pose refiner is on,
    /// else computed once per frame.
    fn posed_frame(&mut self, frame: usize) -> anyhow::Result<PosedFrame> {
        let params = &self.data.params[frame];
        if self.networks.as_ref().is_some_and(|n| n.has_pose_refiner()) {
            return frame_pose(&self.data.rig, self.networks.as_ref(), params)
                .with_context(|| format!("frame {frame}"));
        }
        if self.poses[frame].is_none() {
            let posed = self
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

    /// Images of one iteration: a random training image, plus other training images of the
    /// same frame up to `cameras_per_step`.
    fn pick_images(&mut self) -> Vec<usize> {
        let first = self.train_images[self.rng.below(self.train_images.len())];
        let frame = self.data.images[first].frame;
        let mut others: Vec<usize> = self
            .train_images
            .iter()
            .copied()
            .filter(|&i| i != first && self.data.images[i].frame == frame)
            .collect();
        let mut chosen = vec![first];
        while chosen.len() < self.config.cameras_per_step && !others.is_empty() {
            let k = self.rng.below(others.len());
            chosen.push(others.swap_remove(k));
        }
        chosen
    }

    fn avatar_gaussians(&self) -> anyhow::Result<AvatarGaussians> {
        avatar_gaussians(&self.state)
    }

    /// One training iteration: the phases of [`Phase`] in order, each timed into
    /// [`Trainer::phase_times`].
    pub fn step(&mut self) -> anyhow::Result<IterationStats> {
        if self.resident.is_some() {
            return self.resident_step();
        }
        let iteration = self.iteration + 1;
        let mut clock = PhaseClock::start();
        let forward = self.deform_phase(iteration)?;
        clock.lap(&mut self.phase_times, Phase::Deform);
        let rendered = self.splat_phase(&forward)?;
        clock.lap(&mut self.phase_times, Phase::Splat);
        let losses = self.loss_phase(iteration, &forward, &rendered)?;
        clock.lap(&mut self.phase_times, Phase::Losses);
        let mut stats = losses.stats;
        let gradients = self.backward_phase(iteration, &forward, rendered, losses)?;
        clock.lap(&mut self.phase_times, Phase::Backward);
        self.optimiser_phase(iteration, &gradients)?;
        clock.lap(&mut self.phase_times, Phase::Optimiser);
        stats.densified = self.densify_phase(iteration, &gradients)?;
        clock.lap(&mut self.phase_times, Phase::Densify);
        self.phase_times.iterations += 1;
        self.iteration = iteration;
        stats.gaussians = self.state.len();
        self.curve.push(&stats);
        Ok(stats)
    }

    /// Deform: the iteration's images and frame, the (refined) pose, the networks' forward,
    /// skinning and activations.
    fn deform_phase(&mut self, iteration: u64) -> anyhow::Result<Forward> {
        let sh_degree = sh_degree_at(&self.config, iteration);
        let chosen = self.pick_images();
        let frame = self.data.images[chosen[0]].frame;
        if let Some(net) = self.networks.as_mut() {
            net.zero_grad();
        }
        // The master parameters change with every optimiser step (and `networks` is public):
        // the backend's copy (on the gpu) is refreshed before every forward pass.
        if let Some(net) = &self.networks {
            self.device.refresh_networks(net)?;
        }
        let posed = self.posed_frame(frame)?;
        let avatar_config = self.config.avatar();
        let inputs = gather_frame_inputs(
            &avatar_config,
            &self.scales,
            &self.data.motion,
            &self.data.params[frame],
            frame,
        )?;
        let gaussians = self.avatar_gaussians()?;
        let deformed = deform(
            &self.data.rig,
            &self.template_grid,
            self.networks.as_ref(),
            &*self.device,
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
    fn splat_phase(&mut self, forward: &Forward) -> anyhow::Result<Rendered> {
        let cameras: Vec<_> = forward
            .chosen
            .iter()
            .map(|&i| self.data.cameras[self.data.images[i].view].clone())
            .collect();
        let background = self.config.background.draw(&mut self.rng);
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
        iteration: u64,
        forward: &Forward,
        rendered: &Rendered,
    ) -> anyhow::Result<Losses> {
        let chosen = &forward.chosen;
        let weights = ImageLossWeights {
            mask: self.config.mask_weight,
            ssim: self.config.ssim_weight,
        };
        let scale = 1.0 / chosen.len() as f64;
        let mut stats = IterationStats {
            iteration,
            ..Default::default()
        };
        let mut upstream_colour = Vec::with_capacity(chosen.len());
        let mut upstream_alpha = Vec::with_capacity(chosen.len());
        for (image, &index) in rendered.pass.images.iter().zip(chosen) {
            let record = &self.data.images[index];
            let (w, h) = (image.width as usize, image.height as usize);
            let bound = pad_rect(
                record.bound.expect("training images have a foreground"),
                self.config.bound_padding,
                w,
                h,
            );
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
            if let Some(lpips) = &self.lpips {
                // Its image gradient joins the colour gradient before the splatting backward.
                let weight = self.config.lpips_weight;
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
                centre: self.config.aiap_centre_weight,
                covariance: self.config.aiap_covariance_weight,
                neighbours: self.config.aiap_neighbours,
            },
            &mut self.aiap_knn,
        );
        if let Some(aiap) = &aiap {
            stats.aiap = aiap.value;
            stats.total += stats.aiap;
        }
        if !stats.total.is_finite() {
            return Err(Divergence {
                iteration,
                what: "loss",
                tensor: "total".into(),
                detail: format!(
                    " (l1 {}, mask {}, dssim {}, lpips {}, aiap {})",
                    stats.l1, stats.mask_mse, stats.dssim, stats.lpips, stats.aiap
                ),
            }
            .into());
        }
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
                for (a, b) in splat_grads.means.iter_mut().zip(&aiap.deformed_centres) {
                    *a += b;
                }
                for (a, b) in splat_grads
                    .covariances
                    .iter_mut()
                    .zip(&aiap.deformed_covariances)
                {
                    *a += b;
                }
                (aiap.xyz, aiap.log_scale, aiap.rotation)
            }
            None => (vec![0.0; 3 * n], vec![0.0; 3 * n], vec![0.0; 4 * n]),
        };
        let frame_data = self.data.rig.frame(
            &forward.posed.pose,
            self.config.scale_min,
            self.config.scale_max,
        );
        let params = deformed.skin_params(gaussians);
        let skin = skin_backward(
            &frame_data,
            &params,
            &splat_grads.means,
            &splat_grads.covariances,
        );
        for (a, b) in d_xyz.iter_mut().zip(&skin.positions) {
            *a += b;
        }
        if let Some(net) = self.networks.as_mut() {
            let through = deform_backward(
                net,
                &*self.device,
                &self.data.rig,
                &forward.posed,
                deformed,
                &self.data.params[forward.frame],
                &skin,
            )?;
            for (a, b) in d_xyz.iter_mut().zip(&through) {
                *a += b;
            }
        }
        let d_log_scale: Vec<f64> = skin
            .log_scales
            .iter()
            .zip(&d_log_scale_aiap)
            .map(|(a, b)| a + b)
            .collect();
        let d_rotation: Vec<f64> = skin
            .rotations
            .iter()
            .zip(&d_rotation_aiap)
            .map(|(a, b)| a + b)
            .collect();
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
    fn optimiser_phase(&mut self, iteration: u64, gradients: &Gradients) -> anyhow::Result<()> {
        let n = gradients.opacity_logit.len();
        self.adam_step += 1;
        let lr = &self.config.learning_rates;
        let extent = self.data.extent;
        let position_lr = exponential_lr(
            lr.position_initial * extent,
            lr.position_final * extent,
            iteration,
            u64::from(lr.position_decay_steps),
        );
        let adam = AdamConfig {
            eps: lr.adam_eps,
            ..AdamConfig::default()
        };
        for (name, gradient) in gradients.columns() {
            let mut moments = AdamState {
                m: std::mem::take(self.state.values_mut(&format!("{name}.adam_m"))?),
                v: std::mem::take(self.state.values_mut(&format!("{name}.adam_v"))?),
                step: self.adam_step - 1,
            };
            let values = self.state.values_mut(name)?;
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
            *self.state.values_mut(&format!("{name}.adam_m"))? = moments.m;
            *self.state.values_mut(&format!("{name}.adam_v"))? = moments.v;
        }

        // Adam on the networks: per-group rates decayed by `network_decay^(step / iterations)`.
        if let Some(net) = self.networks.as_mut() {
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
            let decay = lr
                .network_decay
                .powf((iteration - 1) as f64 / f64::from(self.config.iterations));
            for param in net.parameters_mut() {
                let rate = decay
                    * match param.group {
                        NetworkGroup::NonRigid => lr.non_rigid,
                        NetworkGroup::PoseRefiner => lr.pose_refiner,
                        NetworkGroup::LbsOffsets => lr.lbs_offsets,
                    };
                let moments = self
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
        iteration: u64,
        gradients: &Gradients,
    ) -> anyhow::Result<Option<DensifyReport>> {
        let c = &self.config;
        if iteration <= u64::from(c.densify_until) {
            let norms: Vec<f64> = gradients
                .mean_2d_norm
                .iter()
                .map(|g| g * gradients.half_size)
                .collect();
            let visible: Vec<bool> = gradients.mean_2d_norm.iter().map(|g| *g > 0.0).collect();
            self.state.accumulate_gradient_stats(&norms, &visible)?;
        }
        if self.density_control_due(iteration) {
            return self.density_control(iteration).map(Some);
        }
        Ok(None)
    }

    /// Whether iteration `iteration` runs the density control (clone, split, prune).
    fn density_control_due(&self, iteration: u64) -> bool {
        let c = &self.config;
        c.densify
            && iteration > u64::from(c.densify_from)
            && iteration <= u64::from(c.densify_until)
            && iteration.is_multiple_of(u64::from(c.densify_interval))
    }

    /// Clone, split and prune the host state's Gaussians (their statistics accumulated).
    fn density_control(&mut self, iteration: u64) -> anyhow::Result<DensifyReport> {
        let c = &self.config;
        let settings = DensifySettings {
            grad_threshold: c.densify_grad_threshold,
            percent_dense: c.percent_dense,
            extent: self.data.extent,
            min_opacity: c.prune_opacity,
            max_gaussians: c.max_gaussians,
        };
        let report = densify_and_prune(&mut self.state, &settings, &mut self.rng)?;
        anyhow::ensure!(
            report.count > 0,
            "iteration {iteration}: density control pruned every Gaussian"
        );
        Ok(report)
    }

    /// One iteration on the device ([`ResidentStep`]): the host makes the same draws as the
    /// `cpu` path (images, frame, background, densification), records and submits; the
    /// logged scalars are read every `log_every` iterations, before densification and at
    /// the last iteration. The returned statistics are the last ones read.
    fn resident_step(&mut self) -> anyhow::Result<IterationStats> {
        let iteration = self.iteration + 1;
        let mut clock = PhaseClock::start();
        let sh_degree = sh_degree_at(&self.config, iteration);
        let chosen = self.pick_images();
        let frame = self.data.images[chosen[0]].frame;
        let background = self.config.background.draw(&mut self.rng);
        self.adam_step += 1;
        let densify_now = self.density_control_due(iteration);
        let plan = IterationPlan {
            iteration,
            frame,
            images: &chosen,
            background,
            sh_degree,
            adam_step: self.adam_step,
            density_statistics: iteration <= u64::from(self.config.densify_until),
        };
        let resident = self.resident.as_mut().expect("resident step");
        resident
            .record(&plan, self.data, self.lpips.as_ref())
            .with_context(|| format!("iteration {iteration} on the device"))?;
        clock.lap(&mut self.phase_times, Phase::Deform);
        self.iteration = iteration;
        self.phase_times.iterations += 1;
        let due = resident.unread() >= self.log_every.clamp(1, resident.log_capacity())
            || iteration >= u64::from(self.config.iterations)
            || densify_now;
        if due {
            self.read_log()?;
        }
        let mut stats = IterationStats {
            iteration,
            gaussians: self.state.len(),
            densified: None,
            ..self.last_logged
        };
        if densify_now {
            let resident = self.resident.as_ref().expect("resident step");
            resident.download_state(&mut self.state)?;
            let report = self.density_control(iteration)?;
            let resident = self.resident.as_mut().expect("resident step");
            resident.upload_state(&self.state)?;
            stats.densified = Some(report);
            stats.gaussians = self.state.len();
            clock.lap(&mut self.phase_times, Phase::Densify);
        }
        Ok(stats)
    }

    /// Reads the logged scalars of the iterations recorded on the device since the last
    /// read into the loss curve (and checks them: a non-finite value is a [`Divergence`]).
    fn read_log(&mut self) -> anyhow::Result<()> {
        let Some(resident) = self.resident.as_mut() else {
            return Ok(());
        };
        let count = resident.unread() as u64;
        let logged = resident.read_log(self.iteration)?;
        for (offset, values) in logged.iter().enumerate() {
            let stats = IterationStats {
                iteration: self.iteration + 1 - count + offset as u64,
                total: values.image_total + values.aiap,
                l1: values.l1,
                mask_mse: values.mask_mse,
                dssim: values.dssim,
                lpips: values.lpips,
                aiap: values.aiap,
                psnr: values.psnr,
                gaussians: self.state.len(),
                densified: None,
            };
            self.curve.push(&stats);
            self.last_logged = stats;
        }
        Ok(())
    }

    /// Brings the host state (Gaussians, networks, their Adam moments, the loss curve) up to
    /// date with the device on the `gpu` backend (nothing to do on `cpu`): before a
    /// checkpoint, the trained avatar, or reading [`Trainer::state`], [`Trainer::networks`]
    /// or [`Trainer::curve`].
    pub fn sync(&mut self) -> anyhow::Result<()> {
        self.read_log()?;
        if let Some(resident) = &self.resident {
            resident.download_state(&mut self.state)?;
            if let Some(networks) = self.networks.as_mut() {
                resident.download_networks(networks, &mut self.network_adam)?;
            }
        }
        Ok(())
    }

    /// Iterations between two reads of the logged scalars on the `gpu` backend (1: every
    /// iteration's statistics are exact when [`Trainer::step`] returns them; at most the
    /// log ring's capacity).
    pub fn set_log_every(&mut self, iterations: usize) {
        self.log_every = iterations.max(1);
    }

    /// Waits until the device has run every submitted iteration (for timing: a resident
    /// step returns once its work is submitted); nothing to do on `cpu`.
    pub fn wait_for_device(&mut self) -> anyhow::Result<()> {
        match self.resident.as_mut() {
            Some(resident) => resident.wait_idle(),
            None => Ok(()),
        }
    }

    /// Whether the iteration runs on the device ([`ResidentStep`]).
    pub fn resident(&self) -> bool {
        self.resident.is_some()
    }

    /// Whether the non-rigid network runs on the gpu (the `gpu` backend with a motion
    /// context that has one).
    pub fn non_rigid_on_gpu(&self) -> bool {
        self.networks.as_ref().is_some_and(|n| n.has_non_rigid()) && self.device.networks_on_gpu()
    }

    /// Full neighbour searches of the AIAP loss and the iterations that asked for
    /// neighbours, since the trainer was built (the rest reused their candidate lists).
    pub fn aiap_neighbour_searches(&self) -> anyhow::Result<(u64, u64)> {
        match &self.resident {
            Some(resident) => resident.aiap_searches(),
            None => Ok((self.aiap_knn.rebuilds(), self.aiap_knn.calls())),
        }
    }

    /// Wall time per phase since the trainer was built or the last
    /// [`Trainer::reset_phase_times`].
    pub fn phase_times(&self) -> &PhaseTimes {
        &self.phase_times
    }

    /// Starts timing each phase of the iteration on the device (`gpu` backend, where the
    /// adapter has timestamps inside encoders; see [`Trainer::device_phase_times`]). Returns
    /// whether it does; `false` on `cpu`.
    pub fn time_device_phases(&mut self) -> anyhow::Result<bool> {
        self.read_log()?;
        match self.resident.as_mut() {
            Some(resident) => resident.time_phases(),
            None => Ok(false),
        }
    }

    /// Device time per phase (densification, which runs on the host, as zero) over the
    /// iterations run since [`Trainer::time_device_phases`], read with the logged scalars
    /// (this reads what is pending); `None` when the device does not time them.
    pub fn device_phase_times(&mut self) -> anyhow::Result<Option<PhaseTimes>> {
        self.read_log()?;
        let Some((seconds, iterations)) = self
            .resident
            .as_ref()
            .and_then(ResidentStep::device_phase_seconds)
        else {
            return Ok(None);
        };
        let mut times = PhaseTimes {
            seconds: [0.0; 6],
            iterations,
        };
        times.seconds[..seconds.len()].copy_from_slice(&seconds);
        Ok(Some(times))
    }

    /// Starts the phase times afresh (after warm-up iterations, say).
    pub fn reset_phase_times(&mut self) {
        self.phase_times = PhaseTimes::default();
    }

    /// Whether the LPIPS loss runs.
    pub fn lpips_active(&self) -> bool {
        self.lpips.is_some()
    }

    /// The current avatar.
    pub fn avatar(&mut self) -> anyhow::Result<TrainedAvatar> {
        self.sync()?;
        Ok(TrainedAvatar::new(
            self.config.avatar(),
            self.data.rig.clone(),
            self.avatar_gaussians()?,
            sh_degree_at(&self.config, self.iteration.max(1)),
            self.scales.clone(),
            self.networks.clone(),
        ))
    }

    /// The complete state as a checkpoint (synchronised from the device first on `gpu`).
    pub fn checkpoint(&mut self) -> anyhow::Result<Checkpoint> {
        self.sync()?;
        Ok(self.host_checkpoint())
    }

    /// The host state as a checkpoint.
    fn host_checkpoint(&self) -> Checkpoint {
        let n = self.state.len();
        let mut tensors: Vec<Tensor> = self
            .state
            .columns
            .iter()
            .map(|c| Tensor {
                name: format!("gaussians/{}", c.name),
                shape: vec![n, c.width],
                dimension_names: vec!["gaussian".into(), "value".into()],
                values: c.values.clone(),
            })
            .collect();
        for (name, values) in LossCurve::NAMES.iter().zip(self.curve.columns()) {
            tensors.push(Tensor {
                name: format!("curve/{name}"),
                shape: vec![values.len()],
                dimension_names: vec!["iteration".into()],
                values: values.clone(),
            });
        }
        if let Some(net) = &self.networks {
            for param in net.parameters() {
                let state = self.network_adam.get(&param.name);
                // Stored in f64: exactly the f32 values.
                let widen = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
                let zeros = || vec![0.0; param.values.len()];
                for (prefix, values) in [
                    ("network", widen(param.values)),
                    ("network_adam_m", state.map_or_else(zeros, |s| widen(&s.m))),
                    ("network_adam_v", state.map_or_else(zeros, |s| widen(&s.v))),
                ] {
                    tensors.push(Tensor {
                        name: format!("{prefix}/{}", param.name),
                        shape: vec![values.len()],
                        dimension_names: vec!["value".into()],
                        values,
                    });
                }
            }
        }
        Checkpoint {
            iteration: self.iteration,
            rng_state: self.rng.state(),
            metadata: serde_json::json!({
                "adam_step": self.adam_step,
                "gaussians": n,
                "config": self.config,
                "columns": self.state.columns.iter().map(|c| serde_json::json!({
                    "name": c.name,
                    "width": c.width,
                    "growth": match c.growth { Growth::Inherit => "inherit", Growth::Zero => "zero" },
                })).collect::<Vec<_>>(),
            }),
            tensors,
        }
    }

    /// Restores a run from a checkpoint written by [`Trainer::checkpoint`] with the same
    /// configuration.
    pub fn resume(
        config: TrainConfig,
        data: &'d TrainingData,
        backend: Backend,
        checkpoint: &Checkpoint,
    ) -> anyhow::Result<Self> {
        let meta = &checkpoint.metadata;
        let stored: TrainConfig = serde_json::from_value(meta["config"].clone())
            .context("checkpoint metadata `config`")?;
        anyhow::ensure!(
            stored == config,
            "the checkpoint was written with a different configuration"
        );
        let adam_step = meta["adam_step"]
            .as_u64()
            .context("checkpoint metadata `adam_step`")?;
        let columns = meta["columns"]
            .as_array()
            .context("checkpoint metadata `columns`")?;
        let find = |name: &str| {
            checkpoint
                .tensors
                .iter()
                .find(|t| t.name == name)
                .ok_or_else(|| anyhow::anyhow!("checkpoint tensor `{name}` is missing"))
        };
        let mut state = GaussianState::default();
        for column in columns {
            let name = column["name"].as_str().context("checkpoint column name")?;
            let width = column["width"]
                .as_u64()
                .context("checkpoint column width")? as usize;
            let growth = match column["growth"].as_str() {
                Some("inherit") => Growth::Inherit,
                Some("zero") => Growth::Zero,
                other => anyhow::bail!("checkpoint column `{name}`: growth {other:?}"),
            };
            let tensor = find(&format!("gaussians/{name}"))?;
            state
                .add(name, width, growth, tensor.values.clone())
                .with_context(|| format!("checkpoint tensor `gaussians/{name}`"))?;
        }
        for (name, _) in TRAINABLE {
            state
                .column(name)
                .with_context(|| format!("checkpoint Gaussians: column `{name}`"))?;
        }
        let mut curve = LossCurve::default();
        for (name, column) in LossCurve::NAMES.iter().zip(curve.columns_mut()) {
            *column = find(&format!("curve/{name}"))?.values.clone();
            anyhow::ensure!(
                column.len() as u64 == checkpoint.iteration,
                "checkpoint tensor `curve/{name}` has {} values for {} iterations",
                column.len(),
                checkpoint.iteration
            );
        }
        let scales = config
            .effective_scales(&data.motion.scales)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut networks = build_networks(&config, data, scales.len())?;
        let mut network_adam = BTreeMap::new();
        // The checkpoint holds the f32 values widened to f64: narrowing restores them exactly.
        let narrow = |t: &Tensor| t.values.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        if let Some(net) = networks.as_mut() {
            net.load_parameters(|name| find(&format!("network/{name}")).ok().map(narrow))
                .context("checkpoint network parameters")?;
            for param in net.parameters() {
                let m = narrow(find(&format!("network_adam_m/{}", param.name))?);
                let v = narrow(find(&format!("network_adam_v/{}", param.name))?);
                anyhow::ensure!(
                    m.len() == param.values.len() && v.len() == param.values.len(),
                    "checkpoint Adam moments of `{}` have the wrong length",
                    param.name
                );
                network_adam.insert(
                    param.name.clone(),
                    AdamState {
                        m,
                        v,
                        step: adam_step,
                    },
                );
            }
        }
        Self::assemble(
            config,
            data,
            backend,
            scales,
            RunState {
                state,
                iteration: checkpoint.iteration,
                adam_step,
                rng: Rng::from_state(checkpoint.rng_state),
                curve,
                networks,
                network_adam,
            },
        )
    }
}

/// The networks a configuration trains, freshly initialised from its seed; `None` when it
/// trains none.
fn build_networks(
    config: &TrainConfig,
    data: &TrainingData,
    scale_count: usize,
) -> anyhow::Result<Option<Networks<f32>>> {
    let avatar_config = config.avatar();
    if !needs_networks(&avatar_config) {
        return Ok(None);
    }
    let net_config = NetworkConfig::from_avatar(
        &avatar_config,
        data.rig.joint_count(),
        data.motion.num_joints,
        scale_count,
    )
    .context("network configuration")?;
    let mut networks = Networks::new(&net_config, config.seed).context("network configuration")?;
    if config.non_rigid_head_init > 0.0 {
        // Start at the identity deformation: small head weights, zero head biases.
        let mut rng = Rng::new(config.seed ^ 0x6865_6164_735f_696e);
        let bound = config.non_rigid_head_init;
        for param in networks.parameters_mut() {
            if param.name == "non_rigid.heads.weight" {
                for w in param.values.iter_mut() {
                    *w = rng.uniform(-bound, bound) as f32;
                }
            } else if param.name == "non_rigid.heads.bias" {
                param.values.fill(0.0);
            }
        }
    }
    Ok(Some(networks))
}

/// The LPIPS loss of a configuration: `None` when its weight is 0 (nothing is loaded), else
/// the configured trunk's weights on the run's backend; a missing or bad file is an error
/// naming the file and the tensor.
pub fn load_lpips_loss(
    config: &TrainConfig,
    backend: &Backend,
) -> anyhow::Result<Option<LpipsLoss>> {
    if !config.lpips_enabled() {
        return Ok(None);
    }
    let path = config
        .lpips_weights
        .as_ref()
        .context("train config field `lpips_weights`: needed when lpips_weight > 0")?;
    let weights = LpipsWeights::load(path, config.lpips_net)
        .with_context(|| format!("train config field `lpips_weights` ({})", path.display()))?;
    let lpips = Lpips::new(weights, backend).context("LPIPS loss")?;
    Ok(Some(LpipsLoss::new(lpips, config.lpips_input())))
}

/// `rect` grown by `pad` pixels on each side, clipped to the image.
pub fn pad_rect(rect: Rect, pad: usize, width: usize, height: usize) -> Rect {
    Rect {
        x0: rect.x0.saturating_sub(pad),
        y0: rect.y0.saturating_sub(pad),
        x1: (rect.x1 + pad).min(width),
        y1: (rect.y1 + pad).min(height),
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
