//! Forward kinematics, linear blend skinning and its vector-Jacobian product.
//!
//! The forward map, for shape `beta`, expression `psi`, local rotations `R_j = exp(theta_j)`
//! and world transform `(W = exp(omega), T)`:
//!
//! ```text
//! s_v = t_v + S_v beta + E_v psi                 shaped vertices
//! J_j = sum_v Q_jv s_v                           rest joints (regressor)
//! p_v = s_v + P_v f(R),  f = vec(R_j - I), j>=1  pose blend shapes
//! M_j = M_par R_j,  g_j = M_par (J_j - J_par) + g_par   (root: M_0 = R_0, g_0 = J_0)
//! A_j = [M_j | g_j - M_j J_j]                    skinning transform of joint j
//! x_v = sum_j w_vj A_j p_v                       skinned vertex
//! y_v = W x_v + T,   k_j = W g_j + T             world vertices and joints
//! ```
//!
//! [`BodyModel::vjp`] runs this backwards (reverse-mode, hand derived) and is checked
//! against central finite differences in f64.

use glam::{DAffine3, DMat3, DVec3};
use rayon::prelude::*;

use super::model::{BodyModel, BodyParams, BodyParamsError};
use crate::rotation::{axis_angle_to_matrix, axis_angle_to_matrix_jacobian};

/// Vertices per rayon task: large enough to amortise scheduling, small enough to balance.
const VERTEX_CHUNK: usize = 512;

/// A posed body: everything the forward pass computed that callers or the VJP need.
#[derive(Clone, Debug)]
pub struct Posed {
    /// World-space skinned vertices `y_v`.
    pub vertices: Vec<DVec3>,
    /// World-space posed joint positions `k_j`.
    pub joints: Vec<DVec3>,
    /// Joint positions regressed from the shaped template, before posing (`J_j`).
    pub rest_joints: Vec<DVec3>,
    /// Per joint, the skinning transform `A_j` (rest space to posed space, before the world
    /// transform).
    pub joint_transforms: Vec<DAffine3>,
    /// The world transform `(W, T)` applied after skinning.
    pub world: DAffine3,
}

/// Gradient of a scalar loss with respect to body parameters (same layout as
/// [`BodyParams`], with `betas` and `expression` as long as the model's).
#[derive(Clone, Debug, PartialEq)]
pub struct BodyGradient {
    pub pose: Vec<DVec3>,
    pub betas: Vec<f64>,
    pub expression: Vec<f64>,
    pub world_rotation: DVec3,
    pub world_translation: DVec3,
}

/// `(R - I)` of every non-root joint flattened row-major: SMPL's pose feature.
fn pose_feature(rotations: &[DMat3]) -> Vec<f64> {
    let mut feature = Vec::with_capacity(9 * rotations.len().saturating_sub(1));
    for r in &rotations[1..] {
        let m = *r - DMat3::IDENTITY;
        for row in 0..3 {
            // glam stores columns: element (row, col) is `col(col)[row]`.
            feature.extend([m.x_axis[row], m.y_axis[row], m.z_axis[row]]);
        }
    }
    feature
}

/// Frobenius inner product `<A, B>`.
fn frobenius(a: DMat3, b: DMat3) -> f64 {
    a.x_axis.dot(b.x_axis) + a.y_axis.dot(b.y_axis) + a.z_axis.dot(b.z_axis)
}

/// Outer product `a b^T`.
fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// `v += sum_k dirs[k] coefficient[k]` for one vertex's `(3, K)` block.
#[inline]
fn add_blend(out: &mut [f64; 3], dirs: &[f64], coefficients: &[f64]) {
    let k = dirs.len() / 3;
    for (c, value) in out.iter_mut().enumerate() {
        let row = &dirs[c * k..c * k + coefficients.len()];
        *value += row
            .iter()
            .zip(coefficients)
            .map(|(d, b)| d * b)
            .sum::<f64>();
    }
}

impl BodyModel {
    /// Shaped template `s_v = t_v + S_v beta + E_v psi` (no pose).
    pub fn shaped_vertices(&self, params: &BodyParams) -> Vec<DVec3> {
        let num_betas = self.arrays.num_betas;
        let num_expr = self.arrays.num_expression;
        let mut out = vec![DVec3::ZERO; self.num_vertices()];
        out.par_chunks_mut(VERTEX_CHUNK)
            .enumerate()
            .for_each(|(chunk, slice)| {
                for (i, value) in slice.iter_mut().enumerate() {
                    let v = chunk * VERTEX_CHUNK + i;
                    let mut s = self.arrays.template[v];
                    if !params.betas.is_empty() {
                        let dirs =
                            &self.arrays.shape_dirs[v * 3 * num_betas..(v + 1) * 3 * num_betas];
                        add_blend(&mut s, dirs, &params.betas);
                    }
                    if !params.expression.is_empty() {
                        let dirs =
                            &self.arrays.expression_dirs[v * 3 * num_expr..(v + 1) * 3 * num_expr];
                        add_blend(&mut s, dirs, &params.expression);
                    }
                    *value = DVec3::from_array(s);
                }
            });
        out
    }

