//! Posing the template for every frame of a sequence at once: the same map as
//! [`BodyModel::forward`] (shape, pose blend shapes, forward kinematics, linear blend
//! skinning, world transform), organised for throughput.
//!
//! Per frame, `BodyModel::forward` recomputes the shaped template and streams the pose blend
//! shapes vertex by vertex in f64. Here:
//! - the shaped template and rest joints are computed once per distinct shape (betas and
//!   expression are usually constant over a sequence);
//! - the pose blend-shape offsets of a batch of frames are one matrix product,
//!   `(3V x P) pose_dirs . (P x frames) features`, in f32 with `seqavatar_core::matmul` (the blend shapes are
//!   stored in f32, and the output arrays are f32);
//! - the skinning transforms come from [`BodyModel::joint_transforms`] and the per-vertex
//!   blend from [`BodyModel::blend_transform`] (core's forward kinematics and LBS), frames in
//!   parallel.
//!
//! The result matches `BodyModel::forward` to f32 rounding (tested).

use rayon::prelude::*;
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::glam::{DAffine3, DMat3, DVec3};
use seqavatar_core::matmul::{Layout, Matrix, MatrixMut, matmul, parallelism_for};
use seqavatar_core::rotation::axis_angle_to_matrix;
use seqavatar_schema::body::BodySequence;

/// Frames whose pose blend-shape offsets are computed by one matrix product: bounds the
/// offset buffer (`3 V x FRAME_BATCH` f32, 4 MB for SMPL-X) while keeping the product wide.
const FRAME_BATCH: usize = 32;

/// SMPL's pose feature of one frame: `(R_j - I)` of every non-root joint, row-major, in
/// the order of the model's `pose_dirs` columns.
pub fn pose_feature(pose: &[DVec3]) -> Vec<f32> {
    let mut out = Vec::with_capacity(9 * pose.len().saturating_sub(1));
    for v in pose.iter().skip(1) {
        let m = axis_angle_to_matrix(*v) - DMat3::IDENTITY;
        for row in 0..3 {
            out.extend([m.x_axis[row], m.y_axis[row], m.z_axis[row]].map(|x| x as f32));
        }
    }
    out
}

/// The shape-dependent part of posing: shaped template and rest joints.
struct Shape {
    betas: Vec<f64>,
    expression: Vec<f64>,
    vertices: Vec<DVec3>,
    rest_joints: Vec<DVec3>,
}

