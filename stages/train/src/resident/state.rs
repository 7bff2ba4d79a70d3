//! The Gaussians on the device: every trainable column, its Adam moments and the
//! densification statistics as f32 [`GpuBuffer`]s with the `cpu` layouts of
//! [`crate::gaussians`], sized for a capacity that grows when densification adds Gaussians;
//! the per-iteration step record the optimiser's kernels read; the status buffer where they
//! flag non-finite values.
//!
//! Buffers (row-major, `N` = [`ResidentGaussians::len`], capacity rows allocated):
//! - columns in [`TRAINABLE`] order: `xyz` `N x 3`, `sh` `N x 16 x 3` (coefficient-major),
//!   `opacity` `N` (logit), `log_scale` `N x 3`, `rotation` `N x 4` (`w x y z`), each with
//!   `first_moment` and `second_moment` of the same layout;
//! - `grad_accum` and `grad_count`, `N` each;
//! - the step record, [`RECORD_WORDS`] u32 words (floats as their bits, see [`record`]);
//! - the status buffer, `2 x` [`STATUS_SLOTS`] u32 words (see [`NonFinite`]).

use std::sync::Arc;

use anyhow::{Context, bail, ensure};
use seqavatar_compute::backend::{GpuBuffer, GpuContext};
use seqavatar_compute::nn::adam::{AdamConfig, AdamStepFactors};

use crate::config::LearningRates;
use crate::densify::{GaussianState, names};
use crate::gaussians::{TRAINABLE, exponential_lr};

/// Word indices of the step record (mirrored as `R_*` constants in `shaders/train_*.wgsl`).
pub mod record {
    /// Gaussians (u32).
    pub const COUNT: usize = 0;
    /// The training iteration (u32), stored with non-finite flags.
    pub const ITERATION: usize = 1;
    /// SH coefficients of the active degree, `(d + 1)^2` (u32).
    pub const SH_COEFFICIENTS: usize = 2;
    pub const BETA1: usize = 4;
    pub const BETA2: usize = 5;
    pub const ONE_MINUS_BETA1: usize = 6;
    pub const ONE_MINUS_BETA2: usize = 7;
    pub const EPS: usize = 8;
    /// `sqrt(1 - beta2^t)`.
    pub const CORRECTION: usize = 9;
    /// Half the largest image side of the iteration's cameras (densification statistics).
    pub const HALF_SIZE: usize = 10;
    /// `lr / (1 - beta1^t)` per rate from here, in [`super::StepSize`] order.
    pub const STEP_SIZE: usize = 16;
}

/// Words of the step record: 88 bytes written per iteration.
pub const RECORD_WORDS: usize = 22;

/// The learning rates of one step, in the order of the record's step sizes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StepSize {
    Position = 0,
    ShDc = 1,
    ShRest = 2,
    Opacity = 3,
    Scaling = 4,
    Rotation = 5,
}

/// Status slots: the gradient of each trainable column, then its values.
pub const STATUS_SLOTS: usize = 2 * TRAINABLE.len();

/// The learning rates of the Gaussians' columns for one iteration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GaussianRates {
    pub position: f64,
    pub sh_dc: f64,
    pub sh_rest: f64,
    pub opacity: f64,
    pub scaling: f64,
    pub rotation: f64,
}

impl GaussianRates {
    /// The trainer's rates at `iteration`: the position rate `exponential_lr(...)` times the
    /// scene extent, the others constant (as `Trainer::optimiser_phase`).
    pub fn at(rates: &LearningRates, extent: f64, iteration: u64) -> Self {
        GaussianRates {
            position: exponential_lr(
                rates.position_initial * extent,
                rates.position_final * extent,
                iteration,
                u64::from(rates.position_decay_steps),
            ),
            sh_dc: rates.sh_dc,
            sh_rest: rates.sh_rest,
            opacity: rates.opacity,
            scaling: rates.scaling,
            rotation: rates.rotation,
        }
    }
}

