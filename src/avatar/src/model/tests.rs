//! Tests of the networks: every gradient against f64 central differences, the per-frame
//! bias trick against a materialised-concatenation forward written with naive loops, the
//! identity start, disabled blocks, extremes and input errors.

use seqavatar_compute::nn::{Precision, Rng};
use seqavatar_core::glam::DVec3;
use seqavatar_core::rotation::axis_angle_to_matrix;

use super::lbs::{blend_weights, blend_weights_backward};
use super::pose_refiner::{regularised_rodrigues, regularised_rodrigues_backward};
use super::*;
use crate::config::MotionContext;

fn random(rng: &mut Rng, len: usize, bound: f64) -> Vec<f64> {
    (0..len).map(|_| rng.uniform(-bound, bound)).collect()
}

/// Small widths so finite differences over every parameter stay fast.
fn small_config(context: MotionContext, n_scales: usize, length: usize) -> NetworkConfig {
    NetworkConfig {
        motion_context: context,
        trunk_width: 7,
        trunk_depth: 2,
        skinning_joints: 3,
        motion_joints: 4,
        tau: 2,
        sequence_length: length,
        n_scales,
        pose_refiner: true,
        lbs_offsets: true,
        widths: Widths {
            encoding_frequencies: 2,
            pose_encoder: 5,
            seq_pose_frame: 3,
            seq_pose: 4,
            seq_xyz_velocity: 5,
            seq_xyz_position: 3,
            seq_xyz_frame: 4,
            seq_xyz_hidden: 6,
            seq_xyz: 5,
            pose_refiner_hidden: 6,
            lbs_hidden: 5,
        },
    }
}

struct Inputs {
    pose: Vec<f64>,
    skeleton: Option<Vec<f64>>,
    xyz: Vec<f64>,
    velocity: Option<Vec<f64>>,
}

fn inputs(config: &NetworkConfig, n: usize, rng: &mut Rng) -> Inputs {
    Inputs {
        pose: random(rng, config.pose_dim(), 1.0),
        skeleton: config
            .motion_context
            .has_skeleton_motion()
            .then(|| random(rng, config.skeleton_motion_len(), 1.0)),
        xyz: random(rng, 3 * n, 1.0),
        velocity: config
            .motion_context
            .has_velocity()
            .then(|| random(rng, n * config.sequence_length * config.seq_xyz_row(), 1.0)),
    }
}

impl Inputs {
    fn frame(&self) -> FrameInputs<'_, f64> {
        FrameInputs {
            local_pose: &self.pose,
            skeleton_motion: self.skeleton.as_deref(),
        }
    }
    fn gaussians(&self) -> GaussianInputs<'_, f64> {
        GaussianInputs {
            xyz: &self.xyz,
            knn_velocity: self.velocity.as_deref(),
        }
    }
}

/// Moves every bias a little so that ReLU units are rarely exactly at their kink and
/// default-initialised biases do not make most units dead for tiny widths.
fn perturb(networks: &mut Networks<f64>, rng: &mut Rng) {
    for param in networks.parameters_mut() {
        for value in param.values.iter_mut() {
            *value += rng.uniform(-0.05, 0.05);
        }
    }
}

struct Probe {
    dxyz: Vec<f64>,
    drot: Vec<f64>,
    dscale: Vec<f64>,
}

fn non_rigid_loss(networks: &Networks<f64>, input: &Inputs, probe: &Probe) -> f64 {
    let (out, _) = networks
        .non_rigid_forward(&input.frame(), &input.gaussians())
        .unwrap();
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    dot(&out.d_xyz, &probe.dxyz) + dot(&out.d_rot, &probe.drot) + dot(&out.d_scale, &probe.dscale)
}

/// Compares every parameter gradient of `group` with central differences of `loss`.
fn check_parameter_gradients(
    networks: &Networks<f64>,
    group: NetworkGroup,
    loss: &dyn Fn(&Networks<f64>) -> f64,
) -> usize {
    let h = 1e-6;
    let analytic: Vec<(String, Vec<f64>)> = networks
        .parameters()
        .into_iter()
        .filter(|p| p.group == group)
        .map(|p| (p.name, p.grads.to_vec()))
        .collect();
    let mut checked = 0;
    for (name, grads) in analytic {
        for i in 0..grads.len() {
            let mut shifted = networks.clone();
            let set = |net: &mut Networks<f64>, delta: f64| {
                for param in net.parameters_mut() {
                    if param.name == name {
                        param.values[i] += delta;
                    }
                }
            };
            set(&mut shifted, h);
            let plus = loss(&shifted);
            set(&mut shifted, -2.0 * h);
            let minus = loss(&shifted);
            let fd = (plus - minus) / (2.0 * h);
            assert!(
                (grads[i] - fd).abs() <= 1e-6 * (1.0 + fd.abs()),
                "{name}[{i}]: analytic {} vs finite difference {fd}",
                grads[i]
            );
            checked += 1;
        }
    }
    checked
}

fn check_non_rigid(config: &NetworkConfig, n: usize, seed: u64) {
    let mut rng = Rng::new(seed);
    let mut networks = Networks::<f64>::new(config, seed).unwrap();
    perturb(&mut networks, &mut rng);
    let input = inputs(config, n, &mut rng);
    let probe = Probe {
        dxyz: random(&mut rng, 3 * n, 1.0),
        drot: random(&mut rng, 4 * n, 1.0),
        dscale: random(&mut rng, 3 * n, 1.0),
    };
    let (out, cache) = networks
        .non_rigid_forward(&input.frame(), &input.gaussians())
        .unwrap();
    assert_eq!(
        (out.d_xyz.len(), out.d_rot.len(), out.d_scale.len()),
        (3 * n, 4 * n, 3 * n)
    );
    networks.zero_grad();
    let d_xyz = networks
        .non_rigid_backward(&cache, &probe.dxyz, &probe.drot, &probe.dscale)
        .unwrap();
    let checked = check_parameter_gradients(&networks, NetworkGroup::NonRigid, &|net| {
        non_rigid_loss(net, &input, &probe)
    });
    assert_eq!(
        checked,
        networks
            .parameters()
            .iter()
            .filter(|p| p.group == NetworkGroup::NonRigid)
            .map(|p| p.values.len())
            .sum::<usize>()
    );
    // The position gradient flows through the encoding.
    let h = 1e-6;
    for i in 0..input.xyz.len() {
        let mut shifted = Inputs {
            pose: input.pose.clone(),
            skeleton: input.skeleton.clone(),
            xyz: input.xyz.clone(),
            velocity: input.velocity.clone(),
        };
        shifted.xyz[i] += h;
        let plus = non_rigid_loss(&networks, &shifted, &probe);
        shifted.xyz[i] -= 2.0 * h;
        let minus = non_rigid_loss(&networks, &shifted, &probe);
        let fd = (plus - minus) / (2.0 * h);
        assert!(
            (d_xyz[i] - fd).abs() <= 1e-6 * (1.0 + fd.abs()),
            "d_xyz[{i}]: analytic {} vs finite difference {fd}",
            d_xyz[i]
        );
    }
}

#[test]
fn non_rigid_gradients_match_finite_differences_at_every_level() {
    check_non_rigid(&small_config(MotionContext::Pose, 1, 2), 4, 1);
    check_non_rigid(&small_config(MotionContext::Skeleton, 1, 2), 4, 2);
    check_non_rigid(&small_config(MotionContext::Velocity, 1, 3), 3, 3);
    check_non_rigid(&small_config(MotionContext::Multiscale, 2, 2), 3, 4);
}

#[test]
fn non_rigid_extremes_one_gaussian_one_frame_one_scale_and_full_encoding() {
    let mut config = small_config(MotionContext::Multiscale, 1, 1);
    check_non_rigid(&config, 1, 5);
    config.widths.encoding_frequencies = 10;
    config.tau = 1;
    check_non_rigid(&config, 2, 6);
}

#[test]
fn zero_gaussians_give_empty_outputs_and_only_per_frame_gradients() {
    let config = small_config(MotionContext::Multiscale, 2, 2);
    let mut rng = Rng::new(9);
    let mut networks = Networks::<f64>::new(&config, 3).unwrap();
    let input = inputs(&config, 0, &mut rng);
    let (out, cache) = networks
        .non_rigid_forward(&input.frame(), &input.gaussians())
        .unwrap();
    assert!(out.d_xyz.is_empty() && out.d_rot.is_empty() && out.d_scale.is_empty());
    let d_xyz = networks.non_rigid_backward(&cache, &[], &[], &[]).unwrap();
    assert!(d_xyz.is_empty());
    assert!(
        networks
            .parameters()
            .iter()
            .all(|p| p.grads.iter().all(|&g| g == 0.0))
    );
    let (offsets, lbs_cache) = networks.lbs_offsets_forward(&[]).unwrap();
    assert!(offsets.is_empty());
    networks.lbs_offsets_backward(&lbs_cache, &[]).unwrap();
}

