//! Tests of the cpu splatting backend: an independent per-pixel reference renderer, central
//! finite differences in f64 for every parameter kind, and the numeric extremes.

// Index loops mirror the matrix and per-channel formulas they implement.
#![allow(clippy::needless_range_loop)]

use glam::{DMat3, DVec3};
use seqavatar_core::camera::{Camera, Intrinsics};

use super::lanes::{LanePath, available_isas};
use super::project::{CameraParams, Splat2d};
use super::raster::{self, Compositing};
use super::*;
use crate::splat::covariance::covariance_from_scale_rotation;
use crate::splat::scene::SplitMix64;
use crate::splat::sh::{SH_C0, sh_basis};
use crate::splat::{
    ALPHA_THRESHOLD, GaussianBuffers, GaussianSet, ImageGradient, MAX_EXTENT_SIGMAS, RasterOptions,
    SplatError, sh_coefficient_count,
};

fn intrinsics(f: f64, width: u32, height: u32) -> Intrinsics {
    Intrinsics {
        fx: f,
        fy: f * 1.1,
        cx: f64::from(width) / 2.0 + 0.3,
        cy: f64::from(height) / 2.0 - 0.2,
    }
}

/// A 40 x 28 camera (3 x 2 tiles, the last ones partial) looking at the origin from `eye`.
fn small_camera(eye: DVec3) -> Camera {
    Camera::look_at(40, 28, intrinsics(40.0, 40, 28), eye, DVec3::ZERO, DVec3::Y)
}

/// Gaussians from scales and rotations, with degree-`degree` SH whose colour stays positive.
fn gaussians_from(
    means: Vec<f64>,
    scales: &[f64],
    rotations: &[f64],
    opacities: Vec<f64>,
    degree: u32,
    rng: &mut SplitMix64,
) -> GaussianBuffers<f64> {
    let n = opacities.len();
    let k = sh_coefficient_count(degree);
    let mut sh = Vec::with_capacity(n * k * 3);
    for _ in 0..n {
        for coefficient in 0..k {
            for _ in 0..3 {
                sh.push(if coefficient == 0 {
                    (rng.uniform(0.35, 0.85) - 0.5) / SH_C0
                } else {
                    rng.uniform(-0.06, 0.06)
                });
            }
        }
    }
    GaussianBuffers {
        means,
        covariances: covariance_from_scale_rotation(scales, rotations)
            .unwrap()
            .covariances,
        opacities,
        sh,
        sh_degree: degree,
    }
}

/// Eight overlapping Gaussians at distinct depths near the origin, plus one beyond the right
/// guard band whose box still reaches the image (exercises the clamped Jacobian).
fn gradient_scene() -> (GaussianBuffers<f64>, Vec<Camera>) {
    let mut rng = SplitMix64::new(7);
    let n = 8;
    let mut means = Vec::new();
    let mut scales = Vec::new();
    let mut rotations = Vec::new();
    let mut opacities = Vec::new();
    for i in 0..n {
        means.extend([
            rng.uniform(-0.35, 0.35),
            rng.uniform(-0.25, 0.25),
            -0.4 + 0.1 * i as f64 + rng.uniform(0.0, 0.02),
        ]);
        scales.extend([
            rng.uniform(0.08, 0.2),
            rng.uniform(0.05, 0.15),
            rng.uniform(0.03, 0.1),
        ]);
        let q: [f64; 4] = std::array::from_fn(|_| rng.normal());
        rotations.extend(q);
        opacities.push(rng.uniform(0.2, 0.6));
    }
    // Camera 0 looks from -z; x/z = 1.05 is beyond its band (x limit about 0.8).
    means.extend([3.2, 0.0, 0.0]);
    scales.extend([0.6, 0.5, 0.4]);
    rotations.extend([1.0, 0.1, 0.0, 0.0]);
    opacities.push(0.5);
    let gaussians = gaussians_from(means, &scales, &rotations, opacities, 3, &mut rng);
    let cameras = vec![
        small_camera(DVec3::new(0.2, -0.3, -3.0)),
        small_camera(DVec3::new(-2.5, 0.5, -1.8)),
    ];
    (gaussians, cameras)
}

/// A loss that uses every output: random weights on colour, alpha and depth.
struct Loss {
    colour: Vec<Vec<f64>>,
    alpha: Vec<Vec<f64>>,
    depth: Vec<Vec<f64>>,
}

impl Loss {
    fn new(cameras: &[Camera], seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed);
        let mut draw = |len: usize| (0..len).map(|_| rng.normal()).collect::<Vec<f64>>();
        let pixels: Vec<usize> = cameras
            .iter()
            .map(|c| (c.width * c.height) as usize)
            .collect();
        Self {
            colour: pixels.iter().map(|&p| draw(p * 3)).collect(),
            alpha: pixels.iter().map(|&p| draw(p)).collect(),
            depth: pixels
                .iter()
                .map(|&p| draw(p).iter().map(|v| 0.1 * v).collect())
                .collect(),
        }
    }

    fn value(&self, forward: &CpuForward<f64>) -> f64 {
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        forward
            .images
            .iter()
            .enumerate()
            .map(|(c, image)| {
                dot(&image.colour, &self.colour[c])
                    + dot(&image.alpha, &self.alpha[c])
                    + dot(&image.depth, &self.depth[c])
            })
            .sum()
    }

    fn upstream(&self) -> Vec<ImageGradient<'_, f64>> {
        (0..self.colour.len())
            .map(|c| ImageGradient {
                colour: &self.colour[c],
                alpha: Some(&self.alpha[c]),
                depth: Some(&self.depth[c]),
            })
            .collect()
    }
}

fn smooth_options() -> RasterOptions {
    RasterOptions {
        background: [0.2, 0.5, 0.9],
        smooth_cutoff: true,
    }
}