/// The per-iteration scalars of the optimiser piece, written as one record.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OptimiserStep {
    /// The training iteration (1-based), stored with non-finite flags.
    pub iteration: u64,
    /// The 1-based index of this Adam update of the Gaussians (the trainer's `adam_step`).
    pub adam_step: u64,
    pub adam: AdamConfig,
    pub rates: GaussianRates,
    /// Active SH degree (0 to 3): the splatting's SH gradient is `N x (d + 1)^2 x 3`.
    pub sh_degree: usize,
    /// Half the largest image side of the iteration's cameras.
    pub half_size: f64,
}

/// One trainable column on the device with its Adam moments.
#[derive(Debug)]
pub struct ResidentColumn {
    pub name: &'static str,
    /// Values per Gaussian.
    pub width: usize,
    pub values: GpuBuffer,
    pub first_moment: GpuBuffer,
    pub second_moment: GpuBuffer,
}

/// A non-finite value the optimiser's kernels flagged: reported as the `cpu` path's
/// `Divergence` (`what` `tensor` at `iteration`, Gaussian `gaussian`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NonFinite {
    pub iteration: u64,
    /// `"gradient of"` or `"parameter"`.
    pub what: &'static str,
    /// `gaussians/<column>`.
    pub tensor: String,
    pub gaussian: usize,
}

/// The Gaussians, their moments and statistics on the device (see the module doc).
#[derive(Debug)]
pub struct ResidentGaussians {
    context: Arc<GpuContext>,
    count: usize,
    capacity: usize,
    columns: Vec<ResidentColumn>,
    grad_accum: GpuBuffer,
    grad_count: GpuBuffer,
    record: GpuBuffer,
    status: GpuBuffer,
}

/// Capacity for `count` Gaussians when the buffers must grow: half as many again, so a run
/// of densifications reallocates a few times, not every time.
fn grown_capacity(count: usize) -> usize {
    (count + count / 2).max(16)
}

fn to_f32(values: &[f64]) -> Vec<f32> {
    values.iter().map(|&v| v as f32).collect()
}

impl ResidentGaussians {
    /// Uploads every trainable column, its `.adam_m` / `.adam_v` moments and the statistics
    /// of `state` (all must exist), with room for half as many again.
    pub fn upload(context: &Arc<GpuContext>, state: &GaussianState) -> anyhow::Result<Self> {
        let count = state.len();
        let mut gaussians = Self::allocate(context, grown_capacity(count))?;
        gaussians.write_state(state)?;
        Ok(gaussians)
    }

    fn allocate(context: &Arc<GpuContext>, capacity: usize) -> anyhow::Result<Self> {
        let zeros = |what: &str, len: usize| {
            context
                .zeros(what, len, 4)
                .with_context(|| format!("allocating resident Gaussians' `{what}`"))
        };
        let mut columns = Vec::with_capacity(TRAINABLE.len());
        for (name, width) in TRAINABLE {
            columns.push(ResidentColumn {
                name,
                width,
                values: zeros(name, capacity * width)?,
                first_moment: zeros(&format!("{name}.adam_m"), capacity * width)?,
                second_moment: zeros(&format!("{name}.adam_v"), capacity * width)?,
            });
        }
        Ok(ResidentGaussians {
            context: context.clone(),
            count: 0,
            capacity,
            columns,
            grad_accum: zeros(names::GRAD_ACCUM, capacity)?,
            grad_count: zeros(names::GRAD_COUNT, capacity)?,
            record: zeros("optimiser step record", RECORD_WORDS)?,
            status: zeros("optimiser status", 2 * STATUS_SLOTS)?,
        })
    }

    /// Every buffer with its [`GaussianState`] column name and values per Gaussian: each
    /// trainable column and its moments, then the statistics.
    fn buffers(&self) -> Vec<(String, usize, &GpuBuffer)> {
        let mut buffers = Vec::new();
        for column in &self.columns {
            for (suffix, buffer) in [
                ("", &column.values),
                (".adam_m", &column.first_moment),
                (".adam_v", &column.second_moment),
            ] {
                buffers.push((format!("{}{suffix}", column.name), column.width, buffer));
            }
        }
        buffers.push((names::GRAD_ACCUM.into(), 1, &self.grad_accum));
        buffers.push((names::GRAD_COUNT.into(), 1, &self.grad_count));
        buffers
    }