/// Poses `sequence` with `model` and writes world-space vertices `(frame, vertex, xyz)` into
/// `out`. Errors name the frame (and, for non-finite values, the joint).
pub fn pose_sequence(
    model: &BodyModel,
    sequence: &BodySequence,
    out: &mut [f32],
) -> anyhow::Result<()> {
    let (f, v) = (sequence.num_frames, model.num_vertices());
    anyhow::ensure!(
        out.len() == f * v * 3,
        "output holds {} values, expected {f} frames x {v} vertices x 3",
        out.len()
    );
    sequence
        .check_finite("body")
        .map_err(|message| anyhow::anyhow!("{message}"))?;
    let params: Vec<BodyParams> = sequence.to_params();
    for (t, p) in params.iter().enumerate() {
        model
            .check_params(p)
            .map_err(|e| anyhow::anyhow!("frame {t}: {e}"))?;
    }
    // Distinct shapes, in order; `shape_of[t]` indexes them.
    let mut shapes: Vec<Shape> = Vec::new();
    let mut shape_of = Vec::with_capacity(f);
    for p in &params {
        let known = shapes
            .iter()
            .rposition(|s| s.betas == p.betas && s.expression == p.expression);
        let index = match known {
            Some(i) => i,
            None => {
                let vertices = model.shaped_vertices(p);
                let rest_joints = model.regress_joints(&vertices);
                shapes.push(Shape {
                    betas: p.betas.clone(),
                    expression: p.expression.clone(),
                    vertices,
                    rest_joints,
                });
                shapes.len() - 1
            }
        };
        shape_of.push(index);
    }
    let pose_dirs = &model.arrays().pose_dirs;
    let num_features = if model.has_pose_dirs() {
        9 * model.num_joints().saturating_sub(1)
    } else {
        0
    };
    let rows = 3 * v;
    let mut offsets = vec![0.0_f32; rows * FRAME_BATCH.min(f.max(1))];
    let mut features = vec![0.0_f32; num_features * FRAME_BATCH.min(f.max(1))];
    for batch_start in (0..f).step_by(FRAME_BATCH) {
        let batch = FRAME_BATCH.min(f - batch_start);
        let frames = batch_start..batch_start + batch;
        if num_features > 0 {
            for (column, t) in features.chunks_exact_mut(num_features).zip(frames.clone()) {
                column.copy_from_slice(&pose_feature(&params[t].pose));
            }
            // offsets[b * 3V + r] = sum_p pose_dirs[r * P + p] features[b * P + p].
            matmul(
                MatrixMut::new(&mut offsets, Layout::strided(rows, batch, 1, rows)),
                Matrix::new(pose_dirs, Layout::row_major(rows, num_features)),
                Matrix::new(
                    &features,
                    Layout::strided(num_features, batch, 1, num_features),
                ),
                false,
                parallelism_for(rows * batch * num_features),
            );
        }
        out[batch_start * rows..(batch_start + batch) * rows]
            .par_chunks_mut(rows.max(1))
            .zip(frames)
            .enumerate()
            .for_each(|(b, (dst, t))| {
                let p = &params[t];
                let shape = &shapes[shape_of[t]];
                let transforms: Vec<DAffine3> = model.joint_transforms(&shape.rest_joints, &p.pose);
                let world = DAffine3::from_mat3_translation(
                    axis_angle_to_matrix(p.world_rotation),
                    p.world_translation,
                );
                let offset = &offsets[b * rows..(b + 1) * rows];
                for (vertex, d) in dst.chunks_exact_mut(3).enumerate() {
                    let mut x = shape.vertices[vertex];
                    if num_features > 0 {
                        let o = &offset[3 * vertex..3 * vertex + 3];
                        x += DVec3::new(f64::from(o[0]), f64::from(o[1]), f64::from(o[2]));
                    }
                    let blended = model.blend_transform(vertex, &transforms);
                    let y = world.transform_point3(blended.transform_point3(x));
                    d[0] = y.x as f32;
                    d[1] = y.y as f32;
                    d[2] = y.z as f32;
                }
            });
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use seqavatar_core::body::{BodyModelArrays, SMPL_PARENTS};

    /// Deterministic noise in [-1, 1].
    pub(crate) fn noise(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// A small SMPL-tree model (24 joints) with random shape, expression and pose blend
    /// shapes, three skinning influences per vertex.
    pub(crate) fn test_model(num_vertices: usize) -> BodyModel {
        let mut seed = 3;
        let j = 24;
        let template = (0..num_vertices)
            .map(|_| {
                [
                    0.3 * noise(&mut seed),
                    0.9 * noise(&mut seed),
                    0.15 * noise(&mut seed),
                ]
            })
            .collect();
        let mut weights = vec![0.0; num_vertices * j];
        for v in 0..num_vertices {
            for k in 0..3 {
                weights[v * j + (v * 5 + k * 11) % j] += 1.0 / 3.0;
            }
        }
        let mut joint_regressor = vec![0.0; j * num_vertices];
        for joint in 0..j {
            for k in 0..4 {
                joint_regressor[joint * num_vertices + (joint * 7 + k * 13) % num_vertices] += 0.25;
            }
        }
        let (b, e) = (4, 3);
        BodyModel::new(BodyModelArrays {
            template,
            faces: vec![[0, 1, 2]],
            parents: SMPL_PARENTS
                .iter()
                .map(|p| p.map_or(-1, |p| p as i64))
                .collect(),
            weights,
            joint_regressor,
            shape_dirs: (0..num_vertices * 3 * b)
                .map(|_| 0.02 * noise(&mut seed))
                .collect(),
            num_betas: b,
            expression_dirs: (0..num_vertices * 3 * e)
                .map(|_| 0.01 * noise(&mut seed))
                .collect(),
            num_expression: e,
            pose_dirs: (0..num_vertices * 3 * 9 * (j - 1))
                .map(|_| (0.01 * noise(&mut seed)) as f32)
                .collect(),
        })
        .expect("valid test model")
    }

    /// Frames of random poses; the shape changes at frame 20 and the expression at every
    /// frame after 30 (so both the cached and the per-frame shape paths run).
    pub(crate) fn test_params(model: &BodyModel, frames: usize) -> Vec<BodyParams> {
        let mut seed = 11;
        (0..frames)
            .map(|t| {
                let mut p = model.zero_params();
                for v in &mut p.pose {
                    *v = DVec3::new(noise(&mut seed), noise(&mut seed), noise(&mut seed)) * 0.7;
                }
                p.betas = vec![if t < 20 { 0.5 } else { -0.3 }, 0.2, 0.0, 0.1];
                p.expression = vec![if t > 30 { 0.1 * t as f64 } else { 0.0 }, 0.3, -0.2];
                p.world_rotation = DVec3::new(0.1, 0.05 * t as f64, 0.0);
                p.world_translation = DVec3::new(0.02 * t as f64, 0.9, -0.1);
                p
            })
            .collect()
    }

    #[test]
    fn matches_the_body_models_forward_pass() {
        let model = test_model(300);
        // 40 frames: two batches, the second partial.
        let params = test_params(&model, 40);
        let sequence = BodySequence::from_params(&params).unwrap();
        let v = model.num_vertices();
        let mut out = vec![0.0_f32; 40 * v * 3];
        pose_sequence(&model, &sequence, &mut out).unwrap();
        let mut worst = 0.0_f64;
        for (t, p) in params.iter().enumerate() {
            let reference = model.forward(p).unwrap().vertices;
            for (i, r) in reference.iter().enumerate() {
                let at = (t * v + i) * 3;
                let got = DVec3::new(
                    f64::from(out[at]),
                    f64::from(out[at + 1]),
                    f64::from(out[at + 2]),
                );
                worst = worst.max((got - *r).length());
            }
        }
        println!("batched posing vs BodyModel::forward: worst {worst:.2e} m");
        assert!(worst < 1e-5, "{worst}");
        // The output size is checked.
        assert!(pose_sequence(&model, &sequence, &mut out[3..]).is_err());
    }
}