// ---------------------------------------------------------------------------------------
// Independent forward: naive loops, explicit concatenation in the reference order
// (63, 32, 32, 96), every per-frame value copied to every Gaussian and the position branch
// of the SeqXYZEncoder to every window element.

fn naive_layer(x: &[f64], weight: &[f64], bias: &[f64], relu: bool) -> Vec<f64> {
    let out = bias.len();
    assert_eq!(weight.len(), x.len() * out);
    (0..out)
        .map(|j| {
            let sum = bias[j]
                + (0..x.len())
                    .map(|i| x[i] * weight[i * out + j])
                    .sum::<f64>();
            if relu { sum.max(0.0) } else { sum }
        })
        .collect()
}

fn naive_encoding(p: &[f64], frequencies: usize) -> Vec<f64> {
    let mut e = p.to_vec();
    for k in 0..frequencies {
        let s = f64::from(1u32 << k);
        e.extend(p.iter().map(|x| (s * x).sin()));
        e.extend(p.iter().map(|x| (s * x).cos()));
    }
    e
}

fn naive_non_rigid(
    networks: &Networks<f64>,
    config: &NetworkConfig,
    input: &Inputs,
) -> Vec<[f64; 10]> {
    let params: std::collections::HashMap<String, Vec<f64>> = networks
        .parameters()
        .into_iter()
        .map(|p| (p.name, p.values.to_vec()))
        .collect();
    let layer = |name: &str, x: &[f64], relu: bool| {
        naive_layer(
            x,
            &params[&format!("non_rigid.{name}.weight")],
            &params[&format!("non_rigid.{name}.bias")],
            relu,
        )
    };
    let w = config.widths;
    let length = config.sequence_length;
    let pose = layer(
        "pose_encoder.1",
        &layer("pose_encoder.0", &input.pose, true),
        true,
    );
    let seq_pose = input.skeleton.as_ref().map(|motion| {
        let frames: Vec<f64> = motion
            .chunks(config.seq_pose_row())
            .flat_map(|row| layer("seq_pose_encoder.frame", row, true))
            .collect();
        layer("seq_pose_encoder.sequence", &frames, true)
    });
    let n = input.xyz.len() / 3;
    (0..n)
        .map(|g| {
            let encoding = naive_encoding(&input.xyz[3 * g..3 * g + 3], w.encoding_frequencies);
            let seq_xyz = input.velocity.as_ref().map(|velocity| {
                let row = config.seq_xyz_row();
                let position = layer("seq_xyz_encoder.position", &encoding, true);
                let mut frames = Vec::new();
                for l in 0..length {
                    let start = (g * length + l) * row;
                    let mut concat = layer(
                        "seq_xyz_encoder.velocity",
                        &velocity[start..start + row],
                        true,
                    );
                    concat.extend_from_slice(&position);
                    frames.extend(layer("seq_xyz_encoder.frame", &concat, true));
                }
                layer(
                    "seq_xyz_encoder.sequence.1",
                    &layer("seq_xyz_encoder.sequence.0", &frames, true),
                    true,
                )
            });
            // The reference concatenation order: encoding, pose, seq-pose, seq-xyz. Our
            // first trunk weight stores rows (encoding, seq-xyz, pose, seq-pose): permute.
            let mut concat = encoding.clone();
            concat.extend_from_slice(&pose);
            concat.extend(seq_pose.iter().flatten());
            concat.extend(seq_xyz.iter().flatten());
            let weight = &params["non_rigid.trunk.0.weight"];
            let width = config.trunk_width;
            let block =
                |start: usize, rows: usize| weight[start * width..(start + rows) * width].to_vec();
            let e = w.encoding_width();
            let xyz_rows = if seq_xyz.is_some() { w.seq_xyz } else { 0 };
            let seq_pose_rows = if seq_pose.is_some() { w.seq_pose } else { 0 };
            let mut reference_weight = block(0, e);
            reference_weight.extend(block(e + xyz_rows, w.pose_encoder));
            reference_weight.extend(block(e + xyz_rows + w.pose_encoder, seq_pose_rows));
            reference_weight.extend(block(e, xyz_rows));
            let mut h = naive_layer(
                &concat,
                &reference_weight,
                &params["non_rigid.trunk.0.bias"],
                true,
            );
            for index in 1..config.trunk_depth {
                h = layer(&format!("trunk.{index}"), &h, true);
            }
            let heads = layer("heads", &h, false);
            std::array::from_fn(|i| heads[i])
        })
        .collect()
}

#[test]
fn per_frame_bias_equals_the_materialised_concatenation() {
    for (context, scales, length) in [
        (MotionContext::Pose, 1, 1),
        (MotionContext::Skeleton, 1, 3),
        (MotionContext::Velocity, 1, 2),
        (MotionContext::Multiscale, 3, 2),
    ] {
        let mut config = small_config(context, scales, length);
        config.widths = Widths::PAPER;
        config.trunk_width = 32;
        config.trunk_depth = 3;
        let mut rng = Rng::new(21);
        let networks = Networks::<f64>::new(&config, 8).unwrap();
        let input = inputs(&config, 5, &mut rng);
        let (out, _) = networks
            .non_rigid_forward(&input.frame(), &input.gaussians())
            .unwrap();
        let expected = naive_non_rigid(&networks, &config, &input);
        for (g, heads) in expected.iter().enumerate() {
            let ours = [
                &out.d_xyz[3 * g..3 * g + 3],
                &out.d_rot[4 * g..4 * g + 4],
                &out.d_scale[3 * g..3 * g + 3],
            ]
            .concat();
            for i in 0..10 {
                let reference = heads[i] + if i == 3 { 1.0 } else { 0.0 };
                assert!(
                    (ours[i] - reference).abs() < 1e-12,
                    "{context:?} gaussian {g} output {i}: {} vs {reference}",
                    ours[i]
                );
            }
        }
    }
}

#[test]
fn fresh_networks_start_at_the_identity() {
    let config = NetworkConfig {
        motion_context: MotionContext::Multiscale,
        trunk_width: 512,
        trunk_depth: 3,
        skinning_joints: 24,
        motion_joints: 24,
        tau: 8,
        sequence_length: 2,
        n_scales: 3,
        pose_refiner: true,
        lbs_offsets: true,
        widths: Widths::PAPER,
    };
    let mut rng = Rng::new(4);
    let networks = Networks::<f32>::new(&config, 0).unwrap();
    let n = 64;
    let to32 = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect::<Vec<f32>>();
    let input = inputs(&config, n, &mut rng);
    let (pose, skeleton, xyz, velocity) = (
        to32(input.pose),
        to32(input.skeleton.unwrap()),
        to32(input.xyz),
        to32(input.velocity.unwrap()),
    );
    let (out, _) = networks
        .non_rigid_forward(
            &FrameInputs {
                local_pose: &pose,
                skeleton_motion: Some(&skeleton),
            },
            &GaussianInputs {
                xyz: &xyz,
                knn_velocity: Some(&velocity),
            },
        )
        .unwrap();
    // The quaternion is the head output plus [1, 0, 0, 0]: w averages near 1 while the raw
    // head (w - 1) and the vector part average near 0 but are not zero.
    let mean = |c: usize| out.d_rot.chunks(4).map(|q| f64::from(q[c])).sum::<f64>() / n as f64;
    assert!((mean(0) - 1.0).abs() < 0.2, "mean w {}", mean(0));
    for c in 1..4 {
        assert!(mean(c).abs() < 0.2, "mean component {c}: {}", mean(c));
    }
    let raw_spread = out
        .d_rot
        .chunks(4)
        .map(|q| (q[0] - 1.0).abs())
        .fold(0.0f32, f32::max);
    assert!(
        raw_spread > 1e-4,
        "the head output itself is not forced to zero"
    );

    let (rotations, _) = networks.pose_refiner_forward(&pose).unwrap();
    assert_eq!(rotations.len(), 23 * 9);
    for (i, value) in rotations.iter().enumerate() {
        let identity = if i % 9 % 4 == 0 { 1.0 } else { 0.0 };
        assert!((value - identity).abs() < 1e-4, "entry {i}: {value}");
    }
}

