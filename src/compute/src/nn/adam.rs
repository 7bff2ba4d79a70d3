//! Adam with per-group learning-rate schedules on `cpu` (the `gpu` kernel is in [`super::gpu`]).
//!
//! The update is PyTorch's `torch.optim.Adam` (no weight decay, no amsgrad), in its
//! operation order:
//!
//! ```text
//! m = beta1 m + (1 - beta1) g
//! v = beta2 v + (1 - beta2) g^2
//! p = p - (lr / (1 - beta1^t)) m / (sqrt(v) / sqrt(1 - beta2^t) + eps)
//! ```
//!
//! with `t` the 1-based step count of the tensor. The bias-correction factors are computed in
//! f64 on the host for both backends ([`AdamStepFactors`]), so `cpu` f32 and `gpu` agree.

use super::scalar::NnScalar;
use super::{NnError, check_len};

/// Adam's hyper-parameters shared by every group of one optimiser.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// First-moment decay, in `[0, 1)`.
    pub beta1: f64,
    /// Second-moment decay, in `[0, 1)`.
    pub beta2: f64,
    /// Added to the denominator; SeqAvatar (and 3DGS) use 1e-15.
    pub eps: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

impl AdamConfig {
    /// Checks every field, naming the first bad one.
    pub fn validate(&self) -> Result<(), NnError> {
        for (field, value) in [("adam.beta1", self.beta1), ("adam.beta2", self.beta2)] {
            if !(0.0..1.0).contains(&value) {
                return Err(NnError::Config {
                    field: field.into(),
                    message: format!("{value} is not in [0, 1)"),
                });
            }
        }
        if !(self.eps.is_finite() && self.eps >= 0.0) {
            return Err(NnError::Config {
                field: "adam.eps".into(),
                message: format!("{} is not a finite non-negative number", self.eps),
            });
        }
        Ok(())
    }
}

/// A learning rate as a function of the number of completed steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LrSchedule {
    /// The same rate at every step.
    Constant(f64),
    /// `initial * gamma^step` (PyTorch `ExponentialLR`); SeqAvatar's networks use
    /// `gamma = 0.1^(1 / iterations)`, see [`LrSchedule::decay_by`].
    Exponential {
        /// Rate at step 0.
        initial: f64,
        /// Factor per step.
        gamma: f64,
    },
    /// Log-linear from `initial` to `final_lr` over `steps`, then constant (3DGS's
    /// `get_expon_lr_func` without delay): `exp((1 - t) ln initial + t ln final_lr)`,
    /// `t = min(step / steps, 1)`.
    LogLinear {
        /// Rate at step 0.
        initial: f64,
        /// Rate from step `steps` on.
        final_lr: f64,
        /// Length of the decay.
        steps: u64,
    },
}

impl LrSchedule {
    /// `initial` decayed by `total_factor` over `steps` steps, geometrically per step.
    pub fn decay_by(initial: f64, total_factor: f64, steps: u64) -> Self {
        LrSchedule::Exponential {
            initial,
            gamma: total_factor.powf(1.0 / steps.max(1) as f64),
        }
    }

    /// The rate for the update that follows `completed_steps` updates.
    pub fn at(&self, completed_steps: u64) -> f64 {
        match *self {
            LrSchedule::Constant(lr) => lr,
            LrSchedule::Exponential { initial, gamma } => {
                initial * gamma.powf(completed_steps as f64)
            }
            LrSchedule::LogLinear {
                initial,
                final_lr,
                steps,
            } => {
                if initial == 0.0 && final_lr == 0.0 {
                    return 0.0;
                }
                let t = (completed_steps as f64 / steps.max(1) as f64).min(1.0);
                ((1.0 - t) * initial.ln() + t * final_lr.ln()).exp()
            }
        }
    }

    fn validate(&self, field: &str) -> Result<(), NnError> {
        let bad = |message: String| {
            Err(NnError::Config {
                field: field.into(),
                message,
            })
        };
        match *self {
            LrSchedule::Constant(lr) if !(lr.is_finite() && lr >= 0.0) => {
                bad(format!("learning rate {lr} is not finite and non-negative"))
            }
            LrSchedule::Exponential { initial, gamma }
                if !(initial.is_finite() && initial >= 0.0 && gamma.is_finite() && gamma > 0.0) =>
            {
                bad(format!(
                    "initial {initial} must be >= 0 and gamma {gamma} > 0, both finite"
                ))
            }
            LrSchedule::LogLinear {
                initial, final_lr, ..
            } if !log_linear_ends_valid(initial, final_lr) => bad(format!(
                "initial {initial} and final {final_lr} must both be positive (or both 0)"
            )),
            _ => Ok(()),
        }
    }
}

