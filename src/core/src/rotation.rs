//! Rotations: axis-angle (Rodrigues), rotation matrices and unit quaternions.
//!
//! This is the one place rotation math lives. Conventions:
//! - An axis-angle vector `v` rotates by `|v|` radians about `v / |v|` (right-handed).
//! - Matrices act on column vectors: `x' = R x`.
//! - Quaternions are stored `[w, x, y, z]` (scalar first), as 3D Gaussian splatting does.
//!
//! Every function is stable near angle 0 (Taylor branches) and near pi (the matrix logarithm
//! goes through a quaternion and `atan2`, never through `acos` of the trace).

use glam::{DMat3, DQuat, DVec3};

/// Below this angle (radians) the closed forms switch to Taylor series.
const SMALL_ANGLE: f64 = 1e-4;

/// Cross-product matrix `[v]x` such that `[v]x w = v x w`.
pub fn skew(v: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, v.z, -v.y),
        DVec3::new(-v.z, 0.0, v.x),
        DVec3::new(v.y, -v.x, 0.0),
    )
}

/// Rodrigues' formula: axis-angle vector to rotation matrix.
pub fn axis_angle_to_matrix(v: DVec3) -> DMat3 {
    let theta_sq = v.length_squared();
    let theta = theta_sq.sqrt();
    // a = sin(t)/t, b = (1 - cos(t))/t^2, with series near 0.
    let (a, b) = if theta < SMALL_ANGLE {
        (1.0 - theta_sq / 6.0, 0.5 - theta_sq / 24.0)
    } else {
        (theta.sin() / theta, (1.0 - theta.cos()) / theta_sq)
    };
    let k = skew(v);
    DMat3::IDENTITY + k * a + (k * k) * b
}

/// Matrix logarithm: rotation matrix to axis-angle vector with angle in `[0, pi]`.
///
/// Goes through a unit quaternion (Shepperd's method in glam) and `atan2`, so it is accurate
/// at both 0 and pi. At exactly pi the sign of the axis is arbitrary, as it must be.
pub fn matrix_to_axis_angle(r: DMat3) -> DVec3 {
    let q = DQuat::from_mat3(&r).normalize();
    quat_to_axis_angle(q)
}

/// Unit quaternion to axis-angle vector with angle in `[0, pi]`.
pub fn quat_to_axis_angle(q: DQuat) -> DVec3 {
    // q and -q are the same rotation: pick w >= 0 so the angle is at most pi.
    let q = if q.w < 0.0 { -q } else { q };
    let xyz = DVec3::new(q.x, q.y, q.z);
    let sin_half = xyz.length();
    let half = sin_half.atan2(q.w);
    let theta = 2.0 * half;
    // theta / sin(half), with its series 2 + theta^2/12 near 0.
    let scale = if sin_half < 0.5 * SMALL_ANGLE {
        2.0 + theta * theta / 12.0
    } else {
        theta / sin_half
    };
    xyz * scale
}

/// Axis-angle vector to unit quaternion.
pub fn axis_angle_to_quat(v: DVec3) -> DQuat {
    let theta = v.length();
    let half = 0.5 * theta;
    // sin(theta/2)/theta, with series near 0.
    let s = if theta < SMALL_ANGLE {
        0.5 - theta * theta / 48.0
    } else {
        half.sin() / theta
    };
    DQuat::from_xyzw(v.x * s, v.y * s, v.z * s, half.cos())
}

/// Quaternion stored `[w, x, y, z]` to a rotation matrix, normalising first.
///
/// A quaternion of (near) zero length carries no rotation: it maps to the identity instead of
/// producing NaN. Callers that must report such input check [`quat_is_degenerate`].
pub fn quat_wxyz_to_matrix(q: [f64; 4]) -> DMat3 {
    if quat_is_degenerate(q) {
        return DMat3::IDENTITY;
    }
    let quat = DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
    DMat3::from_quat(quat)
}

/// True when a `[w, x, y, z]` quaternion is too short (or not finite) to define a rotation.
pub fn quat_is_degenerate(q: [f64; 4]) -> bool {
    let n2 = q.iter().map(|c| c * c).sum::<f64>();
    !(n2.is_finite() && n2 > 1e-24)
}