    /// Rest joints `J = Q s` from shaped vertices.
    pub fn regress_joints(&self, shaped: &[DVec3]) -> Vec<DVec3> {
        (0..self.num_joints())
            .map(|j| {
                let range =
                    self.regressor_offsets[j] as usize..self.regressor_offsets[j + 1] as usize;
                self.regressor_vertices[range.clone()]
                    .iter()
                    .zip(&self.regressor_weights[range])
                    .map(|(&v, &w)| shaped[v as usize] * w)
                    .sum()
            })
            .collect()
    }

    /// Global joint frames `(M_j, g_j)` from rest joints and local rotations.
    fn global_frames(&self, rest_joints: &[DVec3], rotations: &[DMat3]) -> Vec<DAffine3> {
        let mut frames: Vec<DAffine3> = Vec::with_capacity(self.num_joints());
        for (j, parent) in self.parents.iter().enumerate() {
            let frame = match parent {
                None => DAffine3::from_mat3_translation(rotations[j], rest_joints[j]),
                Some(p) => {
                    let pf = frames[*p];
                    DAffine3::from_mat3_translation(
                        pf.matrix3 * rotations[j],
                        pf.matrix3 * (rest_joints[j] - rest_joints[*p]) + pf.translation,
                    )
                }
            };
            frames.push(frame);
        }
        frames
    }

    /// Skinning transforms `A_j` for a pose, given rest joints: maps rest space to posed
    /// space (no world transform). For the canonical big pose pass [`super::big_pose`].
    pub fn joint_transforms(&self, rest_joints: &[DVec3], pose: &[DVec3]) -> Vec<DAffine3> {
        let rotations: Vec<DMat3> = pose.iter().map(|&v| axis_angle_to_matrix(v)).collect();
        self.global_frames(rest_joints, &rotations)
            .into_iter()
            .zip(rest_joints)
            .map(|(g, &rest)| {
                DAffine3::from_mat3_translation(g.matrix3, g.translation - g.matrix3 * rest)
            })
            .collect()
    }

    /// Linear blend of joint transforms with a vertex's weights: `sum_j w_vj A_j`.
    pub fn blend_transform(&self, vertex: usize, joint_transforms: &[DAffine3]) -> DAffine3 {
        let mut m = DMat3::ZERO;
        let mut t = DVec3::ZERO;
        for (j, w) in self.vertex_weights(vertex) {
            m += joint_transforms[j].matrix3 * w;
            t += joint_transforms[j].translation * w;
        }
        DAffine3::from_mat3_translation(m, t)
    }

    /// Pose blend-shape offset `P_v f` of one vertex.
    #[inline]
    fn pose_offset(&self, vertex: usize, feature: &[f64]) -> DVec3 {
        let p = feature.len();
        let block = &self.arrays.pose_dirs[vertex * 3 * p..(vertex + 1) * 3 * p];
        let mut out = [0.0; 3];
        for (c, value) in out.iter_mut().enumerate() {
            let row = &block[c * p..(c + 1) * p];
            *value = row
                .iter()
                .zip(feature)
                .map(|(&d, &f)| d as f64 * f)
                .sum::<f64>();
        }
        DVec3::from_array(out)
    }

    /// The full forward pass: shape, pose blend shapes, forward kinematics, LBS, world.
    pub fn forward(&self, params: &BodyParams) -> Result<Posed, BodyParamsError> {
        self.check_params(params)?;
        let shaped = self.shaped_vertices(params);
        let rest_joints = self.regress_joints(&shaped);
        let rotations: Vec<DMat3> = params
            .pose
            .iter()
            .map(|&v| axis_angle_to_matrix(v))
            .collect();
        let frames = self.global_frames(&rest_joints, &rotations);
        let joint_transforms: Vec<DAffine3> = frames
            .iter()
            .zip(&rest_joints)
            .map(|(g, &rest)| {
                DAffine3::from_mat3_translation(g.matrix3, g.translation - g.matrix3 * rest)
            })
            .collect();
        let world = DAffine3::from_mat3_translation(
            axis_angle_to_matrix(params.world_rotation),
            params.world_translation,
        );
        let feature = if self.has_pose_dirs() {
            pose_feature(&rotations)
        } else {
            Vec::new()
        };
        let mut vertices = shaped;
        vertices
            .par_chunks_mut(VERTEX_CHUNK)
            .enumerate()
            .for_each(|(chunk, slice)| {
                for (i, value) in slice.iter_mut().enumerate() {
                    let v = chunk * VERTEX_CHUNK + i;
                    let mut p = *value;
                    if !feature.is_empty() {
                        p += self.pose_offset(v, &feature);
                    }
                    let blended = self.blend_transform(v, &joint_transforms);
                    *value = world.transform_point3(blended.transform_point3(p));
                }
            });
        let joints = frames
            .iter()
            .map(|g| world.transform_point3(g.translation))
            .collect();
        Ok(Posed {
            vertices,
            joints,
            rest_joints,
            joint_transforms,
            world,
        })
    }