#[test]
fn disabled_blocks_allocate_nothing() {
    let mut config = small_config(MotionContext::None, 1, 2);
    config.widths = Widths::PAPER;
    let none = Networks::<f32>::new(&config, 0).unwrap();
    assert!(!none.has_non_rigid());
    assert!(
        none.parameters()
            .iter()
            .all(|p| !p.name.starts_with("non_rigid."))
    );
    let pose = [0.0f32; 6];
    let error = none
        .non_rigid_forward(
            &FrameInputs {
                local_pose: &pose,
                skeleton_motion: None,
            },
            &GaussianInputs {
                xyz: &[0.0; 3],
                knn_velocity: None,
            },
        )
        .unwrap_err();
    assert_eq!(
        error,
        ModelError::Disabled {
            block: "the non-rigid network"
        }
    );
    // J = 3: refiner 6 -> 128 -> 128 -> 6, LBS 63 -> 128 -> 128 -> 128, 191 -> 128 -> 3.
    let refiner = 6 * 128 + 128 + 128 * 128 + 128 + 128 * 6 + 6;
    let lbs = 63 * 128 + 128 + 2 * (128 * 128 + 128) + 191 * 128 + 128 + 128 * 3 + 3;
    assert_eq!(none.parameter_count(), refiner + lbs);

    config.pose_refiner = false;
    config.lbs_offsets = false;
    let nothing = Networks::<f32>::new(&config, 0).unwrap();
    assert_eq!(nothing.parameter_count(), 0);
    assert!(nothing.pose_refiner_forward(&pose).is_err());

    // Each level adds exactly its block (trunk width 7, depth 2).
    let count = |context, scales| {
        let mut c = small_config(context, scales, 2);
        c.widths = Widths::PAPER;
        c.pose_refiner = false;
        c.lbs_offsets = false;
        let networks = Networks::<f32>::new(&c, 0).unwrap();
        let names: Vec<String> = networks.parameters().into_iter().map(|p| p.name).collect();
        (networks.parameter_count(), names)
    };
    let (pose_count, pose_names) = count(MotionContext::Pose, 1);
    let pose_encoder = 6 * 32 + 32 + 32 * 32 + 32;
    let trunk = |extra: usize| (63 + 32 + extra) * 7 + 7 + 7 * 7 + 7 + 7 * 10 + 10;
    assert_eq!(pose_count, pose_encoder + trunk(0));
    assert!(pose_names.iter().all(|n| !n.contains("seq_")));
    let (skeleton_count, _) = count(MotionContext::Skeleton, 1);
    let seq_pose = |scales: usize| (3 * 4 * scales) * 16 + 16 + 32 * 32 + 32;
    assert_eq!(skeleton_count, pose_encoder + trunk(32) + seq_pose(1));
    let seq_xyz = |scales: usize| {
        (3 * 2 * scales) * 64 + 64 + 63 * 32 + 32 + 96 * 96 + 96 + 192 * 256 + 256 + 256 * 96 + 96
    };
    let (velocity_count, _) = count(MotionContext::Velocity, 1);
    assert_eq!(
        velocity_count,
        pose_encoder + trunk(32 + 96) + seq_pose(1) + seq_xyz(1)
    );
    let (multi_count, _) = count(MotionContext::Multiscale, 3);
    assert_eq!(
        multi_count,
        pose_encoder + trunk(32 + 96) + seq_pose(3) + seq_xyz(3)
    );
}

#[test]
fn regularised_rodrigues_matches_rodrigues_away_from_zero_and_its_backward_is_exact() {
    for v in [
        DVec3::new(0.3, -0.7, 1.1),
        DVec3::new(2.0, 0.5, -0.1),
        DVec3::new(0.0, 0.0, 3.0),
    ] {
        let ours = regularised_rodrigues(v);
        let exact = axis_angle_to_matrix(v);
        let diff = (ours - exact)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, x| m.max(x.abs()));
        // The regulariser changes theta by ~1e-5 / (2 |v|) and the axis by as much.
        assert!(diff < 2e-5 / v.length(), "{v}: {diff}");
    }
    let at_zero = regularised_rodrigues(DVec3::ZERO);
    assert!((at_zero.x_axis.x - (1e-5f64).sqrt().cos()).abs() < 1e-15);
    let mut rng = Rng::new(12);
    for v in [
        DVec3::ZERO,
        DVec3::new(1e-4, -2e-4, 5e-5),
        DVec3::new(0.3, -0.7, 1.1),
        DVec3::new(-2.5, 1.5, 0.2),
    ] {
        let g = seqavatar_core::glam::DMat3::from_cols_array(
            &random(&mut rng, 9, 1.0).try_into().unwrap(),
        );
        let loss = |v: DVec3| {
            let r = regularised_rodrigues(v);
            (0..3).map(|c| r.col(c).dot(g.col(c))).sum::<f64>()
        };
        let analytic = regularised_rodrigues_backward(v, g);
        let h = 1e-7;
        for axis in 0..3 {
            let mut e = DVec3::ZERO;
            e[axis] = h;
            let fd = (loss(v + e) - loss(v - e)) / (2.0 * h);
            assert!(
                (analytic[axis] - fd).abs() < 1e-7 * (1.0 + fd.abs()),
                "{v} axis {axis}: {} vs {fd}",
                analytic[axis]
            );
        }
    }
}

#[test]
fn pose_refiner_gradients_match_finite_differences() {
    let config = small_config(MotionContext::None, 1, 1);
    let mut rng = Rng::new(31);
    let mut networks = Networks::<f64>::new(&config, 5).unwrap();
    // Large last-layer values so the rotations are far from the identity.
    for param in networks.parameters_mut() {
        for value in param.values.iter_mut() {
            *value += rng.uniform(-0.3, 0.3);
        }
    }
    let pose = random(&mut rng, config.pose_dim(), 1.0);
    let probe = random(&mut rng, 9 * 2, 1.0);
    let (rotations, cache) = networks.pose_refiner_forward(&pose).unwrap();
    assert_eq!(rotations.len(), 18);
    // Each matrix is the regularised Rodrigues of the network output.
    for (m, v) in rotations.chunks(9).zip(cache.rotation_vectors().chunks(3)) {
        let r = regularised_rodrigues(DVec3::new(v[0], v[1], v[2]));
        for row in 0..3 {
            for col in 0..3 {
                assert_eq!(m[3 * row + col], r.col(col)[row]);
            }
        }
    }
    networks.zero_grad();
    networks.pose_refiner_backward(&cache, &probe).unwrap();
    let loss = |net: &Networks<f64>| {
        let (r, _) = net.pose_refiner_forward(&pose).unwrap();
        r.iter().zip(&probe).map(|(a, b)| a * b).sum::<f64>()
    };
    let checked = check_parameter_gradients(&networks, NetworkGroup::PoseRefiner, &loss);
    assert_eq!(checked, 6 * 6 + 6 + 6 * 6 + 6 + 6 * 6 + 6);
}

#[test]
fn lbs_offsets_gradients_match_finite_differences() {
    let config = small_config(MotionContext::None, 1, 1);
    let mut rng = Rng::new(41);
    let mut networks = Networks::<f64>::new(&config, 6).unwrap();
    perturb(&mut networks, &mut rng);
    let n = 4;
    let xyz = random(&mut rng, 3 * n, 1.0);
    let probe = random(&mut rng, 3 * n, 1.0);
    let (offsets, cache) = networks.lbs_offsets_forward(&xyz).unwrap();
    assert_eq!(offsets.len(), 3 * n);
    networks.zero_grad();
    networks.lbs_offsets_backward(&cache, &probe).unwrap();
    let loss = |net: &Networks<f64>| {
        let (o, _) = net.lbs_offsets_forward(&xyz).unwrap();
        o.iter().zip(&probe).map(|(a, b)| a * b).sum::<f64>()
    };
    check_parameter_gradients(&networks, NetworkGroup::LbsOffsets, &loss);
    // The skip layer reads the encoding: compare one output with naive loops.
    let params: std::collections::HashMap<String, Vec<f64>> = networks
        .parameters()
        .into_iter()
        .map(|p| (p.name, p.values.to_vec()))
        .collect();
    let layer = |i: usize, x: &[f64], relu: bool| {
        naive_layer(
            x,
            &params[&format!("lbs_offsets.{i}.weight")],
            &params[&format!("lbs_offsets.{i}.bias")],
            relu,
        )
    };
    let e = naive_encoding(&xyz[3..6], 2);
    let mut h = layer(2, &layer(1, &layer(0, &e, true), true), true);
    h.extend_from_slice(&e);
    let expected = layer(4, &layer(3, &h, true), false);
    for j in 0..3 {
        assert!((offsets[3 + j] - expected[j]).abs() < 1e-12);
    }
}

