//! Gaussian skinning: canonical (big-pose) Gaussians after the non-rigid offsets to world
//! space, and its exact backward.
//!
//! Per Gaussian, following docs/method.md ("Skinning"):
//! - `scale = clamp(exp(log_scale) + d_scale, min, max)` (linear space; the clamp keeps it
//!   positive and bounded, its gradient is zero where it is active);
//! - `rot = d_rot (x) rot_canonical` (Hamilton product, `[w, x, y, z]`), normalised inside the
//!   rotation matrix; `Sigma' = R diag(scale^2) R^T`;
//! - skinning weights `w = softmax(log(w_template[nearest] + 1e-9) + offset)`;
//! - blended transforms `B = sum_k w_k G_k^big`, `A = sum_k w_k G_k^target` (3 x 4, the target
//!   ones already include the global `R(Rh), Th`), and
//!   `x_o = A_lin (B_lin^-1 (x' - B_t) + offset[nearest]) + A_t` where the per-vertex offset
//!   is `-pose_blend(big)[v] + shape[v] + pose_blend(target)[v]`;
//! - `Sigma_o = M Sigma' M^T` with `M = A_lin B_lin^-1`.
//!
//! Transforms are row-major 3 x 4 `[r00 r01 r02 t0 r10 ... t2]`. Covariances are the upper
//! triangle `(xx, xy, xz, yy, yz, zz)`; as in the splatting contract, the gradient of an
//! off-diagonal entry counts both `(i, j)` and `(j, i)`.

use glam::{DMat3, DQuat, DVec3};
use rayon::prelude::*;
use seqavatar_core::rotation::{quat_is_degenerate, quat_wxyz_to_matrix};

/// Added inside the logarithm of template weights (docs/method.md; the reference's value).
pub const WEIGHT_LOG_EPS: f64 = 1e-9;

/// Per-frame skinning data shared by all Gaussians.
pub struct SkinningFrame<'a> {
    pub joint_count: usize,
    /// `J` big-pose (canonical) joint transforms, row-major 3 x 4.
    pub canonical_joints: &'a [[f64; 12]],
    /// `J` target joint transforms including the global rotation and translation.
    pub target_joints: &'a [[f64; 12]],
    /// Template skinning weights, `V x J`.
    pub template_weights: &'a [f64],
    /// Per-template-vertex offset added in rest pose, `V x 3`.
    pub vertex_offsets: &'a [f64],
    /// Bounds of the linear scale after the non-rigid offset.
    pub scale_min: f64,
    pub scale_max: f64,
}

/// Per-Gaussian inputs of the skinning (all flat, row-major).
pub struct GaussianParams<'a> {
    /// Canonical centres after the non-rigid offset, `N x 3`.
    pub positions: &'a [f64],
    pub log_scales: &'a [f64],
    /// Non-rigid scale offsets, `N x 3` (linear space).
    pub d_scales: &'a [f64],
    /// Canonical rotations, `N x 4`.
    pub rotations: &'a [f64],
    /// Non-rigid rotation offsets, `N x 4` (`[1, 0, 0, 0]` is none).
    pub d_rotations: &'a [f64],
    /// Skinning-weight logit offsets, `N x J`; `None` means zero.
    pub weight_offsets: Option<&'a [f64]>,
    /// Nearest template vertex of each (post-non-rigid) centre, `N`.
    pub nearest: &'a [u32],
}

/// Skinned Gaussians in world space.
#[derive(Clone, Debug, PartialEq)]
pub struct Skinned {
    pub positions: Vec<f64>,
    pub covariances: Vec<f64>,
}

/// Gradients of the skinning with respect to every differentiable input.
#[derive(Clone, Debug, PartialEq)]
pub struct SkinningGrads {
    pub positions: Vec<f64>,
    pub log_scales: Vec<f64>,
    pub d_scales: Vec<f64>,
    pub rotations: Vec<f64>,
    pub d_rotations: Vec<f64>,
    pub weight_offsets: Vec<f64>,
    /// `J x 12`.
    pub target_joints: Vec<f64>,
    /// `V x 3`.
    pub vertex_offsets: Vec<f64>,
}

