//! The op `covariance_from_scale_rotation` and its backward: world covariances
//! `Sigma = R diag(s)^2 R^T` of Gaussians from linear scales and `[w, x, y, z]` quaternions.
//!
//! The rotation comes from `seqavatar_core::rotation::quat_wxyz_to_matrix` (normalised inside;
//! a degenerate quaternion gives the identity). Each Gaussian is computed in `f64` whatever the
//! storage precision: it costs nothing next to rasterisation and keeps `f32` callers accurate.

// Index loops mirror the matrix and per-channel formulas they implement.
#![allow(clippy::needless_range_loop)]

use glam::DMat3;
use rayon::prelude::*;
use seqavatar_core::rotation::{quat_is_degenerate, quat_wxyz_to_matrix};

use super::{SplatError, check_len};
use crate::scalar::Scalar;

/// Covariances and what was wrong with the input.
#[derive(Clone, Debug, PartialEq)]
pub struct CovarianceOutput<S> {
    /// `N x 6` upper triangles `(xx, xy, xz, yy, yz, zz)`.
    pub covariances: Vec<S>,
    /// Quaternions too short to define a rotation (the identity was used).
    pub degenerate_rotations: usize,
    /// Gaussians with a non-finite scale or rotation, or whose covariance overflowed the
    /// storage precision; their covariance is written as zeros.
    pub non_finite: usize,
}

/// Gradients of `covariance_from_scale_rotation`.
#[derive(Clone, Debug, PartialEq)]
pub struct CovarianceGradients<S> {
    /// `N x 3`.
    pub scales: Vec<S>,
    /// `N x 4`, with respect to the unnormalised quaternion (zero for degenerate ones).
    pub rotations: Vec<S>,
}