#[test]
fn blend_weights_is_a_softmax_of_log_weights_with_an_exact_backward() {
    let template = [0.7f64, 0.3, 0.0, 0.1, 0.1, 0.8];
    let offsets = [0.2f64, -0.1, 0.5, 0.0, 0.0, 0.0];
    let weights = blend_weights(&template, &offsets, 3).unwrap();
    // Zero offsets return the (normalised) template weights; a zero weight stays ~1e-9.
    for j in 0..3 {
        assert!((weights[3 + j] - template[3 + j]).abs() < 1e-8);
    }
    let logits: Vec<f64> = (0..3)
        .map(|j| (template[j] + 1e-9f64).ln() + offsets[j])
        .collect();
    let sum: f64 = logits.iter().map(|l| l.exp()).sum();
    for j in 0..3 {
        assert!((weights[j] - logits[j].exp() / sum).abs() < 1e-14);
    }
    assert!(weights[2] < 1e-8);
    // Large offsets do not overflow.
    let big = blend_weights(&[0.5f64, 0.5], &[800.0, 0.0], 2).unwrap();
    assert!((big[0] - 1.0).abs() < 1e-15 && big[1] >= 0.0);

    let probe = [0.3, -1.2, 0.7, 0.4, 0.9, -0.5];
    let d_offsets = blend_weights_backward(&weights, &probe, 3).unwrap();
    let h = 1e-6;
    for i in 0..6 {
        let (mut plus, mut minus) = (offsets, offsets);
        plus[i] += h;
        minus[i] -= h;
        let f = |o: &[f64]| {
            blend_weights(&template, o, 3)
                .unwrap()
                .iter()
                .zip(&probe)
                .map(|(w, g)| w * g)
                .sum::<f64>()
        };
        let fd = (f(&plus) - f(&minus)) / (2.0 * h);
        assert!(
            (d_offsets[i] - fd).abs() < 1e-8,
            "{i}: {} vs {fd}",
            d_offsets[i]
        );
    }
    let error = blend_weights(&[0.5, -0.1], &[0.0, 0.0], 2).unwrap_err();
    assert!(error.to_string().contains("row 0, joint 1"), "{error}");
    assert!(blend_weights(&[0.5, f64::NAN], &[0.0, 0.0], 2).is_err());
    assert!(blend_weights(&[0.5; 3], &[0.0; 3], 2).is_err());
}

#[test]
fn parameters_round_trip_and_bad_arrays_are_named() {
    let config = small_config(MotionContext::Multiscale, 2, 2);
    let source = Networks::<f32>::new(&config, 1).unwrap();
    let mut target = Networks::<f32>::new(&config, 2).unwrap();
    assert_ne!(source, target);
    let arrays: std::collections::HashMap<String, Vec<f32>> = source
        .parameters()
        .into_iter()
        .map(|p| (p.name, p.values.to_vec()))
        .collect();
    // Names are unique and shapes match lengths.
    assert_eq!(arrays.len(), source.parameters().len());
    for p in source.parameters() {
        assert_eq!(
            p.shape.iter().product::<usize>(),
            p.values.len(),
            "{}",
            p.name
        );
    }
    target
        .load_parameters(|name| arrays.get(name).cloned())
        .unwrap();
    assert_eq!(source, target);

    let before = target.clone();
    let error = target
        .load_parameters(|name| (name != "non_rigid.heads.bias").then(|| arrays[name].clone()))
        .unwrap_err();
    assert_eq!(
        error,
        ModelError::Parameter {
            name: "non_rigid.heads.bias".into(),
            message: "missing".into()
        }
    );
    let error = target
        .load_parameters(|name| {
            let mut values = arrays[name].clone();
            if name == "lbs_offsets.3.weight" {
                values.pop();
            }
            Some(values)
        })
        .unwrap_err();
    assert!(
        error.to_string().contains("lbs_offsets.3.weight"),
        "{error}"
    );
    assert!(error.to_string().contains("[20, 5]"), "{error}");
    let error = target
        .load_parameters(|name| {
            let mut values = arrays[name].clone();
            if name == "pose_refiner.0.bias" {
                values[1] = f32::NAN;
            }
            Some(values)
        })
        .unwrap_err();
    assert!(error.to_string().contains("pose_refiner.0.bias"), "{error}");
    assert_eq!(target, before, "a failed load changes nothing");
}

#[test]
fn bad_inputs_name_the_field() {
    let config = small_config(MotionContext::Multiscale, 2, 2);
    let mut rng = Rng::new(2);
    let networks = Networks::<f64>::new(&config, 0).unwrap();
    let input = inputs(&config, 2, &mut rng);
    let run = |frame: FrameInputs<'_, f64>, gaussians: GaussianInputs<'_, f64>| {
        networks
            .non_rigid_forward(&frame, &gaussians)
            .unwrap_err()
            .to_string()
    };
    let short = &input.velocity.as_ref().unwrap()[1..];
    let message = run(
        input.frame(),
        GaussianInputs {
            knn_velocity: Some(short),
            ..input.gaussians()
        },
    );
    assert!(
        message.contains("gaussians.knn_velocity: expected"),
        "{message}"
    );
    let message = run(
        input.frame(),
        GaussianInputs {
            knn_velocity: None,
            ..input.gaussians()
        },
    );
    assert!(
        message.contains("gaussians.knn_velocity: required"),
        "{message}"
    );
    let message = run(
        FrameInputs {
            skeleton_motion: None,
            ..input.frame()
        },
        input.gaussians(),
    );
    assert!(message.contains("frame.skeleton_motion"), "{message}");
    let message = run(
        FrameInputs {
            local_pose: &input.pose[1..],
            ..input.frame()
        },
        input.gaussians(),
    );
    assert!(message.contains("frame.local_pose"), "{message}");
    let message = run(
        input.frame(),
        GaussianInputs {
            xyz: &input.xyz[1..],
            ..input.gaussians()
        },
    );
    assert!(message.contains("gaussians.xyz"), "{message}");

    let mut bad_xyz = input.xyz.clone();
    bad_xyz[4] = f64::NAN;
    let message = run(
        input.frame(),
        GaussianInputs {
            xyz: &bad_xyz,
            ..input.gaussians()
        },
    );
    assert!(
        message.contains("gaussians.xyz: value 4 is NaN"),
        "{message}"
    );
    let mut bad_velocity = input.velocity.clone().unwrap();
    bad_velocity[7] = f64::INFINITY;
    let message = run(
        input.frame(),
        GaussianInputs {
            knn_velocity: Some(&bad_velocity),
            ..input.gaussians()
        },
    );
    assert!(
        message.contains("gaussians.knn_velocity: value 7"),
        "{message}"
    );
    let message = networks
        .pose_refiner_forward(&[f64::NAN; 6])
        .unwrap_err()
        .to_string();
    assert!(message.contains("local_pose: value 0"), "{message}");
    let message = networks
        .lbs_offsets_forward(&[0.0, f64::NEG_INFINITY, 0.0])
        .unwrap_err()
        .to_string();
    assert!(message.contains("lbs xyz: value 1"), "{message}");

    let mut pose_only = config.clone();
    pose_only.motion_context = MotionContext::Pose;
    pose_only.n_scales = 1;
    let pose_networks = Networks::<f64>::new(&pose_only, 0).unwrap();
    let message = pose_networks
        .non_rigid_forward(&input.frame(), &input.gaussians())
        .unwrap_err()
        .to_string();
    assert!(message.contains("does not use it"), "{message}");

    let mut bad = config.clone();
    bad.motion_context = MotionContext::Velocity;
    let message = Networks::<f64>::new(&bad, 0).unwrap_err().to_string();
    assert!(message.contains("n_scales"), "{message}");
    bad.n_scales = 1;
    bad.tau = 0;
    assert!(
        Networks::<f64>::new(&bad, 0)
            .unwrap_err()
            .to_string()
            .contains("tau")
    );
}