/// The linear part of a row-major 3 x 4.
pub(crate) fn mat_lin(t: &[f64]) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(t[0], t[4], t[8]),
        DVec3::new(t[1], t[5], t[9]),
        DVec3::new(t[2], t[6], t[10]),
    )
}

/// The translation of a row-major 3 x 4.
pub(crate) fn mat_trans(t: &[f64]) -> DVec3 {
    DVec3::new(t[3], t[7], t[11])
}

fn entry(m: &DMat3, row: usize, col: usize) -> f64 {
    m.col(col)[row]
}

/// Symmetric matrix from an upper triangle.
pub fn sym_from_upper(u: &[f64]) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(u[0], u[1], u[2]),
        DVec3::new(u[1], u[3], u[4]),
        DVec3::new(u[2], u[4], u[5]),
    )
}

/// Upper triangle of a (symmetric) matrix.
pub fn upper_from_sym(m: &DMat3) -> [f64; 6] {
    [
        entry(m, 0, 0),
        entry(m, 0, 1),
        entry(m, 0, 2),
        entry(m, 1, 1),
        entry(m, 1, 2),
        entry(m, 2, 2),
    ]
}

/// The full-matrix gradient of a gradient given on the upper triangle (off-diagonals
/// counting both halves).
fn sym_grad_from_upper(g: &[f64]) -> DMat3 {
    sym_from_upper(&[g[0], 0.5 * g[1], 0.5 * g[2], g[3], 0.5 * g[4], g[5]])
}

/// Hamilton product `a (x) b` of `[w, x, y, z]` quaternions.
pub fn quat_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    let qa = DQuat::from_xyzw(a[1], a[2], a[3], a[0]);
    let qb = DQuat::from_xyzw(b[1], b[2], b[3], b[0]);
    let p = qa * qb;
    [p.w, p.x, p.y, p.z]
}

/// Backward of [`quat_mul`]: gradients for `a` and `b` given the gradient of the product.
fn quat_mul_backward(a: [f64; 4], b: [f64; 4], g: [f64; 4]) -> ([f64; 4], [f64; 4]) {
    // The product is bilinear: p = L(a) b = R(b) a, with the matrices written out below.
    let l = [
        [a[0], -a[1], -a[2], -a[3]],
        [a[1], a[0], -a[3], a[2]],
        [a[2], a[3], a[0], -a[1]],
        [a[3], -a[2], a[1], a[0]],
    ];
    let r = [
        [b[0], -b[1], -b[2], -b[3]],
        [b[1], b[0], b[3], -b[2]],
        [b[2], -b[3], b[0], b[1]],
        [b[3], b[2], -b[1], b[0]],
    ];
    let mut ga = [0.0; 4];
    let mut gb = [0.0; 4];
    for i in 0..4 {
        for j in 0..4 {
            gb[j] += l[i][j] * g[i];
            ga[j] += r[i][j] * g[i];
        }
    }
    (ga, gb)
}

/// Gradient of `R(q / |q|)` with respect to the unnormalised quaternion `q`, given `dL/dR`.
fn quat_matrix_backward(q: [f64; 4], g: &DMat3) -> [f64; 4] {
    if quat_is_degenerate(q) {
        return [0.0; 4];
    }
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / norm);
    let e = |r, c| entry(g, r, c);
    // Derivatives of the standard unit-quaternion matrix entries.
    let dw =
        2.0 * (-z * e(0, 1) + y * e(0, 2) + z * e(1, 0) - x * e(1, 2) - y * e(2, 0) + x * e(2, 1));
    let dx = 2.0
        * (y * e(0, 1) + z * e(0, 2) + y * e(1, 0) - 2.0 * x * e(1, 1) - w * e(1, 2)
            + z * e(2, 0)
            + w * e(2, 1)
            - 2.0 * x * e(2, 2));
    let dy = 2.0
        * (-2.0 * y * e(0, 0) + x * e(0, 1) + w * e(0, 2) + x * e(1, 0) + z * e(1, 2)
            - w * e(2, 0)
            + z * e(2, 1)
            - 2.0 * y * e(2, 2));
    let dz = 2.0
        * (-2.0 * z * e(0, 0) - w * e(0, 1) + x * e(0, 2) + w * e(1, 0) - 2.0 * z * e(1, 1)
            + y * e(1, 2)
            + x * e(2, 0)
            + y * e(2, 1));
    let gn = [dw, dx, dy, dz];
    let unit = [w, x, y, z];
    let dot: f64 = gn.iter().zip(&unit).map(|(a, b)| a * b).sum();
    std::array::from_fn(|i| (gn[i] - unit[i] * dot) / norm)
}

