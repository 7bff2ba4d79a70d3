//! The training step, chosen once: [`training_step`] is the trainer's one backend factory. It
//! builds the [`host`] step on `cpu` and the [`device`] (resident) step on the gpu; the
//! trainer calls through the [`TrainingStep`] it returns and never asks which it is.

pub(crate) mod device;
pub(crate) mod host;

use anyhow::Context;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::lpips::{Lpips, LpipsWeights};

use crate::config::TrainConfig;
use crate::losses::LpipsLoss;
use crate::run::{Run, TrainingStep};

/// The step of `run` on `backend`: on `cpu` the host phases through the avatar's backend, on
/// the gpu the whole iteration on the device (the run's state uploaded here, once).
pub(crate) fn training_step(
    backend: Backend,
    run: &Run<'_>,
) -> anyhow::Result<Box<dyn TrainingStep>> {
    Ok(match backend {
        Backend::Cpu => Box::new(host::HostStep::new(backend, run)?),
        Backend::Gpu(context) => Box::new(device::DeviceStep::new(context, run)?),
    })
}

/// The LPIPS loss of a configuration: `None` when its weight is 0 (nothing is loaded), else
/// the configured trunk's weights on the host (the host step runs it there; the device step
/// uploads its own trunk from them); a missing or bad file is an error naming the file and
/// the tensor.
pub(crate) fn load_lpips_loss(config: &TrainConfig) -> anyhow::Result<Option<LpipsLoss>> {
    if !config.lpips_enabled() {
        return Ok(None);
    }
    let path = config
        .lpips_weights
        .as_ref()
        .context("train config field `lpips_weights`: needed when lpips_weight > 0")?;
    let weights = LpipsWeights::load(path, config.lpips_net)
        .with_context(|| format!("train config field `lpips_weights` ({})", path.display()))?;
    let lpips = Lpips::new(weights, &Backend::Cpu).context("LPIPS loss")?;
    Ok(Some(LpipsLoss::new(lpips, config.lpips_input())))
}
