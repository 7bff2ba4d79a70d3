//! The motion context on plain arrays: skeleton motion and vertex velocity per (frame, scale),
//! and the gather that turns any `(t, l, s)` window of the paper into indices.
//!
//! Frames are *sampled* frames: index `u` is the `u`-th body fit of the sequence, which is raw
//! video frame `u * sampling_interval` in the reference code. Scales are given in raw video
//! frames (as the paper and the reference scripts state them) and must be multiples of the
//! sampling interval, so that a scale is a whole number of sampled frames ("step").
//!
//! For frame `t`, step `k` and `l` in `0..L` the reference code uses
//! `cur = max(t - l k, 0)` and `former = max(t - (l + 1) k, 0)`. Since
//! `former = max(cur - k, 0)` in both branches of the clamp, every quantity of the window is a
//! per-(frame, scale) quantity evaluated at `cur`: the stage stores
//! `delta[u, s] = f(u, max(u - k_s, 0))` once and a window is a gather of rows `cur`.

use rayon::prelude::*;
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_core::rotation::matrix_to_axis_angle;
use seqavatar_schema::motion::ContextError;

/// The earlier frame a per-(frame, scale) delta is taken against: `max(u - step, 0)`.
pub fn former_frame(frame: usize, step: usize) -> usize {
    frame.saturating_sub(step)
}

/// Skeleton motion per (frame, scale, joint): `axis_angle(R[u] R[max(u - k, 0)]^-1)`.
///
/// `rotations` holds `n_frames * n_joints` rotations, frame-major. The result has shape
/// `(n_frames, n_scales, n_joints, 3)`, row-major.
pub fn skeleton_motion(
    rotations: &[DMat3],
    n_frames: usize,
    n_joints: usize,
    steps: &[usize],
) -> Result<Vec<f32>, ContextError> {
    check_len("joint rotations", n_frames * n_joints, rotations.len())?;
    let row = steps.len() * n_joints * 3;
    let mut out = vec![0.0_f32; n_frames * row];
    out.par_chunks_mut(row.max(1))
        .enumerate()
        .for_each(|(frame, dst)| {
            skeleton_motion_frame(rotations, n_joints, steps, frame, dst);
        });
    Ok(out)
}

/// One frame of [`skeleton_motion`]: writes `(n_scales, n_joints, 3)` values into `dst`.
pub fn skeleton_motion_frame(
    rotations: &[DMat3],
    n_joints: usize,
    steps: &[usize],
    frame: usize,
    dst: &mut [f32],
) {
    let current = &rotations[frame * n_joints..(frame + 1) * n_joints];
    for (scale_slot, &step) in steps.iter().enumerate() {
        let former_index = former_frame(frame, step);
        let former = &rotations[former_index * n_joints..(former_index + 1) * n_joints];
        for joint in 0..n_joints {
            // R_cur R_former^-1; the transpose is the inverse of a rotation.
            let delta = if former_index == frame {
                DVec3::ZERO
            } else {
                matrix_to_axis_angle(current[joint] * former[joint].transpose())
            };
            let at = (scale_slot * n_joints + joint) * 3;
            dst[at] = delta.x as f32;
            dst[at + 1] = delta.y as f32;
            dst[at + 2] = delta.z as f32;
        }
    }
}

/// One frame of vertex velocity: `factor_s * (T[u] - T[max(u - k_s, 0)])` for every scale,
/// written as `(n_scales, n_vertices, 3)` into `dst`.
///
/// `posed` holds the posed world-space template of every frame, `(n_frames, n_vertices, 3)`.
pub fn vertex_velocity_frame(
    posed: &[f32],
    n_vertices: usize,
    steps: &[usize],
    factors: &[f64],
    frame: usize,
    dst: &mut [f32],
) {
    let stride = n_vertices * 3;
    let current = &posed[frame * stride..(frame + 1) * stride];
    for (scale_slot, (&step, &factor)) in steps.iter().zip(factors).enumerate() {
        let former_index = former_frame(frame, step);
        let former = &posed[former_index * stride..(former_index + 1) * stride];
        let out = &mut dst[scale_slot * stride..(scale_slot + 1) * stride];
        let factor = factor as f32;
        for ((o, &c), &f) in out.iter_mut().zip(current).zip(former) {
            *o = (c - f) * factor;
        }
    }
}

/// Vertex velocity of every frame, `(n_frames, n_scales, n_vertices, 3)`.
pub fn vertex_velocity(
    posed: &[f32],
    n_frames: usize,
    n_vertices: usize,
    steps: &[usize],
    factors: &[f64],
) -> Result<Vec<f32>, ContextError> {
    check_len("posed vertices", n_frames * n_vertices * 3, posed.len())?;
    check_len("velocity factors", steps.len(), factors.len())?;
    let row = steps.len() * n_vertices * 3;
    let mut out = vec![0.0_f32; n_frames * row];
    out.par_chunks_mut(row.max(1))
        .enumerate()
        .for_each(|(frame, dst)| {
            vertex_velocity_frame(posed, n_vertices, steps, factors, frame, dst);
        });
    Ok(out)
}

