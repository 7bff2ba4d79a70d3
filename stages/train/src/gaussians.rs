//! The canonical Gaussians as trainable per-Gaussian columns, and one optimisation step of
//! them through skinning, the real `cpu` splatting and the photometric loss.
//!
//! Columns (see [`crate::densify::GaussianState`]): `xyz` (3), `sh` (`16 x 3`, degree 3,
//! coefficient-major; the active degree uses the first `(d + 1)^2` coefficients), `opacity`
//! (1, logit), `log_scale` (3), `rotation` (4), each with `<name>.adam_m` / `<name>.adam_v`
//! moments, and the densification statistics `grad_accum`, `grad_count`.
//!
//! This step is the "no non-rigid" model (ablation row (a)): the non-rigid offsets enter the
//! skinning as zeros until the networks are wired in.

use anyhow::{Context, bail};
use seqavatar_compute::nn::adam::{AdamConfig, AdamState, adam_update};
use seqavatar_compute::splat::{self, GaussianSet, ImageGradient, RasterOptions};
use seqavatar_core::camera::Camera;

use crate::densify::{GaussianState, Growth, names};
use crate::losses::{ImageLossTerms, ImageLossWeights, ImagePair, Rect, image_loss};
use crate::skinning::{GaussianParams, SkinningFrame, skin_backward, skin_forward};

/// Spherical-harmonics DC constant (3DGS `C0`).
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// Coefficients stored per colour channel (degree 3).
pub const SH_STORED: usize = 16;
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

/// Builds the initial state (method.md, "Init"): given centres, colours in `[0, 1]`, an
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
        state.add(
            &format!("{name}.adam_m"),
            width,
            Growth::Zero,
            vec![0.0; n * width],
        )?;
        state.add(
            &format!("{name}.adam_v"),
            width,
            Growth::Zero,
            vec![0.0; n * width],
        )?;
    }
    state.add(names::GRAD_ACCUM, 1, Growth::Zero, vec![0.0; n])?;
    state.add(names::GRAD_COUNT, 1, Growth::Zero, vec![0.0; n])?;
    Ok(state)
}

/// Learning rates of one step, per trainable column (same order as [`TRAINABLE`]; SH uses
/// `sh_dc` for the first coefficient and `sh_rest` for the others).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepRates {
    pub position: f64,
    pub sh_dc: f64,
    pub sh_rest: f64,
    pub opacity: f64,
    pub scaling: f64,
    pub rotation: f64,
}

/// 3DGS's exponential (log-linear) decay from `initial` to `final_` over `steps`.
pub fn exponential_lr(initial: f64, final_: f64, step: u64, steps: u64) -> f64 {
    let t = (step as f64 / steps.max(1) as f64).clamp(0.0, 1.0);
    (initial.ln() * (1.0 - t) + final_.ln() * t).exp()
}

/// One camera's supervision.
pub struct Target<'a> {
    pub camera: &'a Camera,
    pub colour: &'a [f64],
    pub mask: &'a [f64],
    pub bound: Rect,
}

