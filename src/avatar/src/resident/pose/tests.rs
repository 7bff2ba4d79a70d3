//! The device pose path against [`BodyRig::pose_with_chain`] and [`BodyRig::pose_backward`]
//! (f64), and the device backward against central differences of the device forward.

use std::sync::Arc;

use glam::{DMat3, DVec3};
use seqavatar_compute::backend::test_support::{
    gpu_test_context, gpu_test_context_with_dispatch_limit,
};
use seqavatar_compute::backend::{AdapterChoice, GpuContext};
use seqavatar_core::body::procedural::procedural_body;
use seqavatar_core::body::{BodyModel, BodyModelArrays, BodyParams};
use seqavatar_core::rng::SplitMix64;
use seqavatar_core::rotation::axis_angle_to_matrix;

use super::ResidentPose;
use crate::rig::{BodyRig, refine_pose};

/// Read-backs of the workspace (one round trip each) and the clearing of the status.
impl ResidentPose {
    /// Reads the target joints and vertex offsets back: one round trip.
    fn download_pose(&self) -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
        let mut values = self.context.download_all::<f32>(
            self.context.encoder(),
            &[
                (&self.target_joints.buffer, self.target_joints.len),
                (&self.vertex_offsets.buffer, self.vertex_offsets.len),
            ],
        )?;
        let offsets = values.pop().unwrap_or_default();
        let joints = values.pop().unwrap_or_default();
        Ok((joints, offsets))
    }

    /// Reads `dL/dR_ref` back, `(J - 1) x 9`: one round trip.
    fn download_refinement_gradients(&self) -> anyhow::Result<Vec<f32>> {
        Ok(self.context.download(
            self.context.encoder(),
            &self.refinement_gradients.buffer,
            self.refinement_gradients.len,
        )?)
    }

    fn clear_status(&self, encoder: &mut wgpu::CommandEncoder) {
        encoder.clear_buffer(&self.status.buffer, 0, None);
    }
}

/// `model` with random pose blend shapes (the procedural body has none).
fn with_pose_dirs(model: &BodyModel, seed: u64) -> BodyModel {
    let mut arrays = model.arrays().clone();
    let features = 9 * (model.num_joints() - 1);
    let mut rng = SplitMix64::new(seed);
    arrays.pose_dirs = (0..model.num_vertices() * 3 * features)
        .map(|_| rng.uniform(-0.01, 0.01) as f32)
        .collect();
    BodyModel::new(arrays).unwrap()
}

fn random_vector(rng: &mut SplitMix64, scale: f64) -> DVec3 {
    DVec3::new(
        rng.uniform(-scale, scale),
        rng.uniform(-scale, scale),
        rng.uniform(-scale, scale),
    )
}

/// A random rotation vector of angle `angle` about a random axis.
fn axis_angle(rng: &mut SplitMix64, angle: f64) -> DVec3 {
    loop {
        let v = random_vector(rng, 1.0);
        if v.length() > 0.1 {
            return v.normalize() * angle;
        }
    }
}

/// Frames covering the cases: moderate random poses, every joint near pi (one exactly at
/// pi), a second body shape, and non-zero world transforms throughout.
fn test_frames(model: &BodyModel, rng: &mut SplitMix64) -> Vec<BodyParams> {
    let joints = model.num_joints();
    let mut frames = Vec::new();
    for kind in 0..4 {
        let mut params = model.zero_params();
        for (j, p) in params.pose.iter_mut().enumerate() {
            *p = match kind {
                1 => axis_angle(rng, std::f64::consts::PI - 1e-3 * (j % 3) as f64),
                2 => {
                    let angle = rng.uniform(2.5, 3.1);
                    axis_angle(rng, angle)
                }
                _ => random_vector(rng, 0.6),
            };
        }
        if kind == 3 {
            for b in params.betas.iter_mut() {
                *b = rng.uniform(-1.0, 1.0);
            }
        }
        let angle = rng.uniform(0.2, 3.0);
        params.world_rotation = axis_angle(rng, angle);
        params.world_translation = random_vector(rng, 2.0);
        assert_eq!(params.pose.len(), joints);
        frames.push(params);
    }
    frames
}

fn random_rotations(rng: &mut SplitMix64, count: usize, angle: f64) -> Vec<DMat3> {
    (0..count)
        .map(|_| axis_angle_to_matrix(random_vector(rng, angle)))
        .collect()
}

/// Row-major f32 of 3 x 3 matrices.
fn flatten(matrices: &[DMat3]) -> Vec<f32> {
    matrices.iter().flat_map(|m| super::rows_f32(*m)).collect()
}