/// `Sigma = R diag(s)^2 R^T` per Gaussian; `scales` is `N x 3`, `rotations` `N x 4`.
pub fn covariance_from_scale_rotation<S: Scalar>(
    scales: &[S],
    rotations: &[S],
) -> Result<CovarianceOutput<S>, SplatError> {
    let n = scales.len() / 3;
    check_len("scales", scales.len(), n * 3)?;
    check_len("rotations", rotations.len(), n * 4)?;
    let mut covariances = vec![S::ZERO; n * 6];
    let (degenerate_rotations, non_finite) = covariances
        .par_chunks_mut(6)
        .zip(scales.par_chunks(3))
        .zip(rotations.par_chunks(4))
        .with_min_len(1024)
        .map(|((out, s), q)| {
            let q = [q[0].to_f64(), q[1].to_f64(), q[2].to_f64(), q[3].to_f64()];
            let s = [s[0].to_f64(), s[1].to_f64(), s[2].to_f64()];
            if !q.iter().chain(&s).all(|v| v.is_finite()) {
                return (0, 1);
            }
            let degenerate = usize::from(quat_is_degenerate(q));
            let r = quat_wxyz_to_matrix(q);
            let m = r * DMat3::from_diagonal(glam::DVec3::from_array(s));
            let sigma = m * m.transpose();
            let upper = upper_triangle(sigma).map(S::from_f64);
            if upper.iter().all(|v| v.is_finite()) {
                out.copy_from_slice(&upper);
                (degenerate, 0)
            } else {
                (degenerate, 1)
            }
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    Ok(CovarianceOutput {
        covariances,
        degenerate_rotations,
        non_finite,
    })
}

/// Backward of [`covariance_from_scale_rotation`] given `d_covariances` (`N x 6`, the
/// gradient of the upper-triangle entries, off-diagonals counting both halves).
pub fn covariance_from_scale_rotation_backward<S: Scalar>(
    scales: &[S],
    rotations: &[S],
    d_covariances: &[S],
) -> Result<CovarianceGradients<S>, SplatError> {
    let n = scales.len() / 3;
    check_len("scales", scales.len(), n * 3)?;
    check_len("rotations", rotations.len(), n * 4)?;
    check_len("d_covariances", d_covariances.len(), n * 6)?;
    let mut d_scales = vec![S::ZERO; n * 3];
    let mut d_rotations = vec![S::ZERO; n * 4];
    d_scales
        .par_chunks_mut(3)
        .zip(d_rotations.par_chunks_mut(4))
        .zip(scales.par_chunks(3).zip(rotations.par_chunks(4)))
        .zip(d_covariances.par_chunks(6))
        .with_min_len(1024)
        .for_each(|(((ds, dq), (s, q)), dc)| {
            let q = [q[0].to_f64(), q[1].to_f64(), q[2].to_f64(), q[3].to_f64()];
            let s = [s[0].to_f64(), s[1].to_f64(), s[2].to_f64()];
            let dc: [f64; 6] = std::array::from_fn(|i| dc[i].to_f64());
            let Some((grad_s, grad_q)) = scale_rotation_backward_f64(s, q, dc) else {
                return;
            };
            let grad_s = grad_s.map(S::from_f64);
            let grad_q = grad_q.map(S::from_f64);
            // Overflowed gradients are dropped rather than let out.
            if grad_s.iter().chain(&grad_q).all(|v| v.is_finite()) {
                ds.copy_from_slice(&grad_s);
                dq.copy_from_slice(&grad_q);
            }
        });
    Ok(CovarianceGradients {
        scales: d_scales,
        rotations: d_rotations,
    })
}

/// `(xx, xy, xz, yy, yz, zz)` of a symmetric matrix.
fn upper_triangle(m: DMat3) -> [f64; 6] {
    // glam is column-major: `m.col(j)[i]` is row i, column j.
    [
        m.col(0)[0],
        m.col(1)[0],
        m.col(2)[0],
        m.col(1)[1],
        m.col(2)[1],
        m.col(2)[2],
    ]
}

/// One Gaussian's backward; `None` for non-finite input.
fn scale_rotation_backward_f64(
    s: [f64; 3],
    q: [f64; 4],
    dc: [f64; 6],
) -> Option<([f64; 3], [f64; 4])> {
    if !q.iter().chain(&s).chain(&dc).all(|v| v.is_finite()) {
        return None;
    }
    // Symmetric matrix G with dL = sum_ij G_ij dSigma_ij: off-diagonal entries split in half.
    let g = [
        [dc[0], 0.5 * dc[1], 0.5 * dc[2]],
        [0.5 * dc[1], dc[3], 0.5 * dc[4]],
        [0.5 * dc[2], 0.5 * dc[4], dc[5]],
    ];
    let r = quat_wxyz_to_matrix(q);
    let rm = |i: usize, j: usize| r.col(j)[i];
    // Sigma = R D R^T with D = diag(s^2): dL/dD_kk = (R^T G R)_kk, dL/dR = 2 G R D.
    let mut grad_s = [0.0; 3];
    for (k, gs) in grad_s.iter_mut().enumerate() {
        let mut rtgr = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                rtgr += rm(i, k) * g[i][j] * rm(j, k);
            }
        }
        *gs = 2.0 * s[k] * rtgr;
    }
    if quat_is_degenerate(q) {
        return Some((grad_s, [0.0; 4]));
    }
    let mut gr = [[0.0; 3]; 3];
    for (i, row) in gr.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for k in 0..3 {
                acc += g[i][k] * rm(k, j);
            }
            *v = 2.0 * acc * s[j] * s[j];
        }
    }
    let norm = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|c| c / norm);
    // Derivatives of the unit-quaternion rotation matrix entries (3DGS's build_rotation).
    let d_unit = [
        2.0 * (-z * gr[0][1] + y * gr[0][2] + z * gr[1][0] - x * gr[1][2] - y * gr[2][0]
            + x * gr[2][1]),
        2.0 * (y * gr[0][1] + z * gr[0][2] + y * gr[1][0] - 2.0 * x * gr[1][1] - w * gr[1][2]
            + z * gr[2][0]
            + w * gr[2][1]
            - 2.0 * x * gr[2][2]),
        2.0 * (-2.0 * y * gr[0][0] + x * gr[0][1] + w * gr[0][2] + x * gr[1][0] + z * gr[1][2]
            - w * gr[2][0]
            + z * gr[2][1]
            - 2.0 * y * gr[2][2]),
        2.0 * (-2.0 * z * gr[0][0] - w * gr[0][1] + x * gr[0][2] + w * gr[1][0]
            - 2.0 * z * gr[1][1]
            + y * gr[1][2]
            + x * gr[2][0]
            + y * gr[2][1]),
    ];
    // Through the normalisation q / |q|: (I - u u^T) / |q|.
    let unit = [w, x, y, z];
    let radial: f64 = unit.iter().zip(&d_unit).map(|(a, b)| a * b).sum();
    let grad_q = std::array::from_fn(|i| (d_unit[i] - unit[i] * radial) / norm);
    Some((grad_s, grad_q))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loss_weights() -> [f64; 6] {
        [0.7, -1.3, 0.4, 0.9, -0.2, 1.1]
    }

    fn loss(scales: &[f64], rotations: &[f64]) -> f64 {
        let out = covariance_from_scale_rotation(scales, rotations).unwrap();
        let w = loss_weights();
        out.covariances
            .chunks(6)
            .map(|c| c.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>())
            .sum()
    }

    #[test]
    fn matches_closed_form_for_axis_rotation() {
        // 90 degrees about z maps x to y: variances swap between x and y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let out = covariance_from_scale_rotation(&[2.0_f64, 3.0, 5.0], &[h, 0.0, 0.0, h]).unwrap();
        let expected = [9.0, 0.0, 0.0, 4.0, 0.0, 25.0];
        for (a, b) in out.covariances.iter().zip(expected) {
            assert!((a - b).abs() < 1e-12, "{:?}", out.covariances);
        }
    }

    #[test]
    fn gradients_match_central_differences() {
        let scales = vec![0.3, 1.7, 0.05, 2.0, 0.4, 0.9];
        let rotations = vec![0.9, -0.3, 0.2, 0.5, -0.1, 0.8, 0.4, -0.6];
        let n = 2;
        let d_cov: Vec<f64> = (0..n).flat_map(|_| loss_weights()).collect();
        let grads = covariance_from_scale_rotation_backward(&scales, &rotations, &d_cov).unwrap();
        let h = 1e-6;
        for i in 0..scales.len() {
            let (mut p, mut m) = (scales.clone(), scales.clone());
            p[i] += h;
            m[i] -= h;
            let fd = (loss(&p, &rotations) - loss(&m, &rotations)) / (2.0 * h);
            assert!(
                (fd - grads.scales[i]).abs() < 1e-7 * (1.0 + fd.abs()),
                "scale {i}: {fd} vs {}",
                grads.scales[i]
            );
        }
        for i in 0..rotations.len() {
            let (mut p, mut m) = (rotations.clone(), rotations.clone());
            p[i] += h;
            m[i] -= h;
            let fd = (loss(&scales, &p) - loss(&scales, &m)) / (2.0 * h);
            assert!(
                (fd - grads.rotations[i]).abs() < 1e-7 * (1.0 + fd.abs()),
                "rotation {i}: {fd} vs {}",
                grads.rotations[i]
            );
        }
    }

    #[test]
    fn extremes_give_finite_output_and_are_counted() {
        let scales = [
            1e-7_f32,
            1e-7,
            1e-7,
            1e3,
            1e3,
            1e3,
            f32::NAN,
            1.0,
            1.0,
            1e30,
            1.0,
            1.0,
            1.0,
            1.0,
            1.0,
        ];
        let rotations = [
            1.0_f32, 0.0, 0.0, 0.0, //
            0.0, 1e-20, 0.0, 0.0, // degenerate: identity
            1.0, 0.0, 0.0, 0.0, //
            1.0, 0.0, 0.0, 0.0, // scale overflows f32 when squared
            1e-10, 1e-10, 0.0, 0.0, // tiny but valid
        ];
        let out = covariance_from_scale_rotation(&scales, &rotations).unwrap();
        assert!(out.covariances.iter().all(|v| v.is_finite()));
        assert_eq!(out.degenerate_rotations, 1);
        assert_eq!(out.non_finite, 2);
        assert!((out.covariances[6] - 1e6).abs() < 1.0);
        assert!(out.covariances[0] > 0.0, "1e-14 is representable in f32");
        let grads =
            covariance_from_scale_rotation_backward(&scales, &rotations, &[1.0; 30]).unwrap();
        assert!(
            grads
                .scales
                .iter()
                .chain(&grads.rotations)
                .all(|v| v.is_finite())
        );
        assert!(grads.rotations[4..8].iter().all(|&v| v == 0.0));
        assert!(matches!(
            covariance_from_scale_rotation(&scales[..4], &rotations[..4]),
            Err(SplatError::Length {
                field: "scales",
                ..
            })
        ));
    }
}
