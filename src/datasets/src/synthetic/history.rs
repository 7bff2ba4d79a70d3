//! The motion script of the history scene (`dataset.scene: history`): a walk whose body pose
//! is a function of an integer gait phase alone, visited at different speeds, with
//! stop-and-hold segments, turns and restarts, so exact poses recur under different histories.
//!
//! - The gait cycle has [`PHASES`] phases; frame `k` shows phase `c_k mod PHASES`, where the
//!   cumulative phase `c_k` advances by a whole number of phases per frame (0 = hold,
//!   1 = slow walk 0.6 m/s, 2 = fast walk 1.2 m/s at 30 fps). [`gait_pose`] is the pose of a
//!   phase; phases 0 and `PHASES / 2` (feet together) are the same pose, the one held in
//!   every stop.
//! - The heading is the body's world rotation (`Rh`, about +y), not part of the pose, so
//!   turning does not change the pose either.
//! - Between frames the cumulative phase and the heading follow monotone cubic (Fritsch-
//!   Carlson) interpolation through the frame values, so they are smooth, never overshoot
//!   (a hold is exactly still), and the garment simulation sees finite accelerations. The
//!   path integrates the speed along the heading; a frame's position is that integral.

use seqavatar_core::glam::{DMat3, DVec2, DVec3};
use seqavatar_core::rotation::{axis_angle_to_matrix, matrix_to_axis_angle};

/// Gait phases per cycle (two steps).
pub const PHASES: u64 = 60;
/// The frame rate the script is written for.
pub const FPS: f64 = 30.0;
/// Path length of one gait cycle (m): 2 cm per phase.
pub const STRIDE: f64 = 1.2;

/// A stretch of the script: `frames` frames advancing `step` phases each, turning the heading
/// by `turn` radians along a smoothstep (the turn rate rises from and falls back to zero).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub frames: usize,
    pub step: u64,
    pub turn: f64,
}

const fn segment(frames: usize, step: u64, turn: f64) -> Segment {
    Segment { frames, step, turn }
}

/// The script: stand; start slowly and walk fast; slow down and stop (hold 1.5 s); restart
/// slowly through a U-turn; walk fast and stop short (hold 1.5 s); restart briskly into a
/// fast walk through a quarter turn; slow walk. Every hold lands on a feet-together phase (a multiple of
/// `PHASES / 2`).
pub const SCRIPT: [Segment; 12] = [
    segment(8, 0, 0.0),
    segment(6, 1, 0.0),
    segment(21, 2, 0.0),
    segment(12, 1, 0.0),
    segment(45, 0, 0.0),
    segment(30, 1, std::f64::consts::PI),
    segment(12, 2, 0.0),
    segment(6, 1, 0.0),
    segment(45, 0, 0.0),
    segment(3, 1, 0.0),
    segment(15, 2, -std::f64::consts::FRAC_PI_2),
    segment(15, 1, 0.0),
];

/// Number of frames of [`SCRIPT`].
pub const LENGTH: usize = {
    let mut total = 0;
    let mut i = 0;
    while i < SCRIPT.len() {
        total += SCRIPT[i].frames;
        i += 1;
    }
    total
};

/// Per frame of the script: the cumulative gait phase and the heading (radians about +y).
pub fn frame_values() -> (Vec<u64>, Vec<f64>) {
    let mut phases = Vec::with_capacity(LENGTH);
    let mut headings = Vec::with_capacity(LENGTH);
    let (mut phase, mut heading) = (0u64, 0.0f64);
    for segment in SCRIPT {
        let start = heading;
        for k in 0..segment.frames {
            if !phases.is_empty() {
                phase += segment.step;
            }
            let u = (k + 1) as f64 / segment.frames as f64;
            heading = start + segment.turn * u * u * (3.0 - 2.0 * u);
            phases.push(phase);
            headings.push(heading);
        }
    }
    (phases, headings)
}

/// `sin(2 pi phase / PHASES)` computed from the phase in the first half cycle, so phases
/// `p` and `p + PHASES / 2` give exactly opposite values (and 0 at both feet-together phases).
fn phase_sine(phase: u64) -> f64 {
    let p = phase % PHASES;
    let half = PHASES / 2;
    let angle = |q: u64| std::f64::consts::TAU * q as f64 / PHASES as f64;
    if p < half {
        angle(p).sin()
    } else {
        -angle(p - half).sin()
    }
}