/// `Sigma = R diag(scale^2) R^T` from a linear scale and an unnormalised quaternion.
pub fn covariance_from_scale_rotation(scale: [f64; 3], rotation: [f64; 4]) -> [f64; 6] {
    let r = quat_wxyz_to_matrix(rotation);
    let d = DMat3::from_diagonal(DVec3::from(scale.map(|s| s * s)));
    upper_from_sym(&(r * d * r.transpose()))
}

/// Backward of [`covariance_from_scale_rotation`] from a full symmetric `dL/dSigma`.
fn covariance_backward(scale: [f64; 3], rotation: [f64; 4], g: &DMat3) -> ([f64; 3], [f64; 4]) {
    let r = quat_wxyz_to_matrix(rotation);
    let d = DMat3::from_diagonal(DVec3::from(scale.map(|s| s * s)));
    let gs = (*g + g.transpose()) * 0.5;
    let rt_g_r = r.transpose() * gs * r;
    let d_scale = std::array::from_fn(|i| 2.0 * scale[i] * entry(&rt_g_r, i, i));
    let d_r = gs * r * d * 2.0;
    (d_scale, quat_matrix_backward(rotation, &d_r))
}

/// Gradients of [`covariance_from_scale_rotation`] given the upper-triangle gradient.
pub fn covariance_from_scale_rotation_backward(
    scale: [f64; 3],
    rotation: [f64; 4],
    d_covariance: &[f64],
) -> ([f64; 3], [f64; 4]) {
    covariance_backward(scale, rotation, &sym_grad_from_upper(d_covariance))
}

fn get3(v: &[f64], i: usize) -> [f64; 3] {
    [v[3 * i], v[3 * i + 1], v[3 * i + 2]]
}

fn get4(v: &[f64], i: usize) -> [f64; 4] {
    [v[4 * i], v[4 * i + 1], v[4 * i + 2], v[4 * i + 3]]
}

/// Intermediate values of one Gaussian's forward pass, recomputed in the backward.
struct Forward {
    raw_scale: [f64; 3],
    scale: [f64; 3],
    rotation: [f64; 4],
    weights: Vec<f64>,
    a_lin: DMat3,
    b_inv: DMat3,
    b_t: DVec3,
    rest: DVec3,
    sigma: DMat3,
    position: DVec3,
    covariance: DMat3,
}

fn forward_one(frame: &SkinningFrame<'_>, params: &GaussianParams<'_>, i: usize) -> Forward {
    let j = frame.joint_count;
    let log_scale = get3(params.log_scales, i);
    let d_scale = get3(params.d_scales, i);
    let raw_scale: [f64; 3] = std::array::from_fn(|a| log_scale[a].exp() + d_scale[a]);
    let scale = raw_scale.map(|s| s.clamp(frame.scale_min, frame.scale_max));
    let rotation = quat_mul(get4(params.d_rotations, i), get4(params.rotations, i));
    let r = quat_wxyz_to_matrix(rotation);
    let sigma = r * DMat3::from_diagonal(DVec3::from(scale.map(|s| s * s))) * r.transpose();
    let v = params.nearest[i] as usize;
    let mut logits: Vec<f64> = (0..j)
        .map(|k| (frame.template_weights[v * j + k] + WEIGHT_LOG_EPS).ln())
        .collect();
    if let Some(offsets) = params.weight_offsets {
        for k in 0..j {
            logits[k] += offsets[i * j + k];
        }
    }
    let weights = softmax(&logits);
    let mut a = [0.0; 12];
    let mut b = [0.0; 12];
    for k in 0..j {
        for e in 0..12 {
            a[e] += weights[k] * frame.target_joints[k][e];
            b[e] += weights[k] * frame.canonical_joints[k][e];
        }
    }
    let a_lin = mat_lin(&a);
    let b_inv = mat_lin(&b).inverse();
    let b_t = mat_trans(&b);
    let x = DVec3::from(get3(params.positions, i));
    let rest = b_inv * (x - b_t) + DVec3::from(get3(frame.vertex_offsets, v));
    let position = a_lin * rest + mat_trans(&a);
    let m = a_lin * b_inv;
    let covariance = m * sigma * m.transpose();
    Forward {
        raw_scale,
        scale,
        rotation,
        weights,
        a_lin,
        b_inv,
        b_t,
        rest,
        sigma,
        position,
        covariance,
    }
}