#[test]
fn from_avatar_uses_one_scale_below_multiscale() {
    let mut train = crate::config::AvatarConfig::for_tests();
    train.trunk_width = 512;
    train.tau = 8;
    let config = NetworkConfig::from_avatar(&train, 24, 24, 3).unwrap();
    assert_eq!(
        (config.n_scales, config.trunk_width, config.tau),
        (3, 512, 8)
    );
    assert_eq!(config.pose_dim(), 69);
    train.motion_context = MotionContext::Velocity;
    assert_eq!(
        NetworkConfig::from_avatar(&train, 24, 24, 3)
            .unwrap()
            .n_scales,
        1
    );
}

// ---------------------------------------------------------------------------------------
// gpu parity (lavapipe in CI; skipped without an adapter unless CI is set).

/// `max |gpu - cpu| <= tolerance * max(1, max |cpu|)` over the whole array.
fn assert_close_f32(what: &str, gpu: &[f32], cpu: &[f32], tolerance: f32) {
    assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
    let scale = cpu.iter().fold(1.0f32, |m, x| m.max(x.abs()));
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(
            (g - c).abs() <= tolerance * scale,
            "{what}[{i}]: gpu {g} vs cpu {c} (scale {scale})"
        );
    }
}

fn to_f32(values: &[f64]) -> Vec<f32> {
    values.iter().map(|&x| x as f32).collect()
}

/// The uploaded networks' kernels take the path their precision chooses on the context, once:
/// f32 for `f32`; for `mixed` the tensor cores where the adapter has them, else f32 (as on
/// lavapipe).
#[test]
fn gpu_upload_takes_the_path_of_its_precision() {
    use super::gpu::GpuNetworks;
    use seqavatar_compute::nn::gpu::MatmulPath;
    let Some(context) = seqavatar_compute::backend::test_support::gpu_test_context() else {
        return;
    };
    let cpu = Networks::<f32>::new(&small_config(MotionContext::Pose, 1, 2), 3).unwrap();
    let path = |precision| {
        GpuNetworks::upload(context.clone(), &cpu, precision)
            .unwrap()
            .kernels()
            .matmul_path()
    };
    assert_eq!(path(Precision::F32), MatmulPath::F32);
    let mixed = path(Precision::Mixed);
    assert_eq!(mixed, MatmulPath::choose(&context, Precision::Mixed));
    assert_eq!(
        matches!(mixed, MatmulPath::TensorCores(_)),
        context.tensor_cores().is_some()
    );
}

// ---------------------------------------------------------------------------------------
// The description and its generic interpreter.

/// Random inputs for every block of `spec` with `n` Gaussians.
fn spec_inputs(spec: &spec::NetworkSpec, n: usize, rng: &mut Rng) -> Vec<Vec<f64>> {
    spec.inputs
        .iter()
        .map(|input| {
            let len =
                input.width * input.rows.block_rows(n, spec.window) * input.rows.calls(spec.window);
            random(rng, len, 1.0)
        })
        .collect()
}

fn spec_loss(net: &network::Network<f64>, inputs: &[Vec<f64>], probe: &[f64]) -> f64 {
    let slices: Vec<&[f64]> = inputs.iter().map(Vec::as_slice).collect();
    let activations = net.forward(&slices).unwrap();
    activations
        .output()
        .iter()
        .zip(probe)
        .map(|(a, b)| a * b)
        .sum()
}

/// Every parameter and every input gradient the description asks for, against central
/// differences of `<output, probe>`, through the generic `cpu` interpreter in f64.
fn check_spec_gradients(spec: spec::NetworkSpec, n: usize, seed: u64) -> usize {
    let mut rng = Rng::new(seed);
    let mut net = network::Network::<f64>::new(spec.clone(), &mut rng).unwrap();
    for layer in &mut net.layers {
        for value in layer.weight.iter_mut().chain(layer.bias.iter_mut()) {
            *value += rng.uniform(-0.05, 0.05);
        }
    }
    let inputs = spec_inputs(&spec, n, &mut rng);
    let slices: Vec<&[f64]> = inputs.iter().map(Vec::as_slice).collect();
    let activations = net.forward(&slices).unwrap();
    let probe = random(&mut rng, activations.output().len(), 1.0);
    let input_grads = net.backward(&activations, &probe).unwrap();
    let h = 1e-6;
    let close = |what: &str, analytic: f64, fd: f64| {
        assert!(
            (analytic - fd).abs() <= 1e-6 * (1.0 + fd.abs()),
            "{what}: analytic {analytic} vs finite difference {fd}"
        );
    };
    let mut checked = 0;
    for layer in 0..net.layers.len() {
        for bias in [false, true] {
            let len = if bias {
                net.layers[layer].bias.len()
            } else {
                net.layers[layer].weight.len()
            };
            for i in 0..len {
                let mut shifted = net.clone();
                let shift = |net: &mut network::Network<f64>, delta: f64| {
                    let dense = &mut net.layers[layer];
                    if bias {
                        dense.bias[i] += delta;
                    } else {
                        dense.weight[i] += delta;
                    }
                };
                shift(&mut shifted, h);
                let plus = spec_loss(&shifted, &inputs, &probe);
                shift(&mut shifted, -2.0 * h);
                let minus = spec_loss(&shifted, &inputs, &probe);
                let analytic = if bias {
                    net.layers[layer].d_bias[i]
                } else {
                    net.layers[layer].d_weight[i]
                };
                let name = &net.layers[layer].name;
                close(
                    &format!("{name} [{i}]"),
                    analytic,
                    (plus - minus) / (2.0 * h),
                );
                checked += 1;
            }
        }
    }
    for (index, input) in spec.inputs.iter().enumerate() {
        let Some(grad) = &input_grads[index] else {
            assert!(!input.gradient, "{} has no gradient", input.name);
            continue;
        };
        assert!(input.gradient, "{} returned a gradient", input.name);
        assert_eq!(grad.len(), inputs[index].len());
        for i in 0..grad.len() {
            let mut shifted = inputs.clone();
            shifted[index][i] += h;
            let plus = spec_loss(&net, &shifted, &probe);
            shifted[index][i] -= 2.0 * h;
            let minus = spec_loss(&net, &shifted, &probe);
            close(
                &format!("{} [{i}]", input.name),
                grad[i],
                (plus - minus) / (2.0 * h),
            );
            checked += 1;
        }
    }
    checked
}

#[test]
fn an_extra_input_block_is_one_change_and_its_gradients_match_finite_differences() {
    use spec::{Rows, Source};
    let config = small_config(MotionContext::Multiscale, 2, 2);
    let mut spec = spec::NetworkSpec::non_rigid(&config);
    let trunk = spec
        .layers
        .iter()
        .position(|l| l.name == "trunk.0")
        .unwrap();
    let before = spec.in_features(trunk);
    // The one change: two new input blocks (a per-Gaussian one read before the per-frame
    // ones, with a gradient; a per-frame one, folded into the per-frame bias, with a
    // gradient) and the trunk's first layer reading them.
    let colour = spec.input("gaussians.colour", Rows::Gaussian, 2, None, true);
    let expression = spec.input("frame.expression", Rows::Frame, 4, None, true);
    let sources = &mut spec.layers[trunk].sources;
    let first_frame = sources.iter().position(|s| *s == Source::Layer(1)).unwrap();
    sources.insert(first_frame, colour);
    sources.push(expression);
    spec.validate().unwrap();
    assert_eq!(spec.in_features(trunk), before + 2 + 4);
    let parameters: usize = (0..spec.layers.len())
        .map(|j| spec.shape(j).weight_len() + spec.layers[j].out)
        .sum();
    let checked = check_spec_gradients(spec.clone(), 3, 11);
    // Every parameter, then xyz (3 n), colour (2 n) and expression (4) values.
    assert_eq!(checked, parameters + 3 * 3 + 2 * 3 + 4);

    // The unchanged descriptions go through the same interpreter and check.
    check_spec_gradients(spec::NetworkSpec::lbs_offsets(&config), 3, 12);
    check_spec_gradients(spec::NetworkSpec::pose_refiner(&config), 0, 13);
}

