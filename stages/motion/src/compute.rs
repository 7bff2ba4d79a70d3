//! The motion templates of a whole sequence, in memory: posed template vertices, per-joint
//! rotations, skeleton motion and vertex velocity per (frame, scale), and the canonical
//! template with its KNN graph. The stage writes these arrays; the benchmark times this.

use rayon::prelude::*;
use seqavatar_core::body::{BodyModel, BodyParams, big_pose};
use seqavatar_core::glam::DMat3;
use seqavatar_core::rotation::axis_angle_to_matrix;
use seqavatar_fit::io::BodySequence;

use crate::context::{self, Scales, VelocityNormalisation};
use crate::knn::{KnnGraph, knn_graph};

/// Per-frame motion arrays, row-major, frame-major.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionArrays {
    pub num_frames: usize,
    pub num_vertices: usize,
    pub num_joints: usize,
    /// `(frame, vertex, 3)` posed world-space template vertices.
    pub posed_vertices: Vec<f32>,
    /// `(frame, joint, 3, 3)` rotation matrices, row-major: joint 0 is the root's world
    /// orientation `R(Rh) R(pose_0)`, the others are local joint rotations.
    pub joint_rotations: Vec<f32>,
    /// `(frame, scale, joint, 3)` axis-angle of `R_t R_{t-s}^-1`.
    pub skeleton_motion: Vec<f32>,
    /// `(frame, scale, vertex, 3)` vertex velocity.
    pub vertex_velocity: Vec<f32>,
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
    let mut rotations = vec![DMat3::IDENTITY; f * j];
    posed_vertices
        .par_chunks_mut((v * 3).max(1))
        .zip(rotations.par_chunks_mut(j.max(1)))
        .enumerate()
        .try_for_each(|(t, (dst, rot))| -> anyhow::Result<()> {
            let params = sequence.params(t);
            let posed = model
                .forward(&params)
                .map_err(|e| anyhow::anyhow!("frame {t}: {e}"))?;
            for (d, p) in dst.chunks_exact_mut(3).zip(&posed.vertices) {
                d[0] = p.x as f32;
                d[1] = p.y as f32;
                d[2] = p.z as f32;
            }
            rot.copy_from_slice(&motion_rotations(&params));
            Ok(())
        })?;
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
