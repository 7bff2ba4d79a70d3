//! The scripted motion of the synthetic subject: walk, turn while walking, stop, stand, walk
//! again. Phases are fractions of the sequence length, so any frame count shows all of them.
//!
//! The script is integrated at the simulation rate (path position, heading and gait phase
//! are integrals of speed and turn rate), so poses are smooth in time and the garment
//! simulation sees the accelerations of a real stop-and-go.

use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_core::rotation::{axis_angle_to_matrix, matrix_to_axis_angle};

/// Top walking speed (m/s).
pub const WALK_SPEED: f64 = 0.8;
/// Path length of one gait cycle (two steps) at full speed (m).
const STRIDE: f64 = 1.2;
/// Total heading change of the turn (radians).
const TURN: f64 = std::f64::consts::FRAC_PI_2;

/// The motion state at one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionSample {
    /// Local axis-angle per SMPL joint; `pose[0]` holds the heading.
    pub pose: Vec<DVec3>,
    /// World position of the pelvis joint, floor at y = 0 under a standing subject.
    pub position: DVec3,
}

fn smoothstep(edge0: f64, edge1: f64, x: f64) -> f64 {
    let t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Speed as a fraction of [`WALK_SPEED`] at normalised time `u` (0..1 over the sequence;
/// negative during the warm-up).
pub fn speed_fraction(u: f64) -> f64 {
    let start = smoothstep(0.0, 0.08, u);
    let stop = 1.0 - smoothstep(0.55, 0.62, u);
    let go = smoothstep(0.78, 0.85, u);
    start * stop.max(go)
}

/// Heading (radians about +y; 0 = facing +z) at normalised time `u`.
fn heading(u: f64) -> f64 {
    TURN * smoothstep(0.3, 0.55, u)
}

/// Body pose for gait phase `phase` with amplitude `a` (0 = standing) and heading.
fn pose(phase: f64, a: f64, heading: f64) -> Vec<DVec3> {
    let mut pose = vec![DVec3::ZERO; 24];
    let (s, c) = phase.sin_cos();
    pose[0] = DVec3::new(0.0, heading, 0.0);
    // Hips swing (negative x rotation moves the leg forward), knees bend in swing.
    pose[1] = DVec3::new(-0.45 * a * s, 0.0, 0.0);
    pose[2] = DVec3::new(0.45 * a * s, 0.0, 0.0);
    pose[4] = DVec3::new(a * (0.1 + 0.6 * (-c).max(0.0).powi(2)), 0.0, 0.0);
    pose[5] = DVec3::new(a * (0.1 + 0.6 * c.max(0.0).powi(2)), 0.0, 0.0);
    pose[7] = DVec3::new(0.2 * a * s, 0.0, 0.0);
    pose[8] = DVec3::new(-0.2 * a * s, 0.0, 0.0);
    // Torso counter-rotation.
    pose[3] = DVec3::new(0.0, 0.08 * a * s, 0.0);
    pose[6] = DVec3::new(0.04, -0.04 * a * s, 0.0);
    // Arms down from the T-pose, swinging against the legs; elbows slightly bent.
    let lower = 1.25;
    let swing = 0.35 * a * s;
    let left = axis_angle_to_matrix(DVec3::new(swing, 0.0, 0.0)) * DMat3::from_rotation_z(-lower);
    let right = axis_angle_to_matrix(DVec3::new(-swing, 0.0, 0.0)) * DMat3::from_rotation_z(lower);
    pose[16] = matrix_to_axis_angle(left);
    pose[17] = matrix_to_axis_angle(right);
    let bend = 0.3 + 0.2 * a;
    pose[18] = DVec3::new(0.0, -bend, 0.0);
    pose[19] = DVec3::new(0.0, bend, 0.0);
    pose
}

/// Samples the script every `dt` seconds over `[-warmup, duration]`, for a subject whose
/// pelvis stands `pelvis_height` above the floor. The path is centred on the origin over
/// the sequence (warm-up excluded).
pub fn sample_script(duration: f64, warmup: f64, dt: f64, pelvis_height: f64) -> Vec<MotionSample> {
    let steps = ((duration + warmup) / dt).round() as usize + 1;
    let mut samples = Vec::with_capacity(steps);
    let (mut x, mut z, mut phase) = (0.0, 0.0, 0.0);
    let mut in_sequence = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for step in 0..steps {
        let t = step as f64 * dt - warmup;
        let u = t / duration;
        let a = speed_fraction(u);
        let psi = heading(u);
        if step > 0 {
            let speed = WALK_SPEED * a;
            x += speed * psi.sin() * dt;
            z += speed * psi.cos() * dt;
            phase += std::f64::consts::TAU * speed / STRIDE * dt;
        }
        if t >= 0.0 {
            in_sequence = (
                in_sequence.0.min(x),
                in_sequence.1.max(x),
                in_sequence.2.min(z),
                in_sequence.3.max(z),
            );
        }
        let bob = -0.02 * a * (1.0 - (2.0 * phase).cos()) * 0.5;
        samples.push(MotionSample {
            pose: pose(phase, a, psi),
            position: DVec3::new(x, pelvis_height + bob, z),
        });
    }
    let centre = DVec3::new(
        0.5 * (in_sequence.0 + in_sequence.1),
        0.0,
        0.5 * (in_sequence.2 + in_sequence.3),
    );
    for s in &mut samples {
        s.position -= centre;
    }
    samples
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn script_walks_turns_stops_and_goes() {
        let duration = 4.0;
        let dt = 1.0 / 100.0;
        let samples = sample_script(duration, 1.0, dt, 0.95);
        let at = |t: f64| &samples[((t + 1.0) / dt).round() as usize];
        // Standing still during the warm-up and the stop.
        assert_eq!(at(-0.5).position, at(-0.9).position);
        let stop = (0.65 * duration, 0.75 * duration);
        assert!((at(stop.0).position - at(stop.1).position).length() < 1e-9);
        // Walking at full speed mid-way.
        let speed = (at(0.2 * duration + dt).position - at(0.2 * duration).position).length() / dt;
        assert!((speed - WALK_SPEED).abs() < 0.05, "{speed}");
        // Heading turned by 90 degrees after the turn.
        assert!((at(0.6 * duration).pose[0].y - TURN).abs() < 1e-9);
        // Standing pose during the stop: legs straight.
        assert!(at(0.7 * duration).pose[1].length() < 1e-9);
        // The path is centred on the origin over the sequence.
        let xs: Vec<f64> = samples[100..].iter().map(|s| s.position.x).collect();
        let (lo, hi) = xs
            .iter()
            .fold((f64::MAX, f64::MIN), |(l, h), &x| (l.min(x), h.max(x)));
        assert!((lo + hi).abs() < 1e-9);
        // The arms hang down: the left upper arm points mostly along -y.
        let arm = axis_angle_to_matrix(at(0.7 * duration).pose[16]) * DVec3::X;
        assert!(arm.y < -0.9, "{arm:?}");
    }
}
