//! The body rig of an avatar: the canonical (big-pose) joint transforms, and per frame the
//! target joint transforms and per-vertex rest offsets that [`crate::skinning`] consumes.
//!
//! Everything is derived from the body model's public forward pass in `seqavatar-core`
//! (forward kinematics and LBS live there only):
//! - canonical joints `B_j`: skinning transforms of the big pose with zero shape (the motion
//!   stage's `canonical_vertices` are this pose's vertices);
//! - target joints `W A_j + T`: the frame's skinning transforms with the world transform;
//! - vertex offsets `-pose_blend(big)_v + shape_v + pose_blend(target)_v`, obtained exactly as
//!   `A_v^-1 y_v - B_v^-1 c_v` where `y_v` is the frame's posed vertex without the world
//!   transform, `c_v` the canonical vertex, and `A_v`, `B_v` their blended transforms: LBS is
//!   `y_v = A_v (s_v + P_v f)`, so this needs neither the shape nor the pose blend shapes here.

use glam::{DAffine3, DMat3, DVec3};
use rayon::prelude::*;
use seqavatar_core::body::{BodyModel, BodyParams, big_pose};
use seqavatar_core::rotation::{axis_angle_to_matrix, matrix_to_axis_angle};

use crate::skinning::{SkinningFrame, mat_lin, mat_trans, outer};

/// A row-major 3 x 4 `[r00 r01 r02 t0 r10 ... t2]` from an affine transform.
pub fn affine_to_rows(a: &DAffine3) -> [f64; 12] {
    let m = a.matrix3;
    let t = a.translation;
    let mut out = [0.0; 12];
    for r in 0..3 {
        out[4 * r] = m.x_axis[r];
        out[4 * r + 1] = m.y_axis[r];
        out[4 * r + 2] = m.z_axis[r];
        out[4 * r + 3] = t[r];
    }
    out
}

/// The affine transform of a row-major 3 x 4 (the inverse of [`affine_to_rows`]).
pub fn rows_to_affine(rows: &[f64; 12]) -> DAffine3 {
    DAffine3::from_cols_array(&[
        rows[0], rows[4], rows[8], rows[1], rows[5], rows[9], rows[2], rows[6], rows[10], rows[3],
        rows[7], rows[11],
    ])
}

/// A body model with its canonical space.
#[derive(Clone, Debug)]
pub struct BodyRig {
    pub model: BodyModel,
    /// `J` big-pose skinning transforms (zero shape), row-major 3 x 4.
    pub canonical_joints: Vec<[f64; 12]>,
    /// Canonical template vertices (big pose, zero shape), `V x 3`.
    pub canonical_vertices: Vec<f64>,
    /// Template skinning weights, `V x J`.
    pub template_weights: Vec<f64>,
    /// `B_v^-1 c_v = t_v + P_v f(big)` per vertex.
    canonical_rest: Vec<DVec3>,
}

/// What the backward of [`BodyRig::pose`] needs: local rotations, rest joints, global
/// frames and the world rotation of the frame.
#[derive(Clone, Debug)]
pub struct PoseChain {
    rotations: Vec<DMat3>,
    rest_joints: Vec<DVec3>,
    /// Global joint frames `(M_j, g_j)`.
    frames: Vec<(DMat3, DVec3)>,
    world: DMat3,
}

/// One frame's target of the skinning.
#[derive(Clone, Debug, PartialEq)]
pub struct FramePose {
    /// `J` world-space target joint transforms, row-major 3 x 4.
    pub target_joints: Vec<[f64; 12]>,
    /// `V x 3` rest-space offsets added at the nearest template vertex.
    pub vertex_offsets: Vec<f64>,
}

impl BodyRig {
    pub fn new(model: BodyModel) -> anyhow::Result<Self> {
        let mut params = model.zero_params();
        params.pose = big_pose(model.num_joints());
        let posed = model
            .forward(&params)
            .map_err(|e| anyhow::anyhow!("canonical big pose: {e}"))?;
        let canonical_joints = posed.joint_transforms.iter().map(affine_to_rows).collect();
        let canonical_rest = inverse_blend(&model, &posed.joint_transforms, &posed.vertices)?;
        let canonical_vertices = posed.vertices.iter().flat_map(|v| v.to_array()).collect();
        let template_weights = model.arrays().weights.clone();
        Ok(Self {
            model,
            canonical_joints,
            canonical_vertices,
            template_weights,
            canonical_rest,
        })
    }