fn row_major(m: DMat3) -> [f64; 9] {
    let mut out = [0.0; 9];
    for r in 0..3 {
        out[3 * r] = m.x_axis[r];
        out[3 * r + 1] = m.y_axis[r];
        out[3 * r + 2] = m.z_axis[r];
    }
    out
}

/// Largest `|got - expected|` and largest `|expected|`.
fn worst(got: &[f32], expected: impl IntoIterator<Item = f64>) -> (f64, f64) {
    let expected: Vec<f64> = expected.into_iter().collect();
    assert_eq!(got.len(), expected.len());
    got.iter()
        .zip(&expected)
        .fold((0.0f64, 0.0f64), |(e, m), (g, x)| {
            (e.max((f64::from(*g) - x).abs()), m.max(x.abs()))
        })
}

/// Runs a forward (and, with gradients, a backward) on the device and waits.
fn run(
    context: &GpuContext,
    pose: &ResidentPose,
    frame: usize,
    refinements: Option<&[f32]>,
    gradients: Option<(&[f32], &[f32])>,
) {
    let refinements = refinements.map(|r| context.upload("refinements", r).unwrap());
    let gradients = gradients.map(|(t, o)| {
        (
            context.upload("d target joints", t).unwrap(),
            context.upload("d vertex offsets", o).unwrap(),
        )
    });
    let mut encoder = context.encoder();
    pose.forward(&mut encoder, frame, refinements.as_ref())
        .unwrap();
    if let Some((t, o)) = &gradients {
        pose.backward(&mut encoder, t, o).unwrap();
    }
    context.submit_and_wait(encoder).unwrap();
}

/// The procedural body with pose blend shapes drawn from seed `dirs_seed`, its rig, and
/// test frames drawn from a generator seeded `seed`, returned to draw on.
fn blended_body_frames(dirs_seed: u64, seed: u64) -> (BodyRig, Vec<BodyParams>, SplitMix64) {
    let model = with_pose_dirs(&procedural_body(0.05), dirs_seed);
    let rig = BodyRig::new(model.clone()).unwrap();
    let mut rng = SplitMix64::new(seed);
    let frames = test_frames(&model, &mut rng);
    (rig, frames, rng)
}

/// Forward and backward of every test frame against the rig, with no refiner, identity
/// refinements and random ones.
fn check_against_rig(context: Arc<GpuContext>, model: BodyModel, seed: u64) {
    let mut rng = SplitMix64::new(seed);
    let rig = BodyRig::new(model.clone()).unwrap();
    let frames = test_frames(&model, &mut rng);
    let pose = ResidentPose::new(context.clone(), &rig, &frames).unwrap();
    assert_eq!(pose.frame_count(), frames.len());
    assert_eq!(pose.shape_count(), 2);
    let joints = rig.joint_count();
    let vertices = rig.vertex_count();
    for (frame, params) in frames.iter().enumerate() {
        let identity = vec![DMat3::IDENTITY; joints - 1];
        let random = random_rotations(&mut rng, joints - 1, 1.2);
        for refinements in [None, Some(&identity), Some(&random)] {
            let refined = match refinements {
                Some(r) => refine_pose(params, r),
                None => params.clone(),
            };
            let (expected, chain) = rig.pose_with_chain(&refined).unwrap();
            let d_target: Vec<f64> = (0..12 * joints).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let d_offsets: Vec<f64> = (0..3 * vertices).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let d_target_f32: Vec<f32> = d_target.iter().map(|x| *x as f32).collect();
            let d_offsets_f32: Vec<f32> = d_offsets.iter().map(|x| *x as f32).collect();
            // The oracle's gradients from the f32 values the device sees.
            let d_target: Vec<f64> = d_target_f32.iter().map(|x| f64::from(*x)).collect();
            let d_offsets: Vec<f64> = d_offsets_f32.iter().map(|x| f64::from(*x)).collect();
            let flat = refinements.map(|r| flatten(r));
            run(
                &context,
                &pose,
                frame,
                flat.as_deref(),
                Some((&d_target_f32, &d_offsets_f32)),
            );
            let case = format!(
                "frame {frame}, refinements {}",
                match refinements {
                    None => "none",
                    Some(r) if r[0] == DMat3::IDENTITY => "identity",
                    Some(_) => "random",
                }
            );

            let (target, offsets) = pose.download_pose().unwrap();
            let (error, size) = worst(&target, expected.target_joints.iter().flatten().copied());
            assert!(
                error < 2e-6 * (1.0 + size),
                "{case}: target joints off by {error} (largest {size})"
            );
            let (error, size) = worst(&offsets, expected.vertex_offsets.iter().copied());
            assert!(
                error < 2e-6 * (1.0 + size),
                "{case}: vertex offsets off by {error} (largest {size})"
            );

            let d_rotations = rig.pose_backward(&chain, &d_target, &d_offsets);
            let (rotations, gradients) = pose.download_rotation_gradients().unwrap();
            let rig_rotations: Vec<DMat3> = refined
                .pose
                .iter()
                .map(|v| axis_angle_to_matrix(*v))
                .collect();
            let (error, _) = worst(&rotations, rig_rotations.iter().flat_map(|m| row_major(*m)));
            assert!(error < 1e-6, "{case}: refined rotations off by {error}");
            let (error, size) = worst(&gradients, d_rotations.iter().flat_map(|m| row_major(*m)));
            assert!(
                error < 2e-6 * size.max(1.0),
                "{case}: dL/dR' off by {error} (largest {size})"
            );
            // dL/dR_ref_j = R_j^T dL/dR'_j with the frame's own rotation.
            let expected_refinement = (1..joints).flat_map(|j| {
                row_major(axis_angle_to_matrix(params.pose[j]).transpose() * d_rotations[j])
            });
            let got = pose.download_refinement_gradients().unwrap();
            let (error, size) = worst(&got, expected_refinement);
            assert!(
                error < 2e-6 * size.max(1.0),
                "{case}: dL/dR_ref off by {error} (largest {size})"
            );
        }
    }
    assert!(pose.download_status().unwrap().is_clean());
}

