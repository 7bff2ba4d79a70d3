//! Temporal smoothing of one track (one joint's rotations, or the root translation) by
//! Levenberg-Marquardt on the rotation manifold.
//!
//! Energy of a rotation track `R_0..R_{F-1}` with input fits `Q_t`:
//!
//! ```text
//! E = sum_t |R_t - Q_t|_F^2 / (2 sn^2)  +  sum_{t=1}^{F-2} robust(|A_t|_F / (sqrt(2) sa))
//! A_t = R_t^T R_{t+1} - R_{t-1}^T R_t
//! ```
//!
//! Both terms are chordal distances, so they are measured in rotation space (never on
//! axis-angle components): `|R - Q|_F = 2 sqrt(2) sin(theta / 2) ~ sqrt(2) theta` for the
//! geodesic angle `theta` between them, and `A_t = 0` exactly when the body-frame step
//! `R_{t-1}^T R_t` is constant (zero angular acceleration). Chordal residuals are smooth
//! everywhere, including at a rotation of pi, where the logarithm jumps. `sn` is the noise of
//! the input fit and `sa` the expected angular acceleration (radians per frame squared).
//!
//! A Cauchy kernel `rho` on accelerations keeps genuine
//! discontinuities (a 180-degree flip, a teleport) instead of smearing them over neighbouring
//! frames. Each step solves the Gauss-Newton normal equations (iteratively reweighted for
//! the kernel) with Levenberg damping;
//! updates are right-multiplied, `R <- R Exp(delta)`. The normal equations are banded (a
//! residual touches three consecutive frames), so a step costs `O(F)`.
//! Translations use the same energy with Euclidean residuals (a linear least-squares problem
//! apart from the robust weights).
//!
//! # Weights from the data
//!
//! `sn` and `sa` are estimated per track ([`SmoothingPlan`], [`estimate_noise`], [`sure_lambda`])
//! unless the configuration fixes them. The noise of an input fit is white; the motion is
//! smooth, so the sixth difference `D6_t = sum_k c_k Q_{t+k}`, `c = (1, -6, 15, -20, 15, -6,
//! 1)` (of the matrix entries, or of the translation) removes the motion up to its quintic
//! part, and damps a motion of `w` radians per frame by `(2 sin(w / 2))^6` (a gait cycle in 8
//! frames: 0.3), while it keeps the noise with `E|D6 N|^2 = 924 E|N|^2`. Both energy terms
//! have the form `|X|^2 / (2 s^2)` with `s^2 = E|X|^2 / 3` (three degrees of freedom per
//! frame), so
//!
//! ```text
//! sn^2 = E|D6|^2 / 2772    from the median of |D6_t|^2 (robust to fast segments)
//! ```
//!
//! (`|D6_t|^2` of a 3-dof Gaussian is `chi^2_3` distributed: mean = median x 3 / 2.366.)
//! The balance `lambda = sn^2 / sa^2` is then chosen by Stein's unbiased risk estimate of the
//! linear (small-step) version of the same smoother, with that noise ([`sure_lambda`]): the
//! weight that minimises the expected error against the unknown true motion. A track fitted
//! exactly has `sn` near zero, every smoothing only adds error, and the smallest weight wins,
//! so the solution stays on the input; a jittered one gets the weight its jitter and its
//! motion call for (the fixed weights matched one noise level and one speed).

use crate::banded::{BandedError, BandedMatrix};
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_core::rotation::{axis_angle_to_matrix, skew};

/// Standard deviations and solver limits of the smoothing energy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmoothingWeights {
    /// Expected error of an input rotation, radians.
    pub rotation_noise: f64,
    /// Expected angular acceleration of a joint, radians per frame squared.
    pub rotation_acceleration: f64,
    /// Expected error of an input translation, metres.
    pub translation_noise: f64,
    /// Expected acceleration of the root translation, metres per frame squared.
    pub translation_acceleration: f64,
    /// Scale of the Cauchy kernel on acceleration residuals, in standard deviations.
    pub robust_threshold: f64,
    /// Levenberg-Marquardt iteration limit.
    pub max_iterations: usize,
}

/// Where each track's standard deviations come from: a fixed value, or (`None`) estimated
/// from the track itself (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmoothingPlan {
    pub rotation_noise: Option<f64>,
    pub rotation_acceleration: Option<f64>,
    pub translation_noise: Option<f64>,
    pub translation_acceleration: Option<f64>,
    /// Scale of the Cauchy kernel on acceleration residuals, in standard deviations.
    pub robust_threshold: f64,
    /// Levenberg-Marquardt iteration limit.
    pub max_iterations: usize,
}

impl Default for SmoothingPlan {
    /// Every standard deviation estimated from the data.
    fn default() -> Self {
        let w = SmoothingWeights::default();
        Self {
            rotation_noise: None,
            rotation_acceleration: None,
            translation_noise: None,
            translation_acceleration: None,
            robust_threshold: w.robust_threshold,
            max_iterations: w.max_iterations,
        }
    }
}

/// Smallest standard deviation an estimate may return (radians or metres): keeps the
/// energy finite for a track that does not move at all.
pub const MIN_STANDARD_DEVIATION: f64 = 1e-6;

/// Mean over median of a chi-square variable with three degrees of freedom.
const CHI2_3_MEAN_OVER_MEDIAN: f64 = 3.0 / 2.365_973_884_375_5;

/// Binomial weights of the sixth difference, and their sum of squares.
const SIXTH_DIFFERENCE: [f64; 7] = [1.0, -6.0, 15.0, -20.0, 15.0, -6.0, 1.0];
const SIXTH_DIFFERENCE_GAIN: f64 = 924.0;