    /// Replaces the template skinning weights by their average over the canonical
    /// template, each vertex weighting the vertices within `3 sigma` by
    /// `exp(-d^2 / (2 sigma^2))` of their canonical (big-pose) distance `d`; `sigma <= 0`
    /// keeps them.
    ///
    /// Why: the skinning weights are `softmax(log(w + 1e-9) + offset)` at the nearest template
    /// vertex, so a Gaussian that starts on the thigh has a pelvis weight of 1e-9, whose
    /// softmax gradient is 1e-9 too: no training moves it. A loose skirt's Gaussians start
    /// there and must follow the pelvis, not the legs. Diffused weights give every joint
    /// near a vertex a weight the offsets can grow or remove (the "diffused skinning" of
    /// volumetric avatars), at the price of softer joints where nothing asks for it.
    pub fn smooth_template_weights(&mut self, sigma: f64) {
        if sigma <= 0.0 || !sigma.is_finite() {
            return;
        }
        let joints = self.joint_count();
        let points = seqavatar_knn::as_points(&self.canonical_vertices);
        let grid = seqavatar_knn::KnnGrid::new(&points, 8.0);
        let weights = &self.template_weights;
        let reach = 3.0 * sigma;
        let smoothed: Vec<f64> = points
            .par_iter()
            .flat_map_iter(|p| {
                let mut sum = vec![0.0; joints];
                let mut total = 0.0;
                // Never empty: a vertex is within any radius of itself.
                for u in grid.within(p, reach) {
                    let q = &points[u as usize];
                    let d2 = (0..3).map(|a| (p[a] - q[a]).powi(2)).sum::<f64>();
                    let kernel = (-d2 / (2.0 * sigma * sigma)).exp();
                    total += kernel;
                    let row = &weights[u as usize * joints..(u as usize + 1) * joints];
                    for (s, w) in sum.iter_mut().zip(row) {
                        *s += kernel * w;
                    }
                }
                sum.into_iter().map(move |s| s / total)
            })
            .collect();
        self.template_weights = smoothed;
    }

    pub fn joint_count(&self) -> usize {
        self.model.num_joints()
    }

    pub fn vertex_count(&self) -> usize {
        self.model.num_vertices()
    }

    /// `B_v^-1 c_v = t_v + P_v f(big)` per vertex: what [`BodyRig::pose`] subtracts from a
    /// frame's rest vertices to get its vertex offsets.
    pub fn canonical_rest(&self) -> &[DVec3] {
        &self.canonical_rest
    }

    /// The skinning target of one frame's body parameters.
    pub fn pose(&self, params: &BodyParams) -> anyhow::Result<FramePose> {
        Ok(self.pose_with_chain(params)?.0)
    }

    /// [`BodyRig::pose`] and what its backward needs.
    pub fn pose_with_chain(&self, params: &BodyParams) -> anyhow::Result<(FramePose, PoseChain)> {
        let local = BodyParams {
            world_rotation: DVec3::ZERO,
            world_translation: DVec3::ZERO,
            ..params.clone()
        };
        let posed = self
            .model
            .forward(&local)
            .map_err(|e| anyhow::anyhow!("posing the body: {e}"))?;
        let rest = inverse_blend(&self.model, &posed.joint_transforms, &posed.vertices)?;
        let vertex_offsets = rest
            .iter()
            .zip(&self.canonical_rest)
            .flat_map(|(r, c)| (*r - *c).to_array())
            .collect();
        let world = DAffine3::from_mat3_translation(
            axis_angle_to_matrix(params.world_rotation),
            params.world_translation,
        );
        let target_joints = posed
            .joint_transforms
            .iter()
            .map(|a| affine_to_rows(&(world * *a)))
            .collect();
        let rotations: Vec<DMat3> = params
            .pose
            .iter()
            .map(|v| axis_angle_to_matrix(*v))
            .collect();
        let frames = posed
            .joint_transforms
            .iter()
            .zip(&posed.rest_joints)
            .map(|(a, rest)| (a.matrix3, a.translation + a.matrix3 * *rest))
            .collect();
        let chain = PoseChain {
            rotations,
            rest_joints: posed.rest_joints,
            frames,
            world: world.matrix3,
        };
        Ok((
            FramePose {
                target_joints,
                vertex_offsets,
            },
            chain,
        ))
    }