/// Checks `analytic` against central differences of `loss(values)` for every entry.
fn check_gradient(
    name: &str,
    values: &[f64],
    analytic: &[f64],
    step: f64,
    mut loss: impl FnMut(&[f64]) -> f64,
) {
    assert_eq!(values.len(), analytic.len(), "{name}");
    let scale = analytic.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    assert!(
        scale > 0.0,
        "{name}: all gradients are zero, the check would be vacuous"
    );
    let mut perturbed = values.to_vec();
    for i in 0..values.len() {
        perturbed[i] = values[i] + step;
        let plus = loss(&perturbed);
        perturbed[i] = values[i] - step;
        let minus = loss(&perturbed);
        perturbed[i] = values[i];
        let fd = (plus - minus) / (2.0 * step);
        let error = (fd - analytic[i]).abs();
        assert!(
            error <= 1e-6 * scale + 1e-7 * fd.abs().max(analytic[i].abs()) * 1e2,
            "{name}[{i}]: finite difference {fd}, analytic {}, scale {scale}",
            analytic[i]
        );
    }
}

#[test]
fn gradients_of_every_parameter_match_central_differences() {
    let (gaussians, cameras) = gradient_scene();
    let options = smooth_options();
    let loss = Loss::new(&cameras, 11);
    let forward_pass = forward(&gaussians.view(), &cameras, &options).unwrap();
    assert_eq!(
        forward_pass.diagnostics[0].visible, 9,
        "{:?}",
        forward_pass.diagnostics[0]
    );
    let grads = backward(&forward_pass, &gaussians.view(), &loss.upstream()).unwrap();
    assert_eq!(grads.non_finite_gradients, 0);

    let eval =
        |g: &GaussianBuffers<f64>| loss.value(&forward(&g.view(), &cameras, &options).unwrap());
    check_gradient("means", &gaussians.means, &grads.means, 1e-6, |v| {
        eval(&GaussianBuffers {
            means: v.to_vec(),
            ..gaussians.clone()
        })
    });
    check_gradient(
        "covariances",
        &gaussians.covariances,
        &grads.covariances,
        1e-7,
        |v| {
            eval(&GaussianBuffers {
                covariances: v.to_vec(),
                ..gaussians.clone()
            })
        },
    );
    check_gradient(
        "opacities",
        &gaussians.opacities,
        &grads.opacities,
        1e-6,
        |v| {
            eval(&GaussianBuffers {
                opacities: v.to_vec(),
                ..gaussians.clone()
            })
        },
    );
    check_gradient("sh", &gaussians.sh, &grads.sh, 1e-6, |v| {
        eval(&GaussianBuffers {
            sh: v.to_vec(),
            ..gaussians.clone()
        })
    });
    // The clamped Gaussian (index 8) is seen by camera 0 beyond the band: its gradient is
    // still checked above; here make sure it actually reached the rasteriser and mattered.
    assert!(grads.means[24..27].iter().any(|v| v.abs() > 1e-6));
}

#[test]
fn composite_gradients_match_central_differences_of_projected_values() {
    // Checks the rasteriser alone (gradients with respect to the 2D mean, conic, opacity,
    // colour and depth of each splat, the quantities behind the densification statistic).
    let (gaussians, cameras) = gradient_scene();
    let options = smooth_options();
    let loss = Loss::new(&cameras[..1], 5);
    let params = CameraParams::<f64>::new(&cameras[0]);
    let (splats, rects, _) = project_all(&params, &gaussians.view());
    let tiles = (params.tiles_x * params.tiles_y) as usize;
    let background = options.background;
    let render = |splats: &[Splat2d<f64>]| {
        let binning = raster::bin(splats, &rects, tiles, params.tiles_x).unwrap();
        let buffers = raster::forward(
            &raster::sort_splats(splats, &binning),
            None,
            &binning,
            Compositing {
                width: params.width,
                height: params.height,
                background,
                smooth: true,
            },
        );
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        dot(&buffers.colour, &loss.colour[0])
            + dot(&buffers.alpha, &loss.alpha[0])
            + dot(&buffers.depth, &loss.depth[0])
    };
    let binning = raster::bin(&splats, &rects, tiles, params.tiles_x).unwrap();
    let sorted = raster::sort_splats(&splats, &binning);
    let buffers = raster::forward(
        &sorted,
        None,
        &binning,
        Compositing {
            width: params.width,
            height: params.height,
            background,
            smooth: true,
        },
    );
    let upstream = Upstream {
        colour: &loss.colour[0],
        alpha: Some(&loss.alpha[0]),
        depth: Some(&loss.depth[0]),
    };
    let slots = raster::backward(
        &sorted,
        None,
        &binning,
        &buffers.pixels,
        &upstream,
        Compositing {
            width: params.width,
            height: params.height,
            background,
            smooth: true,
        },
    );
    let mut per_splat = vec![[0.0; 10]; splats.len()];
    for (position, &rank) in binning.tile_gaussians.iter().enumerate() {
        let g = binning.sorted[rank as usize] as usize;
        for (acc, v) in per_splat[g].iter_mut().zip(&slots[position]) {
            *acc += v;
        }
    }
    let flatten = |s: &Splat2d<f64>| {
        [
            s.mean[0],
            s.mean[1],
            s.conic[0],
            s.conic[1],
            s.conic[2],
            s.opacity,
            s.colour[0],
            s.colour[1],
            s.colour[2],
            s.depth,
        ]
    };
    let unflatten = |v: &[f64], original: &Splat2d<f64>| Splat2d {
        mean: [v[0], v[1]],
        conic: [v[2], v[3], v[4]],
        opacity: v[5],
        colour: [v[6], v[7], v[8]],
        depth: v[9],
        min_power: original.min_power,
        pixel_box: original.pixel_box,
        row_span: original.row_span,
    };
    let values: Vec<f64> = splats.iter().flat_map(flatten).collect();
    let analytic: Vec<f64> = per_splat.iter().flatten().copied().collect();
    check_gradient("splat", &values, &analytic, 1e-6, |v| {
        let perturbed: Vec<Splat2d<f64>> = v
            .chunks(10)
            .zip(&splats)
            .map(|(chunk, s)| unflatten(chunk, s))
            .collect();
        render(&perturbed)
    });
}

