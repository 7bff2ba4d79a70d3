//! Tests of the body model against closed forms and central finite differences.
// The reference computations index dense arrays the way the formulas are written.
#![allow(clippy::needless_range_loop)]

use glam::{DMat3, DVec3};

use super::procedural::{self, DEFAULT_GRID_SPACING, JOINTS};
use super::*;
use crate::rotation::axis_angle_to_matrix;

/// Deterministic uniform numbers in [-1, 1) (SplitMix64).
struct Numbers(u64);

impl Numbers {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }

    fn vec3(&mut self, scale: f64) -> DVec3 {
        DVec3::new(self.next(), self.next(), self.next()) * scale
    }
}

/// A small random model with a branching tree and every kind of blend shape.
fn random_model(seed: u64, pose_dirs: bool) -> BodyModel {
    let mut rng = Numbers(seed);
    let parents = vec![-1, 0, 1, 1, 0, 4, 3];
    let num_joints = parents.len();
    let num_vertices = 40;
    let (num_betas, num_expression) = (3, 2);
    let template: Vec<[f64; 3]> = (0..num_vertices)
        .map(|_| rng.vec3(0.5).to_array())
        .collect();
    let mut weights = vec![0.0; num_vertices * num_joints];
    for v in 0..num_vertices {
        // Three joints per vertex, positive weights summing to one.
        let picks = [
            v % num_joints,
            (v * 3 + 1) % num_joints,
            (v * 5 + 2) % num_joints,
        ];
        let raw: Vec<f64> = picks.iter().map(|_| rng.next() + 1.5).collect();
        let total: f64 = raw.iter().sum();
        for (j, w) in picks.iter().zip(raw) {
            weights[v * num_joints + j] += w / total;
        }
    }
    let mut joint_regressor = vec![0.0; num_joints * num_vertices];
    for j in 0..num_joints {
        for k in 0..5 {
            joint_regressor[j * num_vertices + (j * 5 + k) % num_vertices] = 0.2;
        }
    }
    let shape_dirs = (0..num_vertices * 3 * num_betas)
        .map(|_| rng.next() * 0.05)
        .collect();
    let expression_dirs = (0..num_vertices * 3 * num_expression)
        .map(|_| rng.next() * 0.02)
        .collect();
    let pose_dirs = if pose_dirs {
        (0..num_vertices * 3 * 9 * (num_joints - 1))
            .map(|_| (rng.next() * 0.03) as f32)
            .collect()
    } else {
        Vec::new()
    };
    BodyModel::new(BodyModelArrays {
        template,
        faces: vec![[0, 1, 2], [2, 3, 4]],
        parents,
        weights,
        joint_regressor,
        shape_dirs,
        num_betas,
        expression_dirs,
        num_expression,
        pose_dirs,
    })
    .unwrap()
}

fn random_params(model: &BodyModel, seed: u64) -> BodyParams {
    let mut rng = Numbers(seed);
    BodyParams {
        pose: (0..model.num_joints()).map(|_| rng.vec3(0.8)).collect(),
        betas: (0..model.num_betas()).map(|_| rng.next()).collect(),
        expression: (0..model.num_expression()).map(|_| rng.next()).collect(),
        world_rotation: rng.vec3(1.0),
        world_translation: rng.vec3(2.0),
    }
}

#[test]
fn rest_pose_returns_the_template_and_regressed_joints() {
    let model = random_model(1, true);
    let posed = model.forward(&model.zero_params()).unwrap();
    for v in 0..model.num_vertices() {
        assert!((posed.vertices[v] - model.template_vertex(v)).length() < 1e-12);
    }
    for (j, joint) in posed.joints.iter().enumerate() {
        let expected: DVec3 = (0..5)
            .map(|k| model.template_vertex((j * 5 + k) % model.num_vertices()) * 0.2)
            .sum();
        assert!((*joint - expected).length() < 1e-12);
    }
}