#[test]
fn resident_pose_matches_the_rig_with_pose_blend_shapes() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    check_against_rig(context, with_pose_dirs(&procedural_body(0.05), 3), 11);
}

#[test]
fn resident_pose_matches_the_rig_without_pose_blend_shapes() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let model = procedural_body(0.05);
    assert!(!model.has_pose_dirs());
    check_against_rig(context, model, 12);
}

/// A random body with more joints than a workgroup has threads (the strided joint loops),
/// a deep random tree, and fewer vertex coordinates than one workgroup of either vertex
/// kernel.
fn random_tree_body(joints: usize, vertices: usize, seed: u64) -> BodyModel {
    let mut rng = SplitMix64::new(seed);
    let parents: Vec<i64> = (0..joints)
        .map(|j| {
            if j == 0 {
                -1
            } else {
                // Mostly the previous joint: long chains, as in arms and fingers.
                let p = if rng.uniform(0.0, 1.0) < 0.7 {
                    j - 1
                } else {
                    rng.below(j)
                };
                p as i64
            }
        })
        .collect();
    let template: Vec<[f64; 3]> = (0..vertices)
        .map(|_| random_vector(&mut rng, 1.0).to_array())
        .collect();
    // Every vertex mostly follows one joint (well-conditioned blends).
    let mut weights = vec![0.0; vertices * joints];
    for v in 0..vertices {
        let main = rng.below(joints);
        let other = rng.below(joints);
        weights[v * joints + main] += 0.8;
        weights[v * joints + other] += 0.2;
    }
    let mut joint_regressor = vec![0.0; joints * vertices];
    for j in 0..joints {
        let a = rng.below(vertices);
        let b = rng.below(vertices);
        joint_regressor[j * vertices + a] += 0.5;
        joint_regressor[j * vertices + b] += 0.5;
    }
    let num_betas = 3;
    let shape_dirs = (0..vertices * 3 * num_betas)
        .map(|_| rng.uniform(-0.05, 0.05))
        .collect();
    let features = 9 * (joints - 1);
    let pose_dirs = (0..vertices * 3 * features)
        .map(|_| rng.uniform(-0.01, 0.01) as f32)
        .collect();
    BodyModel::new(BodyModelArrays {
        template,
        faces: Vec::new(),
        parents,
        weights,
        joint_regressor,
        shape_dirs,
        num_betas,
        expression_dirs: Vec::new(),
        num_expression: 0,
        pose_dirs,
    })
    .unwrap()
}

#[test]
fn resident_pose_matches_the_rig_on_a_large_tree() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    check_against_rig(context, random_tree_body(70, 5, 21), 13);
}

