//! The canonical Gaussians as trainable per-Gaussian columns: their layout, initial state,
//! the position learning-rate schedule and the training PSNR (the optimisation step itself is
//! [`crate::trainer`]).
//!
//! Columns (see [`crate::densify::GaussianState`]): `xyz` (3), `sh` (`16 x 3`, degree 3,
//! coefficient-major; the active degree uses the first `(d + 1)^2` coefficients), `opacity`
//! (1, logit), `log_scale` (3), `rotation` (4), each with `<name>.adam_m` / `<name>.adam_v`
//! moments, and the densification statistics `grad_accum`, `grad_count`.

use anyhow::bail;
use seqavatar_avatar::avatar::AvatarGaussians;

use crate::densify::{GaussianState, Growth, names};
use crate::losses::Rect;

pub use seqavatar_avatar::avatar::{SH_C0, SH_STORED};

/// Column of the SH coefficients.
pub const SH: &str = "sh";

/// Trainable columns with their Adam moments.
pub const TRAINABLE: [(&str, usize); 5] = [
    (names::POSITION, 3),
    (SH, 3 * SH_STORED),
    (names::OPACITY_LOGIT, 1),
    (names::LOG_SCALE, 3),
    (names::ROTATION, 4),
];

/// Builds the initial state (docs/method.md, "Init"): given centres, colours in `[0, 1]`, an
/// opacity and linear scales.
pub fn initial_state(
    centres: &[f64],
    colours: &[f64],
    opacity: f64,
    scales: &[f64],
) -> anyhow::Result<GaussianState> {
    let n = centres.len() / 3;
    if colours.len() != 3 * n || scales.len() != 3 * n || !(0.0 < opacity && opacity < 1.0) {
        bail!("initial Gaussians: {n} centres need {n} colours and scales and 0 < opacity < 1");
    }
    let mut sh = vec![0.0; n * 3 * SH_STORED];
    for i in 0..n {
        for c in 0..3 {
            sh[i * 3 * SH_STORED + c] = (colours[3 * i + c] - 0.5) / SH_C0;
        }
    }
    let logit = (opacity / (1.0 - opacity)).ln();
    let mut state = GaussianState::default();
    state.add(names::POSITION, 3, Growth::Inherit, centres.to_vec())?;
    state.add(SH, 3 * SH_STORED, Growth::Inherit, sh)?;
    state.add(names::OPACITY_LOGIT, 1, Growth::Inherit, vec![logit; n])?;
    state.add(
        names::LOG_SCALE,
        3,
        Growth::Inherit,
        scales.iter().map(|s| s.max(1e-9).ln()).collect(),
    )?;
    state.add(
        names::ROTATION,
        4,
        Growth::Inherit,
        [1.0, 0.0, 0.0, 0.0].repeat(n),
    )?;
    for (name, width) in TRAINABLE {
        for moment in ["adam_m", "adam_v"] {
            let zeros = vec![0.0; n * width];
            state.add(&format!("{name}.{moment}"), width, Growth::Zero, zeros)?;
        }
    }
    state.add(names::GRAD_ACCUM, 1, Growth::Zero, vec![0.0; n])?;
    state.add(names::GRAD_COUNT, 1, Growth::Zero, vec![0.0; n])?;
    Ok(state)
}

/// The avatar's Gaussians: the trainable columns of a training state.
pub fn avatar_gaussians(state: &GaussianState) -> anyhow::Result<AvatarGaussians> {
    Ok(AvatarGaussians {
        xyz: state.values(names::POSITION)?.to_vec(),
        sh: state.values(SH)?.to_vec(),
        opacity_logit: state.values(names::OPACITY_LOGIT)?.to_vec(),
        log_scale: state.values(names::LOG_SCALE)?.to_vec(),
        rotation: state.values(names::ROTATION)?.to_vec(),
    })
}

/// 3DGS's exponential (log-linear) decay from `initial` to `final_` over `steps`.
pub fn exponential_lr(initial: f64, final_: f64, step: u64, steps: u64) -> f64 {
    let t = (step as f64 / steps.max(1) as f64).clamp(0.0, 1.0);
    (initial.ln() * (1.0 - t) + final_.ln() * t).exp()
}

/// PSNR over the pixels of `rect` (colours in `[0, 1]`).
pub fn psnr(colour: &[f64], target: &[f64], width: usize, rect: Rect) -> f64 {
    let mut sum = 0.0;
    for row in rect.y0..rect.y1 {
        for col in rect.x0..rect.x1 {
            for c in 0..3 {
                let i = 3 * (row * width + col) + c;
                sum += (colour[i] - target[i]).powi(2);
            }
        }
    }
    let mse = sum / (3 * rect.area()) as f64;
    -10.0 * mse.max(1e-20).log10()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponential_lr_endpoints() {
        assert!((exponential_lr(1.6e-4, 1.6e-6, 0, 100) - 1.6e-4).abs() < 1e-18);
        assert!((exponential_lr(1.6e-4, 1.6e-6, 100, 100) - 1.6e-6).abs() < 1e-18);
        assert!((exponential_lr(1.6e-4, 1.6e-6, 50, 100) - 1.6e-5).abs() < 1e-17);
        assert!((exponential_lr(1.6e-4, 1.6e-6, 500, 100) - 1.6e-6).abs() < 1e-18);
    }
}