    /// Backward of [`BodyRig::pose`] with respect to the local joint rotation matrices `R_j`
    /// (root included), given `dL/d target_joints` (`J x 12`) and `dL/d vertex_offsets`
    /// (`V x 3`, through the pose blend shapes when the model has them).
    pub fn pose_backward(
        &self,
        chain: &PoseChain,
        d_target_joints: &[f64],
        d_vertex_offsets: &[f64],
    ) -> Vec<DMat3> {
        let j_count = self.joint_count();
        assert_eq!(d_target_joints.len(), 12 * j_count);
        assert_eq!(d_vertex_offsets.len(), 3 * self.vertex_count());
        let wt = chain.world.transpose();
        // Target = W [M_j | g_j - M_j J_j] + T.
        let mut d_m = vec![DMat3::ZERO; j_count];
        let mut d_g = vec![DVec3::ZERO; j_count];
        for j in 0..j_count {
            let t = &d_target_joints[12 * j..12 * j + 12];
            let d_t = wt * mat_trans(t);
            d_m[j] = wt * mat_lin(t) - outer(d_t, chain.rest_joints[j]);
            d_g[j] = d_t;
        }
        let mut d_r = vec![DMat3::ZERO; j_count];
        let parents = self.model.parents();
        for j in (0..j_count).rev() {
            match parents[j] {
                None => d_r[j] += d_m[j],
                Some(p) => {
                    let (m_p, _) = chain.frames[p];
                    d_r[j] += m_p.transpose() * d_m[j];
                    let dm_p = d_m[j] * chain.rotations[j].transpose()
                        + outer(d_g[j], chain.rest_joints[j] - chain.rest_joints[p]);
                    d_m[p] += dm_p;
                    let dg = d_g[j];
                    d_g[p] += dg;
                }
            }
        }
        // Pose blend shapes: offset_v += P_v vec(R_j - I), j >= 1, row-major.
        let dirs = &self.model.arrays().pose_dirs;
        if !dirs.is_empty() {
            let features = 9 * (j_count - 1);
            let mut d_feature = vec![0.0; features];
            for v in 0..self.vertex_count() {
                for k in 0..3 {
                    let g = d_vertex_offsets[3 * v + k];
                    if g != 0.0 {
                        let row = &dirs[(3 * v + k) * features..(3 * v + k + 1) * features];
                        for (d, p) in d_feature.iter_mut().zip(row) {
                            *d += g * f64::from(*p);
                        }
                    }
                }
            }
            for j in 1..j_count {
                // Row-major.
                d_r[j] += DMat3::from_cols_slice(&d_feature[9 * (j - 1)..9 * j]).transpose();
            }
        }
        d_r
    }

    /// The skinning inputs of a frame.
    pub fn frame<'a>(
        &'a self,
        pose: &'a FramePose,
        scale_min: f64,
        scale_max: f64,
    ) -> SkinningFrame<'a> {
        SkinningFrame {
            joint_count: self.joint_count(),
            canonical_joints: &self.canonical_joints,
            target_joints: &pose.target_joints,
            template_weights: &self.template_weights,
            vertex_offsets: &pose.vertex_offsets,
            scale_min,
            scale_max,
        }
    }
}

/// `A_v^-1 y_v` for every vertex, `A_v` the template-weight blend of `transforms`.
fn inverse_blend(
    model: &BodyModel,
    transforms: &[DAffine3],
    vertices: &[DVec3],
) -> anyhow::Result<Vec<DVec3>> {
    let rest: Vec<Option<DVec3>> = vertices
        .par_iter()
        .enumerate()
        .map(|(v, y)| {
            let blend = model.blend_transform(v, transforms);
            (blend.matrix3.determinant().abs() > 1e-12)
                .then(|| blend.inverse().transform_point3(*y))
        })
        .collect();
    rest.into_iter()
        .enumerate()
        .map(|(v, r)| {
            r.ok_or_else(|| {
                anyhow::anyhow!("vertex {v}: its blended skinning transform is singular")
            })
        })
        .collect()
}