/// Both ends positive and finite (a log-linear interpolation needs logarithms), or both 0.
fn log_linear_ends_valid(initial: f64, final_lr: f64) -> bool {
    let positive = |lr: f64| lr.is_finite() && lr > 0.0;
    (positive(initial) && positive(final_lr)) || (initial == 0.0 && final_lr == 0.0)
}

/// A named set of tensors that share a learning-rate schedule.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamGroup {
    /// The group's name, used in error messages (e.g. `"non_rigid"`).
    pub name: String,
    /// Its learning rate over time.
    pub schedule: LrSchedule,
}

/// Adam's per-tensor state.
#[derive(Clone, Debug, PartialEq)]
pub struct AdamState<T> {
    /// First moments.
    pub m: Vec<T>,
    /// Second moments.
    pub v: Vec<T>,
    /// Updates applied so far.
    pub step: u64,
}

impl<T: NnScalar> AdamState<T> {
    /// Fresh state for a tensor of `len` values.
    pub fn new(len: usize) -> Self {
        AdamState {
            m: vec![T::ZERO; len],
            v: vec![T::ZERO; len],
            step: 0,
        }
    }
}

/// The scalars of one update, computed in f64 on the host for both backends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamStepFactors {
    /// `lr / (1 - beta1^t)`.
    pub step_size: f64,
    /// `sqrt(1 - beta2^t)`.
    pub bias_correction2_sqrt: f64,
}

impl AdamStepFactors {
    /// Factors for the update with 1-based index `t` at rate `lr`.
    pub fn new(config: &AdamConfig, lr: f64, t: u64) -> Self {
        let t = t.max(1) as i32;
        AdamStepFactors {
            step_size: lr / (1.0 - config.beta1.powi(t)),
            bias_correction2_sqrt: (1.0 - config.beta2.powi(t)).sqrt(),
        }
    }
}

/// One Adam update of `params` from `grads` at rate `lr`; advances `state.step`.
pub fn adam_update<T: NnScalar>(
    config: &AdamConfig,
    lr: f64,
    params: &mut [T],
    grads: &[T],
    state: &mut AdamState<T>,
) -> Result<(), NnError> {
    let n = params.len();
    check_len("adam gradient", n, grads.len())?;
    check_len("adam first moment", n, state.m.len())?;
    check_len("adam second moment", n, state.v.len())?;
    state.step += 1;
    let factors = AdamStepFactors::new(config, lr, state.step);
    let beta1 = T::from_f64(config.beta1);
    let beta2 = T::from_f64(config.beta2);
    let one_minus_beta1 = T::from_f64(1.0 - config.beta1);
    let one_minus_beta2 = T::from_f64(1.0 - config.beta2);
    let eps = T::from_f64(config.eps);
    let step_size = T::from_f64(factors.step_size);
    let correction = T::from_f64(factors.bias_correction2_sqrt);
    for (((p, &g), m), v) in params
        .iter_mut()
        .zip(grads)
        .zip(&mut state.m)
        .zip(&mut state.v)
    {
        *m = beta1 * *m + one_minus_beta1 * g;
        *v = beta2 * *v + one_minus_beta2 * g * g;
        let denominator = v.sqrt() / correction + eps;
        *p -= step_size * *m / denominator;
    }
    Ok(())
}

/// An Adam optimiser over named parameter groups.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    config: AdamConfig,
    groups: Vec<ParamGroup>,
}

impl Adam {
    /// Checks the configuration and every group's schedule.
    pub fn new(config: AdamConfig, groups: Vec<ParamGroup>) -> Result<Self, NnError> {
        config.validate()?;
        for group in &groups {
            group
                .schedule
                .validate(&format!("adam group {}", group.name))?;
        }
        Ok(Adam { config, groups })
    }

    pub fn config(&self) -> &AdamConfig {
        &self.config
    }

    /// The groups, in the order given.
    pub fn groups(&self) -> &[ParamGroup] {
        &self.groups
    }

    /// The index of the group named `name`.
    pub fn group_index(&self, name: &str) -> Option<usize> {
        self.groups.iter().position(|group| group.name == name)
    }

    fn group(&self, group: usize) -> Result<&ParamGroup, NnError> {
        self.groups.get(group).ok_or_else(|| NnError::Config {
            field: "adam group".into(),
            message: format!("index {group} out of {} groups", self.groups.len()),
        })
    }

    /// The rate of `group` for the update following `completed_steps` updates.
    pub fn learning_rate(&self, group: usize, completed_steps: u64) -> Result<f64, NnError> {
        Ok(self.group(group)?.schedule.at(completed_steps))
    }