fn check_len(what: &'static str, expected: usize, got: usize) -> Result<(), ContextError> {
    if expected == got {
        Ok(())
    } else {
        Err(ContextError::Shape {
            what,
            expected,
            got,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rotation::axis_angle_to_matrix;
    use seqavatar_schema::motion::{
        Scales, VelocityNormalisation, block_rms, scale_blocks, window,
    };
    use std::f64::consts::PI;

    /// The reference code's loop, written independently: for every (l, scale) it computes
    /// `cur` and `former` with Python's floor division on raw frame numbers.
    fn reference_pairs(
        pose_index_raw: i64,
        length: usize,
        raw_scales: &[u32],
        interval: u32,
    ) -> Vec<(usize, usize)> {
        let mut pairs = Vec::new();
        for l in 0..length as i64 {
            for &s in raw_scales {
                let s = i64::from(s);
                let i = i64::from(interval);
                let cur = (pose_index_raw - l * s).div_euclid(i).max(0);
                let former = (pose_index_raw - (l + 1) * s).div_euclid(i).max(0);
                pairs.push((cur as usize, former as usize));
            }
        }
        pairs
    }

    #[test]
    fn window_matches_the_reference_index_arithmetic() {
        for (raw_scales, interval) in [(vec![42, 33, 24], 3), (vec![6, 3], 1), (vec![3, 2, 1], 1)] {
            let scales = Scales::new(&raw_scales, interval).unwrap();
            for t in [0usize, 1, 5, 13, 40, 200] {
                let w = window(t, 8, &scales.steps);
                let pairs =
                    reference_pairs((t as i64) * i64::from(interval), 8, &scales.raw, interval);
                for l in 0..8 {
                    for s in 0..scales.len() {
                        let (cur, former) = pairs[l * scales.len() + s];
                        assert_eq!(w.frame(l, s), cur, "t={t} l={l} s={s}");
                        assert_eq!(former_frame(cur, scales.steps[s]), former);
                    }
                }
            }
        }
    }

    #[test]
    fn windows_before_the_first_frame_clamp_to_zero() {
        let w = window(2, 4, &[3, 1]);
        assert_eq!(w.frames, vec![2, 2, 0, 1, 0, 0, 0, 0]);
        let w = window(0, 3, &[5]);
        assert_eq!(w.frames, vec![0, 0, 0]);
    }

    #[test]
    fn scales_are_validated_and_sorted_largest_first() {
        let s = Scales::new(&[24, 42, 33], 3).unwrap();
        assert_eq!(s.raw, vec![42, 33, 24]);
        assert_eq!(s.steps, vec![14, 11, 8]);
        assert_eq!(
            Scales::new(&[4], 3),
            Err(ContextError::ScaleNotMultiple {
                scale: 4,
                interval: 3
            })
        );
        assert_eq!(Scales::new(&[], 1), Err(ContextError::NoScales));
        assert_eq!(
            Scales::new(&[2, 2], 1),
            Err(ContextError::DuplicateScale { scale: 2 })
        );
        assert_eq!(Scales::new(&[1], 0), Err(ContextError::ZeroInterval));
        assert!(Scales::new(&[0], 1).is_err());
    }

    #[test]
    fn velocity_factors_paper_and_reference_quirk() {
        let s = Scales::new(&[24, 33, 42], 3).unwrap();
        let paper = s.velocity_factors(VelocityNormalisation::PerScale);
        assert_eq!(paper, vec![1.0 / 42.0, 1.0 / 33.0, 1.0 / 24.0]);
        // Reference: multi / float(24 / 3) for every scale.
        let quirk = s.velocity_factors(VelocityNormalisation::Reference { multi: 300.0 });
        assert_eq!(quirk, vec![37.5; 3]);
    }

    #[test]
    fn vertex_velocity_is_a_finite_difference_and_zero_at_the_first_frame() {
        // Two vertices moving along known trajectories x(u) = (u^2, -u, 0.5), y(u) = (0, 2u, u).
        let n_frames = 7;
        let mut posed = Vec::new();
        for u in 0..n_frames {
            let u = u as f32;
            posed.extend_from_slice(&[u * u, -u, 0.5, 0.0, 2.0 * u, u]);
        }
        let steps = [3usize, 1];
        let factors = [1.0 / 3.0, 1.0];
        let v = vertex_velocity(&posed, n_frames, 2, &steps, &factors).unwrap();
        let at = |t: usize, s: usize, vert: usize, c: usize| v[((t * 2 + s) * 2 + vert) * 3 + c];
        for t in 0..n_frames {
            for (s, &k) in steps.iter().enumerate() {
                let f = t.saturating_sub(k) as f32;
                let tt = t as f32;
                let scale = factors[s] as f32;
                assert!((at(t, s, 0, 0) - (tt * tt - f * f) * scale).abs() < 1e-5);
                assert!((at(t, s, 0, 1) - (f - tt) * scale).abs() < 1e-5);
                assert_eq!(at(t, s, 0, 2), 0.0);
                assert!((at(t, s, 1, 1) - 2.0 * (tt - f) * scale).abs() < 1e-5);
            }
        }
        for s in 0..2 {
            for c in 0..6 {
                assert_eq!(v[s * 6 + c], 0.0, "first frame has zero velocity");
            }
        }
        assert!(matches!(
            vertex_velocity(&posed[1..], n_frames, 2, &steps, &factors),
            Err(ContextError::Shape { .. })
        ));
    }

    #[test]
    fn skeleton_motion_recovers_known_relative_rotations_near_zero_and_pi() {
        // Joint 0 spins about z at a constant rate; joint 1 flips by pi between frames 2 and 3;
        // joint 2 barely moves (1e-9 rad per frame).
        let n_frames = 5;
        let rate = 0.3;
        let mut rotations = Vec::new();
        for u in 0..n_frames {
            let uf = u as f64;
            rotations.push(axis_angle_to_matrix(DVec3::new(0.0, 0.0, rate * uf)));
            let flip = if u >= 3 { PI } else { 0.0 };
            rotations.push(
                axis_angle_to_matrix(DVec3::new(flip, 0.0, 0.0))
                    * axis_angle_to_matrix(DVec3::Y * 0.2),
            );
            rotations.push(axis_angle_to_matrix(DVec3::new(1e-9 * uf, 0.0, 0.0)));
        }
        let steps = [2usize, 1];
        let motion = skeleton_motion(&rotations, n_frames, 3, &steps).unwrap();
        let get = |t: usize, s: usize, j: usize| {
            let at = ((t * 2 + s) * 3 + j) * 3;
            DVec3::new(
                f64::from(motion[at]),
                f64::from(motion[at + 1]),
                f64::from(motion[at + 2]),
            )
        };
        for t in 0..n_frames {
            for (s, &k) in steps.iter().enumerate() {
                let dt = (t - t.saturating_sub(k)) as f64;
                assert!((get(t, s, 0) - DVec3::Z * rate * dt).length() < 1e-6);
                let tiny = get(t, s, 2);
                assert!((tiny.x - 1e-9 * dt).abs() < 1e-12 && tiny.y == 0.0);
                let flip = get(t, s, 1);
                let crosses = t >= 3 && t.saturating_sub(k) < 3;
                if crosses {
                    // A pi rotation about x (either sign of the axis is the same rotation).
                    assert!((flip.length() - PI).abs() < 1e-5, "t={t} s={s} {flip:?}");
                    assert!(flip.y.abs() < 1e-6 && flip.z.abs() < 1e-6);
                } else {
                    assert!(flip.length() < 1e-6);
                }
            }
        }
        assert!(matches!(
            skeleton_motion(&rotations[1..], n_frames, 3, &steps),
            Err(ContextError::Shape { .. })
        ));
    }

    #[test]
    fn a_sequence_of_one_frame_has_zero_motion() {
        let rotations = vec![axis_angle_to_matrix(DVec3::new(0.1, 0.2, 0.3)); 2];
        let motion = skeleton_motion(&rotations, 1, 2, &[5, 1]).unwrap();
        assert!(motion.iter().all(|&x| x == 0.0));
        let v = vertex_velocity(&[1.0, 2.0, 3.0], 1, 1, &[5, 1], &[0.2, 1.0]).unwrap();
        assert_eq!(v, vec![0.0; 6]);
        assert_eq!(window(0, 8, &[5, 1]).frames, vec![0; 16]);
    }

    #[test]
    fn block_rms_and_scaling_per_scale_slot() {
        // 2 frames, 2 scales, 1 item: slot 0 holds (3, 4, 0) and (0, 0, 0); slot 1 is zero.
        let mut values = vec![3.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let rms = block_rms(&values, 2, 1);
        assert!((rms[0] - (25.0f64 / 6.0).sqrt()).abs() < 1e-12);
        assert_eq!(rms[1], 0.0);
        scale_blocks(&mut values, 1, &[2.0, 5.0]);
        assert_eq!(values[..3], [6.0, 8.0, 0.0]);
        assert!(values[3..].iter().all(|x| *x == 0.0));
    }
}
