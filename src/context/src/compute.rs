//! The motion templates of a whole sequence, in memory: posed template vertices, per-joint
//! rotations, skeleton motion and vertex velocity per (frame, scale), and the canonical
//! template with its KNN graph. The stage writes these arrays; the benchmark times this.

use rayon::prelude::*;
use seqavatar_core::body::{BodyModel, BodyParams, big_pose};
use seqavatar_core::glam::DMat3;
use seqavatar_core::rotation::axis_angle_to_matrix;
use seqavatar_schema::body::BodySequence;

use crate::context;
use crate::pose::pose_sequence;
use seqavatar_knn::{KnnGraph, knn_graph};
use seqavatar_schema::motion::{
    AUTHORS_MULTI, FrameAxis, InputScales, InputScaling, MotionArrays, MotionTrack, Scales,
    VelocityNormalisation,
};

/// The velocity normalisation `scaling` uses: the authors' quirk with their multiplier for
/// [`InputScaling::Authors`], `configured` otherwise.
pub fn effective_velocity(
    scaling: InputScaling,
    configured: VelocityNormalisation,
) -> VelocityNormalisation {
    match scaling {
        InputScaling::Authors => VelocityNormalisation::Reference {
            multi: AUTHORS_MULTI,
        },
        InputScaling::Rms | InputScaling::None => configured,
    }
}

/// The rotations the skeleton motion differentiates: the root's world orientation (the
/// reference code uses `Rh` for ZJU-MoCap and I3D-Human, where `pose_0` is zero, and
/// `global_orient` for DNA-Rendering, where `Rh` is zero; the product covers both), then the
/// local rotation of every other joint.
pub fn motion_rotations(params: &BodyParams) -> Vec<DMat3> {
    let mut out: Vec<DMat3> = params
        .pose
        .iter()
        .map(|&v| axis_angle_to_matrix(v))
        .collect();
    if let Some(root) = out.first_mut() {
        *root = axis_angle_to_matrix(params.world_rotation) * *root;
    }
    out
}

/// Computes every per-frame motion array of `sequence` posed with `model`.
pub fn compute_motion(
    model: &BodyModel,
    sequence: &BodySequence,
    scales: &Scales,
    normalisation: VelocityNormalisation,
) -> anyhow::Result<MotionArrays> {
    let (f, j, v) = (
        sequence.num_frames,
        sequence.num_joints,
        model.num_vertices(),
    );
    anyhow::ensure!(
        j == model.num_joints(),
        "the body parameters have {j} joints, the body model {}",
        model.num_joints()
    );
    let mut posed_vertices = vec![0.0_f32; f * v * 3];
    pose_sequence(model, sequence, &mut posed_vertices)?;
    let rotations: Vec<DMat3> = (0..f)
        .into_par_iter()
        .flat_map_iter(|t| motion_rotations(&sequence.params(t)))
        .collect();
    let skeleton_motion = context::skeleton_motion(&rotations, f, j, &scales.steps)?;
    let factors = scales.velocity_factors(normalisation);
    let vertex_velocity = context::vertex_velocity(&posed_vertices, f, v, &scales.steps, &factors)?;
    let joint_rotations = rotations
        .iter()
        .flat_map(|m| {
            let r = m.transpose().to_cols_array(); // columns of R^T = rows of R
            r.map(|x| x as f32)
        })
        .collect();
    Ok(MotionArrays {
        num_frames: f,
        num_vertices: v,
        num_joints: j,
        posed_vertices,
        joint_rotations,
        skeleton_motion,
        vertex_velocity,
    })
}

/// The canonical template: the model in the big pose with zero shape and no world transform
/// (as the reference code builds it), and its `k`-nearest-neighbour graph.
pub fn canonical_template(
    model: &BodyModel,
    k: usize,
) -> anyhow::Result<(Vec<[f32; 3]>, KnnGraph)> {
    let mut params = model.zero_params();
    params.pose = big_pose(model.num_joints());
    let posed = model
        .forward(&params)
        .map_err(|e| anyhow::anyhow!("canonical big pose: {e}"))?;
    let vertices: Vec<[f32; 3]> = posed
        .vertices
        .iter()
        .map(|p| [p.x as f32, p.y as f32, p.z as f32])
        .collect();
    let graph = knn_graph(&vertices, k)?;
    Ok((vertices, graph))
}