#[test]
fn root_rotation_rotates_everything_about_the_root_joint() {
    let model = random_model(2, false);
    let mut params = model.zero_params();
    params.pose[0] = DVec3::new(0.3, -1.1, 0.4);
    params.world_translation = DVec3::new(0.5, 0.0, -2.0);
    let r = axis_angle_to_matrix(params.pose[0]);
    let posed = model.forward(&params).unwrap();
    let root = posed.rest_joints[0];
    for v in 0..model.num_vertices() {
        let expected = r * (model.template_vertex(v) - root) + root + params.world_translation;
        assert!((posed.vertices[v] - expected).length() < 1e-12);
    }
    for j in 0..model.num_joints() {
        let expected = r * (posed.rest_joints[j] - root) + root + params.world_translation;
        assert!((posed.joints[j] - expected).length() < 1e-12);
    }
}

#[test]
fn chain_kinematics_match_the_closed_form() {
    // Joint 1 -> 2 -> (3, 6): rotate joint 1 by a and joint 3 by b; joint 6 moves by
    // R_a R_b about the chain.
    let model = random_model(3, false);
    let mut params = model.zero_params();
    let (a, b) = (DVec3::new(0.0, 0.0, 0.9), DVec3::new(0.5, 0.2, 0.0));
    params.pose[1] = a;
    params.pose[3] = b;
    params.world_rotation = DVec3::new(0.0, 0.4, 0.0);
    let posed = model.forward(&params).unwrap();
    let rest = &posed.rest_joints;
    let (ra, rb, w) = (
        axis_angle_to_matrix(a),
        axis_angle_to_matrix(b),
        axis_angle_to_matrix(params.world_rotation),
    );
    let joint3 = rest[1] + ra * (rest[3] - rest[1]);
    let joint6 = joint3 + ra * rb * (rest[6] - rest[3]);
    let joint2 = rest[1] + ra * (rest[2] - rest[1]);
    assert!((posed.joints[3] - w * joint3).length() < 1e-12);
    assert!((posed.joints[6] - w * joint6).length() < 1e-12);
    assert!((posed.joints[2] - w * joint2).length() < 1e-12);
    assert!((posed.joints[4] - w * rest[4]).length() < 1e-12);
    // The skinning transform of joint 6 maps its rest joint onto its posed joint.
    let a6 = posed.joint_transforms[6];
    assert!((w * a6.transform_point3(rest[6]) - posed.joints[6]).length() < 1e-12);
}

#[test]
fn linear_blend_skinning_matches_a_direct_sum() {
    let model = random_model(4, true);
    let params = random_params(&model, 11);
    let posed = model.forward(&params).unwrap();
    let shaped = model.shaped_vertices(&params);
    // Independent pose-feature evaluation from the dense arrays.
    let rotations: Vec<DMat3> = params
        .pose
        .iter()
        .map(|&v| axis_angle_to_matrix(v))
        .collect();
    let num_features = 9 * (model.num_joints() - 1);
    let arrays = model.arrays();
    let w = axis_angle_to_matrix(params.world_rotation);
    for v in 0..model.num_vertices() {
        let mut p = shaped[v];
        for c in 0..3 {
            for j in 1..model.num_joints() {
                let m = rotations[j] - DMat3::IDENTITY;
                for row in 0..3 {
                    for col in 0..3 {
                        let feature = m.col(col)[row];
                        let index = (v * 3 + c) * num_features + (j - 1) * 9 + row * 3 + col;
                        p[c] += arrays.pose_dirs[index] as f64 * feature;
                    }
                }
            }
        }
        let mut x = DVec3::ZERO;
        for j in 0..model.num_joints() {
            let weight = arrays.weights[v * model.num_joints() + j];
            x += posed.joint_transforms[j].transform_point3(p) * weight;
        }
        let expected = w * x + params.world_translation;
        assert!(
            (posed.vertices[v] - expected).length() < 1e-12,
            "vertex {v}"
        );
    }
}