/// Data-driven noise standard deviation of a track from the squared norms of its sixth
/// differences (module docs); `None` when the track is too short to tell (fewer than seven
/// frames).
pub fn estimate_noise(sixth_differences_sq: &[f64]) -> Option<f64> {
    if sixth_differences_sq.is_empty() {
        return None;
    }
    let mut sorted = sixth_differences_sq.to_vec();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len();
    let median = if n % 2 == 1 {
        sorted[n / 2]
    } else {
        0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
    };
    let noise_sq = CHI2_3_MEAN_OVER_MEDIAN * median / (3.0 * SIXTH_DIFFERENCE_GAIN);
    Some(noise_sq.sqrt().max(MIN_STANDARD_DEVIATION))
}

/// The smoothing weights `lambda = sn^2 / sa^2` [`sure_lambda`] tries: 1e-3 to 1e8.
fn lambda_grid() -> impl Iterator<Item = f64> {
    (0..=22).map(|i| 10f64.powf(-3.0 + 0.5 * f64::from(i)))
}

/// Eigenvalues of the second-difference penalty `D2^T D2` of an `n`-frame track, in the
/// cosine approximation `(2 - 2 cos(pi k / n))^2`.
fn penalty_eigenvalues(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| {
            let c = 2.0 - 2.0 * (std::f64::consts::PI * k as f64 / n as f64).cos();
            c * c
        })
        .collect()
}

/// The linear smoother `x = (I + lambda D2^T D2)^-1 y` of a track of `D`-vectors.
pub fn whittaker_smooth<const D: usize>(
    values: &[[f64; D]],
    lambda: f64,
) -> Result<Vec<[f64; D]>, BandedError> {
    let n = values.len();
    let mut h = BandedMatrix::zeros(D * n, 2 * D);
    for i in 0..D * n {
        h.add(i, i, 1.0);
    }
    let coefficients = [1.0, -2.0, 1.0];
    for t in 1..n.saturating_sub(1) {
        for (a, ca) in coefficients.iter().enumerate() {
            for (b, cb) in coefficients.iter().enumerate().take(a + 1) {
                for c in 0..D {
                    h.add(D * (t - 1 + a) + c, D * (t - 1 + b) + c, lambda * ca * cb);
                }
            }
        }
    }
    let rhs: Vec<f64> = values.iter().flatten().copied().collect();
    let x = h.solve(&rhs)?;
    Ok(x.chunks_exact(D)
        .map(|chunk| std::array::from_fn(|c| chunk[c]))
        .collect())
}

/// The smoothing weight `lambda` of the grid that minimises Stein's unbiased risk estimate
/// `|x(lambda) - y|^2 + 2 s^2 tr H(lambda)` of [`whittaker_smooth`], for white noise of
/// total variance `s^2 = noise_variance` per frame (`tr H` from [`penalty_eigenvalues`]).
/// The penalty is the energy's acceleration term in the small-step limit, so
/// `sa = sn / sqrt(lambda)`. Noise-free input chooses the smallest `lambda`.
pub fn sure_lambda<const D: usize>(values: &[[f64; D]], noise_variance: f64) -> f64 {
    let eigenvalues = penalty_eigenvalues(values.len());
    let mut best = (f64::INFINITY, lambda_grid().next().unwrap_or(1.0));
    for lambda in lambda_grid() {
        let Ok(smoothed) = whittaker_smooth(values, lambda) else {
            continue;
        };
        let rss: f64 = smoothed
            .iter()
            .zip(values)
            .map(|(x, y)| x.iter().zip(y).map(|(a, b)| (a - b) * (a - b)).sum::<f64>())
            .sum();
        let trace: f64 = eigenvalues.iter().map(|m| 1.0 / (1.0 + lambda * m)).sum();
        let risk = rss + 2.0 * noise_variance * trace;
        if risk < best.0 {
            best = (risk, lambda);
        }
    }
    best.1
}

/// The estimated (noise, acceleration) standard deviations of one track of `D`-component
/// values: the noise from the median of its squared sixth differences, the smoothing weight
/// by SURE; `None` for a track too short to estimate from (fewer than seven frames).
fn estimate_track<const D: usize>(values: &[[f64; D]]) -> Option<(f64, f64)> {
    let sixth: Vec<f64> = values
        .windows(7)
        .map(|window| {
            (0..D)
                .map(|component| {
                    let mut sum = window[0][component] * SIXTH_DIFFERENCE[0];
                    for (x, c) in window.iter().zip(SIXTH_DIFFERENCE).skip(1) {
                        sum += x[component] * c;
                    }
                    sum * sum
                })
                .sum::<f64>()
        })
        .collect();
    estimate_noise(&sixth).map(|noise| {
        let lambda = sure_lambda(values, 3.0 * noise * noise);
        (noise, noise / lambda.sqrt())
    })
}

impl SmoothingPlan {
    /// Checks every fixed standard deviation and the kernel scale are positive and finite.
    pub fn validate(&self) -> Result<(), SmoothError> {
        let placeholder = 1.0;
        SmoothingWeights {
            rotation_noise: self.rotation_noise.unwrap_or(placeholder),
            rotation_acceleration: self.rotation_acceleration.unwrap_or(placeholder),
            translation_noise: self.translation_noise.unwrap_or(placeholder),
            translation_acceleration: self.translation_acceleration.unwrap_or(placeholder),
            robust_threshold: self.robust_threshold,
            max_iterations: self.max_iterations,
        }
        .validate()
    }

    /// The weights of one rotation track (input fits `track`): its rotation fields are the
    /// fixed or estimated ones; the translation fields repeat them and are not used.
    pub fn rotation_track_weights(&self, track: &[DMat3]) -> SmoothingWeights {
        let values: Vec<[f64; 9]> = track.iter().map(|&m| mat_entries(m)).collect();
        let fixed = (self.rotation_noise, self.rotation_acceleration);
        self.track_weights(&values, fixed, SmoothingWeights::default().rotation_noise)
    }