fn softmax(logits: &[f64]) -> Vec<f64> {
    let max = logits.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let exps: Vec<f64> = logits.iter().map(|l| (l - max).exp()).collect();
    let sum: f64 = exps.iter().sum();
    exps.into_iter().map(|e| e / sum).collect()
}

fn check_sizes(frame: &SkinningFrame<'_>, params: &GaussianParams<'_>) -> usize {
    let n = params.nearest.len();
    let j = frame.joint_count;
    assert_eq!(params.positions.len(), 3 * n);
    assert_eq!(params.log_scales.len(), 3 * n);
    assert_eq!(params.d_scales.len(), 3 * n);
    assert_eq!(params.rotations.len(), 4 * n);
    assert_eq!(params.d_rotations.len(), 4 * n);
    if let Some(o) = params.weight_offsets {
        assert_eq!(o.len(), j * n);
    }
    assert_eq!(frame.canonical_joints.len(), j);
    assert_eq!(frame.target_joints.len(), j);
    let v = frame.template_weights.len() / j.max(1);
    assert_eq!(frame.vertex_offsets.len(), 3 * v);
    assert!(
        params.nearest.iter().all(|&k| (k as usize) < v),
        "nearest vertex out of range"
    );
    n
}

/// World-space centres and covariances of all Gaussians (parallel over Gaussians).
pub fn skin_forward(frame: &SkinningFrame<'_>, params: &GaussianParams<'_>) -> Skinned {
    let n = check_sizes(frame, params);
    let per: Vec<([f64; 3], [f64; 6])> = (0..n)
        .into_par_iter()
        .map(|i| {
            let f = forward_one(frame, params, i);
            (f.position.to_array(), upper_from_sym(&f.covariance))
        })
        .collect();
    Skinned {
        positions: per.iter().flat_map(|p| p.0).collect(),
        covariances: per.iter().flat_map(|p| p.1).collect(),
    }
}