/// Scalar test loss `sum c_v . y_v + sum d_j . k_j` and its gradient by central differences.
fn check_vjp(model: &BodyModel, params: &BodyParams, seed: u64) {
    let mut rng = Numbers(seed);
    let cv: Vec<DVec3> = (0..model.num_vertices()).map(|_| rng.vec3(1.0)).collect();
    let cj: Vec<DVec3> = (0..model.num_joints()).map(|_| rng.vec3(1.0)).collect();
    let loss = |p: &BodyParams| -> f64 {
        let posed = model.forward(p).unwrap();
        posed
            .vertices
            .iter()
            .zip(&cv)
            .map(|(a, b)| a.dot(*b))
            .sum::<f64>()
            + posed
                .joints
                .iter()
                .zip(&cj)
                .map(|(a, b)| a.dot(*b))
                .sum::<f64>()
    };
    let grad = model.vjp(params, &cv, &cj).unwrap();
    let h = 1e-6;
    let check = |name: &str, analytic: f64, perturb: &dyn Fn(&mut BodyParams, f64)| {
        let mut plus = params.clone();
        perturb(&mut plus, h);
        let mut minus = params.clone();
        perturb(&mut minus, -h);
        let numeric = (loss(&plus) - loss(&minus)) / (2.0 * h);
        let tolerance = 1e-6 * (1.0 + numeric.abs());
        assert!(
            (numeric - analytic).abs() < tolerance,
            "{name}: analytic {analytic} numeric {numeric}"
        );
    };
    for j in 0..model.num_joints() {
        for c in 0..3 {
            check(&format!("pose[{j}][{c}]"), grad.pose[j][c], &|p, d| {
                p.pose[j][c] += d
            });
        }
    }
    for c in 0..3 {
        check(
            &format!("world_rotation[{c}]"),
            grad.world_rotation[c],
            &|p, d| p.world_rotation[c] += d,
        );
        check(
            &format!("world_translation[{c}]"),
            grad.world_translation[c],
            &|p, d| p.world_translation[c] += d,
        );
    }
    for b in 0..params.betas.len() {
        check(&format!("betas[{b}]"), grad.betas[b], &|p, d| {
            p.betas[b] += d
        });
    }
    for e in 0..params.expression.len() {
        check(&format!("expression[{e}]"), grad.expression[e], &|p, d| {
            p.expression[e] += d
        });
    }
}

#[test]
fn vjp_matches_central_differences() {
    let model = random_model(5, true);
    check_vjp(&model, &random_params(&model, 21), 31);
    // Rest pose (rotation Jacobians at 0) and a rotation near pi.
    let mut params = model.zero_params();
    check_vjp(&model, &params, 32);
    params.pose[2] = DVec3::new(0.0, std::f64::consts::PI - 1e-3, 0.0);
    params.world_rotation = DVec3::new(1e-7, 0.0, 0.0);
    check_vjp(&model, &params, 33);
    // Without pose blend shapes.
    let model = random_model(6, false);
    check_vjp(&model, &random_params(&model, 22), 34);
}

#[test]
fn vjp_of_joints_only_and_vertices_only() {
    let model = random_model(7, true);
    let params = random_params(&model, 23);
    let cj = vec![DVec3::new(1.0, -2.0, 0.5); model.num_joints()];
    let cv = vec![DVec3::new(0.3, 0.1, -1.0); model.num_vertices()];
    let joints_only = model.vjp(&params, &[], &cj).unwrap();
    let vertices_only = model.vjp(&params, &cv, &[]).unwrap();
    let both = model.vjp(&params, &cv, &cj).unwrap();
    for j in 0..model.num_joints() {
        assert!((joints_only.pose[j] + vertices_only.pose[j] - both.pose[j]).length() < 1e-10);
    }
    // Translation gradient of sum d . k_j is sum d.
    assert!((joints_only.world_translation - cj.iter().sum::<DVec3>()).length() < 1e-12);
}