    /// The weights of the translation track, likewise (the rotation fields repeat the
    /// translation ones and are not used).
    pub fn translation_track_weights(&self, track: &[DVec3]) -> SmoothingWeights {
        let values: Vec<[f64; 3]> = track.iter().map(|v| v.to_array()).collect();
        let fixed = (self.translation_noise, self.translation_acceleration);
        self.track_weights(
            &values,
            fixed,
            SmoothingWeights::default().translation_noise,
        )
    }

    /// The weights of a track of `values` with the `fixed` (noise, acceleration), where set.
    /// Fixed values win; a track too short to estimate from (fewer than seven frames) is left
    /// as it is: the smallest noise against the default noise as acceleration scale.
    fn track_weights<const D: usize>(
        &self,
        values: &[[f64; D]],
        (noise, acceleration): (Option<f64>, Option<f64>),
        short_track_acceleration: f64,
    ) -> SmoothingWeights {
        let (estimated_noise, estimated_acceleration) =
            estimate_track(values).unwrap_or((MIN_STANDARD_DEVIATION, short_track_acceleration));
        let (noise, acceleration) = (
            noise.unwrap_or(estimated_noise),
            acceleration.unwrap_or(estimated_acceleration),
        );
        SmoothingWeights {
            rotation_noise: noise,
            rotation_acceleration: acceleration,
            translation_noise: noise,
            translation_acceleration: acceleration,
            robust_threshold: self.robust_threshold,
            max_iterations: self.max_iterations,
        }
    }
}

impl Default for SmoothingWeights {
    fn default() -> Self {
        Self {
            rotation_noise: 2.0_f64.to_radians(),
            rotation_acceleration: 1.0_f64.to_radians(),
            translation_noise: 0.01,
            translation_acceleration: 0.003,
            robust_threshold: 3.0,
            max_iterations: 50,
        }
    }
}

/// Why a track could not be smoothed.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SmoothError {
    #[error("smoothing weight `{name}` must be positive and finite, got {value}")]
    BadWeight { name: &'static str, value: f64 },
    #[error("input is not finite at frame {frame}")]
    NotFinite { frame: usize },
    #[error(transparent)]
    Solve(#[from] BandedError),
}

/// What the solver did on one track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackReport {
    pub iterations: usize,
    pub initial_energy: f64,
    pub final_energy: f64,
}

impl SmoothingWeights {
    /// Checks every standard deviation is positive and finite.
    pub fn validate(&self) -> Result<(), SmoothError> {
        for (name, value) in [
            ("rotation_noise", self.rotation_noise),
            ("rotation_acceleration", self.rotation_acceleration),
            ("translation_noise", self.translation_noise),
            ("translation_acceleration", self.translation_acceleration),
            ("robust_threshold", self.robust_threshold),
        ] {
            if !(value > 0.0 && value.is_finite()) {
                return Err(SmoothError::BadWeight { name, value });
            }
        }
        Ok(())
    }
}

/// Cauchy (Lorentzian) cost `c^2 ln(1 + s^2 / c^2)` of a residual of norm `s` (in standard
/// deviations) and its IRLS weight `1 / (1 + s^2 / c^2)`. Quadratic (`~ s^2`) well below `c`,
/// logarithmic above: a jump far beyond `c` costs almost the same whether it happens in one
/// frame or is smeared over several, so the data term keeps it sharp. (Huber's linear tail
/// prefers smearing a step over a few frames: its cost falls as `1/k`.)
pub(crate) fn robust(s: f64, scale: f64) -> (f64, f64) {
    let ratio = s * s / (scale * scale);
    (scale * scale * ratio.ln_1p(), 1.0 / (1.0 + ratio))
}

fn mat_entries(m: DMat3) -> [f64; 9] {
    m.to_cols_array()
}

fn frobenius_sq(m: DMat3) -> f64 {
    mat_entries(m).iter().map(|x| x * x).sum()
}

const BASIS: [DVec3; 3] = [DVec3::X, DVec3::Y, DVec3::Z];

/// Acceleration residual matrix `A_t` of a rotation track.
pub fn rotation_acceleration(prev: DMat3, cur: DMat3, next: DMat3) -> DMat3 {
    cur.transpose() * next - prev.transpose() * cur
}

/// Derivatives of `A_t` with respect to right perturbations `R <- R Exp(delta)` of the
/// previous, current and next rotation: `[frame][component]`.
pub fn rotation_acceleration_jacobian(prev: DMat3, cur: DMat3, next: DMat3) -> [[DMat3; 3]; 3] {
    let step_next = cur.transpose() * next;
    let step_prev = prev.transpose() * cur;
    let mut out = [[DMat3::ZERO; 3]; 3];
    for (i, e) in BASIS.iter().enumerate() {
        let k = skew(*e);
        // d(-R_{t-1}^T R_t): (R_{t-1} Exp(d))^T = (I - [d]x) R_{t-1}^T.
        out[0][i] = k * step_prev;
        out[1][i] = -(k * step_next) - step_prev * k;
        out[2][i] = step_next * k;
    }
    out
}

pub(crate) fn rotation_energy(track: &[DMat3], input: &[DMat3], w: &SmoothingWeights) -> f64 {
    let data_scale = 1.0 / (2.0 * w.rotation_noise * w.rotation_noise);
    let accel_scale = 1.0 / (std::f64::consts::SQRT_2 * w.rotation_acceleration);
    let mut energy = 0.0;
    for (r, q) in track.iter().zip(input) {
        energy += frobenius_sq(*r - *q) * data_scale;
    }
    for t in 1..track.len().saturating_sub(1) {
        let a = rotation_acceleration(track[t - 1], track[t], track[t + 1]);
        let s = frobenius_sq(a).sqrt() * accel_scale;
        energy += robust(s, w.robust_threshold).0;
    }
    energy
}