/// Backward of [`skin_forward`] given `dL/d positions` (`N x 3`) and `dL/d covariances`
/// (`N x 6`, upper-triangle convention).
pub fn skin_backward(
    frame: &SkinningFrame<'_>,
    params: &GaussianParams<'_>,
    d_positions: &[f64],
    d_covariances: &[f64],
) -> SkinningGrads {
    let n = check_sizes(frame, params);
    let j = frame.joint_count;
    struct One {
        position: [f64; 3],
        log_scale: [f64; 3],
        d_scale: [f64; 3],
        rotation: [f64; 4],
        d_rotation: [f64; 4],
        logits: Vec<f64>,
        weights: Vec<f64>,
        d_a: [f64; 12],
        d_offset: [f64; 3],
    }
    let per: Vec<One> = (0..n)
        .into_par_iter()
        .map(|i| {
            let f = forward_one(frame, params, i);
            let g_pos = DVec3::from(get3(d_positions, i));
            let g_cov = sym_grad_from_upper(&d_covariances[6 * i..6 * i + 6]);
            let x = DVec3::from(get3(params.positions, i));
            let m = f.a_lin * f.b_inv;
            // Position chain.
            let mut d_a_lin = outer(g_pos, f.rest);
            let d_a_t = g_pos;
            let d_rest = f.a_lin.transpose() * g_pos;
            let d_x = f.b_inv.transpose() * d_rest;
            let d_b_t = -d_x;
            let mut d_b_inv = outer(d_rest, x - f.b_t);
            // Covariance chain: Sigma_o = M Sigma M^T.
            let d_m = g_cov * m * f.sigma * 2.0;
            let d_sigma = m.transpose() * g_cov * m;
            d_a_lin += d_m * f.b_inv.transpose();
            d_b_inv += f.a_lin.transpose() * d_m;
            let d_b_lin = -(f.b_inv.transpose() * d_b_inv * f.b_inv.transpose());
            // Blend weights.
            let mut d_a = [0.0; 12];
            let mut d_b = [0.0; 12];
            for r in 0..3 {
                for c in 0..3 {
                    d_a[4 * r + c] = entry(&d_a_lin, r, c);
                    d_b[4 * r + c] = entry(&d_b_lin, r, c);
                }
                d_a[4 * r + 3] = d_a_t[r];
                d_b[4 * r + 3] = d_b_t[r];
            }
            let d_w: Vec<f64> = (0..j)
                .map(|k| {
                    (0..12)
                        .map(|e| {
                            d_a[e] * frame.target_joints[k][e]
                                + d_b[e] * frame.canonical_joints[k][e]
                        })
                        .sum()
                })
                .collect();
            let dot: f64 = f.weights.iter().zip(&d_w).map(|(w, g)| w * g).sum();
            let logits = (0..j).map(|k| f.weights[k] * (d_w[k] - dot)).collect();
            // Scale and rotation.
            let (d_scale_clamped, d_rot_product) =
                covariance_backward(f.scale, f.rotation, &d_sigma);
            let mut d_scale = [0.0; 3];
            let mut log_scale = [0.0; 3];
            for a in 0..3 {
                if f.raw_scale[a] > frame.scale_min && f.raw_scale[a] < frame.scale_max {
                    d_scale[a] = d_scale_clamped[a];
                    log_scale[a] = d_scale_clamped[a] * params.log_scales[3 * i + a].exp();
                }
            }
            let (d_rotation, rotation) = quat_mul_backward(
                get4(params.d_rotations, i),
                get4(params.rotations, i),
                d_rot_product,
            );
            One {
                position: d_x.to_array(),
                log_scale,
                d_scale,
                rotation,
                d_rotation,
                logits,
                weights: f.weights,
                d_a,
                d_offset: d_rest.to_array(),
            }
        })
        .collect();
    let v_count = frame.vertex_offsets.len() / 3;
    let mut grads = SkinningGrads {
        positions: Vec::with_capacity(3 * n),
        log_scales: Vec::with_capacity(3 * n),
        d_scales: Vec::with_capacity(3 * n),
        rotations: Vec::with_capacity(4 * n),
        d_rotations: Vec::with_capacity(4 * n),
        weight_offsets: Vec::with_capacity(j * n),
        target_joints: vec![0.0; 12 * j],
        vertex_offsets: vec![0.0; 3 * v_count],
    };
    for (i, one) in per.iter().enumerate() {
        grads.positions.extend(one.position);
        grads.log_scales.extend(one.log_scale);
        grads.d_scales.extend(one.d_scale);
        grads.rotations.extend(one.rotation);
        grads.d_rotations.extend(one.d_rotation);
        grads.weight_offsets.extend(&one.logits);
        let v = params.nearest[i] as usize;
        for a in 0..3 {
            grads.vertex_offsets[3 * v + a] += one.d_offset[a];
        }
        // dL/dG_k^target = sum_i w_ik dL/dA_i.
        for k in 0..j {
            for e in 0..12 {
                grads.target_joints[12 * k + e] += one.weights[k] * one.d_a[e];
            }
        }
    }
    grads
}

/// The outer product `a b^T`.
pub(crate) fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// Gradient of the canonical covariances (AIAP uses them) back to `log_scales` and
/// `rotations`, accumulated into the given slices.
pub fn canonical_covariances_backward(
    log_scales: &[f64],
    rotations: &[f64],
    d_covariances: &[f64],
    d_log_scales: &mut [f64],
    d_rotations: &mut [f64],
) {
    let n = log_scales.len() / 3;
    for i in 0..n {
        let scale = get3(log_scales, i).map(f64::exp);
        let (ds, dr) = covariance_from_scale_rotation_backward(
            scale,
            get4(rotations, i),
            &d_covariances[6 * i..6 * i + 6],
        );
        for a in 0..3 {
            d_log_scales[3 * i + a] += ds[a] * scale[a];
        }
        for a in 0..4 {
            d_rotations[4 * i + a] += dr[a];
        }
    }
}

