//! The training loop. [`Trainer::step`] runs one iteration as named phases ([`Phase`], each
//! timed into [`Trainer::phase_times`]) through the [`TrainingStep`] chosen once, when the
//! trainer is built (`step::training_step`): the host step on `cpu`
//! (`step::host`, which documents the phases), the device-resident one on the gpu
//! (`step::device`); the SH degree follows its schedule.
//!
//! A [`Trainer`] holds the complete resumable state ([`Run`]); [`Trainer::checkpoint`] and
//! [`Trainer::resume`] convert it to and from a [`Checkpoint`] exactly, so a resumed `cpu`
//! run reproduces an uninterrupted one bit for bit (every random draw comes from the one
//! [`Rng`] whose state the checkpoint stores, and every reduction has a fixed order).

use anyhow::Context;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::nn::adam::AdamState;
use serde::Deserialize;

use std::collections::BTreeMap;
use std::ops::{Deref, DerefMut};

use seqavatar_avatar::avatar::TrainedAvatar;
use seqavatar_avatar::model::{NetworkConfig, Networks};
use seqavatar_knn::{KnnGrid, as_points, knn_brute_force};

use crate::checkpoint::{Checkpoint, Tensor};
use crate::config::TrainConfig;
use crate::data::TrainingData;
use crate::densify::{GaussianState, Growth};
use crate::gaussians::{TRAINABLE, initial_state};
use crate::rng::Rng;
pub use crate::run::{
    Divergence, IterationStats, LossCurve, Phase, PhaseTimes, Run, TrainingStep, pad_rect,
    sh_degree_at,
};
use crate::step::{load_lpips_loss, training_step};

/// The complete state of a run ([`Run`], whose fields read through the trainer) and the step
/// that advances it, chosen once when the trainer is built.
pub struct Trainer<'d> {
    run: Run<'d>,
    /// The host step on `cpu`; on the gpu the device-resident one, whose state the run's host
    /// fields are brought up to date with by [`Trainer::sync`].
    training_step: Box<dyn TrainingStep>,
}

impl<'d> Deref for Trainer<'d> {
    type Target = Run<'d>;

    fn deref(&self) -> &Run<'d> {
        &self.run
    }
}