/// Adds `weight * J^T J` and `weight * J^T r` of one residual block (a `D`-vector) to the
/// normal equations. `jac[f][i]` is the derivative with respect to the unknown
/// `bases[f] + i` (component `i` of the 3-vector of unknowns starting at `bases[f]`).
pub(crate) fn accumulate<const D: usize>(
    h: &mut BandedMatrix,
    g: &mut [f64],
    bases: &[usize],
    jac: &[[[f64; D]; 3]],
    residual: &[f64; D],
    weight: f64,
) {
    for (fa, &ba) in bases.iter().enumerate() {
        for ia in 0..3 {
            let row = ba + ia;
            let ja = &jac[fa][ia];
            g[row] += weight * ja.iter().zip(residual).map(|(a, b)| a * b).sum::<f64>();
            for (fb, &bb) in bases.iter().enumerate() {
                for (ib, jb) in jac[fb].iter().enumerate() {
                    let col = bb + ib;
                    if col > row {
                        continue;
                    }
                    let v: f64 = ja.iter().zip(jb).map(|(a, b)| a * b).sum();
                    h.add(row, col, weight * v);
                }
            }
        }
    }
}

/// Visits every residual block of a rotation track's energy (the data term, then the
/// acceleration terms) as `(frames, jac, residual, irls_weight)`: `jac[f][i]` is the
/// derivative (a 9-vector) with respect to component `i` of the right perturbation of
/// `track[frames[f]]`. The (iteratively reweighted) Gauss-Newton model of the energy is
/// `sum irls_weight |residual + jac d|^2`.
pub(crate) fn rotation_residuals(
    track: &[DMat3],
    input: &[DMat3],
    w: &SmoothingWeights,
    mut visit: impl FnMut(&[usize], &[[[f64; 9]; 3]], &[f64; 9], f64),
) {
    let n = track.len();
    let data_scale = 1.0 / (std::f64::consts::SQRT_2 * w.rotation_noise);
    for t in 0..n {
        let residual = mat_entries((track[t] - input[t]) * data_scale);
        let jac = [BASIS.map(|e| mat_entries(track[t] * skew(e) * data_scale))];
        visit(&[t], &jac, &residual, 1.0);
    }
    let accel_scale = 1.0 / (std::f64::consts::SQRT_2 * w.rotation_acceleration);
    for t in 1..n.saturating_sub(1) {
        let (p, c, x) = (track[t - 1], track[t], track[t + 1]);
        let a = rotation_acceleration(p, c, x) * accel_scale;
        let residual = mat_entries(a);
        let s = frobenius_sq(a).sqrt();
        let weight = robust(s, w.robust_threshold).1;
        let d = rotation_acceleration_jacobian(p, c, x);
        let jac = d.map(|frame| frame.map(|m| mat_entries(m * accel_scale)));
        visit(&[t - 1, t, t + 1], &jac, &residual, weight);
    }
}

/// The normal equations of one track of `n` frames (three unknowns per frame) from the
/// residual blocks `residuals` visits ([`rotation_residuals`], [`translation_residuals`]).
fn normal_equations<const D: usize>(
    n: usize,
    residuals: impl FnOnce(&mut dyn FnMut(&[usize], &[[[f64; D]; 3]], &[f64; D], f64)),
) -> (BandedMatrix, Vec<f64>) {
    let mut h = BandedMatrix::zeros(3 * n, 8);
    let mut g = vec![0.0; 3 * n];
    residuals(&mut |frames, jac, residual, weight| {
        let bases: Vec<usize> = frames.iter().map(|t| 3 * t).collect();
        accumulate(&mut h, &mut g, &bases, jac, residual, weight);
    });
    (h, g)
}

/// Relative energy decrease below which smoothing a track stops.
const SMOOTH_TOLERANCE: f64 = 1e-12;

/// Generic damped Gauss-Newton loop: `model` gives the (reweighted) normal equations at a
/// state, `energy` the true robust energy, `retract` applies a step.
pub(crate) fn levenberg_marquardt<S: Clone>(
    start: S,
    max_iterations: usize,
    relative_tolerance: f64,
    energy: impl Fn(&S) -> f64,
    model: impl Fn(&S) -> (BandedMatrix, Vec<f64>),
    retract: impl Fn(&S, &[f64]) -> S,
) -> Result<(S, TrackReport), SmoothError> {
    let mut state = start;
    let initial_energy = energy(&state);
    let mut current = initial_energy;
    let mut damping = 1e-4;
    let mut iterations = 0;
    'outer: while iterations < max_iterations {
        iterations += 1;
        let (h, g) = model(&state);
        // Marquardt's scaling: each unknown is damped in proportion to its own curvature
        // (floored at a tiny fraction of the largest), so tracks whose weights differ by
        // orders of magnitude (data-driven weights) do not damp each other.
        let diagonal: Vec<f64> = (0..h.size()).map(|i| h.get(i, i)).collect();
        let floor = 1e-9 * diagonal.iter().copied().fold(0.0, f64::max).max(1.0);
        let mut accepted = false;
        for _attempt in 0..20 {
            let mut damped = h.clone();
            for (i, d) in diagonal.iter().enumerate() {
                damped.add(i, i, damping * d.max(floor));
            }
            let rhs: Vec<f64> = g.iter().map(|x| -x).collect();
            let step = damped.solve(&rhs)?;
            let candidate = retract(&state, &step);
            let e = energy(&candidate);
            if e.is_finite() && e <= current {
                let decrease = current - e;
                state = candidate;
                current = e;
                damping = (damping / 3.0).max(1e-12);
                accepted = true;
                let step_norm = step.iter().fold(0.0_f64, |m, x| m.max(x.abs()));
                if step_norm < 1e-10 || decrease <= relative_tolerance * current.max(1e-300) {
                    break 'outer;
                }
                break;
            }
            damping *= 4.0;
        }
        if !accepted {
            break;
        }
    }
    Ok((
        state,
        TrackReport {
            iterations,
            initial_energy,
            final_energy: current,
        },
    ))
}

