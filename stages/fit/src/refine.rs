//! Refinement of a whole body-parameter sequence: every joint's rotation track, the world
//! rotation track and the translation track are smoothed independently and in parallel
//! ([`crate::smooth`]); the shape is shared per subject. Also the measures the stage reports:
//! joint positions, per-frame joint jitter, and errors against a ground truth.

use rayon::prelude::*;
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_core::rotation::{axis_angle_to_matrix, matrix_to_axis_angle};

use crate::smooth::{SmoothError, SmoothingPlan, smooth_rotation_track, smooth_translation_track};
use seqavatar_schema::body::BodySequence;

/// The axis-angle vector of rotation `r` closest to `reference` among all equivalent ones
/// (`u (theta + 2 pi k)`), so a refined pose keeps the input's branch: networks read raw
/// axis-angle components, which jump by `2 pi` between branches.
pub fn axis_angle_near(r: DMat3, reference: DVec3) -> DVec3 {
    let v = matrix_to_axis_angle(r);
    let theta = v.length();
    let tau = std::f64::consts::TAU;
    if theta < 1e-12 {
        // Identity: the candidates are any multiple of 2 pi along any axis; keep the
        // reference's axis and nearest multiple.
        let len = reference.length();
        let k = (len / tau).round();
        return if k == 0.0 || len == 0.0 {
            DVec3::ZERO
        } else {
            reference / len * (k * tau)
        };
    }
    let axis = v / theta;
    let mut best = v;
    let mut best_distance = (v - reference).length_squared();
    for k in -2..=2 {
        let candidate = axis * (theta + tau * f64::from(k));
        let d = (candidate - reference).length_squared();
        if d < best_distance {
            best = candidate;
            best_distance = d;
        }
    }
    best
}

/// What refinement did, for the log and the manifest.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RefineSummary {
    pub max_iterations_used: usize,
    pub energy_before: f64,
    pub energy_after: f64,
    /// True when per-frame betas differed and were replaced by their mean.
    pub betas_averaged: bool,
}

/// Refines every track of `input` (smooth mode), each with its own weights from `plan`.
/// Shape: the mean of the per-frame betas, which is the least-squares shared shape.
pub fn refine_sequence(
    input: &BodySequence,
    plan: &SmoothingPlan,
) -> Result<(BodySequence, RefineSummary), SmoothError> {
    plan.validate()?;
    let (f, j) = (input.num_frames, input.num_joints);
    // Track 0..j: joints; track j: world rotation.
    let rotation_tracks: Vec<Vec<DMat3>> = (0..=j)
        .map(|track| {
            (0..f)
                .map(|t| {
                    let v = if track < j {
                        input.pose[t * j + track]
                    } else {
                        input.world_rotation[t]
                    };
                    axis_angle_to_matrix(v)
                })
                .collect()
        })
        .collect();
    let rotation_results: Vec<_> = rotation_tracks
        .par_iter()
        .map(|track| smooth_rotation_track(track, &plan.rotation_track_weights(track)))
        .collect();
    let (translation, translation_report) = smooth_translation_track(
        &input.world_translation,
        &plan.translation_track_weights(&input.world_translation),
    )?;

    let mut output = input.clone();
    let mut summary = RefineSummary {
        max_iterations_used: translation_report.iterations,
        energy_before: translation_report.initial_energy,
        energy_after: translation_report.final_energy,
        betas_averaged: false,
    };
    for (track, result) in rotation_results.into_iter().enumerate() {
        let (rotations, report) = result?;
        summary.max_iterations_used = summary.max_iterations_used.max(report.iterations);
        summary.energy_before += report.initial_energy;
        summary.energy_after += report.final_energy;
        for (t, r) in rotations.into_iter().enumerate() {
            let slot = if track < j {
                &mut output.pose[t * j + track]
            } else {
                &mut output.world_rotation[t]
            };
            *slot = axis_angle_near(r, *slot);
        }
    }
    output.world_translation = translation;

    summary.betas_averaged = shared_betas(&mut output);
    Ok((output, summary))
}

