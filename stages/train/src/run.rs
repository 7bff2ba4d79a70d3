//! What both training steps share: a run's state ([`Run`]), the step that advances it
//! ([`TrainingStep`]: `step::host` on `cpu`, `step::device` on the gpu,
//! chosen once by `step::training_step`), and the statistics, curves and phase times
//! they report.

use std::collections::BTreeMap;
use std::time::Instant;

use seqavatar_avatar::avatar::AvatarGaussians;
use seqavatar_avatar::model::Networks;
use seqavatar_compute::nn::adam::AdamState;

use crate::config::TrainConfig;
use crate::data::TrainingData;
use crate::densify::{DensifyReport, DensifySettings, GaussianState, densify_and_prune};
use crate::gaussians::avatar_gaussians;
use crate::losses::{LpipsLoss, Rect};
use crate::rng::Rng;

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

impl IterationStats {
    /// A [`Divergence`] naming the terms when the total loss is not finite.
    pub(crate) fn check_finite(&self) -> anyhow::Result<()> {
        if self.total.is_finite() {
            return Ok(());
        }
        Err(Divergence {
            iteration: self.iteration,
            what: "loss",
            tensor: "total".into(),
            detail: format!(
                " (l1 {}, mask {}, dssim {}, lpips {}, aiap {})",
                self.l1, self.mask_mse, self.dssim, self.lpips, self.aiap
            ),
        }
        .into())
    }
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

    pub(crate) fn columns(&self) -> [&Vec<f64>; 8] {
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

    pub(crate) fn columns_mut(&mut self) -> [&mut Vec<f64>; 8] {
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

    pub fn get(&self, name: &str) -> Option<&Vec<f64>> {
        Self::NAMES
            .iter()
            .position(|n| *n == name)
            .map(|i| self.columns()[i])
    }

    pub(crate) fn push(&mut self, s: &IterationStats) {
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
    pub(crate) seconds: [f64; 6],
    pub(crate) iterations: u64,
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
pub(crate) struct PhaseClock(Instant);

impl PhaseClock {
    pub(crate) fn start() -> Self {
        PhaseClock(Instant::now())
    }

    pub(crate) fn lap(&mut self, times: &mut PhaseTimes, phase: Phase) {
        let now = Instant::now();
        times.seconds[phase as usize] += (now - self.0).as_secs_f64();
        self.0 = now;
    }
}

/// The state of a run that both steps read and advance: the Gaussians, the networks and their
/// Adam state, the generator, the curves. [`crate::trainer::Trainer`] owns one and reads
/// through to it.
pub struct Run<'d> {
    pub config: TrainConfig,
    pub(crate) data: &'d TrainingData,
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
    pub(crate) network_adam: BTreeMap<String, AdamState<f32>>,
    pub(crate) train_images: Vec<usize>,
    /// The LPIPS loss, loaded only when `lpips_weight > 0`.
    pub(crate) lpips: Option<LpipsLoss>,
    pub(crate) phase_times: PhaseTimes,
}

impl Run<'_> {
    /// Images of one iteration: a random training image, plus other training images of the
    /// same frame up to `cameras_per_step`.
    pub(crate) fn pick_images(&mut self) -> Vec<usize> {
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

    pub(crate) fn avatar_gaussians(&self) -> anyhow::Result<AvatarGaussians> {
        avatar_gaussians(&self.state)
    }

    /// Whether iteration `iteration` runs the density control (clone, split, prune).
    pub(crate) fn density_control_due(&self, iteration: u64) -> bool {
        let c = &self.config;
        c.densify
            && iteration > u64::from(c.densify_from)
            && iteration <= u64::from(c.densify_until)
            && iteration.is_multiple_of(u64::from(c.densify_interval))
    }

    /// Clone, split and prune the host state's Gaussians (their statistics accumulated).
    pub(crate) fn density_control(&mut self, iteration: u64) -> anyhow::Result<DensifyReport> {
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
}

/// One training iteration on the backend the run was built for, and what it keeps beside the
/// [`Run`]. Built once, by `step::training_step`; the trainer calls through it and
/// never asks which backend it is. What the host step has nothing to do for has a default.
pub trait TrainingStep: Send {
    /// One iteration: the phases of [`Phase`] in order, each timed into the run's phase
    /// times; the statistics returned are the last ones read (exact on the host).
    fn step(&mut self, run: &mut Run<'_>) -> anyhow::Result<IterationStats>;

    /// Whether the iteration runs on the device.
    fn on_device(&self) -> bool {
        false
    }

    /// Brings the run's host state (Gaussians, networks, their Adam moments, the loss curve)
    /// up to date with the device.
    fn sync(&mut self, _run: &mut Run<'_>) -> anyhow::Result<()> {
        Ok(())
    }

    /// Iterations between two reads of the logged scalars on the device.
    fn set_log_every(&mut self, _iterations: usize) {}

    /// Waits until the device has run every submitted iteration.
    fn wait_for_device(&mut self) -> anyhow::Result<()> {
        Ok(())
    }

    /// Full neighbour searches of the AIAP loss and the iterations that asked for neighbours.
    fn aiap_neighbour_searches(&self) -> anyhow::Result<(u64, u64)>;

    /// Starts timing each phase on the device; whether it does.
    fn time_device_phases(&mut self, _run: &mut Run<'_>) -> anyhow::Result<bool> {
        Ok(false)
    }

    /// Device time per phase since [`TrainingStep::time_device_phases`]; `None` when the
    /// device does not time them.
    fn device_phase_times(&mut self, _run: &mut Run<'_>) -> anyhow::Result<Option<PhaseTimes>> {
        Ok(None)
    }
}

/// The active SH degree at (1-based) iteration `iteration`: one more every `interval`.
pub fn sh_degree_at(config: &TrainConfig, iteration: u64) -> u32 {
    let steps = iteration / u64::from(config.sh_degree_interval.max(1));
    steps.min(u64::from(config.sh_degree)) as u32
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