/// Smooths one joint's rotation track (input fits `input`, one per frame).
pub fn smooth_rotation_track(
    input: &[DMat3],
    w: &SmoothingWeights,
) -> Result<(Vec<DMat3>, TrackReport), SmoothError> {
    w.validate()?;
    if let Some(frame) = input
        .iter()
        .position(|m| m.to_cols_array().iter().any(|x| !x.is_finite()))
    {
        return Err(SmoothError::NotFinite { frame });
    }
    levenberg_marquardt(
        input.to_vec(),
        w.max_iterations,
        SMOOTH_TOLERANCE,
        |track| rotation_energy(track, input, w),
        |track| normal_equations::<9>(track.len(), |v| rotation_residuals(track, input, w, v)),
        |track, step| {
            track
                .iter()
                .enumerate()
                .map(|(t, r)| {
                    let delta = DVec3::new(step[3 * t], step[3 * t + 1], step[3 * t + 2]);
                    *r * axis_angle_to_matrix(delta)
                })
                .collect()
        },
    )
}

pub(crate) fn translation_energy(track: &[DVec3], input: &[DVec3], w: &SmoothingWeights) -> f64 {
    let mut energy = 0.0;
    for (x, q) in track.iter().zip(input) {
        energy += (*x - *q).length_squared() / (w.translation_noise * w.translation_noise);
    }
    for t in 1..track.len().saturating_sub(1) {
        let a = track[t + 1] - 2.0 * track[t] + track[t - 1];
        energy += robust(a.length() / w.translation_acceleration, w.robust_threshold).0;
    }
    energy
}

/// Visits every residual block of the translation track's energy, as
/// [`rotation_residuals`] does (3-vector residuals; `jac[f][i]` is the derivative with
/// respect to component `i` of `track[frames[f]]`).
pub(crate) fn translation_residuals(
    track: &[DVec3],
    input: &[DVec3],
    w: &SmoothingWeights,
    mut visit: impl FnMut(&[usize], &[[[f64; 3]; 3]], &[f64; 3], f64),
) {
    let n = track.len();
    let unit = |scale: f64| BASIS.map(|e| (e * scale).to_array());
    for t in 0..n {
        let r = (track[t] - input[t]) / w.translation_noise;
        visit(&[t], &[unit(1.0 / w.translation_noise)], &r.to_array(), 1.0);
    }
    let coefficients = [1.0, -2.0, 1.0];
    for t in 1..n.saturating_sub(1) {
        let a = (track[t + 1] - 2.0 * track[t] + track[t - 1]) / w.translation_acceleration;
        let irls = robust(a.length(), w.robust_threshold).1;
        let jac = coefficients.map(|c| unit(c / w.translation_acceleration));
        visit(&[t - 1, t, t + 1], &jac, &a.to_array(), irls);
    }
}