#[test]
fn params_are_validated() {
    let model = random_model(8, false);
    let mut params = model.zero_params();
    params.pose.pop();
    assert_eq!(
        model.forward(&params).unwrap_err(),
        BodyParamsError::PoseLength {
            expected: 7,
            got: 6
        }
    );
    let mut params = model.zero_params();
    params.betas = vec![0.0; 4];
    assert!(matches!(
        model.forward(&params).unwrap_err(),
        BodyParamsError::TooManyCoefficients { field: "betas", .. }
    ));
    let mut params = model.zero_params();
    params.world_translation.y = f64::NAN;
    assert_eq!(
        model.forward(&params).unwrap_err(),
        BodyParamsError::NotFinite
    );
    // Absurd magnitudes (a pose file with global_orient = 1e30): refused, naming the field.
    let mut params = model.zero_params();
    params.pose[0].x = 1e30;
    assert!(matches!(
        model.forward(&params).unwrap_err(),
        BodyParamsError::Absurd {
            field: "global_orient",
            ..
        }
    ));
    let mut params = model.zero_params();
    params.pose[3].z = -1.5e3;
    assert!(matches!(
        model.forward(&params).unwrap_err(),
        BodyParamsError::Absurd {
            field: "body_pose",
            ..
        }
    ));
    let mut params = model.zero_params();
    params.world_translation.x = 2e4;
    let error = model.forward(&params).unwrap_err();
    assert!(
        matches!(
            error,
            BodyParamsError::Absurd {
                field: "transl",
                ..
            }
        ),
        "{error}"
    );
    // Large but plausible values pass: several turns, a kilometre away.
    let mut params = model.zero_params();
    params.pose[0].x = 20.0;
    params.world_translation.x = 1e3;
    model.forward(&params).unwrap();
    // Fewer betas than the model has: the rest are zero.
    let mut short = model.zero_params();
    short.betas = vec![0.5];
    let mut full = model.zero_params();
    full.betas = vec![0.5, 0.0, 0.0];
    assert_eq!(
        model.forward(&short).unwrap().vertices,
        model.forward(&full).unwrap().vertices
    );
}

#[test]
fn model_arrays_are_validated_with_field_names() {
    let good = random_model(9, true).arrays().clone();
    let mut bad = good.clone();
    bad.weights.pop();
    let err = BodyModel::new(bad).unwrap_err();
    assert!(err.to_string().contains("`weights`"), "{err}");
    let mut bad = good.clone();
    bad.parents[3] = 5;
    assert_eq!(
        BodyModel::new(bad).unwrap_err(),
        BodyModelError::BadParent {
            joint: 3,
            parent: 5
        }
    );
    let mut bad = good.clone();
    bad.faces[1][2] = 40;
    assert!(matches!(
        BodyModel::new(bad).unwrap_err(),
        BodyModelError::FaceIndex {
            face: 1,
            index: 40,
            ..
        }
    ));
    let mut bad = good.clone();
    bad.weights[0] += 0.1;
    assert!(matches!(
        BodyModel::new(bad).unwrap_err(),
        BodyModelError::WeightSum { vertex: 0, .. }
    ));
    let mut bad = good.clone();
    bad.pose_dirs[7] = f32::INFINITY;
    assert_eq!(
        BodyModel::new(bad).unwrap_err(),
        BodyModelError::NotFinite {
            field: "posedirs",
            index: 7
        }
    );
    let mut bad = good.clone();
    bad.shape_dirs.push(0.0);
    assert!(
        BodyModel::new(bad)
            .unwrap_err()
            .to_string()
            .contains("`shapedirs`")
    );
    let mut bad = good;
    bad.template.clear();
    assert!(matches!(
        BodyModel::new(bad).unwrap_err(),
        BodyModelError::Empty { .. }
    ));
}

#[test]
fn procedural_body_is_a_closed_skinned_surface() {
    let model = procedural::procedural_body(DEFAULT_GRID_SPACING);
    let num_vertices = model.num_vertices();
    assert!(
        (2500..8000).contains(&num_vertices),
        "{num_vertices} vertices"
    );
    assert_eq!(model.num_joints(), 24);
    assert_eq!(model.num_betas(), 2);
    // Closed and consistently oriented: every directed edge has its reverse exactly once.
    let mut edges = std::collections::HashMap::new();
    for f in model.faces() {
        for k in 0..3 {
            *edges.entry((f[k], f[(k + 1) % 3])).or_insert(0) += 1;
        }
    }
    for (&(a, b), &count) in &edges {
        assert_eq!(count, 1, "edge {a}->{b} used {count} times");
        assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}->{b} has no twin");
    }
    // Outward orientation: the signed volume is positive and near the capsules' volume.
    let volume: f64 = model
        .faces()
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| model.template_vertex(i as usize));
            a.dot(b.cross(c)) / 6.0
        })
        .sum();
    assert!((0.03..0.12).contains(&volume), "volume {volume} m^3");
    // Height about 1.74 m from sole to crown.
    let ys: Vec<f64> = (0..num_vertices)
        .map(|v| model.template_vertex(v).y)
        .collect();
    let (lo, hi) = (
        ys.iter().cloned().fold(f64::MAX, f64::min),
        ys.iter().cloned().fold(f64::MIN, f64::max),
    );
    assert!((1.65..1.85).contains(&(hi - lo)), "height {}", hi - lo);
    // The regressor reproduces the designed joints on the template.
    let posed = model.forward(&model.zero_params()).unwrap();
    for (j, joint) in JOINTS.iter().enumerate() {
        assert!(
            (posed.joints[j] - DVec3::from_array(*joint)).length() < 1e-9,
            "joint {j}"
        );
    }
    // Weights: at most four joints per vertex, summing to one; hands follow the wrist chain.
    for v in 0..num_vertices {
        let w: Vec<(usize, f64)> = model.vertex_weights(v).collect();
        assert!(w.len() <= 4);
        assert!((w.iter().map(|x| x.1).sum::<f64>() - 1.0).abs() < 1e-12);
        let p = model.template_vertex(v);
        if p.x > 0.8 {
            let dominant = w.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap().0;
            assert_eq!(dominant, 22, "fingertip vertex {v} at {p:?}");
        }
    }
}