    /// Vector-Jacobian product of [`BodyModel::forward`]: given `dL/dy_v` (world vertices)
    /// and `dL/dk_j` (world joints), returns `dL/d(params)`. Either gradient slice may be
    /// empty, meaning zero.
    pub fn vjp(
        &self,
        params: &BodyParams,
        grad_vertices: &[DVec3],
        grad_joints: &[DVec3],
    ) -> Result<BodyGradient, BodyParamsError> {
        self.check_params(params)?;
        let num_vertices = self.num_vertices();
        let num_joints = self.num_joints();
        assert!(
            grad_vertices.is_empty() || grad_vertices.len() == num_vertices,
            "vertex gradient length {} != {num_vertices}",
            grad_vertices.len()
        );
        assert!(
            grad_joints.is_empty() || grad_joints.len() == num_joints,
            "joint gradient length {} != {num_joints}",
            grad_joints.len()
        );
        // Recompute the forward intermediates.
        let shaped = self.shaped_vertices(params);
        let rest_joints = self.regress_joints(&shaped);
        let rotations: Vec<DMat3> = params
            .pose
            .iter()
            .map(|&v| axis_angle_to_matrix(v))
            .collect();
        let frames = self.global_frames(&rest_joints, &rotations);
        let world_matrix = axis_angle_to_matrix(params.world_rotation);
        let has_pose_dirs = self.has_pose_dirs();
        let feature = if has_pose_dirs {
            pose_feature(&rotations)
        } else {
            Vec::new()
        };
        let num_features = feature.len();
        let transforms: Vec<DAffine3> = frames
            .iter()
            .zip(&rest_joints)
            .map(|(g, &rest)| {
                DAffine3::from_mat3_translation(g.matrix3, g.translation - g.matrix3 * rest)
            })
            .collect();

        // Per-vertex backward pass, reduced over vertices: per joint dL/dM_j and dL/da_j,
        // dL/dW, dL/dT, dL/df; per vertex dL/dp_v (which equals the direct part of dL/ds_v).
        struct Accumulator {
            grad_m: Vec<DMat3>,
            grad_a: Vec<DVec3>,
            grad_world: DMat3,
            grad_translation: DVec3,
            grad_feature: Vec<f64>,
        }
        let new_accumulator = || Accumulator {
            grad_m: vec![DMat3::ZERO; num_joints],
            grad_a: vec![DVec3::ZERO; num_joints],
            grad_world: DMat3::ZERO,
            grad_translation: DVec3::ZERO,
            grad_feature: vec![0.0; num_features],
        };
        let mut grad_shaped = vec![DVec3::ZERO; num_vertices];
        let accumulator = if grad_vertices.is_empty() {
            new_accumulator()
        } else {
            grad_shaped
                .par_chunks_mut(VERTEX_CHUNK)
                .enumerate()
                .fold(new_accumulator, |mut acc, (chunk, slice)| {
                    for (i, grad_s) in slice.iter_mut().enumerate() {
                        let v = chunk * VERTEX_CHUNK + i;
                        let mut p = shaped[v];
                        if has_pose_dirs {
                            p += self.pose_offset(v, &feature);
                        }
                        let blended = self.blend_transform(v, &transforms);
                        let x = blended.transform_point3(p);
                        let grad_y = grad_vertices[v];
                        acc.grad_world += outer(grad_y, x);
                        acc.grad_translation += grad_y;
                        let grad_x = world_matrix.transpose() * grad_y;
                        for (j, w) in self.vertex_weights(v) {
                            acc.grad_m[j] += outer(grad_x * w, p);
                            acc.grad_a[j] += grad_x * w;
                        }
                        let grad_p = blended.matrix3.transpose() * grad_x;
                        *grad_s = grad_p;
                        if has_pose_dirs {
                            let block = &self.arrays.pose_dirs
                                [v * 3 * num_features..(v + 1) * 3 * num_features];
                            for c in 0..3 {
                                let g = grad_p[c];
                                let row = &block[c * num_features..(c + 1) * num_features];
                                for (out, &d) in acc.grad_feature.iter_mut().zip(row) {
                                    *out += d as f64 * g;
                                }
                            }
                        }
                    }
                    acc
                })
                .reduce(new_accumulator, |mut a, b| {
                    for j in 0..num_joints {
                        a.grad_m[j] += b.grad_m[j];
                        a.grad_a[j] += b.grad_a[j];
                    }
                    a.grad_world += b.grad_world;
                    a.grad_translation += b.grad_translation;
                    for (x, y) in a.grad_feature.iter_mut().zip(&b.grad_feature) {
                        *x += y;
                    }
                    a
                })
        };
        let Accumulator {
            mut grad_m,
            grad_a,
            mut grad_world,
            mut grad_translation,
            grad_feature,
        } = accumulator;

        // Joint outputs k_j = W g_j + T.
        let mut grad_g = vec![DVec3::ZERO; num_joints];
        for (j, &grad_k) in grad_joints.iter().enumerate() {
            grad_world += outer(grad_k, frames[j].translation);
            grad_translation += grad_k;
            grad_g[j] += world_matrix.transpose() * grad_k;
        }
        // a_j = g_j - M_j J_j.
        let mut grad_rest = vec![DVec3::ZERO; num_joints];
        for j in 0..num_joints {
            grad_g[j] += grad_a[j];
            grad_m[j] -= outer(grad_a[j], rest_joints[j]);
            grad_rest[j] -= frames[j].matrix3.transpose() * grad_a[j];
        }
        // Forward kinematics, children before parents.
        let mut grad_r = vec![DMat3::ZERO; num_joints];
        for j in (0..num_joints).rev() {
            match self.parents[j] {
                None => {
                    grad_r[j] += grad_m[j];
                    grad_rest[j] += grad_g[j];
                }
                Some(p) => {
                    let parent_m = frames[p].matrix3;
                    let bone = rest_joints[j] - rest_joints[p];
                    let (gg, gm) = (grad_g[j], grad_m[j]);
                    grad_m[p] += outer(gg, bone) + gm * rotations[j].transpose();
                    grad_rest[j] += parent_m.transpose() * gg;
                    grad_rest[p] -= parent_m.transpose() * gg;
                    grad_g[p] += gg;
                    grad_r[j] += parent_m.transpose() * gm;
                }
            }
        }
        // Pose feature f = vec(R_j - I), row-major, joints 1.. .
        for (j, grad) in grad_r.iter_mut().enumerate().skip(1) {
            if grad_feature.is_empty() {
                break;
            }
            let block = &grad_feature[(j - 1) * 9..j * 9];
            let rows = DMat3::from_cols_array(&[
                block[0], block[3], block[6], block[1], block[4], block[7], block[2], block[5],
                block[8],
            ]);
            *grad += rows;
        }
        let pose = params
            .pose
            .iter()
            .zip(&grad_r)
            .map(|(&theta, &grad)| {
                let d = axis_angle_to_matrix_jacobian(theta);
                DVec3::new(
                    frobenius(grad, d[0]),
                    frobenius(grad, d[1]),
                    frobenius(grad, d[2]),
                )
            })
            .collect();
        let d_world = axis_angle_to_matrix_jacobian(params.world_rotation);
        let world_rotation = DVec3::new(
            frobenius(grad_world, d_world[0]),
            frobenius(grad_world, d_world[1]),
            frobenius(grad_world, d_world[2]),
        );
        // Regressor: s_v += sum_j Q_jv dL/dJ_j.
        for (j, &g) in grad_rest.iter().enumerate() {
            let range = self.regressor_offsets[j] as usize..self.regressor_offsets[j + 1] as usize;
            for (&v, &w) in self.regressor_vertices[range.clone()]
                .iter()
                .zip(&self.regressor_weights[range])
            {
                grad_shaped[v as usize] += g * w;
            }
        }
        let project = |dirs: &[f64], count: usize| -> Vec<f64> {
            let mut out = vec![0.0; count];
            if count == 0 {
                return out;
            }
            for (v, g) in grad_shaped.iter().enumerate() {
                let block = &dirs[v * 3 * count..(v + 1) * 3 * count];
                for c in 0..3 {
                    for (o, &d) in out.iter_mut().zip(&block[c * count..(c + 1) * count]) {
                        *o += d * g[c];
                    }
                }
            }
            out
        };
        Ok(BodyGradient {
            pose,
            betas: project(&self.arrays.shape_dirs, self.arrays.num_betas),
            expression: project(&self.arrays.expression_dirs, self.arrays.num_expression),
            world_rotation,
            world_translation: grad_translation,
        })
    }
}