/// The body pose of gait phase `phase` (local axis-angle per SMPL joint, root zero): a function
/// of `phase mod PHASES` only. Every term follows `sin` of the phase, so the two feet-together
/// phases (0 and `PHASES / 2`) give the same standing pose.
pub fn gait_pose(phase: u64) -> Vec<DVec3> {
    let s = phase_sine(phase);
    let mut pose = vec![DVec3::ZERO; 24];
    // Hips swing (negative x rotation moves the leg forward); the leading leg's knee bends.
    pose[1] = DVec3::new(-0.45 * s, 0.0, 0.0);
    pose[2] = DVec3::new(0.45 * s, 0.0, 0.0);
    pose[4] = DVec3::new(0.1 + 0.6 * s.max(0.0).powi(2), 0.0, 0.0);
    pose[5] = DVec3::new(0.1 + 0.6 * (-s).max(0.0).powi(2), 0.0, 0.0);
    pose[7] = DVec3::new(0.2 * s, 0.0, 0.0);
    pose[8] = DVec3::new(-0.2 * s, 0.0, 0.0);
    // Torso counter-rotation.
    pose[3] = DVec3::new(0.0, 0.08 * s, 0.0);
    pose[6] = DVec3::new(0.04, -0.04 * s, 0.0);
    // Arms down from the T-pose, swinging against the legs; elbows slightly bent.
    let lower = 1.25;
    let swing = 0.35 * s;
    let left = axis_angle_to_matrix(DVec3::new(swing, 0.0, 0.0)) * DMat3::from_rotation_z(-lower);
    let right = axis_angle_to_matrix(DVec3::new(-swing, 0.0, 0.0)) * DMat3::from_rotation_z(lower);
    pose[16] = matrix_to_axis_angle(left);
    pose[17] = matrix_to_axis_angle(right);
    pose[18] = DVec3::new(0.0, -0.5, 0.0);
    pose[19] = DVec3::new(0.0, 0.5, 0.0);
    pose
}

/// Pelvis height change (m) at gait phase `phase`: lowest mid-stride, 0 with the feet together.
pub fn bob(phase: u64) -> f64 {
    -0.02 * phase_sine(phase).powi(2)
}

/// A monotone cubic (Fritsch-Carlson) through values at integer times `0, 1, ...`: never
/// overshoots, constant wherever two neighbouring values are equal.
#[derive(Clone, Debug, PartialEq)]
pub struct MonotoneCubic {
    values: Vec<f64>,
    tangents: Vec<f64>,
}

impl MonotoneCubic {
    pub fn new(values: &[f64]) -> Self {
        let n = values.len();
        let secant = |k: usize| values[k + 1] - values[k];
        let tangents = (0..n)
            .map(|k| {
                if n < 2 {
                    return 0.0;
                }
                if k == 0 {
                    return secant(0);
                }
                if k == n - 1 {
                    return secant(n - 2);
                }
                let (a, b) = (secant(k - 1), secant(k));
                if a * b <= 0.0 {
                    0.0
                } else {
                    // Harmonic mean (Fritsch-Butland): keeps the cubic monotone.
                    2.0 * a * b / (a + b)
                }
            })
            .collect();
        Self {
            values: values.to_vec(),
            tangents,
        }
    }

    /// Value, first and second derivative at time `t` (clamped to the knots' range).
    pub fn eval(&self, t: f64) -> (f64, f64, f64) {
        let n = self.values.len();
        if n < 2 {
            return (self.values.first().copied().unwrap_or(0.0), 0.0, 0.0);
        }
        let t = t.clamp(0.0, (n - 1) as f64);
        let k = (t.floor() as usize).min(n - 2);
        let u = t - k as f64;
        let (y0, m0, m1) = (self.values[k], self.tangents[k], self.tangents[k + 1]);
        let delta = self.values[k + 1] - y0;
        // Hermite form with the secant: y0 + delta h01 + m0 h10 + m1 h11, where
        // h01 = 3u^2 - 2u^3, h10 = u^3 - 2u^2 + u, h11 = u^3 - u^2.
        let (u2, u3) = (u * u, u * u * u);
        let value = y0 + delta * (3.0 * u2 - 2.0 * u3) + m0 * (u3 - 2.0 * u2 + u) + m1 * (u3 - u2);
        let first = delta * (6.0 * u - 6.0 * u2)
            + m0 * (3.0 * u2 - 4.0 * u + 1.0)
            + m1 * (3.0 * u2 - 2.0 * u);
        let second = delta * (6.0 - 12.0 * u) + m0 * (6.0 * u - 4.0) + m1 * (6.0 * u - 2.0);
        (value, first, second)
    }
}

/// The pelvis's horizontal path (x, z) at a substep: position, velocity and acceleration in
/// metres and seconds, from the interpolated cumulative phase and heading (frame time `t`).
pub struct PathSample {
    pub velocity: DVec2,
    pub acceleration: DVec2,
    pub heading: f64,
    pub heading_acceleration: f64,
}

/// The body's horizontal axes (world x, z) at heading `heading` (radians about +y): forward
/// `(sin, cos)` and across, to its side, `(cos, -sin)`.
pub fn heading_axes(heading: f64) -> (DVec2, DVec2) {
    (
        DVec2::new(heading.sin(), heading.cos()),
        DVec2::new(heading.cos(), -heading.sin()),
    )
}