#[test]
fn procedural_shape_parameters_scale_height_and_girth() {
    let model = procedural::procedural_body(0.03);
    let mut params = model.zero_params();
    params.betas = vec![1.0, 0.0];
    let tall = model.forward(&params).unwrap();
    for v in 0..model.num_vertices() {
        let expected = model.template_vertex(v) * (1.0 + procedural::HEIGHT_PER_BETA);
        assert!((tall.vertices[v] - expected).length() < 1e-12);
    }
    // Joints scale the same way (the regressor is affine).
    for (j, joint) in JOINTS.iter().enumerate() {
        let expected = DVec3::from_array(*joint) * (1.0 + procedural::HEIGHT_PER_BETA);
        assert!((tall.joints[j] - expected).length() < 1e-9);
    }
    // Girth: the upper arm's cross-section grows by 15 %, its joints barely move.
    params.betas = vec![0.0, 1.0];
    let wide = model.forward(&params).unwrap();
    let shoulder = DVec3::from_array(JOINTS[16]);
    let elbow = DVec3::from_array(JOINTS[18]);
    let mid = (shoulder + elbow) * 0.5;
    let radius = |vertices: &[DVec3]| -> f64 {
        let near: Vec<f64> = vertices
            .iter()
            .filter(|p| (p.x - mid.x).abs() < 0.02)
            .map(|p| ((p.y - mid.y).powi(2) + (p.z - mid.z).powi(2)).sqrt())
            .collect();
        near.iter().sum::<f64>() / near.len() as f64
    };
    let rest = model.forward(&model.zero_params()).unwrap();
    let ratio = radius(&wide.vertices) / radius(&rest.vertices);
    assert!(
        (ratio - 1.0 - procedural::GIRTH_PER_BETA).abs() < 0.01,
        "girth ratio {ratio}"
    );
    assert!((wide.joints[18] - elbow).length() < 0.01);
}

#[test]
fn procedural_body_vjp_matches_central_differences() {
    let model = procedural::procedural_body(0.04);
    let mut params = model.zero_params();
    params.pose = big_pose(24);
    params.pose[18] = DVec3::new(0.2, 0.9, -0.1);
    params.betas = vec![0.3, -0.5];
    params.world_rotation = DVec3::new(0.0, 1.2, 0.0);
    check_vjp(&model, &params, 41);
}

#[test]
fn big_pose_spreads_the_legs_and_keeps_the_feet_flat() {
    let model = procedural::procedural_body(0.03);
    let mut params = model.zero_params();
    params.pose = big_pose(24);
    let posed = model.forward(&params).unwrap();
    let rest = model.forward(&model.zero_params()).unwrap();
    let spread = |p: &Posed| p.joints[7].x - p.joints[8].x;
    assert!(
        spread(&posed) > spread(&rest) + 0.4,
        "{} vs {}",
        spread(&posed),
        spread(&rest)
    );
    // The ankle undoes part of the hip rotation: the foot bone turns by 45 - 30 = 15 deg.
    let foot = posed.joints[10] - posed.joints[7];
    let foot_rest = rest.joints[10] - rest.joints[7];
    let expected = axis_angle_to_matrix(DVec3::new(0.0, 0.0, 15f64.to_radians())) * foot_rest;
    assert!((foot - expected).length() < 1e-9);
}