/// Replaces the per-frame betas by their mean, the least-squares shared shape; true when
/// they differed.
pub fn shared_betas(sequence: &mut BodySequence) -> bool {
    let (f, b) = (sequence.num_frames, sequence.num_betas);
    if f == 0 || b == 0 {
        return false;
    }
    let mut mean = vec![0.0; b];
    for frame in sequence.betas.chunks_exact(b) {
        for (m, x) in mean.iter_mut().zip(frame) {
            *m += x / f as f64;
        }
    }
    let differed = sequence
        .betas
        .chunks_exact(b)
        .any(|frame| frame != mean.as_slice());
    sequence.betas = mean.repeat(f);
    differed
}

/// World-space joint positions of one frame: forward kinematics only (no vertices).
pub fn frame_joint_positions(model: &BodyModel, params: &BodyParams) -> Vec<DVec3> {
    let shaped = model.shaped_vertices(params);
    let rest = model.regress_joints(&shaped);
    let transforms = model.joint_transforms(&rest, &params.pose);
    let world_rotation = axis_angle_to_matrix(params.world_rotation);
    transforms
        .iter()
        .zip(&rest)
        .map(|(a, &r)| world_rotation * a.transform_point3(r) + params.world_translation)
        .collect()
}

/// World joint positions of every frame, `(frame, joint)`.
pub fn joint_positions(model: &BodyModel, sequence: &BodySequence) -> anyhow::Result<Vec<DVec3>> {
    let frames: Vec<anyhow::Result<Vec<DVec3>>> = (0..sequence.num_frames)
        .into_par_iter()
        .map(|t| {
            let params = sequence.params(t);
            model
                .check_params(&params)
                .map_err(|e| anyhow::anyhow!("frame {t}: {e}"))?;
            Ok(frame_joint_positions(model, &params))
        })
        .collect();
    let mut out = Vec::with_capacity(sequence.num_frames * sequence.num_joints);
    for frame in frames {
        out.extend(frame?);
    }
    Ok(out)
}

/// Per-frame joint jitter: the mean over joints of the second difference of joint
/// positions, `|k[t+1] - 2 k[t] + k[t-1]|` (metres per frame squared); zero at both ends.
pub fn joint_jitter(positions: &[DVec3], num_frames: usize, num_joints: usize) -> Vec<f64> {
    let mut out = vec![0.0; num_frames];
    if num_joints == 0 {
        return out;
    }
    for (t, value) in out
        .iter_mut()
        .enumerate()
        .take(num_frames.saturating_sub(1))
        .skip(1)
    {
        let sum: f64 = (0..num_joints)
            .map(|j| {
                let at = |u: usize| positions[u * num_joints + j];
                (at(t + 1) - 2.0 * at(t) + at(t - 1)).length()
            })
            .sum();
        *value = sum / num_joints as f64;
    }
    out
}

/// Mean Euclidean distance between two equally long point lists.
pub fn mean_distance(a: &[DVec3], b: &[DVec3]) -> f64 {
    if a.is_empty() {
        return 0.0;
    }
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x - *y).length())
        .sum::<f64>()
        / a.len() as f64
}