/// The motion track of `params` posed with `model`, at the raw `scales` of the motion entry,
/// its velocity normalisation and its recorded input scales (the motion crate's computation;
/// the scales are the trained-on entry's, not recomputed on `params`), on the frame `axis` of
/// the poses' source: how `pipeline render`, `export` and `view` drive an avatar with other
/// poses.
pub fn motion_track_for(
    model: &BodyModel,
    params: &[BodyParams],
    raw_scales: &[u32],
    interval: u32,
    normalisation: VelocityNormalisation,
    axis: FrameAxis,
    input_scales: &InputScales,
) -> anyhow::Result<MotionTrack> {
    let scales = Scales::new(raw_scales, interval)?;
    let sequence = BodySequence::from_params(params).map_err(anyhow::Error::msg)?;
    let mut arrays = compute_motion(model, &sequence, &scales, normalisation)?;
    arrays.scale_inputs(input_scales);
    Ok(MotionTrack {
        num_frames: arrays.num_frames,
        num_joints: arrays.num_joints,
        garment_rows: 0,
        num_vertices: arrays.num_vertices,
        scales: scales.raw.clone(),
        scale_steps: scales.steps.clone(),
        skeleton_motion: arrays.skeleton_motion,
        vertex_velocity: arrays.vertex_velocity,
        axis,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::tests::{test_model, test_params};
    use seqavatar_core::glam::DVec3;
    use std::f64::consts::PI;

    fn velocity_at(m: &MotionArrays, scales: usize, t: usize, slot: usize, v: usize) -> DVec3 {
        let at = ((t * scales + slot) * m.num_vertices + v) * 3;
        let x = &m.vertex_velocity[at..at + 3];
        DVec3::new(f64::from(x[0]), f64::from(x[1]), f64::from(x[2]))
    }

    fn skeleton_at(m: &MotionArrays, scales: usize, t: usize, slot: usize, j: usize) -> DVec3 {
        let at = ((t * scales + slot) * m.num_joints + j) * 3;
        let x = &m.skeleton_motion[at..at + 3];
        DVec3::new(f64::from(x[0]), f64::from(x[1]), f64::from(x[2]))
    }

    /// A still body that teleports 3 m at frame 5 while joint 3 flips by 180 degrees and
    /// joint 7 sits at a rotation of almost pi: every array stays finite, the teleport is
    /// one velocity spike per scale (and no skeleton motion), the flip is a rotation of pi.
    #[test]
    fn teleport_and_flip_between_frames() {
        let model = test_model(60);
        let mut params = test_params(&model, 10);
        let still = params[0].clone();
        for (t, p) in params.iter_mut().enumerate() {
            *p = still.clone();
            p.pose[7] = DVec3::new(0.0, PI - 1e-7, 0.0);
            if t >= 5 {
                p.world_translation += DVec3::new(3.0, 0.0, 0.0);
                p.pose[3] = DVec3::new(PI, 0.0, 0.0);
            } else {
                p.pose[3] = DVec3::ZERO;
            }
        }
        let sequence = BodySequence::from_params(&params).unwrap();
        let scales = Scales::new(&[2, 1], 1).unwrap();
        let m =
            compute_motion(&model, &sequence, &scales, VelocityNormalisation::PerScale).unwrap();
        assert!(m.posed_vertices.iter().all(|x| x.is_finite()));
        assert!(m.vertex_velocity.iter().all(|x| x.is_finite()));
        assert!(m.skeleton_motion.iter().all(|x| x.is_finite()));
        // Slots are largest scale first: slot 0 = 2 frames, slot 1 = 1 frame.
        let posed = |t: usize, v: usize| {
            let at = (t * 60 + v) * 3;
            DVec3::new(
                f64::from(m.posed_vertices[at]),
                f64::from(m.posed_vertices[at + 1]),
                f64::from(m.posed_vertices[at + 2]),
            )
        };
        for v in [0, 30, 59] {
            // The displacement over the scale, divided by the scale.
            let jump = posed(5, v) - posed(4, v);
            assert!((velocity_at(&m, 2, 5, 1, v) - jump).length() < 1e-5);
            assert!((velocity_at(&m, 2, 6, 0, v) - jump / 2.0).length() < 1e-5);
            assert!((velocity_at(&m, 2, 5, 0, v) - jump / 2.0).length() < 1e-5);
            for t in [1, 2, 3, 4, 7, 8, 9] {
                assert!(velocity_at(&m, 2, t, 1, v).length() < 1e-5, "t={t}");
            }
        }
        for t in 0..10 {
            for slot in 0..2 {
                // Translation is not skeleton motion; the near-pi joint does not move.
                assert!(skeleton_at(&m, 2, t, slot, 0).length() < 1e-6);
                assert!(skeleton_at(&m, 2, t, slot, 7).length() < 1e-5);
                let step = [2, 1][slot];
                let crosses = t >= 5 && t.saturating_sub(step) < 5;
                let flip = skeleton_at(&m, 2, t, slot, 3).length();
                if crosses {
                    assert!((flip - PI).abs() < 1e-5, "t={t} slot={slot} {flip}");
                } else {
                    assert!(flip < 1e-6, "t={t} slot={slot} {flip}");
                }
            }
        }
    }

    #[test]
    fn one_frame_and_nan_pose() {
        let model = test_model(40);
        let params = test_params(&model, 3);
        let scales = Scales::new(&[3, 1], 1).unwrap();
        let one = BodySequence::from_params(&params[..1]).unwrap();
        let m = compute_motion(&model, &one, &scales, VelocityNormalisation::PerScale).unwrap();
        assert_eq!(m.num_frames, 1);
        assert!(m.vertex_velocity.iter().all(|x| *x == 0.0));
        assert!(m.skeleton_motion.iter().all(|x| *x == 0.0));
        assert!(m.posed_vertices.iter().all(|x| x.is_finite()));
        let mut bad = params.clone();
        bad[2].pose[5].y = f64::NAN;
        let sequence = BodySequence::from_params(&bad).unwrap();
        let message = compute_motion(&model, &sequence, &scales, VelocityNormalisation::PerScale)
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("body_pose") && message.contains("frame 2, joint 5"),
            "{message}"
        );
    }

    /// On the history scene, `rms` gives every input block RMS 1 (the unscaled blocks are far
    /// from it), and `authors` reproduces the per-scale arrays times 300 times the raw scale
    /// over the smallest step (the reference quirk), skeleton motion unchanged.
    #[test]
    fn rms_scaling_gives_unit_blocks_and_authors_reproduces_the_reference_arrays() {
        use seqavatar_datasets::DatasetReader;
        use seqavatar_datasets::synthetic::{SceneKind, SyntheticConfig, SyntheticScene, history};
        let scene = SyntheticScene::generate(&SyntheticConfig {
            scene: SceneKind::History,
            fps: history::FPS,
            frames: history::LENGTH,
            cameras: 1,
            width: 32,
            height: 32,
            supersample: 1,
            garment: false,
            body_grid_spacing: 0.05,
            ..Default::default()
        })
        .unwrap();
        let (model, _) = scene.body_model().unwrap();
        let fits: Vec<_> = (0..history::LENGTH)
            .map(|f| scene.body_params(f).unwrap())
            .collect();
        let sequence = BodySequence::from_params(&fits).unwrap();
        let scales = Scales::new(&[6, 3], 1).unwrap();
        let per_scale =
            compute_motion(&model, &sequence, &scales, VelocityNormalisation::PerScale).unwrap();
        let before = (
            seqavatar_schema::motion::block_rms(
                &per_scale.skeleton_motion,
                2,
                per_scale.num_joints,
            ),
            seqavatar_schema::motion::block_rms(
                &per_scale.vertex_velocity,
                2,
                per_scale.num_vertices,
            ),
        );
        eprintln!(
            "history scene, unscaled RMS: skeleton motion {:?}, velocity {:?}",
            before.0, before.1
        );
        assert!(before.1.iter().all(|r| *r < 0.1), "{before:?}");
        let input_scales = InputScales::for_scaling(InputScaling::Rms, &per_scale, 2);
        let mut scaled = per_scale.clone();
        scaled.scale_inputs(&input_scales);
        for rms in
            seqavatar_schema::motion::block_rms(&scaled.skeleton_motion, 2, scaled.num_joints)
                .into_iter()
                .chain(seqavatar_schema::motion::block_rms(
                    &scaled.vertex_velocity,
                    2,
                    scaled.num_vertices,
                ))
        {
            assert!((rms - 1.0).abs() < 1e-4, "{rms}");
        }
        for (slot, factor) in input_scales.vertex_velocity.iter().enumerate() {
            assert!((factor * before.1[slot] - 1.0).abs() < 1e-9);
        }
        // Authors: per-scale velocity (displacement / raw scale) x raw scale x 300 / smallest
        // step; skeleton motion as computed.
        let normalisation =
            effective_velocity(InputScaling::Authors, VelocityNormalisation::PerScale);
        let mut authors = compute_motion(&model, &sequence, &scales, normalisation).unwrap();
        authors.scale_inputs(&InputScales::for_scaling(
            InputScaling::Authors,
            &authors,
            2,
        ));
        assert_eq!(authors.skeleton_motion, per_scale.skeleton_motion);
        let smallest = 3.0;
        let n = per_scale.num_vertices * 3;
        for (index, (a, p)) in authors
            .vertex_velocity
            .iter()
            .zip(&per_scale.vertex_velocity)
            .enumerate()
        {
            let raw = [6.0, 3.0][(index / n) % 2];
            let expected = f64::from(*p) * raw * 300.0 / smallest;
            assert!(
                (f64::from(*a) - expected).abs() <= 1e-4 * expected.abs().max(1.0),
                "{index}: {a} vs {expected}"
            );
        }
    }
}