#[test]
fn networks_use_their_descriptions_and_the_parameter_names_are_unchanged() {
    let config = small_config(MotionContext::Multiscale, 2, 2);
    let networks = Networks::<f32>::new(&config, 4).unwrap();
    let names: Vec<String> = networks
        .parameters()
        .iter()
        .filter(|p| p.name.ends_with(".weight"))
        .map(|p| p.name.trim_end_matches(".weight").to_string())
        .collect();
    let expected = [
        "non_rigid.pose_encoder.0",
        "non_rigid.pose_encoder.1",
        "non_rigid.seq_pose_encoder.frame",
        "non_rigid.seq_pose_encoder.sequence",
        "non_rigid.seq_xyz_encoder.velocity",
        "non_rigid.seq_xyz_encoder.position",
        "non_rigid.seq_xyz_encoder.frame",
        "non_rigid.seq_xyz_encoder.sequence.0",
        "non_rigid.seq_xyz_encoder.sequence.1",
        "non_rigid.trunk.0",
        "non_rigid.trunk.1",
        "non_rigid.heads",
        "pose_refiner.0",
        "pose_refiner.1",
        "pose_refiner.2",
        "lbs_offsets.0",
        "lbs_offsets.1",
        "lbs_offsets.2",
        "lbs_offsets.3",
        "lbs_offsets.4",
    ];
    assert_eq!(names, expected);
    // Trunk rows: encoding (2 bands: 15), seq-xyz 5, then pose 5 and seq-pose 4.
    let trunk = networks
        .parameters()
        .into_iter()
        .find(|p| p.name == "non_rigid.trunk.0.weight")
        .unwrap();
    assert_eq!(trunk.shape, vec![15 + 5 + 5 + 4, 7]);
}

#[test]
fn bad_descriptions_name_the_layer() {
    use seqavatar_compute::nn::Activation::Relu;
    use spec::{NetworkSpec, Rows, Source};
    let message = |spec: &NetworkSpec| spec.validate().unwrap_err().to_string();
    let mut spec = NetworkSpec::new("toy", NetworkGroup::NonRigid, 2);
    let frame = spec.input("frame", Rows::Frame, 2, None, false);
    let points = spec.input("points", Rows::Gaussian, 3, None, true);
    spec.layer("mixed", Rows::Gaussian, &[frame, points], 4, Relu);
    assert!(
        message(&spec).contains("toy.mixed") && message(&spec).contains("must come last"),
        "{}",
        message(&spec)
    );
    spec.layers[0].sources = vec![points, frame];
    spec.validate().unwrap();
    spec.layer("ahead", Rows::Gaussian, &[Source::Layer(2)], 4, Relu);
    assert!(message(&spec).contains("toy.ahead"), "{}", message(&spec));
    spec.layers[1].sources = vec![Source::Layer(0)];
    spec.layer("window", Rows::Gaussian, &[Source::Window(1)], 4, Relu);
    assert!(message(&spec).contains("toy.window"), "{}", message(&spec));
    spec.layers.pop();
    spec.output = 0;
    assert!(
        message(&spec).contains("toy.ahead: is never read"),
        "{}",
        message(&spec)
    );
    let mut frame_reads_points = NetworkSpec::new("toy", NetworkGroup::NonRigid, 2);
    let points = frame_reads_points.input("points", Rows::Gaussian, 3, None, false);
    frame_reads_points.layer("pooled", Rows::Frame, &[points], 4, Relu);
    assert!(message(&frame_reads_points).contains("toy.pooled"));
}

#[test]
fn forward_flops_match_an_independent_count() {
    let config = small_config(MotionContext::Multiscale, 2, 3);
    let w = config.widths;
    let n = 5;
    let l = config.sequence_length;
    let enc = 3 * (1 + 2 * w.encoding_frequencies);
    let pose = config.pose_dim();
    let t = config.trunk_width;
    // Multiply-adds, written out layer by layer.
    let pose_encoder = pose * w.pose_encoder + w.pose_encoder * w.pose_encoder;
    let seq_pose = l * (config.n_scales * config.motion_joints * 3) * w.seq_pose_frame
        + (w.seq_pose_frame * l) * w.seq_pose;
    let seq_xyz = n * l * (config.tau * config.n_scales * 3) * w.seq_xyz_velocity
        + n * enc * w.seq_xyz_position
        + n * l * (w.seq_xyz_velocity + w.seq_xyz_position) * w.seq_xyz_frame
        + n * (w.seq_xyz_frame * l) * w.seq_xyz_hidden
        + n * w.seq_xyz_hidden * w.seq_xyz;
    let trunk = n * (enc + w.seq_xyz) * t
        + (w.pose_encoder + w.seq_pose) * t
        + (config.trunk_depth - 1) * n * t * t
        + n * t * HEAD_WIDTH;
    let refiner = pose * w.pose_refiner_hidden
        + w.pose_refiner_hidden * w.pose_refiner_hidden
        + w.pose_refiner_hidden * pose;
    let h = w.lbs_hidden;
    let lbs = n * (enc * h + 2 * h * h + (h + enc) * h + h * config.skinning_joints);
    let non_rigid = 2 * (pose_encoder + seq_pose + seq_xyz + trunk);
    assert_eq!(
        spec::NetworkSpec::non_rigid(&config).forward_flops(n),
        non_rigid as f64
    );
    assert_eq!(
        spec::NetworkSpec::pose_refiner(&config).forward_flops(n),
        (2 * refiner) as f64
    );
    assert_eq!(
        spec::NetworkSpec::lbs_offsets(&config).forward_flops(n),
        (2 * lbs) as f64
    );
    assert_eq!(
        config.forward_flops(n),
        (non_rigid + 2 * refiner + 2 * lbs) as f64
    );
}

// ---- The resident networks: device inputs, device outputs, device Adam -------------------

/// One resident iteration's host view: outputs and input gradients downloaded after the
/// recorded forward and backward of every network.
struct ResidentRun {
    heads: Vec<f32>,
    d_xyz: Vec<f32>,
    rotations: Vec<f32>,
    offsets: Vec<f32>,
}

/// The host inputs and output gradients of one resident check, uploaded once.
struct DeviceCase {
    n: usize,
    pose: seqavatar_compute::backend::GpuBuffer,
    skeleton: Option<seqavatar_compute::backend::GpuBuffer>,
    xyz: seqavatar_compute::backend::GpuBuffer,
    velocity: Vec<seqavatar_compute::backend::GpuBuffer>,
    d_heads: seqavatar_compute::backend::GpuBuffer,
    d_rotations: seqavatar_compute::backend::GpuBuffer,
    d_offsets: seqavatar_compute::backend::GpuBuffer,
}

struct HostCase {
    pose: Vec<f32>,
    skeleton: Option<Vec<f32>>,
    xyz: Vec<f32>,
    velocity: Option<Vec<f32>>,
    d_dxyz: Vec<f32>,
    d_drot: Vec<f32>,
    d_dscale: Vec<f32>,
    d_rotations: Vec<f32>,
    d_offsets: Vec<f32>,
}

fn host_case(config: &NetworkConfig, n: usize, seed: u64) -> HostCase {
    let mut rng = Rng::new(seed);
    let input = inputs(config, n, &mut rng);
    let joints = config.pose_dim() / 3;
    HostCase {
        pose: to_f32(&input.pose),
        skeleton: input.skeleton.as_deref().map(to_f32),
        xyz: to_f32(&input.xyz),
        velocity: input.velocity.as_deref().map(to_f32),
        d_dxyz: to_f32(&random(&mut rng, 3 * n, 1.0)),
        d_drot: to_f32(&random(&mut rng, 4 * n, 1.0)),
        d_dscale: to_f32(&random(&mut rng, 3 * n, 1.0)),
        d_rotations: to_f32(&random(&mut rng, 9 * joints, 1.0)),
        d_offsets: to_f32(&random(&mut rng, n * config.skinning_joints, 1.0)),
    }
}

fn device_case(
    context: &seqavatar_compute::backend::GpuContext,
    config: &NetworkConfig,
    host: &HostCase,
) -> DeviceCase {
    let n = host.xyz.len() / 3;
    let up = |what: &str, values: &[f32]| context.upload(what, values).unwrap();
    let d_heads = non_rigid::heads_gradient(n, &host.d_dxyz, &host.d_drot, &host.d_dscale).unwrap();
    DeviceCase {
        n,
        pose: up("pose", &host.pose),
        skeleton: host.skeleton.as_deref().map(|s| up("skeleton", s)),
        xyz: up("xyz", &host.xyz),
        velocity: host
            .velocity
            .as_deref()
            .map(|v| {
                spec::window_blocks(v, config.sequence_length, config.seq_xyz_row())
                    .iter()
                    .map(|block| up("velocity", block))
                    .collect()
            })
            .unwrap_or_default(),
        d_heads: up("d heads", &d_heads),
        d_rotations: up("d rotations", &host.d_rotations),
        d_offsets: up("d offsets", &host.d_offsets),
    }
}