/// Mean error of per-frame template vertex velocity `(V[t] - V[t-1])` between a sequence and
/// the ground truth, over frames `1..F` and all vertices (metres per frame).
pub fn vertex_velocity_error(
    model: &BodyModel,
    sequence: &BodySequence,
    truth: &BodySequence,
) -> anyhow::Result<f64> {
    let pose_all = |s: &BodySequence| -> anyhow::Result<Vec<Vec<DVec3>>> {
        (0..s.num_frames)
            .into_par_iter()
            .map(|t| {
                model
                    .forward(&s.params(t))
                    .map(|p| p.vertices)
                    .map_err(|e| anyhow::anyhow!("frame {t}: {e}"))
            })
            .collect()
    };
    let a = pose_all(sequence)?;
    let b = pose_all(truth)?;
    let mut sum = 0.0;
    let mut count = 0usize;
    for t in 1..a.len() {
        for v in 0..a[t].len() {
            let va = a[t][v] - a[t - 1][v];
            let vb = b[t][v] - b[t - 1][v];
            sum += (va - vb).length();
            count += 1;
        }
    }
    Ok(if count == 0 { 0.0 } else { sum / count as f64 })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::smooth::{SmoothingPlan, SmoothingWeights};
    use seqavatar_datasets::DatasetReader;
    use seqavatar_datasets::synthetic::{SyntheticConfig, SyntheticScene};
    use std::f64::consts::PI;

    /// The acceptance test: on the synthetic scene (exact ground truth, jittered
    /// fits), smoothing must reduce the mean joint position error and the template vertex
    /// velocity error against the ground truth.
    #[test]
    fn smoothing_the_synthetic_scene_reduces_joint_and_velocity_error() {
        let config = SyntheticConfig {
            garment: false,
            frames: 48,
            ..SyntheticConfig::default()
        };
        let scene = SyntheticScene::generate(&config).unwrap();
        let (model, _) = scene.body_model().unwrap();
        let fits: Vec<BodyParams> = (0..config.frames)
            .map(|f| scene.body_params(f).unwrap())
            .collect();
        let input = BodySequence::from_params(&fits).unwrap();
        let truth = BodySequence::from_params(scene.ground_truth()).unwrap();
        let plan = crate::FitConfig::default().plan();
        let (refined, summary) = refine_sequence(&input, &plan).unwrap();
        assert!(summary.energy_after < summary.energy_before);

        let truth_joints = joint_positions(&model, &truth).unwrap();
        let before = mean_distance(&joint_positions(&model, &input).unwrap(), &truth_joints);
        let after = mean_distance(&joint_positions(&model, &refined).unwrap(), &truth_joints);
        let velocity_before = vertex_velocity_error(&model, &input, &truth).unwrap();
        let velocity_after = vertex_velocity_error(&model, &refined, &truth).unwrap();
        let jitter = |s: &BodySequence| {
            let j = joint_jitter(
                &joint_positions(&model, s).unwrap(),
                s.num_frames,
                s.num_joints,
            );
            j.iter().sum::<f64>() / j.len() as f64
        };
        println!(
            "synthetic scene, {} frames: joint error {:.2} -> {:.2} mm; vertex velocity error {:.3} -> {:.3} mm/frame; jitter {:.3} -> {:.3} (truth {:.3}) mm/frame^2",
            config.frames,
            before * 1e3,
            after * 1e3,
            velocity_before * 1e3,
            velocity_after * 1e3,
            jitter(&input) * 1e3,
            jitter(&refined) * 1e3,
            jitter(&truth) * 1e3,
        );
        assert!(after < before, "joint error {before} -> {after}");
        // README: 34.5 mm input; the fixed weights reached 19.1 mm.
        assert!(after <= 0.019, "joint error {before} -> {after}");
        assert!(
            velocity_after < 0.7 * velocity_before,
            "velocity error {velocity_before} -> {velocity_after}"
        );
    }

    /// The no-harm test: exact fits (the synthetic scene's ground truth) stay put,
    /// at the scene's pace and with twice the motion per frame (half the frame rate: a gait
    /// cycle in 11 frames, 11 cm of travel per frame).
    #[test]
    fn exact_fits_stay_put_even_through_fast_motion() {
        for fps in [15.0, 7.5] {
            let config = SyntheticConfig {
                garment: false,
                frames: 48,
                fps,
                ..SyntheticConfig::default()
            };
            let scene = SyntheticScene::generate(&config).unwrap();
            let (model, _) = scene.body_model().unwrap();
            let exact = BodySequence::from_params(scene.ground_truth()).unwrap();
            let (refined, _) = refine_sequence(&exact, &SmoothingPlan::default()).unwrap();
            let before = joint_positions(&model, &exact).unwrap();
            let after = joint_positions(&model, &refined).unwrap();
            let moved: Vec<f64> = before
                .iter()
                .zip(&after)
                .map(|(a, b)| (*a - *b).length())
                .collect();
            let mean = moved.iter().sum::<f64>() / moved.len() as f64;
            let max = moved.iter().copied().fold(0.0, f64::max);
            // The former fixed weights (2 degrees of noise, 1 degree per frame squared).
            let fixed = SmoothingWeights::default();
            let fixed_plan = SmoothingPlan {
                rotation_noise: Some(fixed.rotation_noise),
                rotation_acceleration: Some(fixed.rotation_acceleration),
                translation_noise: Some(fixed.translation_noise),
                translation_acceleration: Some(fixed.translation_acceleration),
                ..SmoothingPlan::default()
            };
            let (damaged, _) = refine_sequence(&exact, &fixed_plan).unwrap();
            let fixed_max = joint_positions(&model, &damaged)
                .unwrap()
                .iter()
                .zip(&before)
                .map(|(a, b)| (*a - *b).length())
                .fold(0.0, f64::max);
            println!(
                "exact fits at {fps} fps: joints moved {:.4} mm mean, {:.4} mm max (fixed weights: {:.2} mm max)",
                mean * 1e3,
                max * 1e3,
                fixed_max * 1e3
            );
            assert!(
                mean < 0.002 && max < 0.010,
                "{fps} fps: mean {mean}, max {max}"
            );
            assert!(
                fixed_max > 5.0 * max,
                "the fixed weights did harm: {fixed_max}"
            );
        }
    }

    #[test]
    fn axis_angle_near_keeps_the_reference_branch() {
        let r = axis_angle_to_matrix(DVec3::new(0.0, 0.0, 0.5));
        // Reference on the 2 pi + 0.5 branch.
        let v = axis_angle_near(r, DVec3::new(0.0, 0.0, 0.5 + 2.0 * PI));
        assert!((v - DVec3::new(0.0, 0.0, 0.5 + 2.0 * PI)).length() < 1e-9);
        // Reference near -pi about z: the rotation by pi - 0.01 about z is also
        // -(pi + 0.01) about... its nearest representative.
        let r = axis_angle_to_matrix(DVec3::new(0.0, 0.0, PI - 0.01));
        let v = axis_angle_near(r, DVec3::new(0.0, 0.0, -PI - 0.01));
        assert!(
            (v - DVec3::new(0.0, 0.0, -PI - 0.01)).length() < 1e-9,
            "{v:?}"
        );
        // Every result is the same rotation.
        assert!(
            (axis_angle_to_matrix(v) - r)
                .to_cols_array()
                .iter()
                .all(|x| x.abs() < 1e-9)
        );
        // Identity with a reference on the 2 pi branch.
        let v = axis_angle_near(DMat3::IDENTITY, DVec3::new(0.0, 2.0 * PI + 0.1, 0.0));
        assert!((v - DVec3::new(0.0, 2.0 * PI, 0.0)).length() < 1e-12);
        assert_eq!(axis_angle_near(DMat3::IDENTITY, DVec3::ZERO), DVec3::ZERO);
    }

    #[test]
    fn jitter_of_uniform_motion_is_zero_and_of_a_spike_is_known() {
        // Two joints moving uniformly: zero jitter.
        let positions: Vec<DVec3> = (0..5)
            .flat_map(|t| [DVec3::X * t as f64, DVec3::Y * 2.0 * t as f64])
            .collect();
        assert_eq!(joint_jitter(&positions, 5, 2), vec![0.0; 5]);
        // A spike of 1 on joint 0 at frame 2: second differences 1, 2, 1 at frames 1, 2, 3,
        // averaged over two joints.
        let mut spiked = positions.clone();
        spiked[4].z = 1.0;
        assert_eq!(joint_jitter(&spiked, 5, 2), vec![0.0, 0.5, 1.0, 0.5, 0.0]);
        assert_eq!(joint_jitter(&[DVec3::ZERO], 1, 1), vec![0.0]);
    }
}