#[test]
fn gradients_are_summed_over_cameras_and_the_densification_norm_too() {
    let (gaussians, cameras) = gradient_scene();
    let options = smooth_options();
    let loss = Loss::new(&cameras, 3);
    let both = backward(
        &forward(&gaussians.view(), &cameras, &options).unwrap(),
        &gaussians.view(),
        &loss.upstream(),
    )
    .unwrap();
    let mut sum = SplatGradients::<f64>::zeros(gaussians.opacities.len(), 16);
    for c in 0..2 {
        let single = Loss {
            colour: vec![loss.colour[c].clone()],
            alpha: vec![loss.alpha[c].clone()],
            depth: vec![loss.depth[c].clone()],
        };
        let fwd = forward(&gaussians.view(), &cameras[c..=c], &options).unwrap();
        let g = backward(&fwd, &gaussians.view(), &single.upstream()).unwrap();
        for (a, b) in [
            (&mut sum.means, &g.means),
            (&mut sum.covariances, &g.covariances),
            (&mut sum.opacities, &g.opacities),
            (&mut sum.sh, &g.sh),
            (&mut sum.mean_2d_norm, &g.mean_2d_norm),
        ] {
            for (x, y) in a.iter_mut().zip(b) {
                *x += y;
            }
        }
    }
    let close = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= 1e-12 * (1.0 + x.abs()))
    };
    assert!(close(&both.means, &sum.means));
    assert!(close(&both.covariances, &sum.covariances));
    assert!(close(&both.opacities, &sum.opacities));
    assert!(close(&both.sh, &sum.sh));
    assert!(close(&both.mean_2d_norm, &sum.mean_2d_norm));
    assert!(both.mean_2d_norm.iter().take(8).all(|&v| v > 0.0));
}

/// An independent per-pixel renderer written straight from SPLATTING.md in f64 with glam:
/// no tiles, no boxes, every non-culled Gaussian evaluated at every pixel.
fn reference_render(
    g: &GaussianBuffers<f64>,
    camera: &Camera,
    background: [f64; 3],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    struct Projected {
        depth: f64,
        index: usize,
        mean: [f64; 2],
        conic: [f64; 3],
        opacity: f64,
        colour: [f64; 3],
    }
    let Intrinsics { fx, fy, cx, cy } = camera.intrinsics;
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let k = sh_coefficient_count(g.sh_degree);
    let mut projected = Vec::new();
    for i in 0..g.opacities.len() {
        let mean = DVec3::from_slice(&g.means[3 * i..]);
        let c = &g.covariances[6 * i..6 * i + 6];
        let sigma = DMat3::from_cols_array(&[c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5]]);
        let p = camera.world_to_camera(mean);
        if p.z < 0.01 || p.z > 1e10 {
            continue;
        }
        let w_cam = camera.rotation * sigma * camera.rotation.transpose();
        let tx = p.z * (p.x / p.z).clamp(-(cx / fx + 0.15 * w / fx), (w - cx) / fx + 0.15 * w / fx);
        let ty = p.z * (p.y / p.z).clamp(-(cy / fy + 0.15 * h / fy), (h - cy) / fy + 0.15 * h / fy);
        // Rows of J as the columns of a glam matrix transpose: J is 2x3, embed in 3x3.
        let j = DMat3::from_cols(
            DVec3::new(fx / p.z, 0.0, 0.0),
            DVec3::new(0.0, fy / p.z, 0.0),
            DVec3::new(-fx * tx / (p.z * p.z), -fy * ty / (p.z * p.z), 0.0),
        );
        let s2 = j * w_cam * j.transpose();
        let (a, b, cc) = (s2.col(0).x + 0.3, s2.col(1).x, s2.col(1).y + 0.3);
        let det = a * cc - b * b;
        if det <= 0.0 {
            continue;
        }
        let opacity = g.opacities[i];
        if opacity < 1.0 / 255.0 {
            continue;
        }
        let dir = (mean - camera.center()).normalize();
        let basis = sh_basis(dir.to_array(), g.sh_degree, None);
        let sh = &g.sh[3 * k * i..3 * k * (i + 1)];
        let colour: [f64; 3] = std::array::from_fn(|ch| {
            (0..k)
                .map(|kk| sh[3 * kk + ch] * basis[kk])
                .sum::<f64>()
                .max(-0.5)
                + 0.5
        });
        projected.push(Projected {
            depth: p.z,
            index: i,
            mean: [fx * p.x / p.z + cx, fy * p.y / p.z + cy],
            conic: [cc / det, -b / det, a / det],
            opacity,
            colour,
        });
    }
    projected.sort_by(|x, y| {
        (x.depth as f32)
            .total_cmp(&(y.depth as f32))
            .then(x.index.cmp(&y.index))
    });
    let pixels = (camera.width * camera.height) as usize;
    let (mut colour, mut alpha, mut depth) =
        (vec![0.0; pixels * 3], vec![0.0; pixels], vec![0.0; pixels]);
    for row in 0..camera.height {
        for col in 0..camera.width {
            let q = [f64::from(col) + 0.5, f64::from(row) + 0.5];
            let mut t = 1.0;
            let (mut c, mut d) = ([0.0; 3], 0.0);
            for s in &projected {
                let (dx, dy) = (s.mean[0] - q[0], s.mean[1] - q[1]);
                let power =
                    -0.5 * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) - s.conic[1] * dx * dy;
                if power > 0.0 {
                    continue;
                }
                let a = (s.opacity * power.exp()).min(0.99);
                if a < 1.0 / 255.0 {
                    continue;
                }
                let t_next = t * (1.0 - a);
                if t_next <= 1e-4 {
                    break;
                }
                for ch in 0..3 {
                    c[ch] += a * t * s.colour[ch];
                }
                d += a * t * s.depth;
                t = t_next;
            }
            let index = (row * camera.width + col) as usize;
            for ch in 0..3 {
                colour[3 * index + ch] = c[ch] + t * background[ch];
            }
            alpha[index] = 1.0 - t;
            depth[index] = d;
        }
    }
    (colour, alpha, depth)
}