/// Records the forward and backward of every enabled network (and, when given, the Adam
/// update) into one encoder; submits; returns the encoder-free host view when `download`.
fn resident_iteration(
    (gpu, context, config): (
        &mut gpu::GpuNetworks,
        &seqavatar_compute::backend::GpuContext,
        &NetworkConfig,
    ),
    case: &DeviceCase,
    adam: Option<(&seqavatar_compute::nn::AdamConfig, f64)>,
    download: bool,
) -> Option<ResidentRun> {
    let mut encoder = context.encoder();
    gpu.record_zero_grad(&mut encoder);
    let n = case.n;
    let mut sources: Vec<(wgpu::Buffer, usize)> = Vec::new();
    if config.motion_context.has_non_rigid() {
        let velocity: Vec<&wgpu::Buffer> = case.velocity.iter().map(|b| &b.buffer).collect();
        let heads = gpu
            .record_non_rigid_forward(
                &mut encoder,
                n,
                &gpu::NonRigidDeviceInputs {
                    local_pose: &case.pose.buffer,
                    skeleton_motion: case.skeleton.as_ref().map(|b| &b.buffer),
                    xyz: &case.xyz.buffer,
                    knn_velocity: &velocity,
                },
            )
            .unwrap()
            .clone();
        sources.push((heads, n * HEAD_WIDTH));
        let d_xyz = gpu
            .record_non_rigid_backward(&mut encoder, &case.d_heads.buffer)
            .unwrap()
            .clone();
        sources.push((d_xyz, 3 * n));
    }
    let joints = config.pose_dim() / 3;
    let rotations = gpu
        .record_forward(
            &mut encoder,
            NetworkGroup::PoseRefiner,
            0,
            &[&[&case.pose.buffer]],
        )
        .unwrap()
        .clone();
    sources.push((rotations, 9 * joints));
    gpu.record_backward(
        &mut encoder,
        NetworkGroup::PoseRefiner,
        &case.d_rotations.buffer,
    )
    .unwrap();
    let offsets = gpu
        .record_forward(
            &mut encoder,
            NetworkGroup::LbsOffsets,
            n,
            &[&[&case.xyz.buffer]],
        )
        .unwrap()
        .clone();
    sources.push((offsets, n * config.skinning_joints));
    gpu.record_backward(
        &mut encoder,
        NetworkGroup::LbsOffsets,
        &case.d_offsets.buffer,
    )
    .unwrap();
    if let Some((adam, rate)) = adam {
        gpu.record_adam(&mut encoder, adam, |_| rate).unwrap();
    }
    if !download {
        context.submit_and_wait(encoder).unwrap();
        return None;
    }
    let refs: Vec<(&wgpu::Buffer, usize)> = sources.iter().map(|(b, l)| (b, *l)).collect();
    let mut arrays = context
        .download_all::<f32>(encoder, &refs)
        .unwrap()
        .into_iter();
    let (heads, d_xyz) = if config.motion_context.has_non_rigid() {
        (arrays.next().unwrap(), arrays.next().unwrap())
    } else {
        (Vec::new(), Vec::new())
    };
    Some(ResidentRun {
        heads,
        d_xyz,
        rotations: arrays.next().unwrap(),
        offsets: arrays.next().unwrap(),
    })
}

/// The resident forward and backward of every network against the `cpu` f32 networks:
/// outputs, input gradients and parameter gradients, twice (the second time replaying the
/// programs), then at another Gaussian count on the same workspace.
fn check_resident_parity(
    context: std::sync::Arc<seqavatar_compute::backend::GpuContext>,
    config: &NetworkConfig,
    counts: &[usize],
) {
    let mut cpu = Networks::<f32>::new(config, 11).unwrap();
    let mut gpu = gpu::GpuNetworks::upload(context.clone(), &cpu, Precision::F32).unwrap();
    for (round, &n) in counts.iter().enumerate() {
        let label = format!("{:?} n = {n} (round {round})", config.motion_context);
        let host = host_case(config, n, 31 + round as u64);
        let case = device_case(&context, config, &host);
        for replay in 0..2 {
            let run = resident_iteration((&mut gpu, &context, config), &case, None, true).unwrap();
            cpu.zero_grad();
            let frame = FrameInputs {
                local_pose: &host.pose,
                skeleton_motion: host.skeleton.as_deref(),
            };
            let gaussians = GaussianInputs {
                xyz: &host.xyz,
                knn_velocity: host.velocity.as_deref(),
            };
            let label = format!("{label} replay {replay}");
            if config.motion_context.has_non_rigid() {
                let (out, cache) = cpu.non_rigid_forward(&frame, &gaussians).unwrap();
                let mut heads = Vec::with_capacity(n * HEAD_WIDTH);
                for g in 0..n {
                    heads.extend_from_slice(&out.d_xyz[3 * g..3 * g + 3]);
                    heads.push(out.d_rot[4 * g] - 1.0);
                    heads.extend_from_slice(&out.d_rot[4 * g + 1..4 * g + 4]);
                    heads.extend_from_slice(&out.d_scale[3 * g..3 * g + 3]);
                }
                assert_close_f32(&format!("{label} heads"), &run.heads, &heads, 1e-4);
                let d_xyz = cpu
                    .non_rigid_backward(&cache, &host.d_dxyz, &host.d_drot, &host.d_dscale)
                    .unwrap();
                assert_close_f32(&format!("{label} d xyz"), &run.d_xyz, &d_xyz, 1e-4);
            }
            let (rotations, cache) = cpu.pose_refiner_forward(&host.pose).unwrap();
            assert_close_f32(
                &format!("{label} rotations"),
                &run.rotations,
                &rotations,
                1e-5,
            );
            cpu.pose_refiner_backward(&cache, &host.d_rotations)
                .unwrap();
            let (offsets, cache) = cpu.lbs_offsets_forward(&host.xyz).unwrap();
            assert_close_f32(&format!("{label} offsets"), &run.offsets, &offsets, 1e-4);
            cpu.lbs_offsets_backward(&cache, &host.d_offsets).unwrap();
            let mut downloaded = cpu.clone();
            gpu.download_into(&mut downloaded).unwrap();
            for (c, g) in cpu.parameters().iter().zip(downloaded.parameters()) {
                assert_close_f32(
                    &format!("{label} {} gradient", c.name),
                    g.grads,
                    c.grads,
                    1e-4,
                );
            }
        }
    }
}

#[test]
fn resident_networks_match_cpu_at_every_level_and_the_extremes() {
    let Some(context) = seqavatar_compute::backend::test_support::gpu_test_context() else {
        return;
    };
    let mut multiscale = small_config(MotionContext::Multiscale, 3, 3);
    multiscale.widths = Widths::PAPER;
    multiscale.trunk_width = 80;
    multiscale.skinning_joints = 24;
    // 300 is not a multiple of the 64-row tile; then a shrink and a growth of the workspace.
    check_resident_parity(context.clone(), &multiscale, &[300, 1, 0, 301]);
    check_resident_parity(
        context.clone(),
        &small_config(MotionContext::Pose, 1, 1),
        &[5, 0],
    );
    check_resident_parity(
        context.clone(),
        &small_config(MotionContext::Skeleton, 1, 2),
        &[1, 70],
    );
    check_resident_parity(
        context.clone(),
        &small_config(MotionContext::Velocity, 1, 2),
        &[0, 65],
    );
    check_resident_parity(context, &small_config(MotionContext::None, 1, 1), &[7]);
}

#[test]
fn resident_networks_match_cpu_with_two_dimensional_grids() {
    let Some(context) =
        seqavatar_compute::backend::test_support::gpu_test_context_with_dispatch_limit(8)
    else {
        return;
    };
    check_resident_parity(
        context,
        &small_config(MotionContext::Multiscale, 2, 3),
        &[300],
    );
}