/// `sum a . target_joints + sum b . vertex_offsets` of the last forward, in f64.
fn loss(pose: &ResidentPose, a: &[f32], b: &[f32]) -> f64 {
    let (target, offsets) = pose.download_pose().unwrap();
    let dot = |x: &[f32], y: &[f32]| -> f64 {
        x.iter()
            .zip(y)
            .map(|(p, q)| f64::from(*p) * f64::from(*q))
            .sum()
    };
    dot(&target, a) + dot(&offsets, b)
}

/// The device backward against central differences of the device forward, in directions
/// of single refinement matrices (the forward is linear in each, so the differences are
/// exact up to rounding) and of all of them at once. The device takes any matrices, so the
/// directions need not stay on the rotations.
#[test]
fn resident_pose_backward_matches_finite_differences() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let (rig, frames, mut rng) = blended_body_frames(4, 31);
    let pose = ResidentPose::new(context.clone(), &rig, &frames).unwrap();
    let joints = rig.joint_count();
    let a: Vec<f32> = (0..12 * joints)
        .map(|_| rng.uniform(-1.0, 1.0) as f32)
        .collect();
    let b: Vec<f32> = (0..3 * rig.vertex_count())
        .map(|_| rng.uniform(-1.0, 1.0) as f32)
        .collect();
    for frame in [0, 1] {
        let base = flatten(&random_rotations(&mut rng, joints - 1, 1.0));
        run(&context, &pose, frame, Some(&base), Some((&a, &b)));
        let gradient = pose.download_refinement_gradients().unwrap();
        let mut directions: Vec<(Vec<f32>, f64)> = Vec::new();
        for joint in [1, 4, 9, joints - 1] {
            let mut d = vec![0.0f32; base.len()];
            for k in 0..9 {
                d[9 * (joint - 1) + k] = rng.uniform(-1.0, 1.0) as f32;
            }
            directions.push((d, 0.05));
        }
        let all: Vec<f32> = (0..base.len())
            .map(|_| rng.uniform(-1.0, 1.0) as f32)
            .collect();
        directions.push((all, 1e-2));
        for (index, (direction, step)) in directions.iter().enumerate() {
            let at = |s: f64| {
                let moved: Vec<f32> = base
                    .iter()
                    .zip(direction)
                    .map(|(x, d)| (f64::from(*x) + s * f64::from(*d)) as f32)
                    .collect();
                run(&context, &pose, frame, Some(&moved), None);
                loss(&pose, &a, &b)
            };
            let numeric = (at(*step) - at(-*step)) / (2.0 * step);
            let analytic: f64 = gradient
                .iter()
                .zip(direction)
                .map(|(g, d)| f64::from(*g) * f64::from(*d))
                .sum();
            assert!(
                (numeric - analytic).abs() < 2e-3 * (1.0 + analytic.abs()),
                "frame {frame}, direction {index}: numeric {numeric}, analytic {analytic}"
            );
        }
    }
}

/// A steady-state iteration (forward and backward recorded and submitted) reads nothing
/// back and uploads only its 16-byte record.
#[test]
fn resident_pose_steady_state_uploads_only_its_record() {
    if gpu_test_context().is_none() {
        return;
    }
    // A context of its own: other tests share the common one and would be counted.
    let context = Arc::new(GpuContext::new(AdapterChoice::AllowSoftware).unwrap());
    let (rig, frames, mut rng) = blended_body_frames(5, 41);
    let pose = ResidentPose::new(context.clone(), &rig, &frames).unwrap();
    let joints = rig.joint_count();
    let refinements = context
        .upload(
            "refinements",
            &flatten(&random_rotations(&mut rng, joints - 1, 0.5)),
        )
        .unwrap();
    let d_target = context
        .upload("d target", &vec![0.5f32; 12 * joints])
        .unwrap();
    let d_offsets = context
        .upload("d offsets", &vec![0.25f32; 3 * rig.vertex_count()])
        .unwrap();
    let iteration = |frame: usize| {
        let mut encoder = context.encoder();
        pose.record_refiner_input(&mut encoder, frame).unwrap();
        pose.forward(&mut encoder, frame, Some(&refinements))
            .unwrap();
        pose.backward(&mut encoder, &d_target, &d_offsets).unwrap();
        context.submit_and_wait(encoder).unwrap();
    };
    iteration(0);
    let before = context.transfers();
    let iterations = 5;
    for i in 0..iterations {
        iteration(i % frames.len());
    }
    let traffic = context.transfers().since(&before);
    assert_eq!(traffic.readbacks, 0, "{traffic:?}");
    assert_eq!(traffic.bytes_down, 0, "{traffic:?}");
    assert_eq!(traffic.bytes_up, 16 * iterations as u64, "{traffic:?}");
    assert!(pose.download_status().unwrap().is_clean());
    // The refiner's input is the last iteration's frame's local pose.
    let last = (iterations - 1) % frames.len();
    let input: Vec<f32> = context
        .download(
            context.encoder(),
            &pose.refiner_input().buffer,
            pose.refiner_input().len,
        )
        .unwrap();
    let expected: Vec<f32> = crate::avatar::local_pose(&frames[last])
        .iter()
        .map(|x| *x as f32)
        .collect();
    assert_eq!(input, expected);
}