fn max_abs_difference<S: Scalar>(a: &[S], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .fold(0.0, |m, (x, y)| m.max((x.to_f64() - y).abs()))
}

/// A denser scene for forward checks: 300 Gaussians, some saturating pixels (early stop).
fn dense_scene(width: u32, height: u32) -> (GaussianBuffers<f64>, Camera) {
    let mut rng = SplitMix64::new(99);
    let n = 300;
    let (mut means, mut scales, mut rotations, mut opacities) = (vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        means.extend([
            rng.uniform(-1.2, 1.2),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        ]);
        scales.extend((0..3).map(|_| rng.uniform(0.01, 0.25)));
        rotations.extend((0..4).map(|_| rng.normal()));
        opacities.push(rng.uniform(0.0, 1.0));
    }
    // Below 1/255: culled by opacity.
    opacities[0] = 0.002;
    let gaussians = gaussians_from(means, &scales, &rotations, opacities, 2, &mut rng);
    let camera = Camera::look_at(
        width,
        height,
        intrinsics(f64::from(width), width, height),
        DVec3::new(0.4, -0.6, -3.0),
        DVec3::ZERO,
        DVec3::Y,
    );
    (gaussians, camera)
}

#[test]
fn forward_matches_an_independent_per_pixel_renderer() {
    let (gaussians, camera) = dense_scene(70, 45);
    let background = [0.1, 0.2, 0.3];
    let options = RasterOptions {
        background,
        smooth_cutoff: false,
    };
    let (colour, alpha, depth) = reference_render(&gaussians, &camera, background);
    let f64_pass = forward(&gaussians.view(), std::slice::from_ref(&camera), &options).unwrap();
    let image = &f64_pass.images[0];
    assert!(max_abs_difference(&image.colour, &colour) < 1e-12);
    assert!(max_abs_difference(&image.alpha, &alpha) < 1e-12);
    assert!(max_abs_difference(&image.depth, &depth) < 1e-11);
    // Some pixels saturate, so early termination is exercised.
    assert!(alpha.iter().any(|&a| a > 0.999), "scene does not saturate");
    let single = gaussians.convert::<f32>();
    let f32_pass = forward(&single.view(), std::slice::from_ref(&camera), &options).unwrap();
    let image = &f32_pass.images[0];
    assert!(max_abs_difference(&image.colour, &colour) < 1e-4);
    assert!(max_abs_difference(&image.alpha, &alpha) < 1e-4);
    assert!(max_abs_difference(&image.depth, &depth) < 1e-3);
    let diag = f64_pass.diagnostics[0];
    assert_eq!(diag.gaussians, 300);
    assert_eq!(
        diag.visible
            + diag.culled_opacity
            + diag.culled_offscreen
            + diag.culled_depth
            + diag.culled_covariance,
        300
    );
    assert!(diag.culled_opacity > 0 && diag.visible > 200, "{diag:?}");
}

/// [`dense_scene`]'s cloud (2.4 units across) at `unit` metres per unit, seen from about 31
/// units through a ten times longer lens: the same image at every unit, and every Gaussian
/// beyond the near plane down to a cloud 1 mm across (then 13 mm from the camera).
fn dense_scene_at(unit: f64) -> (GaussianBuffers<f64>, Camera) {
    let (mut gaussians, camera) = dense_scene(70, 45);
    gaussians.means.iter_mut().for_each(|value| *value *= unit);
    gaussians
        .covariances
        .iter_mut()
        .for_each(|value| *value *= unit * unit);
    let mut lens = camera.intrinsics;
    (lens.fx, lens.fy) = (lens.fx * 10.0, lens.fy * 10.0);
    let eye = DVec3::new(0.4, -0.6, -3.0) * 10.0 * unit;
    let camera = Camera::look_at(70, 45, lens, eye, DVec3::ZERO, DVec3::Y);
    (gaussians, camera)
}

/// Numeric extremes of scale: a cloud 1 mm across (Gaussians of 4 to 100 um, covariances
/// down to 1e-11 m^2) renders in f32 as the same cloud 2.4 m across does, every Gaussian
/// drawn, and its gradients are the metre cloud's scaled by the unit (1/unit for means,
/// 1/unit^2 for covariances, the same for opacities and colours): nothing in projection,
/// compositing or backward depends on an absolute length but the near and far planes.
#[test]
fn a_millimetre_wide_scene_renders_and_differentiates_as_a_metre_wide_one() {
    let millimetre = 1e-3 / 2.4;
    let pass = |unit: f64| {
        let (gaussians, camera) = dense_scene_at(unit);
        let single = gaussians.convert::<f32>();
        let fwd = forward(
            &single.view(),
            std::slice::from_ref(&camera),
            &RasterOptions::default(),
        )
        .unwrap();
        let ones = vec![1.0_f32; 70 * 45 * 3];
        let upstream = ImageGradient {
            colour: &ones,
            alpha: Some(&ones[..70 * 45]),
            depth: None,
        };
        let grads = backward(&fwd, &single.view(), &[upstream]).unwrap();
        (fwd, grads)
    };
    let (metre, metre_grads) = pass(1.0);
    let (small, small_grads) = pass(millimetre);
    let diag = small.diagnostics[0];
    assert_eq!(diag.culled_depth, 0, "{diag:?}");
    assert!(diag.visible > 200, "{diag:?}");
    assert_eq!(diag, metre.diagnostics[0]);
    // `small` against `metre` times `scale`, relative to the largest value.
    let check = |what: &str, small: &[f32], metre: &[f32], scale: f64, tolerance: f64| {
        assert_all_finite(what, small);
        let expected: Vec<f64> = metre.iter().map(|&v| f64::from(v) * scale).collect();
        let largest = expected.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        let error = max_abs_difference(small, &expected) / largest;
        assert!(error < tolerance, "{what}: relative error {error:e}");
    };
    let (image, metre_image) = (&small.images[0], &metre.images[0]);
    check("colour", &image.colour, &metre_image.colour, 1.0, 1e-4);
    check("alpha", &image.alpha, &metre_image.alpha, 1.0, 1e-4);
    check("depth", &image.depth, &metre_image.depth, millimetre, 1e-4);
    let (g, m) = (&small_grads, &metre_grads);
    check("d means", &g.means, &m.means, 1.0 / millimetre, 1e-3);
    let per_area = 1.0 / (millimetre * millimetre);
    check(
        "d covariances",
        &g.covariances,
        &m.covariances,
        per_area,
        1e-3,
    );
    check("d opacities", &g.opacities, &m.opacities, 1.0, 1e-3);
    check("d sh", &g.sh, &m.sh, 1.0, 1e-3);
}