#[test]
fn resident_rodrigues_matches_the_cpu_map_and_its_backward() {
    let Some(context) = seqavatar_compute::backend::test_support::gpu_test_context() else {
        return;
    };
    let nn = seqavatar_compute::nn::gpu::NnGpu::new(context.device()).unwrap();
    // Zero, tiny, moderate, large and near-pi vectors; 70 of them (not a multiple of 64).
    let mut rng = Rng::new(5);
    let mut vectors = vec![
        0.0, 0.0, 0.0, 1e-4, -2e-4, 3e-4, 3.1, 0.0, 0.0, 0.0, -2.0, 2.0,
    ];
    while vectors.len() < 3 * 70 {
        vectors.push(rng.uniform(-1.5, 1.5));
    }
    let count = vectors.len() / 3;
    let d_matrices = random(&mut rng, 9 * count, 1.0);
    let v32 = to_f32(&vectors);
    let d32 = to_f32(&d_matrices);
    let up = |what: &str, values: &[f32]| context.upload(what, values).unwrap().buffer;
    let (v_buf, d_buf) = (up("vectors", &v32), up("d matrices", &d32));
    let matrices = context.zeros("matrices", 9 * count, 4).unwrap().buffer;
    let d_vectors = context.zeros("d vectors", 3 * count, 4).unwrap().buffer;
    let mut encoder = context.encoder();
    let eps = pose_refiner::THETA_SQUARED_EPSILON;
    nn.rodrigues_forward(&mut encoder, eps, &v_buf, count, &matrices)
        .unwrap();
    nn.rodrigues_backward(&mut encoder, eps, &v_buf, &d_buf, count, &d_vectors)
        .unwrap();
    let got = context
        .download_all::<f32>(encoder, &[(&matrices, 9 * count), (&d_vectors, 3 * count)])
        .unwrap();
    let expected_matrices = pose_refiner::rotations_from_vectors(&vectors);
    let expected_d = pose_refiner::rotation_vectors_backward(&vectors, &d_matrices);
    assert_close_f32("matrices", &got[0], &to_f32(&expected_matrices), 2e-6);
    assert_close_f32("d vectors", &got[1], &to_f32(&expected_d), 5e-5);
}

/// Device Adam of every network parameter against `cpu` `adam_update` over several steps
/// with fresh gradients each step, then a checkpoint round trip (download, upload into a
/// fresh copy, one more step on both).
#[test]
fn resident_adam_matches_cpu_adam_update_and_round_trips() {
    use seqavatar_compute::nn::adam::{AdamConfig, AdamState, adam_update};
    use std::collections::HashMap;
    let Some(context) = seqavatar_compute::backend::test_support::gpu_test_context() else {
        return;
    };
    let config = small_config(MotionContext::Multiscale, 2, 2);
    let mut cpu = Networks::<f32>::new(&config, 3).unwrap();
    let mut gpu = gpu::GpuNetworks::upload(context.clone(), &cpu, Precision::F32).unwrap();
    let adam = AdamConfig {
        eps: 1e-15,
        ..AdamConfig::default()
    };
    let rate = |group: NetworkGroup| match group {
        NetworkGroup::NonRigid => 1e-3,
        NetworkGroup::PoseRefiner => 3e-4,
        NetworkGroup::LbsOffsets => 2e-3,
    };
    let mut states: HashMap<String, AdamState<f32>> = HashMap::new();
    let mut rng = Rng::new(8);
    let step = |cpu: &mut Networks<f32>,
                gpu: &mut gpu::GpuNetworks,
                states: &mut HashMap<String, AdamState<f32>>,
                rng: &mut Rng| {
        let device = gpu.parameters();
        let mut device = device.iter();
        for layer in cpu.layers_mut() {
            for grads in [&mut layer.d_weight, &mut layer.d_bias] {
                let values = to_f32(&random(rng, grads.len(), 1.0));
                context
                    .write(device.next().unwrap().grads, 0, &values)
                    .unwrap();
                grads.copy_from_slice(&values);
            }
        }
        let mut encoder = context.encoder();
        gpu.record_adam(&mut encoder, &adam, rate).unwrap();
        context.submit_and_wait(encoder).unwrap();
        for c in cpu.parameters_mut() {
            let state = states
                .entry(c.name.clone())
                .or_insert_with(|| AdamState::new(c.values.len()));
            adam_update(&adam, rate(c.group), c.values, c.grads, state).unwrap();
        }
    };
    let compare = |cpu: &Networks<f32>,
                   gpu: &gpu::GpuNetworks,
                   states: &HashMap<String, AdamState<f32>>,
                   what: &str| {
        let mut downloaded = cpu.clone();
        gpu.download_into(&mut downloaded).unwrap();
        for (c, g) in cpu.parameters().iter().zip(downloaded.parameters()) {
            assert_close_f32(&format!("{what} {}", c.name), g.values, c.values, 1e-6);
        }
        let device = gpu.download_adam().unwrap();
        for (name, state) in states {
            let d = &device[name];
            assert_eq!(d.step, state.step, "{what} {name} step");
            assert_close_f32(&format!("{what} {name} m"), &d.m, &state.m, 1e-6);
            assert_close_f32(&format!("{what} {name} v"), &d.v, &state.v, 1e-6);
        }
    };
    for _ in 0..3 {
        step(&mut cpu, &mut gpu, &mut states, &mut rng);
    }
    compare(&cpu, &gpu, &states, "after 3 steps");
    // Resume: a fresh device copy of the parameters with the downloaded moments.
    let mut resumed = gpu::GpuNetworks::upload(context.clone(), &cpu, Precision::F32).unwrap();
    resumed
        .upload_adam(&adam, &gpu.download_adam().unwrap())
        .unwrap();
    let resumed_states = resumed.download_adam().unwrap();
    assert!(resumed_states.values().all(|state| state.step == 3));
    step(&mut cpu, &mut resumed, &mut states, &mut rng);
    compare(&cpu, &resumed, &states, "resumed step 4");
    assert_eq!(resumed.download_non_finite().unwrap(), None);
    // A NaN gradient and an infinite value are flagged on the device, first array first.
    let params = resumed.parameters();
    let (first, second) = (&params[1], &params[4]);
    let mut bad = vec![0.5_f32; first.len];
    bad[first.len - 1] = f32::NAN;
    context.write(first.grads, 0, &bad).unwrap();
    let mut huge = vec![0.5_f32; second.len];
    huge[0] = f32::INFINITY;
    context.write(second.grads, 0, &huge).unwrap();
    let (first_name, first_len) = (first.name.clone(), first.len);
    drop(params);
    let mut encoder = context.encoder();
    resumed.record_adam(&mut encoder, &adam, rate).unwrap();
    context.submit_and_wait(encoder).unwrap();
    let flagged = resumed.download_non_finite().unwrap().unwrap();
    assert_eq!(
        flagged,
        gpu::NetworkNonFinite {
            tensor: format!("network.{first_name}"),
            gradient: true,
            index: first_len - 1,
        }
    );
    // A missing state is named.
    let mut partial = gpu.download_adam().unwrap();
    let name = partial.keys().next().unwrap().clone();
    partial.remove(&name);
    let error = resumed.upload_adam(&adam, &partial).unwrap_err();
    assert!(error.to_string().contains(&name), "{error}");
}

/// A steady-state resident iteration (forward, backward and Adam of every network) reads
/// nothing back, uploads only the Adam step record and builds no program.
#[test]
fn resident_steady_state_iteration_reads_back_nothing_and_uploads_under_one_kib() {
    use seqavatar_compute::nn::adam::AdamConfig;
    // A context of its own: the shared one counts the traffic of tests running beside this.
    let Some(context) = seqavatar_compute::backend::test_support::gpu_test_context_alone() else {
        return;
    };
    let mut config = small_config(MotionContext::Multiscale, 3, 3);
    config.widths = Widths::PAPER;
    config.trunk_width = 64;
    let cpu = Networks::<f32>::new(&config, 2).unwrap();
    let mut gpu = gpu::GpuNetworks::upload(context.clone(), &cpu, Precision::F32).unwrap();
    let host = host_case(&config, 200, 4);
    let case = device_case(&context, &config, &host);
    let adam = AdamConfig::default();
    resident_iteration(
        (&mut gpu, &context, &config),
        &case,
        Some((&adam, 1e-3)),
        false,
    );
    let built = gpu.resident_programs_built();
    let before = context.transfers();
    for _ in 0..3 {
        resident_iteration(
            (&mut gpu, &context, &config),
            &case,
            Some((&adam, 1e-3)),
            false,
        );
    }
    let traffic = context.transfers().since(&before);
    assert_eq!(traffic.readbacks, 0, "{traffic:?}");
    assert_eq!(traffic.bytes_down, 0, "{traffic:?}");
    assert!(traffic.bytes_up <= 3 * 24, "{traffic:?}");
    assert!(traffic.bytes_up < 3 * 1024, "{traffic:?}");
    assert_eq!(gpu.resident_programs_built(), built, "no program rebuilt");
    // A different Gaussian count rebuilds (densification), the same count does not.
    let grown = device_case(&context, &config, &host_case(&config, 201, 5));
    resident_iteration(
        (&mut gpu, &context, &config),
        &grown,
        Some((&adam, 1e-3)),
        false,
    );
    assert!(gpu.resident_programs_built() > built);
}