    /// Writes `state` into the buffers (which must hold it).
    fn write_state(&mut self, state: &GaussianState) -> anyhow::Result<()> {
        let count = state.len();
        ensure!(count <= self.capacity, "resident Gaussians: capacity");
        for (name, width, buffer) in self.buffers() {
            let values = state
                .values(&name)
                .with_context(|| format!("uploading the Gaussians' column `{name}`"))?;
            ensure!(
                values.len() == count * width,
                "column `{name}` has {} values, not {count} x {width}",
                values.len()
            );
            self.context.write(&buffer.buffer, 0, &to_f32(values))?;
        }
        self.count = count;
        Ok(())
    }

    /// Replaces the device state by `state` (after the host densified it, or after a
    /// checkpoint was loaded): written into the current buffers while they hold it, else
    /// into new ones of a grown capacity. Returns whether the buffers were reallocated (a
    /// caller holding bind groups of them must rebuild those). The status is kept.
    pub fn reupload(&mut self, state: &GaussianState) -> anyhow::Result<bool> {
        let count = state.len();
        if count <= self.capacity {
            self.write_state(state)?;
            return Ok(false);
        }
        let mut grown = Self::allocate(&self.context, grown_capacity(count))?;
        // Keep the flags found so far.
        let mut encoder = self.context.encoder();
        encoder.copy_buffer_to_buffer(
            &self.status.buffer,
            0,
            &grown.status.buffer,
            0,
            (8 * STATUS_SLOTS) as u64,
        );
        self.context.queue().submit([encoder.finish()]);
        grown.write_state(state)?;
        *self = grown;
        Ok(true)
    }

    /// Reads every column, moment and statistic back into `state`, replacing those columns'
    /// values (a `GaussianState` with other columns must already have this many Gaussians).
    /// One read-back.
    pub fn download_into(&self, state: &mut GaussianState) -> anyhow::Result<()> {
        let sources = self.buffers();
        let read: Vec<(&wgpu::Buffer, usize)> = sources
            .iter()
            .map(|(_, width, buffer)| (&buffer.buffer, self.count * width))
            .collect();
        let values = self
            .context
            .download_all::<f32>(self.context.encoder(), &read)?;
        for ((name, _, _), values) in sources.iter().zip(values) {
            let column = state
                .column_mut(name)
                .with_context(|| format!("downloading the Gaussians' column `{name}`"))?;
            column.values = values.into_iter().map(f64::from).collect();
        }
        if let Some(other) = state
            .columns
            .iter()
            .find(|c| c.values.len() != self.count * c.width)
        {
            bail!(
                "downloading {} Gaussians into a state whose column `{}` has {} values",
                self.count,
                other.name,
                other.values.len()
            );
        }
        Ok(())
    }