#[test]
fn repeated_calls_are_bitwise_identical() {
    let (gaussians, camera) = dense_scene(50, 40);
    let single = gaussians.convert::<f32>();
    let cameras = [camera];
    let upstream: Vec<f32> = (0..50 * 40 * 3)
        .map(|i| ((i * 7919) % 13) as f32 - 6.0)
        .collect();
    let run = || {
        let fwd = forward(&single.view(), &cameras, &RasterOptions::default()).unwrap();
        let grads = backward(
            &fwd,
            &single.view(),
            &[ImageGradient {
                colour: &upstream,
                alpha: None,
                depth: None,
            }],
        )
        .unwrap();
        (fwd.images, grads)
    };
    assert_eq!(run(), run());
}

fn assert_all_finite<S: Scalar>(what: &str, values: &[S]) {
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        panic!("{what}[{i}] = {}", values[i]);
    }
}

/// Runs forward and backward in f32 with a unit upstream gradient; checks nothing
/// non-finite comes out and returns the first camera's diagnostics and the gradients.
fn run_f32(
    gaussians: &GaussianBuffers<f32>,
    camera: &Camera,
) -> (CpuForward<f32>, SplatGradients<f32>) {
    let cameras = std::slice::from_ref(camera);
    let fwd = forward(&gaussians.view(), cameras, &RasterOptions::default()).unwrap();
    let pixels = (camera.width * camera.height) as usize;
    let ones = vec![1.0_f32; pixels * 3];
    let ones_alpha = vec![1.0_f32; pixels];
    let grads = backward(
        &fwd,
        &gaussians.view(),
        &[ImageGradient {
            colour: &ones,
            alpha: Some(&ones_alpha),
            depth: Some(&ones_alpha),
        }],
    )
    .unwrap();
    let image = &fwd.images[0];
    assert_all_finite("colour", &image.colour);
    assert_all_finite("alpha", &image.alpha);
    assert_all_finite("depth", &image.depth);
    assert_all_finite("d means", &grads.means);
    assert_all_finite("d covariances", &grads.covariances);
    assert_all_finite("d opacities", &grads.opacities);
    assert_all_finite("d sh", &grads.sh);
    assert_all_finite("d mean 2d", &grads.mean_2d_norm);
    (fwd, grads)
}

/// Degree-0 Gaussians (grey) from means, isotropic scales and opacities.
fn simple(means: Vec<f64>, scales: Vec<f64>, opacities: Vec<f64>) -> GaussianBuffers<f32> {
    let n = opacities.len();
    let scales3: Vec<f64> = scales.iter().flat_map(|&s| [s, s, s]).collect();
    let rotations: Vec<f64> = (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
    GaussianBuffers {
        means,
        covariances: covariance_from_scale_rotation(&scales3, &rotations)
            .unwrap()
            .covariances,
        opacities,
        sh: vec![0.3; n * 3],
        sh_degree: 0,
    }
    .convert()
}

fn front_camera(width: u32, height: u32) -> Camera {
    Camera::look_at(
        width,
        height,
        intrinsics(f64::from(width.max(height)), width, height),
        DVec3::new(0.0, 0.0, -2.0),
        DVec3::ZERO,
        DVec3::Y,
    )
}

#[test]
fn extreme_scales_and_opacities_stay_finite() {
    let camera = front_camera(64, 48);
    let gaussians = simple(
        vec![
            0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1, 0.5, -0.2, 0.0, 0.2, 0.2, 0.1, -0.3,
        ],
        vec![1e-7, 1e3, 0.1, 0.05, 0.2],
        vec![0.5, 0.5, 1.0 / 255.0, 0.9999, 0.9999],
    );
    let (fwd, grads) = run_f32(&gaussians, &camera);
    let diag = fwd.diagnostics[0];
    // The 1e3 Gaussian covers the whole image; the 1e-7 one is a 0.3 px^2 dot.
    assert!(diag.visible >= 4, "{diag:?}");
    assert!(
        fwd.images[0].alpha.iter().all(|&a| a > 0.3),
        "the huge Gaussian covers everything"
    );
    assert!(grads.opacities[3].abs() > 0.0);
}

#[test]
fn gaussians_behind_on_the_near_plane_and_off_screen_are_culled_and_counted() {
    let camera = front_camera(32, 32);
    // Camera at z = -2 looking down +z: camera z = world z + 2.
    let gaussians = simple(
        vec![
            0.0, 0.0, -3.0, // behind
            0.0, 0.0, -1.9901, // in front of the camera, just nearer than the near plane
            0.0, 0.0, -1.9899, // just beyond the near plane: kept, covers the image
            50.0, 0.0, 0.0, // far off-screen
            0.0, 0.0, 1e12, // beyond the far plane
            0.0, 0.0, 0.0, // visible
        ],
        vec![0.1; 6],
        vec![0.5; 6],
    );
    let (fwd, grads) = run_f32(&gaussians, &camera);
    let diag = fwd.diagnostics[0];
    assert_eq!(diag.culled_depth, 3, "{diag:?}");
    assert_eq!(diag.culled_offscreen, 1, "{diag:?}");
    assert_eq!(diag.visible, 2, "{diag:?}");
    assert!(
        fwd.images[0].alpha.iter().all(|&a| a > 0.4),
        "the near Gaussian covers the image"
    );
    for culled in [0, 1, 3, 4] {
        assert_eq!(&grads.means[3 * culled..3 * culled + 3], &[0.0; 3]);
        assert_eq!(grads.opacities[culled], 0.0);
    }
}

#[test]
fn grazing_views_of_flat_gaussians_stay_finite() {
    // Flat discs seen exactly edge-on: the 3D covariance is singular along the view
    // direction and the 2D one is a line; the blur keeps it invertible.
    let camera = front_camera(48, 48);
    let scales = [0.3, 0.3, 0.0, 0.3, 0.0, 0.3, 1e-7, 0.2, 0.2];
    let rotations = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.7, 0.7, 0.0, 0.0];
    let mut rng = SplitMix64::new(1);
    let gaussians = gaussians_from(
        vec![0.0, 0.0, 0.0, 0.1, 0.0, 0.3, -0.1, 0.1, 0.1],
        &scales,
        &rotations,
        vec![0.8, 0.8, 0.8],
        1,
        &mut rng,
    )
    .convert::<f32>();
    let (fwd, _) = run_f32(&gaussians, &camera);
    assert_eq!(fwd.diagnostics[0].visible, 3);
    // Also the mean lying far out at a grazing angle to the optical axis (x/z = 1e4).
    let far_side = simple(vec![2e4, 0.0, 0.0], vec![1e3], vec![0.9]);
    run_f32(&far_side, &camera);
}

