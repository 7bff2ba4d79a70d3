//! The body-pose refiner: local pose without root -> one correction matrix per non-root
//! joint, and its backward from the matrices' gradient.
//!
//! The network ([`NetworkSpec::pose_refiner`](super::spec::NetworkSpec::pose_refiner)) is `Linear(3 (J - 1), 128)` + ReLU, `Linear(128, 128)` + ReLU,
//! `Linear(128, 3 (J - 1))` with the last weight from `U(-1e-5, 1e-5)` and zero bias, so a
//! fresh refiner returns matrices within ~1e-5 of the identity.

use seqavatar_compute::nn::NnScalar;
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_core::rotation::skew;

use super::network::Activations;
use crate::skinning::outer;

/// The `theta^2` regulariser of [`regularised_rodrigues`].
pub const THETA_SQUARED_EPSILON: f64 = 1e-5;

/// The reference refiner's Rodrigues map: `theta = sqrt(1e-5 + |v|^2)`, `k = v / theta`,
/// `R = cos(theta) I + (1 - cos(theta)) k k^T + sin(theta) [k]x`.
///
/// This is deliberately not [`seqavatar_core::rotation::axis_angle_to_matrix`]: the
/// regulariser makes the map smooth at `v = 0` without a series branch, at the price of not
/// being exactly orthogonal for `|v|` near `sqrt(1e-5)` (at `v = 0` it is
/// `cos(sqrt(1e-5)) I`, 5e-6 from the identity). For `|v| >> 3e-3` the two agree.
pub fn regularised_rodrigues(v: DVec3) -> DMat3 {
    let theta = (THETA_SQUARED_EPSILON + v.length_squared()).sqrt();
    let k = v / theta;
    let (sin, cos) = theta.sin_cos();
    DMat3::IDENTITY * cos + outer(k, k) * (1.0 - cos) + skew(k) * sin
}

/// Backward of [`regularised_rodrigues`]: `dL/dv` from `g = dL/dR`.
pub fn regularised_rodrigues_backward(v: DVec3, g: DMat3) -> DVec3 {
    let theta = (THETA_SQUARED_EPSILON + v.length_squared()).sqrt();
    let k = v / theta;
    let (sin, cos) = theta.sin_cos();
    // <G, [k]x> = k . a with a = (G21 - G12, G02 - G20, G10 - G01) (row, column indices).
    let e = |row: usize, col: usize| g.col(col)[row];
    let a = DVec3::new(e(2, 1) - e(1, 2), e(0, 2) - e(2, 0), e(1, 0) - e(0, 1));
    let trace = e(0, 0) + e(1, 1) + e(2, 2);
    let k_g_k = k.dot(g * k);
    let d_theta = -sin * trace + sin * k_g_k + cos * k.dot(a);
    let d_k = (g + g.transpose()) * k * (1.0 - cos) + a * sin;
    // theta = sqrt(eps + |v|^2): d theta / dv = k; k = v / theta: dk/dv = (I - k k^T) / theta.
    k * d_theta + (d_k - k * k.dot(d_k)) / theta
}

/// The refiner's activations for its backward.
#[derive(Clone, Debug, Default)]
pub struct PoseRefinerCache<S> {
    pub(crate) activations: Activations<S>,
}

impl<S> PoseRefinerCache<S> {
    /// The network output: one axis-angle-like 3-vector per non-root joint.
    pub fn rotation_vectors(&self) -> &[S] {
        self.activations.output()
    }
}

/// `(J - 1) x 3` refiner outputs to `(J - 1)` row-major 3x3 matrices.
pub(crate) fn rotations_from_vectors<S: NnScalar>(vectors: &[S]) -> Vec<S> {
    let mut rotations = Vec::with_capacity(3 * vectors.len());
    for v in vectors.chunks_exact(3) {
        let m = regularised_rodrigues(DVec3::new(v[0].to_f64(), v[1].to_f64(), v[2].to_f64()));
        for row in 0..3 {
            for col in 0..3 {
                rotations.push(S::from_f64(m.col(col)[row]));
            }
        }
    }
    rotations
}

/// `dL/d(vectors)` from `dL/d(matrices)` (row-major), one joint at a time.
pub(crate) fn rotation_vectors_backward<S: NnScalar>(vectors: &[S], d_rotations: &[S]) -> Vec<S> {
    let mut d_vectors = Vec::with_capacity(vectors.len());
    for (v, d) in vectors.chunks_exact(3).zip(d_rotations.chunks_exact(9)) {
        // Row-major.
        let g = DMat3::from_cols_array(&std::array::from_fn(|i| d[i].to_f64())).transpose();
        let dv = regularised_rodrigues_backward(
            DVec3::new(v[0].to_f64(), v[1].to_f64(), v[2].to_f64()),
            g,
        );
        d_vectors.extend([dv.x, dv.y, dv.z].map(S::from_f64));
    }
    d_vectors
}