impl DerefMut for Trainer<'_> {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.run
    }
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
    /// phase runs on `backend`, which the trainer builds its step from once
    /// (`step::training_step`).
    pub fn new(
        config: TrainConfig,
        data: &'d TrainingData,
        backend: Backend,
    ) -> anyhow::Result<Self> {
        let scales = config
            .effective_scales(&data.motion.scales)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut rng = Rng::new(config.seed);
        let mut centres = data.rig.canonical_vertices.clone();
        let mut colours: Vec<f64> = (0..centres.len()).map(|_| rng.next_f64()).collect();
        if let Some(init) = &config.hull_init {
            let hull = crate::hull::hull_gaussians(data, init)?;
            for (slot, colour) in colours.chunks_exact_mut(3).zip(&hull.template_colours) {
                if let Some(colour) = colour {
                    slot.copy_from_slice(colour);
                }
            }
            centres.extend(&hull.centres);
            colours.extend(&hull.colours);
        }
        // Density control never removes Gaussians to meet the cap, so a cap below the
        // starting count would be silently ignored: refuse it instead.
        let starting = centres.len() / 3;
        anyhow::ensure!(
            starting <= config.max_gaussians,
            "train config field `max_gaussians` is {}, below the {starting} Gaussians training \
             starts with (the body template's vertices and any `hull_init` points): set it to \
             at least {starting}",
            config.max_gaussians
        );
        let state = initial_state(&centres, &colours, 0.1, &initial_scales(&centres))?;
        let networks = build_networks(&config, data, scales.len())?;
        Self::assemble(
            backend,
            Run {
                config,
                data,
                state,
                iteration: 0,
                adam_step: 0,
                rng,
                curve: LossCurve::default(),
                scales,
                networks,
                network_adam: BTreeMap::new(),
                train_images: Vec::new(),
                lpips: None,
                phase_times: PhaseTimes::default(),
            },
        )
    }

    /// The trainer of `run` (fresh or a checkpoint's; its training images and LPIPS loss
    /// found here), building the step for `backend` (`step::training_step`).
    fn assemble(backend: Backend, mut run: Run<'d>) -> anyhow::Result<Self> {
        let data = run.data;
        run.train_images = data
            .split(0)
            .into_iter()
            .filter(|&i| data.images[i].bound.is_some())
            .collect();
        anyhow::ensure!(
            !run.train_images.is_empty(),
            "no training image has a non-empty foreground mask"
        );
        run.lpips = load_lpips_loss(&run.config)?;
        if let Some(loss) = &run.lpips {
            for &index in &run.train_images {
                let camera = &data.cameras[data.images[index].view];
                loss.check_image(camera.width as usize, camera.height as usize)
                    .with_context(|| {
                        format!(
                            "LPIPS loss: training camera {} (after resolution_scale {})",
                            data.images[index].view, run.config.resolution_scale
                        )
                    })?;
            }
        }
        let training_step = training_step(backend, &run)?;
        Ok(Self { run, training_step })
    }

    /// One training iteration: the phases of [`Phase`] in order, each timed into
    /// [`Trainer::phase_times`]. On the gpu the statistics returned are the last ones read
    /// ([`Trainer::set_log_every`]).
    pub fn step(&mut self) -> anyhow::Result<IterationStats> {
        self.training_step.step(&mut self.run)
    }

    /// Brings the host state (Gaussians, networks, their Adam moments, the loss curve) up to
    /// date with the device on the `gpu` backend (nothing to do on `cpu`): before a
    /// checkpoint, the trained avatar, or reading [`Trainer::state`], [`Trainer::networks`]
    /// or [`Trainer::curve`].
    pub fn sync(&mut self) -> anyhow::Result<()> {
        self.training_step.sync(&mut self.run)
    }

    /// Iterations between two reads of the logged scalars on the `gpu` backend (1: every
    /// iteration's statistics are exact when [`Trainer::step`] returns them; at most the
    /// log ring's capacity).
    pub fn set_log_every(&mut self, iterations: usize) {
        self.training_step.set_log_every(iterations);
    }

    /// Waits until the device has run every submitted iteration (for timing: a resident
    /// step returns once its work is submitted); nothing to do on `cpu`.
    pub fn wait_for_device(&mut self) -> anyhow::Result<()> {
        self.training_step.wait_for_device()
    }

    /// Whether the iteration runs on the device.
    pub fn resident(&self) -> bool {
        self.training_step.on_device()
    }

    /// Full neighbour searches of the AIAP loss and the iterations that asked for
    /// neighbours, since the trainer was built (the rest reused their candidate lists).
    pub fn aiap_neighbour_searches(&self) -> anyhow::Result<(u64, u64)> {
        self.training_step.aiap_neighbour_searches()
    }

    /// Wall time per phase since the trainer was built or the last
    /// [`Trainer::reset_phase_times`].
    pub fn phase_times(&self) -> &PhaseTimes {
        &self.run.phase_times
    }

    /// Starts timing each phase of the iteration on the device (`gpu` backend, where the
    /// adapter has timestamps inside encoders; see [`Trainer::device_phase_times`]). Returns
    /// whether it does; `false` on `cpu`.
    pub fn time_device_phases(&mut self) -> anyhow::Result<bool> {
        self.training_step.time_device_phases(&mut self.run)
    }

    /// Device time per phase (densification, which runs on the host, as zero) over the
    /// iterations run since [`Trainer::time_device_phases`], read with the logged scalars
    /// (this reads what is pending); `None` when the device does not time them.
    pub fn device_phase_times(&mut self) -> anyhow::Result<Option<PhaseTimes>> {
        self.training_step.device_phase_times(&mut self.run)
    }

    /// Starts the phase times afresh (after warm-up iterations, say).
    pub fn reset_phase_times(&mut self) {
        self.phase_times = PhaseTimes::default();
    }

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
        let stored =
            TrainConfig::deserialize(&meta["config"]).context("checkpoint metadata `config`")?;
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
            backend,
            Run {
                config,
                data,
                state,
                iteration: checkpoint.iteration,
                adam_step,
                rng: Rng::from_state(checkpoint.rng_state),
                curve,
                scales,
                networks,
                network_adam,
                train_images: Vec::new(),
                lpips: None,
                phase_times: PhaseTimes::default(),
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
    if !avatar_config.needs_networks() {
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