#[test]
fn ten_thousand_gaussians_on_one_pixel_terminate_early() {
    let camera = front_camera(16, 16);
    let n = 10_000;
    // All on the same point with the same depth: ties are broken by index.
    let gaussians = simple(
        (0..n).flat_map(|_| [0.0, 0.0, 0.0]).collect(),
        vec![1e-4; n],
        vec![0.3; n],
    );
    let (fwd, grads) = run_f32(&gaussians, &camera);
    let image = &fwd.images[0];
    let centre = fwd.states[0].binning.tile_gaussians.len();
    assert_eq!(centre, n, "each Gaussian touches one tile");
    let max_alpha = image.alpha.iter().fold(0.0_f32, |m, &a| m.max(a));
    assert!(max_alpha > 0.999, "{max_alpha}");
    // Only the Gaussians before each pixel's stop get gradients: about 35 at the pixel
    // nearest the centre (alpha about 0.24), more at the faint edge of the box, and never
    // more than the ln(1e-4) / ln(1 - 1/255) = 2344 an alpha of 1/255 allows.
    let touched = grads.opacities.iter().filter(|&&g| g != 0.0).count();
    assert!((30..=2344).contains(&touched), "{touched}");
    assert!(grads.opacities[n - 1] == 0.0);
}

#[test]
fn zero_gaussians_render_the_background() {
    let camera = front_camera(20, 10);
    let empty = GaussianBuffers::<f32> {
        means: vec![],
        covariances: vec![],
        opacities: vec![],
        sh: vec![],
        sh_degree: 3,
    };
    let options = RasterOptions {
        background: [0.25, 0.5, 1.0],
        smooth_cutoff: false,
    };
    let fwd = forward(&empty.view(), std::slice::from_ref(&camera), &options).unwrap();
    for pixel in fwd.images[0].colour.chunks(3) {
        assert_eq!(pixel, &[0.25, 0.5, 1.0]);
    }
    assert!(fwd.images[0].alpha.iter().all(|&a| a == 0.0));
    let zeros = vec![1.0; 200 * 3];
    let grads = backward(
        &fwd,
        &empty.view(),
        &[ImageGradient {
            colour: &zeros,
            alpha: None,
            depth: None,
        }],
    )
    .unwrap();
    assert!(grads.means.is_empty() && grads.sh.is_empty());
}

#[test]
fn one_pixel_and_very_large_images() {
    let tiny = front_camera(1, 1);
    let gaussians = simple(
        vec![0.0, 0.0, 0.0, 0.01, 0.0, 0.5],
        vec![0.05, 0.2],
        vec![0.7, 0.5],
    );
    let (fwd, grads) = run_f32(&gaussians, &tiny);
    assert!(fwd.images[0].alpha[0] > 0.5);
    assert!(grads.opacities.iter().all(|&g| g != 0.0));

    let large = front_camera(4096, 3000);
    let (fwd, _) = run_f32(&gaussians, &large);
    let image = &fwd.images[0];
    assert!(image.alpha[0] == 0.0, "corner is background");
    let centre = 1500 * 4096 + 2048;
    assert!(image.alpha[centre] > 0.5);
}

#[test]
fn non_finite_inputs_are_culled_counted_and_get_zero_gradients() {
    let camera = front_camera(32, 32);
    let mut gaussians = simple(
        (0..6).flat_map(|i| [0.05 * i as f64, 0.0, 0.0]).collect(),
        vec![0.1; 6],
        vec![0.5; 6],
    );
    gaussians.means[0] = f32::NAN;
    gaussians.covariances[6 + 1] = f32::INFINITY;
    gaussians.opacities[2] = f32::NAN;
    gaussians.sh[3 * 3 + 2] = f32::NEG_INFINITY;
    // Finite but overflowing once projected (x * fx overflows f32).
    gaussians.means[3 * 4] = 3e37;
    let (fwd, grads) = run_f32(&gaussians, &camera);
    let diag = fwd.diagnostics[0];
    assert_eq!(diag.non_finite_inputs, 4, "{diag:?}");
    assert_eq!(
        diag.non_finite_projections + diag.culled_offscreen,
        1,
        "{diag:?}"
    );
    assert_eq!(diag.visible, 1);
    assert!(grads.opacities[..5].iter().all(|&g| g == 0.0));
    assert!(grads.opacities[5] != 0.0);
}