/// Derivatives of Rodrigues' formula: `[dR/dv_x, dR/dv_y, dR/dv_z]`.
///
/// Closed form of Gallego and Yezzi (2015):
/// `dR/dv_i = (v_i [v]x + [v x ((I - R) e_i)]x) / |v|^2 * R`, and `[e_i]x` at `v = 0`
/// (plus the first-order correction near 0).
pub fn axis_angle_to_matrix_jacobian(v: DVec3) -> [DMat3; 3] {
    let theta_sq = v.length_squared();
    let basis = [DVec3::X, DVec3::Y, DVec3::Z];
    if theta_sq.sqrt() < SMALL_ANGLE {
        // R = I + [v]x + [v]x^2 / 2 + O(|v|^3): dR/dv_i = [e_i]x + ([e_i]x[v]x + [v]x[e_i]x) / 2.
        let k = skew(v);
        return basis.map(|e| {
            let ke = skew(e);
            ke + (ke * k + k * ke) * 0.5
        });
    }
    let r = axis_angle_to_matrix(v);
    let k = skew(v);
    let i_minus_r = DMat3::IDENTITY - r;
    let components = [v.x, v.y, v.z];
    let mut out = [DMat3::ZERO; 3];
    for i in 0..3 {
        let w = v.cross(i_minus_r * basis[i]);
        out[i] = (k * components[i] + skew(w)) * (1.0 / theta_sq) * r;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_abs_diff(a: DMat3, b: DMat3) -> f64 {
        (a - b)
            .to_cols_array()
            .iter()
            .fold(0.0_f64, |m, x| m.max(x.abs()))
    }

    #[test]
    fn rodrigues_matches_glam_axis_angle() {
        for v in [
            DVec3::new(0.3, -0.2, 0.9),
            DVec3::new(1e-9, 2e-9, -1e-9),
            DVec3::new(0.0, 0.0, std::f64::consts::PI),
            DVec3::new(2.0, 1.0, -0.5),
        ] {
            let theta = v.length();
            let expected = if theta == 0.0 {
                DMat3::IDENTITY
            } else {
                DMat3::from_axis_angle(v / theta, theta)
            };
            assert!(
                max_abs_diff(axis_angle_to_matrix(v), expected) < 1e-12,
                "{v:?}"
            );
        }
    }

    #[test]
    fn log_inverts_exp_near_zero_and_pi() {
        let pi = std::f64::consts::PI;
        for v in [
            DVec3::new(1e-12, 0.0, 0.0),
            DVec3::new(3e-5, -2e-5, 1e-5),
            DVec3::new(0.4, 0.1, -0.3),
            DVec3::new(0.0, pi - 1e-7, 0.0),
            DVec3::new(pi - 1e-3, 0.0, 0.0),
            DVec3::new(1.0, 1.0, 1.0).normalize() * (pi - 1e-9),
        ] {
            let back = matrix_to_axis_angle(axis_angle_to_matrix(v));
            assert!((back - v).length() < 1e-7, "{v:?} -> {back:?}");
        }
        // Exactly pi: either sign of the axis is the same rotation.
        let v = DVec3::new(0.0, 0.0, pi);
        let back = matrix_to_axis_angle(axis_angle_to_matrix(v));
        assert!((back.length() - pi).abs() < 1e-9);
        assert!(max_abs_diff(axis_angle_to_matrix(back), axis_angle_to_matrix(v)) < 1e-12);
    }

    #[test]
    fn quaternion_round_trip_and_degenerate() {
        let v = DVec3::new(0.2, -0.7, 0.1);
        let q = axis_angle_to_quat(v);
        let m = quat_wxyz_to_matrix([q.w, q.x, q.y, q.z]);
        assert!(max_abs_diff(m, axis_angle_to_matrix(v)) < 1e-12);
        assert!((quat_to_axis_angle(q) - v).length() < 1e-12);
        assert_eq!(quat_wxyz_to_matrix([0.0; 4]), DMat3::IDENTITY);
        assert_eq!(
            quat_wxyz_to_matrix([f64::NAN, 0.0, 0.0, 0.0]),
            DMat3::IDENTITY
        );
        assert!(quat_is_degenerate([1e-13, 0.0, 0.0, 0.0]));
        assert!(!quat_is_degenerate([1e-6, 0.0, 0.0, 0.0]));
    }

    #[test]
    fn jacobian_matches_central_differences() {
        for v in [
            DVec3::new(0.3, -0.2, 0.9),
            DVec3::new(2e-6, -1e-6, 3e-6),
            DVec3::ZERO,
            DVec3::new(0.0, 3.0, 0.1),
        ] {
            let jac = axis_angle_to_matrix_jacobian(v);
            let h = 1e-6;
            for (i, e) in [DVec3::X, DVec3::Y, DVec3::Z].into_iter().enumerate() {
                let fd =
                    (axis_angle_to_matrix(v + e * h) - axis_angle_to_matrix(v - e * h)) * (0.5 / h);
                assert!(max_abs_diff(fd, jac[i]) < 1e-8, "v={v:?} i={i}");
            }
        }
    }
}