/// Results of one step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    pub loss: ImageLossTerms,
    /// PSNR of the render against the target inside the bound box, averaged over cameras.
    pub psnr: f64,
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// One optimisation step of the Gaussians (skinning with zero non-rigid offsets).
#[allow(clippy::too_many_arguments)]
pub fn gaussian_step(
    state: &mut GaussianState,
    adam_step: &mut u64,
    frame: &SkinningFrame<'_>,
    nearest: &[u32],
    targets: &[Target<'_>],
    sh_degree: u32,
    weights: ImageLossWeights,
    rates: StepRates,
    background: [f64; 3],
) -> anyhow::Result<StepStats> {
    let n = state.len();
    let k = splat::sh_coefficient_count(sh_degree);
    let zeros3 = vec![0.0; 3 * n];
    let identity: Vec<f64> = [1.0, 0.0, 0.0, 0.0].repeat(n);
    let params = GaussianParams {
        positions: state.values(names::POSITION)?,
        log_scales: state.values(names::LOG_SCALE)?,
        d_scales: &zeros3,
        rotations: state.values(names::ROTATION)?,
        d_rotations: &identity,
        weight_offsets: None,
        nearest,
    };
    let skinned = skin_forward(frame, &params);
    let logits = state.values(names::OPACITY_LOGIT)?;
    let opacities: Vec<f64> = logits.iter().map(|l| sigmoid(*l)).collect();
    let stored = state.values(SH)?;
    let sh: Vec<f64> = (0..n)
        .flat_map(|i| {
            stored[i * 3 * SH_STORED..i * 3 * SH_STORED + 3 * k]
                .iter()
                .copied()
        })
        .collect();
    let set = GaussianSet {
        means: &skinned.positions,
        covariances: &skinned.covariances,
        opacities: &opacities,
        sh: &sh,
        sh_degree,
    };
    let cameras: Vec<Camera> = targets.iter().map(|t| t.camera.clone()).collect();
    let options = RasterOptions {
        background,
        smooth_cutoff: false,
    };
    let forward = splat::cpu::forward(&set, &cameras, &options).context("splatting forward")?;
    let mut stats = StepStats::default();
    let mut upstream_colour = Vec::with_capacity(targets.len());
    let mut upstream_alpha = Vec::with_capacity(targets.len());
    let scale = 1.0 / targets.len() as f64;
    for (image, target) in forward.images.iter().zip(targets) {
        let pair = ImagePair {
            width: image.width as usize,
            height: image.height as usize,
            colour: &image.colour,
            alpha: &image.alpha,
            target_colour: target.colour,
            target_mask: target.mask,
        };
        let (terms, grads) = image_loss(&pair, target.bound, weights);
        stats.loss.l1 += scale * terms.l1;
        stats.loss.mask_mse += scale * terms.mask_mse;
        stats.loss.dssim += scale * terms.dssim;
        stats.loss.total += scale * terms.total;
        stats.psnr += scale
            * psnr(
                &image.colour,
                target.colour,
                image.width as usize,
                target.bound,
            );
        upstream_colour.push(grads.colour.iter().map(|g| g * scale).collect::<Vec<f64>>());
        upstream_alpha.push(grads.alpha.iter().map(|g| g * scale).collect::<Vec<f64>>());
    }
    let upstream: Vec<ImageGradient<'_, f64>> = upstream_colour
        .iter()
        .zip(&upstream_alpha)
        .map(|(c, a)| ImageGradient {
            colour: c,
            alpha: Some(a),
            depth: None,
        })
        .collect();
    let grads = splat::cpu::backward(&forward, &set, &upstream).context("splatting backward")?;
    let skin_grads = skin_backward(frame, &params, &grads.means, &grads.covariances);
    let d_opacity: Vec<f64> = (0..n)
        .map(|i| grads.opacities[i] * opacities[i] * (1.0 - opacities[i]))
        .collect();
    let mut d_sh = vec![0.0; n * 3 * SH_STORED];
    for i in 0..n {
        d_sh[i * 3 * SH_STORED..i * 3 * SH_STORED + 3 * k]
            .copy_from_slice(&grads.sh[i * 3 * k..(i + 1) * 3 * k]);
    }
    let visible: Vec<bool> = grads.mean_2d_norm.iter().map(|g| *g > 0.0).collect();
    // Densification statistic in 3DGS's NDC units: pixels times half the image size.
    let half_size = targets
        .iter()
        .map(|t| t.camera.width.max(t.camera.height))
        .max()
        .unwrap_or(1) as f64
        * 0.5;
    let norms: Vec<f64> = grads.mean_2d_norm.iter().map(|g| g * half_size).collect();
    state.accumulate_gradient_stats(&norms, &visible)?;
    for (name, values) in [
        (names::POSITION, &skin_grads.positions),
        (SH, &d_sh),
        (names::OPACITY_LOGIT, &d_opacity),
        (names::LOG_SCALE, &skin_grads.log_scales),
        (names::ROTATION, &skin_grads.rotations),
    ] {
        if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
            bail!(
                "gradient of `{name}` is not finite at Gaussian {}",
                bad / (values.len() / n.max(1)).max(1)
            );
        }
    }
    *adam_step += 1;
    let config = AdamConfig::default();
    let gradients: [(&str, &Vec<f64>); 5] = [
        (names::POSITION, &skin_grads.positions),
        (SH, &d_sh),
        (names::OPACITY_LOGIT, &d_opacity),
        (names::LOG_SCALE, &skin_grads.log_scales),
        (names::ROTATION, &skin_grads.rotations),
    ];
    for (name, gradient) in gradients {
        let mut adam = AdamState {
            m: std::mem::take(state.values_mut(&format!("{name}.adam_m"))?),
            v: std::mem::take(state.values_mut(&format!("{name}.adam_v"))?),
            step: *adam_step - 1,
        };
        let values = state.values_mut(name)?;
        if name == SH {
            // DC and higher coefficients have different rates: update them as two tensors.
            update_sh(&config, rates, values, gradient, &mut adam, n)?;
        } else {
            let lr = match name {
                names::POSITION => rates.position,
                names::OPACITY_LOGIT => rates.opacity,
                names::LOG_SCALE => rates.scaling,
                _ => rates.rotation,
            };
            adam_update(&config, lr, values, gradient, &mut adam)?;
        }
        *state.values_mut(&format!("{name}.adam_m"))? = adam.m;
        *state.values_mut(&format!("{name}.adam_v"))? = adam.v;
    }
    Ok(stats)
}