#[test]
fn structurally_wrong_input_is_an_error() {
    let camera = front_camera(8, 8);
    let g = simple(vec![0.0; 3], vec![0.1], vec![0.5]);
    let cameras = std::slice::from_ref(&camera);
    let options = RasterOptions::default();
    let short = GaussianSet {
        means: &g.means[..2],
        ..g.view()
    };
    assert!(matches!(
        forward(&short, cameras, &options),
        Err(SplatError::Length {
            field: "means",
            expected: 3,
            actual: 2
        })
    ));
    let degree = GaussianSet {
        sh_degree: 4,
        ..g.view()
    };
    assert!(matches!(
        forward(&degree, cameras, &options),
        Err(SplatError::ShDegree { degree: 4 })
    ));
    assert!(matches!(
        forward(&g.view(), &[], &options),
        Err(SplatError::NoCameras)
    ));
    let mut bad = camera.clone();
    bad.intrinsics.fx = -1.0;
    assert!(matches!(
        forward(&g.view(), &[camera.clone(), bad], &options),
        Err(SplatError::Camera { index: 1, .. })
    ));
    let nan_background = RasterOptions {
        background: [0.0, f64::NAN, 0.0],
        smooth_cutoff: false,
    };
    assert!(matches!(
        forward(&g.view(), cameras, &nan_background),
        Err(SplatError::Background { .. })
    ));

    let fwd = forward(&g.view(), cameras, &options).unwrap();
    let mut colour = vec![0.0_f32; 8 * 8 * 3];
    assert!(matches!(
        backward(&fwd, &g.view(), &[]),
        Err(SplatError::GradientCount {
            expected: 1,
            actual: 0
        })
    ));
    let short_grad = ImageGradient {
        colour: &colour[..5],
        alpha: None,
        depth: None,
    };
    assert!(matches!(
        backward(&fwd, &g.view(), &[short_grad]),
        Err(SplatError::Length {
            field: "colour",
            ..
        })
    ));
    colour[17] = f32::NAN;
    let nan_grad = ImageGradient {
        colour: &colour,
        alpha: None,
        depth: None,
    };
    assert!(matches!(
        backward(&fwd, &g.view(), &[nan_grad]),
        Err(SplatError::NonFiniteGradient {
            camera: 0,
            field: "colour",
            index: 17
        })
    ));
    let two = simple(vec![0.0; 6], vec![0.1; 2], vec![0.5; 2]);
    let fine = ImageGradient {
        colour: &colour[..0],
        alpha: None,
        depth: None,
    };
    assert!(matches!(
        backward(&fwd, &two.view(), &[fine]),
        Err(SplatError::GaussiansChanged { .. })
    ));
}

#[test]
fn extent_constants_agree_with_the_alpha_threshold() {
    // The box (extent e sigma, e <= 3.33) holds every pixel whose alpha can reach 1/255:
    // opacity * exp(-e^2 / 2) = 1/255 at e = sqrt(2 ln(255 opacity)) <= sqrt(2 ln 255).
    let full = (2.0 * (255.0_f64).ln()).sqrt();
    assert!(full < MAX_EXTENT_SIGMAS);
    assert!((1.0 * (-0.5 * full * full).exp() - ALPHA_THRESHOLD).abs() < 1e-15);
}

/// A scene of awkward cases for the lane path, seen by [`front_camera`] (camera `z` = world
/// `z + 2`): 250 random anisotropic Gaussians (scales from 0.1 mm to 0.5 m) spilling past
/// every image edge, plus one just beyond the near plane (it covers the image), a huge one
/// (covering everything), a sub-pixel one, thin needles crossing tile borders, one far
/// off-screen, one behind the camera and a stack of opaque ones saturating pixels.
fn awkward_scene(width: u32, height: u32) -> (GaussianBuffers<f64>, Camera) {
    let mut rng = SplitMix64::new(17);
    let (mut means, mut scales, mut rotations, mut opacities) = (vec![], vec![], vec![], vec![]);
    let mut push = |mean: [f64; 3], scale: [f64; 3], opacity: f64, rng: &mut SplitMix64| {
        means.extend(mean);
        scales.extend(scale);
        rotations.extend((0..4).map(|_| rng.normal()));
        opacities.push(opacity);
    };
    for _ in 0..250 {
        let mean = [
            rng.uniform(-1.6, 1.6),
            rng.uniform(-1.2, 1.2),
            rng.uniform(-1.0, 1.0),
        ];
        let scale = [0; 3].map(|_| (rng.uniform(1e-4_f64.ln(), 0.5_f64.ln())).exp());
        let opacity = rng.uniform(0.0, 1.0);
        push(mean, scale, opacity, &mut rng);
    }
    push([0.0, 0.0, -1.9899], [0.01; 3], 0.5, &mut rng); // near plane
    push([0.1, -0.1, 0.5], [1e3; 3], 0.3, &mut rng); // huge
    push([0.2, 0.1, -0.5], [1e-7; 3], 0.9, &mut rng); // sub-pixel
    push([-0.3, 0.05, 0.1], [0.8, 1e-4, 1e-4], 0.8, &mut rng); // needles
    push([0.25, -0.2, 0.2], [1e-4, 0.6, 1e-4], 0.8, &mut rng);
    push([50.0, 0.0, 0.0], [0.1; 3], 0.5, &mut rng); // far off-screen
    push([0.0, 0.0, -3.0], [0.1; 3], 0.5, &mut rng); // behind
    for k in 0..6 {
        push(
            [0.05, 0.05, -0.5 + 0.01 * f64::from(k)],
            [0.2; 3],
            0.99,
            &mut rng,
        );
    }
    let gaussians = gaussians_from(means, &scales, &rotations, opacities, 1, &mut rng);
    (gaussians, front_camera(width, height))
}