/// Canonical covariances `N x 6` from log scales and rotations.
pub fn canonical_covariances(log_scales: &[f64], rotations: &[f64]) -> Vec<f64> {
    let n = log_scales.len() / 3;
    (0..n)
        .flat_map(|i| {
            covariance_from_scale_rotation(get3(log_scales, i).map(f64::exp), get4(rotations, i))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rng::SplitMix64 as Rng;
    use seqavatar_core::rotation::axis_angle_to_matrix;

    fn random_transform(rng: &mut Rng, spread: f64) -> [f64; 12] {
        let r = axis_angle_to_matrix(DVec3::new(rng.normal(), rng.normal(), rng.normal()) * spread);
        let s = 1.0 + 0.1 * rng.normal(); // non-rigid blends are not rotations
        let m = r * s;
        let t = [rng.normal(), rng.normal(), rng.normal()];
        let mut out = [0.0; 12];
        for row in 0..3 {
            for col in 0..3 {
                out[4 * row + col] = entry(&m, row, col);
            }
            out[4 * row + 3] = t[row];
        }
        out
    }

    struct Scene {
        j: usize,
        canonical: Vec<[f64; 12]>,
        target: Vec<[f64; 12]>,
        template_weights: Vec<f64>,
        vertex_offsets: Vec<f64>,
        positions: Vec<f64>,
        log_scales: Vec<f64>,
        d_scales: Vec<f64>,
        rotations: Vec<f64>,
        d_rotations: Vec<f64>,
        weight_offsets: Vec<f64>,
        nearest: Vec<u32>,
    }

    impl Scene {
        fn frame(&self, bounds: (f64, f64)) -> SkinningFrame<'_> {
            SkinningFrame {
                joint_count: self.j,
                canonical_joints: &self.canonical,
                target_joints: &self.target,
                template_weights: &self.template_weights,
                vertex_offsets: &self.vertex_offsets,
                scale_min: bounds.0,
                scale_max: bounds.1,
            }
        }

        fn params(&self) -> GaussianParams<'_> {
            GaussianParams {
                positions: &self.positions,
                log_scales: &self.log_scales,
                d_scales: &self.d_scales,
                rotations: &self.rotations,
                d_rotations: &self.d_rotations,
                weight_offsets: Some(&self.weight_offsets),
                nearest: &self.nearest,
            }
        }
    }

    fn scene(seed: u64) -> Scene {
        let mut rng = Rng::new(seed);
        let (j, v, n) = (4, 5, 7);
        let mut template_weights: Vec<f64> = (0..v * j).map(|_| rng.uniform(0.0, 1.0)).collect();
        template_weights[3] = 0.0; // an exact zero weight, as in SMPL
        Scene {
            j,
            canonical: (0..j).map(|_| random_transform(&mut rng, 0.3)).collect(),
            target: (0..j).map(|_| random_transform(&mut rng, 1.0)).collect(),
            template_weights,
            vertex_offsets: (0..3 * v).map(|_| 0.1 * rng.normal()).collect(),
            positions: (0..3 * n).map(|_| rng.normal()).collect(),
            log_scales: (0..3 * n).map(|_| rng.uniform(-3.0, -1.0)).collect(),
            d_scales: (0..3 * n).map(|_| 0.02 * rng.normal()).collect(),
            rotations: (0..4 * n).map(|_| rng.normal()).collect(),
            d_rotations: (0..n)
                .flat_map(|_| {
                    [
                        1.0,
                        0.2 * rng.normal(),
                        0.2 * rng.normal(),
                        0.2 * rng.normal(),
                    ]
                })
                .collect(),
            weight_offsets: (0..j * n).map(|_| rng.normal()).collect(),
            nearest: (0..n).map(|_| rng.below(v) as u32).collect(),
        }
    }

    fn run(s: &Scene, bounds: (f64, f64)) -> Skinned {
        let (frame, params) = (s.frame(bounds), s.params());
        skin_forward(&frame, &params)
    }

    fn upstream(n: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
        let mut rng = Rng::new(seed);
        (
            (0..3 * n).map(|_| rng.normal()).collect(),
            (0..6 * n).map(|_| rng.normal()).collect(),
        )
    }

    fn objective(out: &Skinned, gp: &[f64], gc: &[f64]) -> f64 {
        out.positions
            .iter()
            .zip(gp)
            .map(|(a, b)| a * b)
            .sum::<f64>()
            + out
                .covariances
                .iter()
                .zip(gc)
                .map(|(a, b)| a * b)
                .sum::<f64>()
    }

    #[test]
    fn skinning_gradients_match_finite_differences() {
        // Bounds chosen so that some scales are clamped (zero gradient) and some are not.
        for bounds in [(1e-6, 10.0), (0.1, 0.2)] {
            let s = scene(21);
            let n = s.nearest.len();
            let (gp, gc) = upstream(n, 5);
            let (frame, params) = (s.frame(bounds), s.params());
            let grads = skin_backward(&frame, &params, &gp, &gc);
            let eps = 1e-6;
            type Field = fn(&mut Scene) -> &mut Vec<f64>;
            let fields: [(&str, Field, &Vec<f64>); 7] = [
                ("positions", |s| &mut s.positions, &grads.positions),
                ("log_scales", |s| &mut s.log_scales, &grads.log_scales),
                ("d_scales", |s| &mut s.d_scales, &grads.d_scales),
                ("rotations", |s| &mut s.rotations, &grads.rotations),
                ("d_rotations", |s| &mut s.d_rotations, &grads.d_rotations),
                (
                    "weight_offsets",
                    |s| &mut s.weight_offsets,
                    &grads.weight_offsets,
                ),
                (
                    "vertex_offsets",
                    |s| &mut s.vertex_offsets,
                    &grads.vertex_offsets,
                ),
            ];
            for (name, field, analytic) in fields {
                let len = field(&mut scene(21)).len();
                for index in 0..len {
                    let mut plus = scene(21);
                    field(&mut plus)[index] += eps;
                    let mut minus = scene(21);
                    field(&mut minus)[index] -= eps;
                    let numeric = (objective(&run(&plus, bounds), &gp, &gc)
                        - objective(&run(&minus, bounds), &gp, &gc))
                        / (2.0 * eps);
                    let tol = 1e-6 * (1.0 + numeric.abs());
                    assert!(
                        (numeric - analytic[index]).abs() < tol,
                        "{name}[{index}] bounds {bounds:?}: numeric {numeric} analytic {}",
                        analytic[index]
                    );
                }
            }
            for index in 0..12 * s.j {
                let mut plus = scene(21);
                plus.target[index / 12][index % 12] += eps;
                let mut minus = scene(21);
                minus.target[index / 12][index % 12] -= eps;
                let numeric = (objective(&run(&plus, bounds), &gp, &gc)
                    - objective(&run(&minus, bounds), &gp, &gc))
                    / (2.0 * eps);
                assert!(
                    (numeric - grads.target_joints[index]).abs() < 1e-6 * (1.0 + numeric.abs()),
                    "target_joints[{index}]"
                );
            }
        }
    }

    #[test]
    fn identity_skinning_is_identity_and_covariance_has_closed_form() {
        let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let joints = vec![identity; 2];
        let weights = vec![0.5, 0.5];
        let offsets = vec![0.0; 3];
        let frame = SkinningFrame {
            joint_count: 2,
            canonical_joints: &joints,
            target_joints: &joints,
            template_weights: &weights,
            vertex_offsets: &offsets,
            scale_min: 1e-6,
            scale_max: 1.0,
        };
        // A rotation of 90 degrees about z swaps the x and y variances.
        let half = std::f64::consts::FRAC_PI_4;
        let params = GaussianParams {
            positions: &[0.3, -0.2, 0.7],
            log_scales: &[0.1f64.ln(), 0.2f64.ln(), 0.3f64.ln()],
            d_scales: &[0.0; 3],
            rotations: &[half.cos(), 0.0, 0.0, half.sin()],
            d_rotations: &[1.0, 0.0, 0.0, 0.0],
            weight_offsets: None,
            nearest: &[0],
        };
        let out = skin_forward(&frame, &params);
        for (a, b) in out.positions.iter().zip([0.3, -0.2, 0.7]) {
            assert!((a - b).abs() < 1e-14);
        }
        let expected = [0.04, 0.0, 0.0, 0.01, 0.0, 0.09];
        for (a, b) in out.covariances.iter().zip(expected) {
            assert!((a - b).abs() < 1e-14, "{:?}", out.covariances);
        }
    }

    #[test]
    fn rigid_target_moves_points_and_rotates_covariances() {
        // Every joint the same rigid motion: the result is that motion applied directly.
        let mut rng = Rng::new(2);
        let r = axis_angle_to_matrix(DVec3::new(0.3, -1.1, 0.4));
        let t = DVec3::new(0.5, 1.0, -2.0);
        let mut target = [0.0; 12];
        for row in 0..3 {
            for col in 0..3 {
                target[4 * row + col] = entry(&r, row, col);
            }
            target[4 * row + 3] = t[row];
        }
        let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let frame = SkinningFrame {
            joint_count: 3,
            canonical_joints: &[identity; 3],
            target_joints: &[target; 3],
            template_weights: &[0.2, 0.3, 0.5],
            vertex_offsets: &[0.0; 3],
            scale_min: 1e-6,
            scale_max: 1.0,
        };
        let q: Vec<f64> = (0..4).map(|_| rng.normal()).collect();
        let params = GaussianParams {
            positions: &[0.1, 0.2, 0.3],
            log_scales: &[-2.0, -3.0, -2.5],
            d_scales: &[0.0; 3],
            rotations: &q,
            d_rotations: &[1.0, 0.0, 0.0, 0.0],
            weight_offsets: Some(&[5.0, -3.0, 0.0]),
            nearest: &[0],
        };
        let out = skin_forward(&frame, &params);
        let expected = r * DVec3::new(0.1, 0.2, 0.3) + t;
        assert!((DVec3::from(get3(&out.positions, 0)) - expected).length() < 1e-13);
        let sigma = sym_from_upper(&covariance_from_scale_rotation(
            [(-2.0f64).exp(), (-3.0f64).exp(), (-2.5f64).exp()],
            [q[0], q[1], q[2], q[3]],
        ));
        let expected_cov = upper_from_sym(&(r * sigma * r.transpose()));
        for (a, b) in out.covariances.iter().zip(expected_cov) {
            assert!((a - b).abs() < 1e-14);
        }
    }

    #[test]
    fn canonical_covariance_gradient_matches_finite_differences() {
        let mut rng = Rng::new(4);
        let n = 3;
        let ls: Vec<f64> = (0..3 * n).map(|_| rng.uniform(-2.0, 0.0)).collect();
        let rot: Vec<f64> = (0..4 * n).map(|_| rng.normal()).collect();
        let g: Vec<f64> = (0..6 * n).map(|_| rng.normal()).collect();
        let f = |ls: &[f64], rot: &[f64]| -> f64 {
            canonical_covariances(ls, rot)
                .iter()
                .zip(&g)
                .map(|(a, b)| a * b)
                .sum()
        };
        let mut dls = vec![0.0; 3 * n];
        let mut drot = vec![0.0; 4 * n];
        canonical_covariances_backward(&ls, &rot, &g, &mut dls, &mut drot);
        let eps = 1e-6;
        for i in 0..3 * n {
            let (mut p, mut m) = (ls.clone(), ls.clone());
            p[i] += eps;
            m[i] -= eps;
            assert!(((f(&p, &rot) - f(&m, &rot)) / (2.0 * eps) - dls[i]).abs() < 1e-7);
        }
        for i in 0..4 * n {
            let (mut p, mut m) = (rot.clone(), rot.clone());
            p[i] += eps;
            m[i] -= eps;
            assert!(((f(&ls, &p) - f(&ls, &m)) / (2.0 * eps) - drot[i]).abs() < 1e-7);
        }
        // Degenerate quaternion: identity rotation, zero rotation gradient, finite values.
        let (_, dr) = covariance_from_scale_rotation_backward([0.1; 3], [0.0; 4], &[1.0; 6]);
        assert_eq!(dr, [0.0; 4]);
    }

    /// Upper-triangle gradient of a full-matrix gradient of a symmetric argument.
    fn upper_grad_from_full(g: &DMat3) -> [f64; 6] {
        let s = (*g + g.transpose()) * 0.5;
        [
            entry(&s, 0, 0),
            2.0 * entry(&s, 0, 1),
            2.0 * entry(&s, 0, 2),
            entry(&s, 1, 1),
            2.0 * entry(&s, 1, 2),
            entry(&s, 2, 2),
        ]
    }

    #[test]
    fn upper_gradient_conventions_round_trip() {
        let g = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        assert_eq!(upper_grad_from_full(&sym_grad_from_upper(&g)), g);
    }
}