fn update_sh(
    config: &AdamConfig,
    rates: StepRates,
    values: &mut [f64],
    gradient: &[f64],
    adam: &mut AdamState<f64>,
    n: usize,
) -> anyhow::Result<()> {
    let row = 3 * SH_STORED;
    for (part, lr) in [(0..3, rates.sh_dc), (3..row, rates.sh_rest)] {
        let gather = |v: &[f64]| -> Vec<f64> {
            (0..n)
                .flat_map(|i| v[i * row + part.start..i * row + part.end].iter().copied())
                .collect()
        };
        let mut p = gather(values);
        let mut sub = AdamState {
            m: gather(&adam.m),
            v: gather(&adam.v),
            step: adam.step,
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
    }
    Ok(())
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
    use crate::rng::Rng;
    use seqavatar_core::glam::{DMat3, DVec3};

    const IDENTITY: [f64; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

    fn camera(size: u32) -> Camera {
        Camera {
            width: size,
            height: size,
            intrinsics: seqavatar_core::camera::Intrinsics {
                fx: size as f64 * 1.2,
                fy: size as f64 * 1.2,
                cx: size as f64 * 0.5,
                cy: size as f64 * 0.5,
            },
            rotation: DMat3::IDENTITY,
            translation: DVec3::ZERO,
            distortion: [0.0; 5],
        }
    }

    /// A tiny scene: the target is rendered from "true" Gaussians; training starts from
    /// perturbed positions, random colours and opacity 0.1, and must cut the loss.
    #[test]
    fn tiny_gaussian_training_reduces_the_loss() {
        let mut rng = Rng::new(12);
        let n = 40;
        let size = 32;
        let centres: Vec<f64> = (0..n)
            .flat_map(|_| {
                [
                    rng.uniform(-0.3, 0.3),
                    rng.uniform(-0.3, 0.3),
                    rng.uniform(1.8, 2.2),
                ]
            })
            .collect();
        let colours: Vec<f64> = (0..3 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
        let truth = initial_state(&centres, &colours, 0.8, &vec![0.06; 3 * n]).unwrap();
        let weights_template = [1.0];
        let offsets = [0.0; 3];
        let frame = SkinningFrame {
            joint_count: 1,
            canonical_joints: &[IDENTITY],
            target_joints: &[IDENTITY],
            template_weights: &weights_template,
            vertex_offsets: &offsets,
            scale_min: 1e-5,
            scale_max: 0.5,
        };
        let nearest = vec![0u32; n];
        let cam = camera(size);
        // Render the target with the true Gaussians.
        let sh: Vec<f64> = truth
            .values(SH)
            .unwrap()
            .chunks(3 * SH_STORED)
            .flat_map(|r| r[..3].to_vec())
            .collect();
        let covs = crate::skinning::canonical_covariances(
            truth.values(names::LOG_SCALE).unwrap(),
            truth.values(names::ROTATION).unwrap(),
        );
        let set = GaussianSet {
            means: &centres,
            covariances: &covs,
            opacities: &vec![0.8; n],
            sh: &sh,
            sh_degree: 0,
        };
        let rendered =
            splat::cpu::forward(&set, std::slice::from_ref(&cam), &RasterOptions::default())
                .unwrap();
        let target_colour = rendered.images[0].colour.clone();
        let target_mask = rendered.images[0].alpha.clone();
        let bound =
            crate::losses::bound_box(&target_mask, size as usize, size as usize, 5).unwrap();
        let targets = [Target {
            camera: &cam,
            colour: &target_colour,
            mask: &target_mask,
            bound,
        }];
        let start: Vec<f64> = centres.iter().map(|c| c + 0.02 * rng.normal()).collect();
        let start_colours: Vec<f64> = (0..3 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
        let mut state = initial_state(&start, &start_colours, 0.1, &vec![0.04; 3 * n]).unwrap();
        let mut adam_step = 0;
        let rates = StepRates {
            position: 1e-3,
            sh_dc: 2.5e-2,
            sh_rest: 1.25e-3,
            opacity: 0.05,
            scaling: 5e-3,
            rotation: 1e-3,
        };
        let weights = ImageLossWeights {
            mask: 0.1,
            ssim: 0.1,
        };
        let mut losses = Vec::new();
        for _ in 0..80 {
            let stats = gaussian_step(
                &mut state,
                &mut adam_step,
                &frame,
                &nearest,
                &targets,
                0,
                weights,
                rates,
                [0.0; 3],
            )
            .unwrap();
            losses.push(stats.loss.total);
        }
        let (first, last) = (losses[0], *losses.last().unwrap());
        eprintln!("tiny training: loss {first:.4} -> {last:.4}");
        assert!(last < first / 3.0, "loss {first} -> {last}");
        assert_eq!(adam_step, 80);
        assert!(
            state
                .values(names::GRAD_COUNT)
                .unwrap()
                .iter()
                .any(|c| *c > 0.0)
        );
    }

    #[test]
    fn exponential_lr_endpoints() {
        assert!((exponential_lr(1.6e-4, 1.6e-6, 0, 100) - 1.6e-4).abs() < 1e-18);
        assert!((exponential_lr(1.6e-4, 1.6e-6, 100, 100) - 1.6e-6).abs() < 1e-18);
        assert!((exponential_lr(1.6e-4, 1.6e-6, 50, 100) - 1.6e-5).abs() < 1e-17);
        assert!((exponential_lr(1.6e-4, 1.6e-6, 500, 100) - 1.6e-6).abs() < 1e-18);
    }
}
