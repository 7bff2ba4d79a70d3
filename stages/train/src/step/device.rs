//! The device-resident training step of the `gpu` backend ([`ResidentStep`]): the host makes
//! the same draws as the `cpu` step (images, frame, background, densification), records and
//! submits; the logged scalars are read every `log_every` iterations, before densification
//! and at the last iteration.

use std::sync::Arc;

use anyhow::Context;
use seqavatar_compute::backend::GpuContext;

use crate::resident::step::{IterationPlan, LOG_CAPACITY, ResidentStep};
use crate::run::{IterationStats, Phase, PhaseClock, PhaseTimes, Run, TrainingStep, sh_degree_at};

/// The `gpu` step: the run's state on the device and its iteration, and the logged scalars
/// last read.
pub(crate) struct DeviceStep {
    resident: ResidentStep,
    /// Iterations between two reads of the logged scalars.
    log_every: usize,
    /// The last iteration whose logged scalars were read (`IterationStats` of the iterations
    /// recorded since repeat them).
    last_logged: IterationStats,
}

impl DeviceStep {
    /// Uploads `run` to `context` once ([`ResidentStep::new`]).
    pub(crate) fn new(context: Arc<GpuContext>, run: &Run<'_>) -> anyhow::Result<Self> {
        Ok(Self {
            resident: ResidentStep::new(context, run)
                .context("the device-resident training step")?,
            log_every: LOG_CAPACITY,
            last_logged: IterationStats::default(),
        })
    }

    /// Reads the logged scalars of the iterations recorded on the device since the last
    /// read into the loss curve (and checks them: a non-finite value is a
    /// [`crate::run::Divergence`]).
    fn read_log(&mut self, run: &mut Run<'_>) -> anyhow::Result<()> {
        for stats in self.resident.read_log(run.iteration, run.state.len())? {
            run.curve.push(&stats);
            self.last_logged = stats;
        }
        Ok(())
    }
}

impl TrainingStep for DeviceStep {
    /// Records and submits one iteration; the statistics returned are the last ones read.
    fn step(&mut self, run: &mut Run<'_>) -> anyhow::Result<IterationStats> {
        let iteration = run.iteration + 1;
        let mut clock = PhaseClock::start();
        let sh_degree = sh_degree_at(&run.config, iteration);
        let chosen = run.pick_images();
        let frame = run.data.images[chosen[0]].frame;
        let background = run.config.background.draw(&mut run.rng);
        run.adam_step += 1;
        let densify_now = run.density_control_due(iteration);
        let plan = IterationPlan {
            iteration,
            frame,
            images: &chosen,
            background,
            sh_degree,
            adam_step: run.adam_step,
            density_statistics: iteration <= u64::from(run.config.densify_until),
        };
        self.resident
            .record(&plan, run.data, run.lpips.as_ref())
            .with_context(|| format!("iteration {iteration} on the device"))?;
        clock.lap(&mut run.phase_times, Phase::Deform);
        run.iteration = iteration;
        run.phase_times.iterations += 1;
        let due = self.resident.unread() >= self.log_every.clamp(1, self.resident.log_capacity())
            || iteration >= u64::from(run.config.iterations)
            || densify_now;
        if due {
            self.read_log(run)?;
        }
        let mut stats = IterationStats {
            iteration,
            gaussians: run.state.len(),
            densified: None,
            ..self.last_logged
        };
        if densify_now {
            self.resident.download_state(&mut run.state)?;
            let report = run.density_control(iteration)?;
            self.resident.upload_state(&run.state)?;
            stats.densified = Some(report);
            stats.gaussians = run.state.len();
            clock.lap(&mut run.phase_times, Phase::Densify);
        }
        Ok(stats)
    }

    fn on_device(&self) -> bool {
        true
    }

    fn sync(&mut self, run: &mut Run<'_>) -> anyhow::Result<()> {
        self.read_log(run)?;
        self.resident.download_state(&mut run.state)?;
        if let Some(networks) = run.networks.as_mut() {
            self.resident
                .download_networks(networks, &mut run.network_adam)?;
        }
        Ok(())
    }

    fn set_log_every(&mut self, iterations: usize) {
        self.log_every = iterations.max(1);
    }

    fn wait_for_device(&mut self) -> anyhow::Result<()> {
        self.resident.wait_idle()
    }

    fn aiap_neighbour_searches(&self) -> anyhow::Result<(u64, u64)> {
        self.resident.aiap_searches()
    }

    fn time_device_phases(&mut self, run: &mut Run<'_>) -> anyhow::Result<bool> {
        self.read_log(run)?;
        self.resident.time_phases()
    }

    /// Densification, which runs on the host, counts as zero.
    fn device_phase_times(&mut self, run: &mut Run<'_>) -> anyhow::Result<Option<PhaseTimes>> {
        self.read_log(run)?;
        let Some((seconds, iterations)) = self.resident.device_phase_seconds() else {
            return Ok(None);
        };
        let mut times = PhaseTimes {
            seconds: [0.0; 6],
            iterations,
        };
        times.seconds[..seconds.len()].copy_from_slice(&seconds);
        Ok(Some(times))
    }
}