/// Smooths the root translation track.
pub fn smooth_translation_track(
    input: &[DVec3],
    w: &SmoothingWeights,
) -> Result<(Vec<DVec3>, TrackReport), SmoothError> {
    w.validate()?;
    if let Some(frame) = input.iter().position(|v| !v.is_finite()) {
        return Err(SmoothError::NotFinite { frame });
    }
    levenberg_marquardt(
        input.to_vec(),
        w.max_iterations,
        SMOOTH_TOLERANCE,
        |track| translation_energy(track, input, w),
        |track| normal_equations::<3>(track.len(), |v| translation_residuals(track, input, w, v)),
        |track, step| {
            track
                .iter()
                .enumerate()
                .map(|(t, x)| *x + DVec3::new(step[3 * t], step[3 * t + 1], step[3 * t + 2]))
                .collect()
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rotation::matrix_to_axis_angle;
    use std::f64::consts::PI;

    fn angle_between(a: DMat3, b: DMat3) -> f64 {
        matrix_to_axis_angle(a.transpose() * b).length()
    }

    /// Deterministic noise in [-1, 1].
    fn noise(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    fn max_abs(m: DMat3) -> f64 {
        m.to_cols_array()
            .iter()
            .fold(0.0_f64, |a, x| a.max(x.abs()))
    }

    #[test]
    fn acceleration_jacobian_matches_central_differences() {
        let p = axis_angle_to_matrix(DVec3::new(0.3, -1.2, 0.4));
        let c = axis_angle_to_matrix(DVec3::new(0.1, 2.9, -0.2));
        let x = axis_angle_to_matrix(DVec3::new(-3.0, 0.1, 0.05));
        let jac = rotation_acceleration_jacobian(p, c, x);
        let h = 1e-6;
        for frame in 0..3 {
            for (i, e) in BASIS.iter().enumerate() {
                let perturb = |sign: f64| {
                    let d = axis_angle_to_matrix(*e * (sign * h));
                    let mut m = [p, c, x];
                    m[frame] *= d;
                    rotation_acceleration(m[0], m[1], m[2])
                };
                let fd = (perturb(1.0) - perturb(-1.0)) * (0.5 / h);
                assert!(max_abs(fd - jac[frame][i]) < 1e-8, "frame {frame} comp {i}");
            }
        }
    }

    /// The normal equations' gradient is half the gradient of the energy (E = |r|^2), checked
    /// by central differences of the energy along each tangent direction.
    #[test]
    fn normal_equation_gradient_matches_energy_differences() {
        let w = SmoothingWeights {
            robust_threshold: 0.5, // most residuals far in the kernel's tail
            ..SmoothingWeights::default()
        };
        let mut seed = 3;
        let input: Vec<DMat3> = (0..6)
            .map(|t| {
                axis_angle_to_matrix(DVec3::new(
                    0.2 * t as f64 + 0.05 * noise(&mut seed),
                    0.1 * noise(&mut seed),
                    3.0 + 0.1 * noise(&mut seed),
                ))
            })
            .collect();
        let track: Vec<DMat3> = input
            .iter()
            .map(|r| {
                *r * axis_angle_to_matrix(DVec3::new(
                    0.02 * noise(&mut seed),
                    0.02 * noise(&mut seed),
                    0.02 * noise(&mut seed),
                ))
            })
            .collect();
        let (_, g) =
            normal_equations::<9>(track.len(), |v| rotation_residuals(&track, &input, &w, v));
        let h = 1e-6;
        for t in 0..track.len() {
            for (i, e) in BASIS.iter().enumerate() {
                let energy_at = |sign: f64| {
                    let mut m = track.clone();
                    m[t] *= axis_angle_to_matrix(*e * (sign * h));
                    rotation_energy(&m, &input, &w)
                };
                let fd = (energy_at(1.0) - energy_at(-1.0)) / (2.0 * h);
                let tol = 1e-5 * fd.abs().max(1.0);
                assert!(
                    (fd - 2.0 * g[3 * t + i]).abs() < tol,
                    "t={t} i={i}: {fd} vs {}",
                    2.0 * g[3 * t + i]
                );
            }
        }
        // Translation, likewise.
        let tin: Vec<DVec3> = (0..6)
            .map(|t| DVec3::new(t as f64 * 0.1, noise(&mut seed), 0.0))
            .collect();
        let ttrack: Vec<DVec3> = tin
            .iter()
            .map(|v| *v + DVec3::splat(0.01 * noise(&mut seed)))
            .collect();
        let (_, g) = normal_equations::<3>(ttrack.len(), |v| {
            translation_residuals(&ttrack, &tin, &w, v)
        });
        for t in 0..6 {
            for c in 0..3 {
                let energy_at = |sign: f64| {
                    let mut m = ttrack.clone();
                    m[t][c] += sign * h;
                    translation_energy(&m, &tin, &w)
                };
                let fd = (energy_at(1.0) - energy_at(-1.0)) / (2.0 * h);
                assert!((fd - 2.0 * g[3 * t + c]).abs() < 1e-4 * fd.abs().max(1.0));
            }
        }
    }

    #[test]
    fn smoothing_reduces_rotation_error_of_a_jittered_track() {
        let w = SmoothingWeights::default();
        let mut seed = 11;
        let n = 120;
        let truth: Vec<DMat3> = (0..n)
            .map(|t| {
                let s = t as f64 / 30.0;
                axis_angle_to_matrix(DVec3::new(0.8 * s.sin(), 0.5 * (1.3 * s).cos(), 0.3 * s))
            })
            .collect();
        let sigma = 2.0_f64.to_radians();
        let noisy: Vec<DMat3> = truth
            .iter()
            .map(|r| {
                *r * axis_angle_to_matrix(DVec3::new(
                    sigma * noise(&mut seed),
                    sigma * noise(&mut seed),
                    sigma * noise(&mut seed),
                ))
            })
            .collect();
        let (smooth, report) = smooth_rotation_track(&noisy, &w).unwrap();
        assert!(report.final_energy < report.initial_energy);
        let err = |track: &[DMat3]| {
            track
                .iter()
                .zip(&truth)
                .map(|(a, b)| angle_between(*a, *b))
                .sum::<f64>()
                / n as f64
        };
        let (before, after) = (err(&noisy), err(&smooth));
        println!(
            "rotation error before {:.4} deg after {:.4} deg",
            before.to_degrees(),
            after.to_degrees()
        );
        assert!(after < 0.6 * before, "{before} -> {after}");
    }

    #[test]
    fn tracks_near_pi_and_through_a_flip_stay_finite_and_keep_the_flip() {
        let w = SmoothingWeights::default();
        // A joint rotating slowly around pi about z (crossing the log's discontinuity).
        let near_pi: Vec<DMat3> = (0..40)
            .map(|t| axis_angle_to_matrix(DVec3::Z * (PI - 0.05 + 0.0025 * t as f64)))
            .collect();
        let (out, _) = smooth_rotation_track(&near_pi, &w).unwrap();
        for (a, b) in out.iter().zip(&near_pi) {
            assert!(
                angle_between(*a, *b) < 1e-6,
                "a constant-rate track is already smooth"
            );
        }
        // A 180-degree flip between frames 19 and 20.
        let flip: Vec<DMat3> = (0..40)
            .map(|t| {
                let base = axis_angle_to_matrix(DVec3::new(0.01 * t as f64, 0.2, 0.0));
                if t >= 20 {
                    axis_angle_to_matrix(DVec3::X * PI) * base
                } else {
                    base
                }
            })
            .collect();
        let (out, _) = smooth_rotation_track(&flip, &w).unwrap();
        assert!(
            out.iter()
                .all(|m| m.to_cols_array().iter().all(|x| x.is_finite()))
        );
        for t in 0..40 {
            let moved = angle_between(out[t], flip[t]);
            let far = !(17..=22).contains(&t);
            if far {
                assert!(moved < 2.0_f64.to_radians(), "t={t} moved {moved}");
            }
        }
        assert!(angle_between(out[19], out[20]) > 2.5, "the flip survives");
    }

    #[test]
    fn teleporting_translation_is_kept_and_noise_is_reduced() {
        let w = SmoothingWeights::default();
        let mut seed = 5;
        let n = 60;
        let truth: Vec<DVec3> = (0..n)
            .map(|t| {
                let jump = if t >= 30 { 3.0 } else { 0.0 };
                DVec3::new(0.01 * t as f64 + jump, 0.9, 0.02 * (t as f64 / 10.0).sin())
            })
            .collect();
        let noisy: Vec<DVec3> = truth
            .iter()
            .map(|v| *v + DVec3::new(noise(&mut seed), noise(&mut seed), noise(&mut seed)) * 0.01)
            .collect();
        let (out, _) = smooth_translation_track(&noisy, &w).unwrap();
        assert!(
            (out[30].x - out[29].x) > 2.9,
            "the teleport survives: {}",
            out[30].x - out[29].x
        );
        let err = |track: &[DVec3]| -> f64 {
            track
                .iter()
                .zip(&truth)
                .enumerate()
                .filter(|(t, _)| !(27..=32).contains(t))
                .map(|(_, (a, b))| (*a - *b).length())
                .sum()
        };
        assert!(
            err(&out) < 0.7 * err(&noisy),
            "{} -> {}",
            err(&noisy),
            err(&out)
        );
    }

    /// The noise estimate against the noise put in: a smooth translation path plus white
    /// Gaussian noise of known standard deviation per component.
    #[test]
    fn estimated_noise_matches_the_jitter_put_in() {
        let mut seed = 21;
        let gaussian = |seed: &mut u64| {
            // Box-Muller from two uniforms in (0, 1].
            let u = 0.5 * (noise(seed) + 1.0) + 1e-12;
            let v = 0.5 * (noise(seed) + 1.0);
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let n = 400;
        let truth: Vec<DVec3> = (0..n)
            .map(|t| {
                let s = t as f64 / 15.0;
                DVec3::new(0.8 * s, 0.9 + 0.02 * (4.0 * s).sin(), 0.3 * (0.5 * s).cos())
            })
            .collect();
        for sigma in [0.002, 0.01, 0.03] {
            let noisy: Vec<DVec3> = truth
                .iter()
                .map(|v| {
                    *v + DVec3::new(
                        gaussian(&mut seed),
                        gaussian(&mut seed),
                        gaussian(&mut seed),
                    ) * sigma
                })
                .collect();
            let w = SmoothingPlan::default().translation_track_weights(&noisy);
            println!(
                "translation noise {sigma}: estimated {:.5}, acceleration {:.2e}",
                w.translation_noise, w.translation_acceleration
            );
            assert!(
                (w.translation_noise / sigma - 1.0).abs() < 0.15,
                "noise {sigma}: estimated {}",
                w.translation_noise
            );
        }
        // The exact path: noise far below any jitter, and smoothing leaves it in place.
        let w = SmoothingPlan::default().translation_track_weights(&truth);
        assert!(w.translation_noise < 1e-4, "{}", w.translation_noise);
        let (out, _) = smooth_translation_track(&truth, &w).unwrap();
        let moved = out
            .iter()
            .zip(&truth)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        assert!(moved < 1e-6, "{moved}");
        // Rotations: jitter of sigma per axis-angle component is a chordal noise of
        // sqrt(2) sigma per degree of freedom.
        let sigma = 0.03;
        let rotations: Vec<DMat3> = (0..n)
            .map(|t| {
                let s = t as f64 / 15.0;
                axis_angle_to_matrix(DVec3::new(0.5 * (3.0 * s).sin(), 0.2, 0.1 * s))
                    * axis_angle_to_matrix(
                        DVec3::new(
                            gaussian(&mut seed),
                            gaussian(&mut seed),
                            gaussian(&mut seed),
                        ) * sigma,
                    )
            })
            .collect();
        let w = SmoothingPlan::default().rotation_track_weights(&rotations);
        let expected = std::f64::consts::SQRT_2 * sigma;
        assert!(
            (w.rotation_noise / expected - 1.0).abs() < 0.15,
            "rotation noise {} vs {expected}",
            w.rotation_noise
        );
        // Fixed values win over estimates; short tracks are left alone.
        let fixed = SmoothingPlan {
            rotation_noise: Some(0.5),
            ..SmoothingPlan::default()
        };
        assert_eq!(fixed.rotation_track_weights(&rotations).rotation_noise, 0.5);
        let short = SmoothingPlan::default().translation_track_weights(&truth[..6]);
        assert_eq!(short.translation_noise, MIN_STANDARD_DEVIATION);
    }

    /// A fit with no noise stays where it is, even through motion far faster than the
    /// fixed weights assume (the knee of a sprint: 1.5 rad swings in 6 frames), while the
    /// same track jittered is still smoothed.
    #[test]
    fn estimated_weights_leave_exact_fast_tracks_alone_and_smooth_jittered_ones() {
        let plan = SmoothingPlan::default();
        let n = 90;
        let truth: Vec<DMat3> = (0..n)
            .map(|t| {
                let phase = std::f64::consts::TAU * t as f64 / 12.0;
                // Speed ramps up: slow walk, then sprint.
                let amplitude = if t < 45 { 0.3 } else { 0.75 };
                axis_angle_to_matrix(DVec3::new(amplitude * phase.sin(), 0.1, 0.05 * phase.cos()))
            })
            .collect();
        let (out, _) = smooth_rotation_track(&truth, &plan.rotation_track_weights(&truth)).unwrap();
        let moved = out
            .iter()
            .zip(&truth)
            .map(|(a, b)| angle_between(*a, *b))
            .fold(0.0_f64, f64::max);
        // The fixed weights move it by degrees.
        let (fixed, _) = smooth_rotation_track(&truth, &SmoothingWeights::default()).unwrap();
        let moved_fixed = fixed
            .iter()
            .zip(&truth)
            .map(|(a, b)| angle_between(*a, *b))
            .fold(0.0_f64, f64::max);
        println!(
            "exact fast track: moved at most {:.4} deg (fixed weights {:.2} deg)",
            moved.to_degrees(),
            moved_fixed.to_degrees()
        );
        assert!(moved < 0.05_f64.to_radians(), "{}", moved.to_degrees());
        let mut seed = 8;
        let sigma = 2.0_f64.to_radians();
        let noisy: Vec<DMat3> = truth
            .iter()
            .map(|r| {
                *r * axis_angle_to_matrix(DVec3::new(
                    sigma * noise(&mut seed),
                    sigma * noise(&mut seed),
                    sigma * noise(&mut seed),
                ))
            })
            .collect();
        let (out, _) = smooth_rotation_track(&noisy, &plan.rotation_track_weights(&noisy)).unwrap();
        let err = |track: &[DMat3]| {
            track
                .iter()
                .zip(&truth)
                .map(|(a, b)| angle_between(*a, *b))
                .sum::<f64>()
                / n as f64
        };
        println!(
            "jittered fast track: error {:.3} -> {:.3} deg",
            err(&noisy).to_degrees(),
            err(&out).to_degrees()
        );
        assert!(err(&out) < 0.85 * err(&noisy));
    }

    /// The Whittaker smoother against a dense solve of `(I + lambda D2^T D2) x = y` built
    /// from the difference matrix itself, and the weight Stein's estimate picks against the
    /// weight that is best in truth (known here).
    #[test]
    fn whittaker_smoother_and_sure_weight_against_independent_computations() {
        let n = 9;
        let lambda = 2.5;
        let mut seed = 4;
        let values: Vec<[f64; 2]> = (0..n)
            .map(|_| [noise(&mut seed), noise(&mut seed)])
            .collect();
        // Dense A = I + lambda D^T D, D the (n - 2) x n second-difference matrix.
        let mut d = vec![vec![0.0; n]; n - 2];
        for (t, row) in d.iter_mut().enumerate() {
            row[t] = 1.0;
            row[t + 1] = -2.0;
            row[t + 2] = 1.0;
        }
        let smoothed = whittaker_smooth(&values, lambda).unwrap();
        for c in 0..2 {
            let mut a: Vec<Vec<f64>> = (0..n)
                .map(|i| {
                    (0..n)
                        .map(|j| {
                            let dtd: f64 = d.iter().map(|row| row[i] * row[j]).sum();
                            f64::from(u8::from(i == j)) + lambda * dtd
                        })
                        .collect()
                })
                .collect();
            let mut b: Vec<f64> = values.iter().map(|v| v[c]).collect();
            // Gauss-Jordan elimination (A is symmetric positive definite: no pivoting).
            for k in 0..n {
                let pivot_row = a[k].clone();
                for i in (0..n).filter(|&i| i != k) {
                    let f = a[i][k] / pivot_row[k];
                    for (x, p) in a[i].iter_mut().zip(&pivot_row) {
                        *x -= f * p;
                    }
                    b[i] -= f * b[k];
                }
            }
            for t in 0..n {
                let x = b[t] / a[t][t];
                assert!((x - smoothed[t][c]).abs() < 1e-12, "t={t} c={c}");
            }
        }
        // A smooth signal plus noise of known variance: the weight Stein's estimate picks
        // has a true error close to the best weight of the grid.
        let n = 200;
        let sigma = 0.05;
        let truth: Vec<[f64; 1]> = (0..n).map(|t| [(t as f64 / 9.0).sin()]).collect();
        let noisy: Vec<[f64; 1]> = truth
            .iter()
            .map(|v| [v[0] + sigma * 3f64.sqrt() * noise(&mut seed)])
            .collect();
        let true_error = |lambda: f64| -> f64 {
            whittaker_smooth(&noisy, lambda)
                .unwrap()
                .iter()
                .zip(&truth)
                .map(|(x, y)| (x[0] - y[0]).powi(2))
                .sum()
        };
        let chosen = sure_lambda(&noisy, sigma * sigma);
        let best = lambda_grid().map(true_error).fold(f64::INFINITY, f64::min);
        println!(
            "Stein's weight {chosen:.3e}: error {:.4} (best of the grid {best:.4}, none {:.4})",
            true_error(chosen),
            n as f64 * sigma * sigma
        );
        assert!(true_error(chosen) < 1.5 * best);
        // No noise: the smallest weight.
        assert_eq!(sure_lambda(&truth, 0.0), lambda_grid().next().unwrap());
    }

    #[test]
    fn short_tracks_and_bad_input() {
        let w = SmoothingWeights::default();
        let one = vec![axis_angle_to_matrix(DVec3::new(0.1, 0.2, 0.3))];
        let (out, _) = smooth_rotation_track(&one, &w).unwrap();
        assert!(max_abs(out[0] - one[0]) < 1e-12);
        let (out, _) = smooth_rotation_track(&[], &w).unwrap();
        assert!(out.is_empty());
        let (out, _) = smooth_translation_track(&[DVec3::ONE, DVec3::ZERO], &w).unwrap();
        assert_eq!(out, vec![DVec3::ONE, DVec3::ZERO]);
        let mut bad = vec![DMat3::IDENTITY; 3];
        bad[1].x_axis.y = f64::NAN;
        assert_eq!(
            smooth_rotation_track(&bad, &w).unwrap_err(),
            SmoothError::NotFinite { frame: 1 }
        );
        assert_eq!(
            smooth_translation_track(&[DVec3::ZERO, DVec3::NAN], &w).unwrap_err(),
            SmoothError::NotFinite { frame: 1 }
        );
        let zero = SmoothingWeights {
            rotation_noise: 0.0,
            ..w
        };
        assert!(matches!(
            smooth_rotation_track(&one, &zero),
            Err(SmoothError::BadWeight { .. })
        ));
    }
}