/// The path's derivatives at frame time `t` (the position is their integral).
pub fn path_sample(phase: &MonotoneCubic, heading: &MonotoneCubic, t: f64) -> PathSample {
    let per_phase = STRIDE / PHASES as f64;
    let (_, dc, ddc) = phase.eval(t);
    let (psi, dpsi, ddpsi) = heading.eval(t);
    // Per second: d/dt = FPS d/dframe.
    let (speed, speed_rate) = (per_phase * FPS * dc, per_phase * FPS * FPS * ddc);
    let (turn_rate, turn_acceleration) = (FPS * dpsi, FPS * FPS * ddpsi);
    let (direction, across) = heading_axes(psi);
    PathSample {
        velocity: direction * speed,
        acceleration: direction * speed_rate + across * (speed * turn_rate),
        heading: psi,
        heading_acceleration: turn_acceleration,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn script_recurs_poses_at_different_speeds_and_holds_feet_together() {
        let (phases, headings) = frame_values();
        assert_eq!(phases.len(), LENGTH);
        const { assert!(LENGTH >= 150, "at least 150 frames") };
        // Every hold is on a feet-together phase, and both such phases give one pose.
        assert_eq!(gait_pose(0), gait_pose(PHASES / 2));
        assert_eq!(gait_pose(7), gait_pose(7 + 3 * PHASES));
        for k in 1..LENGTH {
            if phases[k] == phases[k - 1] {
                assert_eq!(phases[k] % (PHASES / 2), 0, "frame {k} holds mid-stride");
            }
        }
        // Each even phase is visited at both speeds (1 and 2 phases per frame).
        let mut speeds = std::collections::BTreeMap::<u64, std::collections::BTreeSet<u64>>::new();
        for k in 1..LENGTH {
            speeds
                .entry(phases[k] % PHASES)
                .or_default()
                .insert(phases[k] - phases[k - 1]);
        }
        let both = (0..PHASES)
            .step_by(2)
            .filter(|p| {
                speeds
                    .get(p)
                    .is_some_and(|s| s.contains(&1) && s.contains(&2))
            })
            .count();
        assert!(both >= 20, "{both} of 30 even phases seen at both speeds");
        // The heading turns by pi then -pi/2.
        assert!((headings[LENGTH - 1] - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
        // The bob is a function of the phase, zero with the feet together.
        assert_eq!(bob(0), 0.0);
        assert_eq!(bob(PHASES / 2), 0.0);
    }

    #[test]
    fn monotone_cubic_interpolates_without_overshoot_and_its_derivatives_match() {
        let values = [0.0, 0.0, 1.0, 3.0, 5.0, 5.0, 5.0, 6.0];
        let cubic = MonotoneCubic::new(&values);
        for (k, v) in values.iter().enumerate() {
            assert!((cubic.eval(k as f64).0 - v).abs() < 1e-12);
        }
        let mut last = f64::MIN;
        for i in 0..=700 {
            let t = i as f64 * 0.01;
            let (value, first, second) = cubic.eval(t);
            assert!(value >= last - 1e-12, "not monotone at {t}");
            last = value;
            // Holds are exactly still.
            if (4.0..=6.0).contains(&t) || t <= 1.0 {
                assert_eq!(first, 0.0, "moving at {t}");
            }
            // Derivatives against central differences inside a piece.
            let frac = t - t.floor();
            if frac > 0.02 && frac < 0.98 {
                let h = 1e-5;
                let (a, da, _) = cubic.eval(t - h);
                let (b, db, _) = cubic.eval(t + h);
                assert!((first - (b - a) / (2.0 * h)).abs() < 1e-6, "{t}");
                assert!((second - (db - da) / (2.0 * h)).abs() < 1e-4, "{t}");
            }
        }
    }

    #[test]
    fn path_acceleration_is_the_derivative_of_its_velocity() {
        let (phases, headings) = frame_values();
        let phase = MonotoneCubic::new(&phases.iter().map(|&p| p as f64).collect::<Vec<_>>());
        let heading = MonotoneCubic::new(&headings);
        // Inside the U-turn (frames 92..122): speed and curvature both act.
        for t in [93.3, 101.7, 119.5] {
            let h = 1e-4; // frames
            let a = path_sample(&phase, &heading, t - h);
            let b = path_sample(&phase, &heading, t + h);
            let numeric = (b.velocity - a.velocity) / (2.0 * h / FPS);
            let analytic = path_sample(&phase, &heading, t).acceleration;
            assert!(
                (numeric - analytic).length() < 1e-5,
                "{t}: {numeric} vs {analytic}"
            );
        }
        // Holding: no velocity.
        assert_eq!(path_sample(&phase, &heading, 60.5).velocity, DVec2::ZERO);
    }
}