    /// Writes the iteration's record (one `GpuContext::write` of [`RECORD_WORDS`] words):
    /// what the Adam and statistics kernels recorded after it read.
    pub fn write_step(&self, step: &OptimiserStep) -> anyhow::Result<()> {
        ensure!(
            step.sh_degree <= 3,
            "optimiser step: SH degree {} is not in 0..=3",
            step.sh_degree
        );
        ensure!(
            step.adam_step >= 1,
            "optimiser step: the Adam step is 1-based"
        );
        step.adam.validate()?;
        let factors = |lr: f64| AdamStepFactors::new(&step.adam, lr, step.adam_step);
        let mut words = [0_u32; RECORD_WORDS];
        let float = |v: f64| (v as f32).to_bits();
        words[record::COUNT] = u32::try_from(self.count).context("Gaussian count")?;
        words[record::ITERATION] = u32::try_from(step.iteration).context("iteration")?;
        words[record::SH_COEFFICIENTS] = ((step.sh_degree + 1) * (step.sh_degree + 1)) as u32;
        words[record::BETA1] = float(step.adam.beta1);
        words[record::BETA2] = float(step.adam.beta2);
        words[record::ONE_MINUS_BETA1] = float(1.0 - step.adam.beta1);
        words[record::ONE_MINUS_BETA2] = float(1.0 - step.adam.beta2);
        words[record::EPS] = float(step.adam.eps);
        words[record::CORRECTION] = float(factors(0.0).bias_correction2_sqrt);
        words[record::HALF_SIZE] = float(step.half_size);
        let r = &step.rates;
        for (size, lr) in [
            (StepSize::Position, r.position),
            (StepSize::ShDc, r.sh_dc),
            (StepSize::ShRest, r.sh_rest),
            (StepSize::Opacity, r.opacity),
            (StepSize::Scaling, r.scaling),
            (StepSize::Rotation, r.rotation),
        ] {
            words[record::STEP_SIZE + size as usize] = float(factors(lr).step_size);
        }
        self.context.write(&self.record.buffer, 0, &words)?;
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.count
    }

    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Gaussians the buffers have room for.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    pub fn context(&self) -> &Arc<GpuContext> {
        &self.context
    }

    /// The trainable columns in [`TRAINABLE`] order.
    pub fn columns(&self) -> &[ResidentColumn] {
        &self.columns
    }

    /// The column named `name` (one of [`TRAINABLE`]).
    pub fn column(&self, name: &str) -> anyhow::Result<&ResidentColumn> {
        self.columns
            .iter()
            .find(|c| c.name == name)
            .with_context(|| format!("resident Gaussians have no column `{name}`"))
    }

    /// Accumulated view-space gradient norms, `N`.
    pub fn grad_accum(&self) -> &GpuBuffer {
        &self.grad_accum
    }

    /// Visibility counts, `N` (f32).
    pub fn grad_count(&self) -> &GpuBuffer {
        &self.grad_count
    }

    /// The step record ([`record`], u32 words).
    pub fn record(&self) -> &GpuBuffer {
        &self.record
    }

    /// The status buffer: for each of [`STATUS_SLOTS`] slots (the gradient of each
    /// [`TRAINABLE`] column, then its values) two u32 words, `0xffffffff - iteration` of the
    /// first iteration that found a non-finite value (0: none) and `0xffffffff - Gaussian` of
    /// the smallest such Gaussian in that iteration. Read it with the logged scalars and
    /// decode with [`ResidentGaussians::decode_status`].
    pub fn status(&self) -> &GpuBuffer {
        &self.status
    }

    /// The earliest non-finite value in a read-back status buffer (gradients before values,
    /// columns in [`TRAINABLE`] order within an iteration), or `None`.
    pub fn decode_status(words: &[u32]) -> Option<NonFinite> {
        (0..STATUS_SLOTS)
            .filter(|&slot| words.get(2 * slot).is_some_and(|&key| key != 0))
            .min_by_key(|&slot| (u32::MAX - words[2 * slot], slot))
            .map(|slot| {
                let column = TRAINABLE[slot % TRAINABLE.len()].0;
                NonFinite {
                    iteration: u64::from(u32::MAX - words[2 * slot]),
                    what: if slot < TRAINABLE.len() {
                        "gradient of"
                    } else {
                        "parameter"
                    },
                    tensor: format!("gaussians/{column}"),
                    gaussian: (u32::MAX - words[2 * slot + 1]) as usize,
                }
            })
    }

    /// Reads the status buffer back (one read-back) and decodes it.
    pub fn download_status(&self) -> anyhow::Result<Option<NonFinite>> {
        let words = self.context.download::<u32>(
            self.context.encoder(),
            &self.status.buffer,
            2 * STATUS_SLOTS,
        )?;
        Ok(Self::decode_status(&words))
    }
}