/// The `f32` lane path (`lanes.rs`) on every instruction set this CPU has against the
/// generic path run in `f32` on the same binned splats: the instruction sets agree bit for
/// bit; against the generic path, images to `f32` rounding (its `exp` differs by at most 2
/// ulp), the same contributor counts, and every intersection's gradient, with and without
/// the smooth cutoff, with and without upstream alpha and depth gradients (the lane walk is
/// specialised for each), on images with partial tiles and saturated pixels: a dense scene
/// and [`awkward_scene`].
#[test]
fn lane_path_matches_the_generic_f32_path() {
    let (width, height) = (70, 45);
    let (dense, dense_camera) = dense_scene(width, height);
    let (awkward, awkward_camera) = awkward_scene(width, height);
    for (scene, (gaussians, camera)) in [
        ("dense", (dense, dense_camera)),
        ("awkward", (awkward, awkward_camera)),
    ] {
        compare_lane_path_with_generic(scene, &gaussians, &camera);
    }
}

fn compare_lane_path_with_generic(scene: &str, gaussians: &GaussianBuffers<f64>, camera: &Camera) {
    let (width, height) = (camera.width, camera.height);
    let single = gaussians.convert::<f32>();
    let view = single.view();
    let params = CameraParams::<f32>::new(camera);
    let (splats, rects, _) = project_all(&params, &view);
    let tiles = (params.tiles_x * params.tiles_y) as usize;
    let binning = raster::bin(&splats, &rects, tiles, params.tiles_x).unwrap();
    let sorted = raster::sort_splats(&splats, &binning);
    let pixels = (width * height) as usize;
    let mut rng = SplitMix64::new(3);
    let mut normals = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.normal() as f32).collect() };
    let (d_colour, d_alpha, d_depth) = (normals(3 * pixels), normals(pixels), normals(pixels));
    let background = [0.1, 0.2, 0.3];
    let variants = [(true, true, true), (false, true, true)]
        .into_iter()
        .chain([(false, false), (false, true), (true, false)].map(|(a, d)| (false, a, d)));
    for (smooth, with_alpha, with_depth) in variants {
        let upstream = Upstream {
            colour: &d_colour,
            alpha: with_alpha.then_some(d_alpha.as_slice()),
            depth: with_depth.then_some(d_depth.as_slice()),
        };
        let run = |fast: Option<LanePath<'_>>| {
            let buffers = raster::forward(
                &sorted,
                fast,
                &binning,
                Compositing {
                    width,
                    height,
                    background,
                    smooth,
                },
            );
            let slots = raster::backward(
                &sorted,
                fast,
                &binning,
                &buffers.pixels,
                &upstream,
                Compositing {
                    width,
                    height,
                    background,
                    smooth,
                },
            );
            (buffers, slots)
        };
        let (generic, generic_slots) = run(None);
        let isas = available_isas();
        let (lanes, lane_slots) = run(Some(LanePath {
            splats: &sorted,
            isa: isas[0],
        }));
        let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        for &isa in &isas[1..] {
            let (other, other_slots) = run(Some(LanePath {
                splats: &sorted,
                isa,
            }));
            let what = format!("{scene} {isa:?} vs {:?} smooth {smooth}", isas[0]);
            assert_eq!(bits(&other.colour), bits(&lanes.colour), "{what}");
            assert_eq!(bits(&other.alpha), bits(&lanes.alpha), "{what}");
            assert_eq!(bits(&other.depth), bits(&lanes.depth), "{what}");
            assert_eq!(
                other.pixels.contributors, lanes.pixels.contributors,
                "{what}"
            );
            let flat = |slots: &[[f32; 10]]| bits(slots.as_flattened());
            assert_eq!(flat(&other_slots), flat(&lane_slots), "{what}");
        }
        let close = |what: &str, a: &[f32], b: &[f32], tolerance: f32| {
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!(
                    (x - y).abs() <= tolerance,
                    "{scene} {what}[{i}] smooth {smooth}: {x} vs {y}"
                );
            }
        };
        close("colour", &lanes.colour, &generic.colour, 2e-6);
        close("alpha", &lanes.alpha, &generic.alpha, 2e-6);
        close("depth", &lanes.depth, &generic.depth, 2e-5);
        close(
            "transmittance",
            &lanes.pixels.final_transmittance,
            &generic.pixels.final_transmittance,
            2e-6,
        );
        assert_eq!(lanes.pixels.contributors, generic.pixels.contributors);
        assert!(
            generic.alpha.iter().any(|&a| a > 0.999),
            "{scene}: no saturation"
        );
        assert_eq!(lane_slots.len(), generic_slots.len());
        for k in 0..10 {
            let scale = generic_slots
                .iter()
                .fold(0.0_f32, |m, slot| m.max(slot[k].abs()));
            if k == 9 && !with_depth {
                // No depth gradient upstream: none downstream either.
                assert_eq!(scale, 0.0);
                assert!(lane_slots.iter().all(|slot| slot[9] == 0.0));
                continue;
            }
            assert!(scale > 0.0, "{scene}: component {k} never has a gradient");
            for (i, (a, b)) in lane_slots.iter().zip(&generic_slots).enumerate() {
                assert!(
                    (a[k] - b[k]).abs() <= 2e-5 * scale,
                    "{scene} slot {i} component {k} smooth {smooth} alpha {with_alpha} depth \
                     {with_depth}: {} vs {} (scale {scale})",
                    a[k],
                    b[k]
                );
            }
        }
    }
}