    /// Updates one tensor of `group` on `cpu`, at the rate its schedule gives for
    /// `state.step` completed updates.
    pub fn update<T: NnScalar>(
        &self,
        group: usize,
        params: &mut [T],
        grads: &[T],
        state: &mut AdamState<T>,
    ) -> Result<(), NnError> {
        let lr = self.learning_rate(group, state.step)?;
        adam_update(&self.config, lr, params, grads, state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Textbook Adam with explicit bias-corrected moments, as an independent reference.
    fn reference(config: &AdamConfig, lrs: &[f64], p0: f64, grads: &[f64]) -> f64 {
        let (mut p, mut m, mut v) = (p0, 0.0, 0.0);
        for (t, (&g, &lr)) in grads.iter().zip(lrs).enumerate() {
            let t = (t + 1) as i32;
            m = config.beta1 * m + (1.0 - config.beta1) * g;
            v = config.beta2 * v + (1.0 - config.beta2) * g * g;
            let m_hat = m / (1.0 - config.beta1.powi(t));
            let v_hat = v / (1.0 - config.beta2.powi(t));
            p -= lr * m_hat / (v_hat.sqrt() + config.eps);
        }
        p
    }

    #[test]
    fn matches_textbook_adam_with_decay() {
        let config = AdamConfig {
            eps: 1e-8,
            ..AdamConfig::default()
        };
        let schedule = LrSchedule::decay_by(1e-2, 0.1, 10);
        let adam = Adam::new(
            config,
            vec![ParamGroup {
                name: "net".into(),
                schedule,
            }],
        )
        .unwrap();
        let grads = [
            0.3, -1.2, 0.05, 2.0, 0.0, -0.7, 1e-3, 0.4, -0.4, 0.9, 0.1, 0.2,
        ];
        let mut params = vec![1.5f64];
        let mut state = AdamState::new(1);
        for &g in &grads {
            adam.update(0, &mut params, &[g], &mut state).unwrap();
        }
        let lrs: Vec<f64> = (0..grads.len())
            .map(|t| 1e-2 * 0.1f64.powf(t as f64 / 10.0))
            .collect();
        let expected = reference(&config, &lrs, 1.5, &grads);
        assert!(
            (params[0] - expected).abs() < 1e-14,
            "{} vs {expected}",
            params[0]
        );
        assert_eq!(state.step, grads.len() as u64);
        // After `steps` updates the rate has fallen by exactly the total factor.
        assert!((adam.learning_rate(0, 10).unwrap() - 1e-3).abs() < 1e-15);
    }

    #[test]
    fn first_step_moves_by_lr_and_zero_gradients_are_finite() {
        // With bias correction the first step is lr * sign(g) for |g| >> eps.
        let config = AdamConfig::default();
        let mut params = vec![0.0f32, 0.0, 0.0, 0.0];
        let mut state = AdamState::new(4);
        adam_update(
            &config,
            0.01,
            &mut params,
            &[3.0, -1e-6, 0.0, 1e30],
            &mut state,
        )
        .unwrap();
        assert!((params[0] + 0.01).abs() < 1e-7);
        assert!((params[1] - 0.01).abs() < 1e-6);
        assert_eq!(params[2], 0.0);
        // g^2 overflows f32 at 1e30: the update is then 0 (m / inf), never NaN.
        assert!(params[3].is_finite());
    }

    #[test]
    fn log_linear_schedule_hits_its_ends() {
        let schedule = LrSchedule::LogLinear {
            initial: 1.6e-4,
            final_lr: 1.6e-6,
            steps: 30_000,
        };
        assert!((schedule.at(0) - 1.6e-4).abs() < 1e-18);
        assert!((schedule.at(15_000) - 1.6e-5).abs() < 1e-17);
        assert!((schedule.at(30_000) - 1.6e-6).abs() < 1e-18);
        assert!((schedule.at(90_000) - 1.6e-6).abs() < 1e-18);
    }

    #[test]
    fn rejects_bad_configuration() {
        let error = Adam::new(
            AdamConfig {
                beta2: 1.0,
                ..AdamConfig::default()
            },
            vec![],
        )
        .unwrap_err();
        assert!(error.to_string().starts_with("adam.beta2"), "{error}");
        let groups = vec![ParamGroup {
            name: "pose".into(),
            schedule: LrSchedule::Constant(-1.0),
        }];
        let error = Adam::new(AdamConfig::default(), groups).unwrap_err();
        assert!(error.to_string().starts_with("adam group pose"), "{error}");
        let mut state = AdamState::<f64>::new(2);
        let error = adam_update(
            &AdamConfig::default(),
            1.0,
            &mut [0.0; 2],
            &[0.0; 3],
            &mut state,
        )
        .unwrap_err();
        assert_eq!(
            error,
            NnError::Length {
                operand: "adam gradient".into(),
                expected: 2,
                actual: 3
            }
        );
    }
}