/// Applies per-joint refinement rotations (`J - 1` row-major 3 x 3, non-root joints) to body
/// parameters: `R_j <- R_j R_ref_j` (right-multiplied, as the pose refiner does).
pub fn refine_pose(params: &BodyParams, refinements: &[DMat3]) -> BodyParams {
    let mut out = params.clone();
    for (j, r) in refinements.iter().enumerate() {
        let joint = j + 1;
        out.pose[joint] = matrix_to_axis_angle(axis_angle_to_matrix(params.pose[joint]) * *r);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skinning::{GaussianParams, skin_forward};
    use seqavatar_core::body::BodyModel;
    use seqavatar_core::body::procedural::procedural_body;

    /// `rows_to_affine` reads back what `affine_to_rows` wrote, entry for entry.
    #[test]
    fn rows_and_affine_transforms_round_trip() {
        let a = DAffine3::from_cols_array(&[
            1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0,
        ]);
        let rows = affine_to_rows(&a);
        assert_eq!(rows[..4], [1.0, 4.0, 7.0, 10.0]);
        assert_eq!(rows_to_affine(&rows), a);
    }

    /// Diffused weights: each row is the kernel-weighted average of the rows within 3 sigma
    /// (a brute-force loop over every pair here, against the grid search), rows still sum
    /// to 1, a vanishing sigma keeps the template's weights, and a vertex of a pure-thigh
    /// row next to the pelvis gains a pelvis weight the softmax gradient can act on.
    #[test]
    fn smoothed_weights_are_the_kernel_average_of_the_neighbours() {
        let rig = BodyRig::new(procedural_body(0.05)).unwrap();
        let (v, j) = (rig.vertex_count(), rig.joint_count());
        let mut tiny = rig.clone();
        tiny.smooth_template_weights(1e-6);
        let close = tiny
            .template_weights
            .iter()
            .zip(&rig.template_weights)
            .all(|(a, b)| (a - b).abs() < 1e-9);
        assert!(close, "sigma 1 um changed the weights");
        let sigma = 0.08;
        let mut smooth = rig.clone();
        smooth.smooth_template_weights(sigma);
        let c = &rig.canonical_vertices;
        for i in (0..v).step_by(7) {
            let mut expected = vec![0.0; j];
            let mut total = 0.0;
            for u in 0..v {
                let d2: f64 = (0..3).map(|a| (c[3 * i + a] - c[3 * u + a]).powi(2)).sum();
                if d2.sqrt() <= 3.0 * sigma {
                    let k = (-d2 / (2.0 * sigma * sigma)).exp();
                    total += k;
                    for (e, w) in expected.iter_mut().zip(&rig.template_weights[u * j..]) {
                        *e += k * w;
                    }
                }
            }
            let row = &smooth.template_weights[i * j..(i + 1) * j];
            for (got, want) in row.iter().zip(&expected) {
                assert!(
                    (got - want / total).abs() < 1e-12,
                    "vertex {i}: {got} vs {}",
                    want / total
                );
            }
            assert!((row.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        // Thigh vertices (left-hip weight > 0.9) with a pelvis weight the softmax gradient
        // can act on (>= 1e-3): few before, most after.
        let thighs: Vec<usize> = (0..v)
            .filter(|&u| rig.template_weights[u * j + 1] > 0.9)
            .collect();
        let reachable = |w: &[f64]| {
            thighs.iter().filter(|&&u| w[u * j] >= 1e-3).count() as f64 / thighs.len() as f64
        };
        let (before, after) = (
            reachable(&rig.template_weights),
            reachable(&smooth.template_weights),
        );
        eprintln!("thigh vertices with pelvis weight >= 1e-3: {before} -> {after}");
        assert!(after > 0.6 && after > 2.0 * before, "{before} -> {after}");
    }

    /// Skinning the canonical template vertices with zero non-rigid offsets, each at its own
    /// vertex, reproduces the body model's posed vertices (an independent forward pass).
    #[test]
    fn canonical_vertices_skin_to_the_posed_body() {
        let model = procedural_body(0.05);
        let rig = BodyRig::new(model.clone()).unwrap();
        let mut params = model.zero_params();
        for (j, p) in params.pose.iter_mut().enumerate() {
            *p = DVec3::new(0.1 * j as f64 % 0.3, -0.05 * j as f64 % 0.2, 0.07);
        }
        for b in params.betas.iter_mut() {
            *b = 0.4;
        }
        params.world_rotation = DVec3::new(0.2, -1.0, 0.3);
        params.world_translation = DVec3::new(0.5, 0.1, -2.0);
        let pose = rig.pose(&params).unwrap();
        let v = rig.vertex_count();
        let nearest: Vec<u32> = (0..v as u32).collect();
        let zeros = vec![0.0; 3 * v];
        let log_scales = vec![(0.01f64).ln(); 3 * v];
        let identity = [1.0, 0.0, 0.0, 0.0].repeat(v);
        let skinned = skin_forward(
            &rig.frame(&pose, 1e-6, 1.0),
            &GaussianParams {
                positions: &rig.canonical_vertices,
                log_scales: &log_scales,
                d_scales: &zeros,
                rotations: &identity,
                d_rotations: &identity,
                weight_offsets: None,
                nearest: &nearest,
            },
        );
        let expected = model.forward(&params).unwrap().vertices;
        let mut worst = 0.0f64;
        for (i, e) in expected.iter().enumerate() {
            let got = DVec3::new(
                skinned.positions[3 * i],
                skinned.positions[3 * i + 1],
                skinned.positions[3 * i + 2],
            );
            worst = worst.max((got - *e).length());
        }
        // The skinning's softmax adds 1e-9 inside the log of the weights: errors of that order.
        assert!(worst < 1e-6, "worst vertex error {worst}");
    }

    /// The chain backward against central differences of rotations `R_j exp(eps e_k)`:
    /// the directional derivative is `<dL/dR_j, R_j skew(e_k)>`. The model gets random pose
    /// blend shapes so that path is checked too.
    #[test]
    fn pose_backward_matches_finite_differences() {
        use seqavatar_core::rotation::skew;
        let base = procedural_body(0.05);
        let mut arrays = base.arrays().clone();
        let j = base.num_joints();
        let features = 9 * (j - 1);
        let mut rng = seqavatar_core::rng::SplitMix64::new(5);
        arrays.pose_dirs = (0..base.num_vertices() * 3 * features)
            .map(|_| rng.uniform(-0.01, 0.01) as f32)
            .collect();
        let model = BodyModel::new(arrays).unwrap();
        let rig = BodyRig::new(model.clone()).unwrap();
        let mut params = model.zero_params();
        for p in params.pose.iter_mut() {
            *p = DVec3::new(
                rng.uniform(-0.4, 0.4),
                rng.uniform(-0.4, 0.4),
                rng.uniform(-0.4, 0.4),
            );
        }
        params.world_rotation = DVec3::new(0.3, 0.5, -0.2);
        params.world_translation = DVec3::new(0.1, 0.2, 0.3);
        let a: Vec<f64> = (0..12 * j).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let b: Vec<f64> = (0..3 * rig.vertex_count())
            .map(|_| rng.uniform(-1.0, 1.0))
            .collect();
        let loss = |p: &BodyParams| {
            let pose = rig.pose(p).unwrap();
            let t: f64 = pose
                .target_joints
                .iter()
                .flatten()
                .zip(&a)
                .map(|(x, y)| x * y)
                .sum();
            let o: f64 = pose.vertex_offsets.iter().zip(&b).map(|(x, y)| x * y).sum();
            t + o
        };
        let (_, chain) = rig.pose_with_chain(&params).unwrap();
        let grads = rig.pose_backward(&chain, &a, &b);
        let eps = 1e-6;
        for joint in [0, 1, 4, j - 1] {
            for k in 0..3 {
                let mut e = DVec3::ZERO;
                e[k] = 1.0;
                let r0 = axis_angle_to_matrix(params.pose[joint]);
                let at = |s: f64| {
                    let mut p = params.clone();
                    p.pose[joint] = matrix_to_axis_angle(r0 * axis_angle_to_matrix(e * s));
                    loss(&p)
                };
                let numeric = (at(eps) - at(-eps)) / (2.0 * eps);
                let direction = r0 * skew(e);
                let g = grads[joint];
                let analytic = g.x_axis.dot(direction.x_axis)
                    + g.y_axis.dot(direction.y_axis)
                    + g.z_axis.dot(direction.z_axis);
                assert!(
                    (numeric - analytic).abs() < 1e-5 * (1.0 + analytic.abs()),
                    "joint {joint} axis {k}: numeric {numeric} analytic {analytic}"
                );
            }
        }
    }

    #[test]
    fn refinement_right_multiplies_non_root_joints() {
        let model = procedural_body(0.05);
        let mut params = model.zero_params();
        params.pose[3] = DVec3::new(0.3, 0.0, 0.1);
        let r = axis_angle_to_matrix(DVec3::new(0.0, 0.2, 0.0));
        let mut refinements = vec![DMat3::IDENTITY; model.num_joints() - 1];
        refinements[2] = r;
        let refined = refine_pose(&params, &refinements);
        let expected = axis_angle_to_matrix(params.pose[3]) * r;
        let got = axis_angle_to_matrix(refined.pose[3]);
        assert!(
            (got - expected)
                .abs()
                .to_cols_array()
                .iter()
                .all(|d| *d < 1e-12)
        );
        assert_eq!(refined.pose[0], params.pose[0]);
        assert_eq!(refined.pose[1], params.pose[1]);
    }
}