/// The vertex kernels split to 2D dispatches beyond the per-dimension limit give the same
/// values as 1D ones (same arithmetic, same order).
#[test]
fn resident_pose_dispatches_in_two_dimensions() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let Some(limited) = gpu_test_context_with_dispatch_limit(2) else {
        return;
    };
    let (rig, frames, mut rng) = blended_body_frames(6, 51);
    let joints = rig.joint_count();
    let refinements = flatten(&random_rotations(&mut rng, joints - 1, 1.0));
    let a: Vec<f32> = (0..12 * joints)
        .map(|_| rng.uniform(-1.0, 1.0) as f32)
        .collect();
    let b: Vec<f32> = (0..3 * rig.vertex_count())
        .map(|_| rng.uniform(-1.0, 1.0) as f32)
        .collect();
    let results: Vec<_> = [context, limited]
        .into_iter()
        .map(|context| {
            let pose = ResidentPose::new(context.clone(), &rig, &frames).unwrap();
            run(&context, &pose, 2, Some(&refinements), Some((&a, &b)));
            (
                pose.download_pose().unwrap(),
                pose.download_refinement_gradients().unwrap(),
            )
        })
        .collect();
    assert!((3 * rig.vertex_count()).div_ceil(super::OFFSET_GROUP) > 2);
    assert_eq!(results[0], results[1]);
}

/// Non-finite refinements are counted in the status buffer (the device keeps going), and
/// clearing resets the counters.
#[test]
fn resident_pose_flags_non_finite_values() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let (rig, frames, _) = blended_body_frames(7, 61);
    let pose = ResidentPose::new(context.clone(), &rig, &frames).unwrap();
    let joints = rig.joint_count();
    let mut refinements = flatten(&vec![DMat3::IDENTITY; joints - 1]);
    // Joint 15 (the head in SMPL's tree) has no children: one target joint goes bad.
    refinements[9 * 14 + 4] = f32::NAN;
    let a = vec![1.0f32; 12 * joints];
    let b = vec![1.0f32; 3 * rig.vertex_count()];
    run(&context, &pose, 0, Some(&refinements), Some((&a, &b)));
    let status = pose.download_status().unwrap();
    assert!(status.target_joints > 0, "{status:?}");
    assert!(status.target_joints <= 12, "{status:?}");
    assert!(status.vertex_offsets > 0, "{status:?}");
    assert!(status.refinement_gradients > 0, "{status:?}");
    let mut encoder = context.encoder();
    pose.clear_status(&mut encoder);
    context.submit_and_wait(encoder).unwrap();
    assert!(pose.download_status().unwrap().is_clean());
}

#[test]
fn resident_pose_rejects_bad_inputs() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let model = procedural_body(0.05);
    let rig = BodyRig::new(model.clone()).unwrap();
    let mut bad = model.zero_params();
    bad.pose.pop();
    let error = ResidentPose::new(context.clone(), &rig, &[model.zero_params(), bad])
        .err()
        .unwrap()
        .to_string();
    assert!(error.contains("frame 1"), "{error}");
    assert!(ResidentPose::new(context.clone(), &rig, &[]).is_err());

    let pose = ResidentPose::new(context.clone(), &rig, &[model.zero_params()]).unwrap();
    let mut encoder = context.encoder();
    let error = pose.forward(&mut encoder, 1, None).unwrap_err().to_string();
    assert!(error.contains("frame 1 out of range"), "{error}");
    let error = pose
        .record_refiner_input(&mut encoder, 3)
        .unwrap_err()
        .to_string();
    assert!(error.contains("frame 3 out of range"), "{error}");
    let short = context.upload("short", &[0.0f32; 9]).unwrap();
    let error = pose
        .forward(&mut encoder, 0, Some(&short))
        .unwrap_err()
        .to_string();
    assert!(error.contains("`refinements`"), "{error}");
    let error = pose
        .backward(&mut encoder, &short, &short)
        .unwrap_err()
        .to_string();
    assert!(error.contains("`d_target_joints`"), "{error}");
}
