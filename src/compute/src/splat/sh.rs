//! Real spherical harmonics up to degree 3 with the constants and sign conventions of 3D
//! Gaussian splatting, and their derivatives with respect to the (unit) direction.
//!
//! Colour of a Gaussian seen along `dir` (unit vector from the camera centre to the mean):
//! `max(0, sum_k sh_k Y_k(dir) + 0.5)` per channel.

// Index loops mirror the matrix and per-channel formulas they implement.
#![allow(clippy::needless_range_loop)]

use crate::scalar::Scalar;

/// `Y_0`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// The factor of the degree-1 basis functions `Y_1..Y_3`.
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// SH basis values `Y_k(dir)` for `k < (degree + 1)^2` (the rest are zero), and when
/// `gradient` is given, `dY_k/d dir` treating the three components as independent.
pub fn sh_basis<S: Scalar>(
    dir: [S; 3],
    degree: u32,
    gradient: Option<&mut [[S; 3]; 16]>,
) -> [S; 16] {
    let c = S::from_f64;
    let [x, y, z] = dir;
    let zero = S::ZERO;
    let mut basis = [zero; 16];
    let mut grad = [[zero; 3]; 16];
    basis[0] = c(SH_C0);
    if degree >= 1 {
        let c1 = c(SH_C1);
        basis[1] = -c1 * y;
        basis[2] = c1 * z;
        basis[3] = -c1 * x;
        grad[1] = [zero, -c1, zero];
        grad[2] = [zero, zero, c1];
        grad[3] = [-c1, zero, zero];
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        let two = c(2.0);
        let k = SH_C2.map(c);
        basis[4] = k[0] * x * y;
        basis[5] = k[1] * y * z;
        basis[6] = k[2] * (two * zz - xx - yy);
        basis[7] = k[3] * x * z;
        basis[8] = k[4] * (xx - yy);
        grad[4] = [k[0] * y, k[0] * x, zero];
        grad[5] = [zero, k[1] * z, k[1] * y];
        grad[6] = [-two * k[2] * x, -two * k[2] * y, c(4.0) * k[2] * z];
        grad[7] = [k[3] * z, zero, k[3] * x];
        grad[8] = [two * k[4] * x, -two * k[4] * y, zero];
    }
    if degree >= 3 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        let (two, three, four, six, eight) = (c(2.0), c(3.0), c(4.0), c(6.0), c(8.0));
        let k = SH_C3.map(c);
        basis[9] = k[0] * y * (three * xx - yy);
        basis[10] = k[1] * x * y * z;
        basis[11] = k[2] * y * (four * zz - xx - yy);
        basis[12] = k[3] * z * (two * zz - three * xx - three * yy);
        basis[13] = k[4] * x * (four * zz - xx - yy);
        basis[14] = k[5] * z * (xx - yy);
        basis[15] = k[6] * x * (xx - three * yy);
        grad[9] = [k[0] * six * x * y, k[0] * three * (xx - yy), zero];
        grad[10] = [k[1] * y * z, k[1] * x * z, k[1] * x * y];
        grad[11] = [
            -k[2] * two * x * y,
            k[2] * (four * zz - xx - three * yy),
            k[2] * eight * y * z,
        ];
        grad[12] = [
            -k[3] * six * x * z,
            -k[3] * six * y * z,
            k[3] * (six * zz - three * xx - three * yy),
        ];
        grad[13] = [
            k[4] * (four * zz - three * xx - yy),
            -k[4] * two * x * y,
            k[4] * eight * x * z,
        ];
        grad[14] = [k[5] * two * x * z, -k[5] * two * y * z, k[5] * (xx - yy)];
        grad[15] = [k[6] * three * (xx - yy), -k[6] * six * x * y, zero];
    }
    if let Some(out) = gradient {
        *out = grad;
    }
    basis
}

/// Unclamped colour `sum_k sh_k Y_k + 0.5` per channel, `sh` being `K x 3` for one Gaussian.
pub fn sh_colour_unclamped<S: Scalar>(sh: &[S], basis: &[S; 16]) -> [S; 3] {
    let half = S::from_f64(0.5);
    let mut colour = [half; 3];
    for (coefficient, &y) in sh.chunks_exact(3).zip(basis.iter()) {
        for channel in 0..3 {
            colour[channel] += coefficient[channel] * y;
        }
    }
    colour
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_gradient_matches_central_differences() {
        let dir = [0.3_f64, -0.5, 0.81];
        let mut grad = [[0.0; 3]; 16];
        let basis = sh_basis(dir, 3, Some(&mut grad));
        let h = 1e-6;
        for axis in 0..3 {
            let mut plus = dir;
            let mut minus = dir;
            plus[axis] += h;
            minus[axis] -= h;
            let bp = sh_basis(plus, 3, None);
            let bm = sh_basis(minus, 3, None);
            for k in 0..16 {
                let fd = (bp[k] - bm[k]) / (2.0 * h);
                assert!(
                    (fd - grad[k][axis]).abs() < 1e-8,
                    "Y_{k} d/d{axis}: {fd} vs {}",
                    grad[k][axis]
                );
            }
        }
        assert!((basis[0] - SH_C0).abs() < 1e-15);
    }

    #[test]
    fn lower_degrees_leave_higher_coefficients_zero() {
        let dir = [0.6_f64, 0.0, 0.8];
        let b1 = sh_basis(dir, 1, None);
        assert!(b1[4..].iter().all(|&v| v == 0.0));
        // Degree-1 band: -C1 y, C1 z, -C1 x.
        assert!((b1[2] - SH_C1 * 0.8).abs() < 1e-15);
        assert!((b1[3] + SH_C1 * 0.6).abs() < 1e-15);
    }

    #[test]
    fn degree_two_and_three_bands_are_orthonormal_on_the_sphere() {
        // Monte-Carlo-free check: a Fibonacci sphere quadrature of Y_i Y_j approximates the
        // identity for real orthonormal SH (up to the sign conventions, which keep norms).
        let n = 20_000;
        let mut gram = [[0.0_f64; 16]; 16];
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * std::f64::consts::PI * (3.0 - 5.0_f64.sqrt());
            let b = sh_basis([r * phi.cos(), r * phi.sin(), z], 3, None);
            for a in 0..16 {
                for c in 0..16 {
                    gram[a][c] += b[a] * b[c] * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for a in 0..16 {
            for c in 0..16 {
                let expected = if a == c { 1.0 } else { 0.0 };
                assert!(
                    (gram[a][c] - expected).abs() < 2e-3,
                    "gram[{a}][{c}] = {}",
                    gram[a][c]
                );
            }
        }
    }
}
