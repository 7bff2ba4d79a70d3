//! Keypoint-driven refinement (`mode: keypoints`): one joint solve over every frame's joint
//! rotations, world rotation and translation, with the shape shared per subject.
//!
//! Energy (unknowns: per frame `t`, the rotation `R_tk` of every track `k` (joints, then the
//! world rotation `W_t`) and the translation `T_t`):
//!
//! ```text
//! E = sum_k E_track(R_.k)                  smooth mode's data + acceleration terms per track
//!   + E_track(T_.)                         (crate::smooth: chordal, robust accelerations)
//!   + sum_t sum_i c_ti rho(|p_j(i)(x_t) - y_ti| / sk)    keypoint term
//! p_j(x_t) = W_t g_j(R_t.) + T_t           posed world joint (forward kinematics)
//! ```
//!
//! `y_ti` is keypoint `i` of frame `t` (the joint `j(i)` it measures comes from the ingest
//! attribute `keypoints_3d_joints`), `c_ti` its confidence, `sk` the keypoint noise and
//! `rho` the Cauchy kernel of [`crate::smooth`] (scale `robust_threshold` standard
//! deviations), so an outlying keypoint loses its pull. The keypoint term couples every joint
//! of a frame; the acceleration terms couple frames `t - 1, t, t + 1`. The Gauss-Newton
//! normal equations are therefore block banded (a block of `3 (J + 2)` unknowns per frame,
//! bandwidth two frames) and are solved whole by banded Cholesky ([`crate::banded`]) with
//! Levenberg damping; rotation updates are right-multiplied, `R <- R Exp(d)`.
//!
//! Jacobians of a posed joint (`g_j`, `M_i` from [`BodyModel::joint_transforms`]): for a
//! right perturbation `d` of the local rotation of a strict ancestor `i` of `j`,
//! `dp_j/dd = -W [g_j - g_i]x M_i`; of the world rotation, `-W [g_j]x`; of the translation,
//! the identity. Frames are independent in the keypoint term and are evaluated in parallel.
//!
//! A keypoint with confidence 0 is ignored whatever its position (ingest stores missing
//! keypoints that way, possibly with a NaN position); a keypoint with positive confidence
//! and a non-finite position, or a negative or non-finite confidence, is an error naming the
//! frame and keypoint. Keypoints that name no joint (`-1`) are ignored; an entry where none
//! names a joint cannot use this mode.

use rayon::prelude::*;
use seqavatar_core::body::BodyModel;
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_core::rotation::{axis_angle_to_matrix, matrix_to_axis_angle, skew};
use seqavatar_schema::ingest::Keypoints3d;

use crate::banded::BandedMatrix;
use crate::refine::{RefineSummary, axis_angle_near, shared_betas};
use crate::smooth::{
    SmoothError, SmoothingPlan, SmoothingWeights, accumulate, levenberg_marquardt, robust,
    rotation_energy, rotation_residuals, translation_energy, translation_residuals,
};
use seqavatar_schema::body::BodySequence;

/// Relative energy decrease below which the joint solve stops.
const KEYPOINT_TOLERANCE: f64 = 1e-7;

/// Why keypoint refinement could not run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum KeypointError {
    #[error(
        "none of the {count} keypoints corresponds to a body joint (every `keypoints_3d_joints` entry is -1)"
    )]
    NoJointKeypoints { count: usize },
    #[error("keypoint {keypoint} names joint {joint}; the body model has {num_joints} joints")]
    BadJoint {
        keypoint: usize,
        joint: usize,
        num_joints: usize,
    },
    #[error("the keypoints have {keypoint_frames} frames, the fits {fit_frames}")]
    FrameCount {
        keypoint_frames: usize,
        fit_frames: usize,
    },
    #[error(
        "frame {frame} keypoint {keypoint}: confidence {confidence} must be finite and non-negative"
    )]
    BadConfidence {
        frame: usize,
        keypoint: usize,
        confidence: f64,
    },
    #[error(
        "frame {frame} keypoint {keypoint}: position {position:?} is not finite but its confidence is {confidence} (a missing keypoint must have confidence 0)"
    )]
    NotFinite {
        frame: usize,
        keypoint: usize,
        position: [f64; 3],
        confidence: f64,
    },
    #[error("keypoint noise must be positive and finite, got {0}")]
    BadNoise(f64),
    #[error("the fits have {fit_joints} joints, the body model {model_joints}")]
    JointCount {
        fit_joints: usize,
        model_joints: usize,
    },
    #[error(transparent)]
    Smooth(#[from] SmoothError),
}

/// The keypoints the solver uses: those that name a joint, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct KeypointObservations {
    pub num_frames: usize,
    /// Per used keypoint, the joint it measures.
    pub joints: Vec<usize>,
    /// Per used keypoint, its index in the ingest arrays (for messages).
    pub source_index: Vec<usize>,
    /// `(frame, used keypoint)`; zero where the confidence is zero.
    pub positions: Vec<DVec3>,
    /// `(frame, used keypoint)`.
    pub confidence: Vec<f64>,
}

impl KeypointObservations {
    /// Selects and validates the keypoints that name a joint of a model with `num_joints`
    /// joints (module docs: confidence 0 means missing).
    pub fn new(keypoints: &Keypoints3d, num_joints: usize) -> Result<Self, KeypointError> {
        let count = keypoints.num_keypoints();
        let num_frames = keypoints.num_frames();
        let mut joints = Vec::new();
        let mut source_index = Vec::new();
        for (keypoint, joint) in keypoints.joints.iter().enumerate() {
            if let Some(joint) = *joint {
                if joint >= num_joints {
                    return Err(KeypointError::BadJoint {
                        keypoint,
                        joint,
                        num_joints,
                    });
                }
                joints.push(joint);
                source_index.push(keypoint);
            }
        }
        if joints.is_empty() {
            return Err(KeypointError::NoJointKeypoints { count });
        }
        let mut positions = Vec::with_capacity(num_frames * joints.len());
        let mut confidence = Vec::with_capacity(num_frames * joints.len());
        for frame in 0..num_frames {
            for &keypoint in &source_index {
                let at = frame * count + keypoint;
                let (p, c) = (keypoints.positions[at], keypoints.confidence[at]);
                if !(c.is_finite() && c >= 0.0) {
                    return Err(KeypointError::BadConfidence {
                        frame,
                        keypoint,
                        confidence: c,
                    });
                }
                if c > 0.0 && !p.is_finite() {
                    return Err(KeypointError::NotFinite {
                        frame,
                        keypoint,
                        position: p.to_array(),
                        confidence: c,
                    });
                }
                positions.push(if c > 0.0 { p } else { DVec3::ZERO });
                confidence.push(c);
            }
        }
        Ok(Self {
            num_frames,
            joints,
            source_index,
            positions,
            confidence,
        })
    }

    /// Used keypoints per frame.
    pub fn per_frame(&self) -> usize {
        self.joints.len()
    }
}

/// Keypoint term settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeypointWeights {
    /// Expected error of a keypoint position, metres.
    pub noise: f64,
}

/// What the keypoint solve did, beyond [`RefineSummary`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct KeypointSummary {
    pub refine: RefineSummary,
    /// Confidence-weighted mean distance between posed joints and keypoints, metres.
    pub keypoint_distance_before: f64,
    pub keypoint_distance_after: f64,
    /// Keypoints that name a joint (per frame).
    pub keypoints_used: usize,
}

/// The solver's state: `(frame, track)` rotations (tracks: joints, then the world rotation)
/// and per-frame translations.
#[derive(Clone, Debug)]
struct State {
    rotations: Vec<DMat3>,
    translations: Vec<DVec3>,
}

/// Everything fixed during the solve.
struct Problem<'a> {
    model: &'a BodyModel,
    /// Per frame (or one for all frames when the shape is constant), the rest joints.
    rest_joints: Vec<Vec<DVec3>>,
    observations: &'a KeypointObservations,
    input_rotations: Vec<Vec<DMat3>>,
    input_translations: Vec<DVec3>,
    /// Per rotation track, its smoothing weights (estimated from its input fits or fixed).
    rotation_weights: Vec<SmoothingWeights>,
    translation_weights: SmoothingWeights,
    robust_threshold: f64,
    keypoint_noise: f64,
    num_frames: usize,
    num_joints: usize,
    /// For every joint, its strict ancestors.
    ancestors: Vec<Vec<usize>>,
}

/// Per-frame forward kinematics through [`BodyModel::joint_transforms`]: the global
/// rotation `M_j` and position `g_j` (body frame, before the world transform) of every joint.
pub fn global_joint_frames(
    model: &BodyModel,
    rest_joints: &[DVec3],
    local_rotations: &[DMat3],
) -> (Vec<DMat3>, Vec<DVec3>) {
    let pose: Vec<DVec3> = local_rotations
        .iter()
        .map(|r| matrix_to_axis_angle(*r))
        .collect();
    let transforms = model.joint_transforms(rest_joints, &pose);
    let rotations = transforms.iter().map(|a| a.matrix3).collect();
    let positions = transforms
        .iter()
        .zip(rest_joints)
        .map(|(a, &rest)| a.transform_point3(rest))
        .collect();
    (rotations, positions)
}

/// Derivatives of the posed world joint `p_j = W g_j + T` with respect to a right
/// perturbation of the local rotation of each strict ancestor (returned as
/// `(ancestor, 3x3 matrix whose column c is d p_j / d d_c)`) and of the world rotation.
pub fn posed_joint_jacobian(
    joint: usize,
    ancestors: &[usize],
    global_rotations: &[DMat3],
    global_positions: &[DVec3],
    world: DMat3,
) -> (Vec<(usize, DMat3)>, DMat3) {
    let g = global_positions[joint];
    let local = ancestors
        .iter()
        .map(|&i| {
            (
                i,
                -(world * skew(g - global_positions[i]) * global_rotations[i]),
            )
        })
        .collect();
    (local, -(world * skew(g)))
}

impl Problem<'_> {
    fn block(&self) -> usize {
        3 * (self.num_joints + 2)
    }

    fn tracks(&self) -> usize {
        self.num_joints + 1
    }

    fn rest(&self, frame: usize) -> &[DVec3] {
        &self.rest_joints[frame.min(self.rest_joints.len() - 1)]
    }

    fn frame_rotations<'s>(&self, state: &'s State, frame: usize) -> &'s [DMat3] {
        &state.rotations[frame * self.tracks()..(frame + 1) * self.tracks()]
    }

    fn track(&self, state: &State, track: usize) -> Vec<DMat3> {
        (0..self.num_frames)
            .map(|t| state.rotations[t * self.tracks() + track])
            .collect()
    }

    /// Keypoint residuals of one frame, `(keypoint, scaled residual, global frames)`.
    fn frame_posed(&self, state: &State, frame: usize) -> (Vec<DMat3>, Vec<DVec3>, DMat3) {
        let rotations = self.frame_rotations(state, frame);
        let (m, g) =
            global_joint_frames(self.model, self.rest(frame), &rotations[..self.num_joints]);
        (m, g, rotations[self.num_joints])
    }

    /// Keypoint energy of one frame and the sum of confidence-weighted distances.
    fn frame_keypoint_energy(&self, state: &State, frame: usize) -> (f64, f64, f64) {
        let (_, g, world) = self.frame_posed(state, frame);
        let k = self.observations.per_frame();
        let mut energy = 0.0;
        let mut distance = 0.0;
        let mut weight = 0.0;
        for i in 0..k {
            let c = self.observations.confidence[frame * k + i];
            if c == 0.0 {
                continue;
            }
            let p = world * g[self.observations.joints[i]] + state.translations[frame];
            let d = (p - self.observations.positions[frame * k + i]).length();
            energy += c * robust(d / self.keypoint_noise, self.robust_threshold).0;
            distance += c * d;
            weight += c;
        }
        (energy, distance, weight)
    }

    fn energy(&self, state: &State) -> f64 {
        let keypoints: f64 = (0..self.num_frames)
            .into_par_iter()
            .map(|t| self.frame_keypoint_energy(state, t).0)
            .sum();
        let rotations: f64 = (0..self.tracks())
            .map(|k| {
                rotation_energy(
                    &self.track(state, k),
                    &self.input_rotations[k],
                    &self.rotation_weights[k],
                )
            })
            .sum();
        keypoints
            + rotations
            + translation_energy(
                &state.translations,
                &self.input_translations,
                &self.translation_weights,
            )
    }

    fn mean_keypoint_distance(&self, state: &State) -> f64 {
        let (d, w) = (0..self.num_frames)
            .into_par_iter()
            .map(|t| {
                let (_, d, w) = self.frame_keypoint_energy(state, t);
                (d, w)
            })
            .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        if w > 0.0 { d / w } else { 0.0 }
    }

    /// Dense lower triangle (`n x n`, row-major) and gradient of one frame's keypoint term.
    fn frame_keypoint_normal_equations(&self, state: &State, frame: usize) -> (Vec<f64>, Vec<f64>) {
        let n = self.block();
        let mut h = vec![0.0; n * n];
        let mut g = vec![0.0; n];
        let (m, positions, world) = self.frame_posed(state, frame);
        let k = self.observations.per_frame();
        let scale = 1.0 / self.keypoint_noise;
        let world_base = 3 * self.num_joints;
        let translation_base = world_base + 3;
        for i in 0..k {
            let c = self.observations.confidence[frame * k + i];
            if c == 0.0 {
                continue;
            }
            let joint = self.observations.joints[i];
            let p = world * positions[joint] + state.translations[frame];
            let residual = (p - self.observations.positions[frame * k + i]) * scale;
            let weight = c * robust(residual.length(), self.robust_threshold).1;
            let (local, world_jac) =
                posed_joint_jacobian(joint, &self.ancestors[joint], &m, &positions, world);
            let mut columns: Vec<(usize, DMat3)> =
                local.into_iter().map(|(a, j)| (3 * a, j * scale)).collect();
            columns.push((world_base, world_jac * scale));
            columns.push((translation_base, DMat3::IDENTITY * scale));
            for &(ba, ja) in &columns {
                for ca in 0..3 {
                    let col_a = ja.col(ca);
                    g[ba + ca] += weight * col_a.dot(residual);
                    for &(bb, jb) in &columns {
                        for cb in 0..3 {
                            let (row, col) = (ba + ca, bb + cb);
                            if col <= row {
                                h[row * n + col] += weight * col_a.dot(jb.col(cb));
                            }
                        }
                    }
                }
            }
        }
        (h, g)
    }

    fn normal_equations(&self, state: &State) -> (BandedMatrix, Vec<f64>) {
        let n = self.block();
        let f = self.num_frames;
        let mut h = BandedMatrix::zeros(n * f, 3 * n - 1);
        let mut g = vec![0.0; n * f];
        let blocks: Vec<(Vec<f64>, Vec<f64>)> = (0..f)
            .into_par_iter()
            .map(|t| self.frame_keypoint_normal_equations(state, t))
            .collect();
        for (t, (block_h, block_g)) in blocks.iter().enumerate() {
            for row in 0..n {
                g[t * n + row] += block_g[row];
                for col in 0..=row {
                    let v = block_h[row * n + col];
                    if v != 0.0 {
                        h.add(t * n + row, t * n + col, v);
                    }
                }
            }
        }
        for k in 0..self.tracks() {
            rotation_residuals(
                &self.track(state, k),
                &self.input_rotations[k],
                &self.rotation_weights[k],
                |frames, jac, residual, weight| {
                    let bases: Vec<usize> = frames.iter().map(|t| t * n + 3 * k).collect();
                    accumulate(&mut h, &mut g, &bases, jac, residual, weight);
                },
            );
        }
        translation_residuals(
            &state.translations,
            &self.input_translations,
            &self.translation_weights,
            |frames, jac, residual, weight| {
                let bases: Vec<usize> = frames.iter().map(|t| t * n + n - 3).collect();
                accumulate(&mut h, &mut g, &bases, jac, residual, weight);
            },
        );
        (h, g)
    }

    fn retract(&self, state: &State, step: &[f64]) -> State {
        let n = self.block();
        let tracks = self.tracks();
        let v = |at: usize| DVec3::new(step[at], step[at + 1], step[at + 2]);
        State {
            rotations: state
                .rotations
                .iter()
                .enumerate()
                .map(|(i, r)| {
                    let (t, k) = (i / tracks, i % tracks);
                    *r * axis_angle_to_matrix(v(t * n + 3 * k))
                })
                .collect(),
            translations: state
                .translations
                .iter()
                .enumerate()
                .map(|(t, x)| *x + v(t * n + n - 3))
                .collect(),
        }
    }
}

/// Strict ancestors of every joint, nearest first.
fn ancestors(model: &BodyModel) -> Vec<Vec<usize>> {
    let parents = model.parents();
    (0..parents.len())
        .map(|j| {
            let mut out = Vec::new();
            let mut at = parents[j];
            while let Some(p) = at {
                out.push(p);
                at = parents[p];
            }
            out
        })
        .collect()
}

/// Refines `input` against 3D keypoints (module docs); every track's smoothing weights come
/// from `plan` (estimated from its input fits unless fixed). The shape is the mean of the
/// per-frame betas, as in smooth mode, and stays fixed.
pub fn refine_with_keypoints(
    model: &BodyModel,
    input: &BodySequence,
    observations: &KeypointObservations,
    plan: &SmoothingPlan,
    keypoint: &KeypointWeights,
) -> Result<(BodySequence, KeypointSummary), KeypointError> {
    plan.validate()?;
    if !(keypoint.noise > 0.0 && keypoint.noise.is_finite()) {
        return Err(KeypointError::BadNoise(keypoint.noise));
    }
    let (f, j) = (input.num_frames, input.num_joints);
    if observations.num_frames != f {
        return Err(KeypointError::FrameCount {
            keypoint_frames: observations.num_frames,
            fit_frames: f,
        });
    }
    if j != model.num_joints() {
        return Err(KeypointError::JointCount {
            fit_joints: j,
            model_joints: model.num_joints(),
        });
    }
    if let Some(at) = input.pose.iter().position(|v| !v.is_finite()) {
        return Err(SmoothError::NotFinite {
            frame: at / j.max(1),
        }
        .into());
    }
    if let Some(frame) = input
        .world_rotation
        .iter()
        .zip(&input.world_translation)
        .position(|(r, t)| !(r.is_finite() && t.is_finite()))
    {
        return Err(SmoothError::NotFinite { frame }.into());
    }
    let mut output = input.clone();
    let betas_averaged = shared_betas(&mut output);
    if f == 0 {
        return Ok((
            output,
            KeypointSummary {
                refine: RefineSummary {
                    betas_averaged,
                    ..RefineSummary::default()
                },
                keypoints_used: observations.per_frame(),
                ..KeypointSummary::default()
            },
        ));
    }
    // Rest joints: the shape is shared; the expression may change per frame.
    let rest_of = |t: usize| {
        let params = output.params(t);
        model.regress_joints(&model.shaped_vertices(&params))
    };
    let rest_joints: Vec<Vec<DVec3>> = if input.num_expression > 0 {
        (0..f).into_par_iter().map(rest_of).collect()
    } else {
        vec![rest_of(0)]
    };
    let tracks = j + 1;
    let start = State {
        rotations: (0..f)
            .flat_map(|t| {
                let pose = &input.pose[t * j..(t + 1) * j];
                pose.iter()
                    .chain(std::iter::once(&input.world_rotation[t]))
                    .map(|v| axis_angle_to_matrix(*v))
                    .collect::<Vec<_>>()
            })
            .collect(),
        translations: input.world_translation.clone(),
    };
    let input_rotations: Vec<Vec<DMat3>> = (0..tracks)
        .map(|k| (0..f).map(|t| start.rotations[t * tracks + k]).collect())
        .collect();
    let problem = Problem {
        model,
        rest_joints,
        observations,
        rotation_weights: input_rotations
            .iter()
            .map(|track| plan.rotation_track_weights(track))
            .collect(),
        translation_weights: plan.translation_track_weights(&input.world_translation),
        robust_threshold: plan.robust_threshold,
        input_rotations,
        input_translations: input.world_translation.clone(),
        keypoint_noise: keypoint.noise,
        num_frames: f,
        num_joints: j,
        ancestors: ancestors(model),
    };
    let distance_before = problem.mean_keypoint_distance(&start);
    let (state, report) = levenberg_marquardt(
        start,
        plan.max_iterations,
        KEYPOINT_TOLERANCE,
        |s| problem.energy(s),
        |s| problem.normal_equations(s),
        |s, step| problem.retract(s, step),
    )?;
    let distance_after = problem.mean_keypoint_distance(&state);
    for t in 0..f {
        for k in 0..tracks {
            let r = state.rotations[t * tracks + k];
            let slot = if k < j {
                &mut output.pose[t * j + k]
            } else {
                &mut output.world_rotation[t]
            };
            *slot = axis_angle_near(r, *slot);
        }
    }
    output.world_translation = state.translations;
    Ok((
        output,
        KeypointSummary {
            refine: RefineSummary {
                max_iterations_used: report.iterations,
                energy_before: report.initial_energy,
                energy_after: report.final_energy,
                betas_averaged,
            },
            keypoint_distance_before: distance_before,
            keypoint_distance_after: distance_after,
            keypoints_used: observations.per_frame(),
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::{joint_positions, mean_distance, refine_sequence, vertex_velocity_error};
    use seqavatar_core::body::BodyParams;
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_datasets::DatasetReader;
    use seqavatar_datasets::synthetic::{SyntheticConfig, SyntheticScene};

    /// Deterministic noise in [-1, 1].
    fn noise(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    fn random_vector(seed: &mut u64, scale: f64) -> DVec3 {
        DVec3::new(noise(seed), noise(seed), noise(seed)) * scale
    }

    /// A random pose of the procedural body, one joint near a rotation of pi.
    fn random_params(model: &BodyModel, seed: &mut u64) -> BodyParams {
        let mut params = model.zero_params();
        params.pose = (0..model.num_joints())
            .map(|_| random_vector(seed, 0.6))
            .collect();
        params.pose[4] = DVec3::new(0.0, 0.0, std::f64::consts::PI - 1e-3);
        params.betas = vec![0.3, -0.2];
        params.world_rotation = random_vector(seed, 1.0);
        params.world_translation = random_vector(seed, 1.0);
        params
    }

    /// `dp_j/dd` of every joint against central differences of the forward kinematics in
    /// f64, for right perturbations of every local rotation and of the world rotation;
    /// non-ancestors must have no effect.
    #[test]
    fn posed_joint_jacobian_matches_central_differences() {
        let model = procedural_body(0.03);
        let mut seed = 17;
        let params = random_params(&model, &mut seed);
        let rest = model.regress_joints(&model.shaped_vertices(&params));
        let local: Vec<DMat3> = params
            .pose
            .iter()
            .map(|v| axis_angle_to_matrix(*v))
            .collect();
        let world = axis_angle_to_matrix(params.world_rotation);
        let posed = |local: &[DMat3], world: DMat3| -> Vec<DVec3> {
            let (_, g) = global_joint_frames(&model, &rest, local);
            g.iter()
                .map(|p| world * *p + params.world_translation)
                .collect()
        };
        // Agrees with the body model's own forward pass.
        let reference = model.forward(&params).unwrap().joints;
        for (a, b) in posed(&local, world).iter().zip(&reference) {
            assert!((*a - *b).length() < 1e-12);
        }
        let (m, g) = global_joint_frames(&model, &rest, &local);
        let all_ancestors = ancestors(&model);
        let h = 1e-6;
        let mut worst = 0.0_f64;
        for (joint, joint_ancestors) in all_ancestors.iter().enumerate() {
            let (by_ancestor, by_world) =
                posed_joint_jacobian(joint, joint_ancestors, &m, &g, world);
            for i in 0..model.num_joints() {
                let analytic = by_ancestor
                    .iter()
                    .find(|(a, _)| *a == i)
                    .map_or(DMat3::ZERO, |(_, jac)| *jac);
                for c in 0..3 {
                    let at = |sign: f64| {
                        let mut perturbed = local.clone();
                        perturbed[i] *= axis_angle_to_matrix(DVec3::AXES[c] * (sign * h));
                        posed(&perturbed, world)[joint]
                    };
                    let fd = (at(1.0) - at(-1.0)) / (2.0 * h);
                    let error = (fd - analytic.col(c)).length();
                    worst = worst.max(error);
                    assert!(
                        error < 1e-7,
                        "joint {joint} ancestor {i} comp {c}: {fd:?} vs {:?}",
                        analytic.col(c)
                    );
                }
            }
            for c in 0..3 {
                let at = |sign: f64| {
                    posed(
                        &local,
                        world * axis_angle_to_matrix(DVec3::AXES[c] * (sign * h)),
                    )[joint]
                };
                let fd = (at(1.0) - at(-1.0)) / (2.0 * h);
                assert!(
                    (fd - by_world.col(c)).length() < 1e-7,
                    "joint {joint} world comp {c}"
                );
            }
        }
        println!("posed joint Jacobian: worst central-difference mismatch {worst:.2e}");
    }

    fn small_problem_inputs(
        frames: usize,
    ) -> (BodyModel, BodySequence, KeypointObservations, SmoothingPlan) {
        let model = procedural_body(0.04);
        let mut seed = 5;
        let params: Vec<BodyParams> = (0..frames)
            .map(|_| random_params(&model, &mut seed))
            .collect();
        let sequence = BodySequence::from_params(&params).unwrap();
        let j = model.num_joints();
        let mut positions = Vec::new();
        for p in &params {
            for joint in model.forward(p).unwrap().joints {
                positions.push(joint + random_vector(&mut seed, 0.05));
            }
        }
        // Keypoint 3 measures nothing; one keypoint is an outlier, one is missing.
        let mut joints: Vec<Option<usize>> = (0..j).map(Some).collect();
        joints[3] = None;
        let mut confidence = vec![0.8; frames * j];
        positions[j + 7] += DVec3::splat(0.5);
        confidence[2 * j + 9] = 0.0;
        positions[2 * j + 9] = DVec3::NAN;
        let keypoints = Keypoints3d {
            joints,
            positions,
            confidence,
        };
        let observations = KeypointObservations::new(&keypoints, j).unwrap();
        // Fixed weights (the short sequences give nothing to estimate from).
        let fixed = SmoothingWeights::default();
        let plan = SmoothingPlan {
            rotation_noise: Some(fixed.rotation_noise),
            rotation_acceleration: Some(fixed.rotation_acceleration),
            translation_noise: Some(fixed.translation_noise),
            translation_acceleration: Some(fixed.translation_acceleration),
            robust_threshold: 1.0, // residuals in both regimes of the kernel
            max_iterations: fixed.max_iterations,
        };
        (model, sequence, observations, plan)
    }

    /// The assembled gradient (`J^T W r` over every term: keypoints, rotation tracks,
    /// translation) is half the gradient of the true robust energy, checked by central
    /// differences along every unknown.
    #[test]
    fn normal_equation_gradient_matches_energy_differences() {
        let frames = 4;
        let (model, sequence, observations, weights) = small_problem_inputs(frames);
        let j = model.num_joints();
        let tracks = j + 1;
        let mut seed = 99;
        // Evaluate away from the input (where the data terms vanish).
        let start = State {
            rotations: (0..frames)
                .flat_map(|t| {
                    let mut r: Vec<DMat3> = sequence.pose[t * j..(t + 1) * j]
                        .iter()
                        .map(|v| axis_angle_to_matrix(*v))
                        .collect();
                    r.push(axis_angle_to_matrix(sequence.world_rotation[t]));
                    r
                })
                .collect(),
            translations: sequence.world_translation.clone(),
        };
        let problem = Problem {
            model: &model,
            rest_joints: vec![model.regress_joints(&model.shaped_vertices(&sequence.params(0)))],
            observations: &observations,
            input_rotations: (0..tracks)
                .map(|k| {
                    (0..frames)
                        .map(|t| start.rotations[t * tracks + k])
                        .collect()
                })
                .collect(),
            input_translations: sequence.world_translation.clone(),
            rotation_weights: vec![weights.rotation_track_weights(&[]); tracks],
            translation_weights: weights.translation_track_weights(&[]),
            robust_threshold: weights.robust_threshold,
            keypoint_noise: 0.03,
            num_frames: frames,
            num_joints: j,
            ancestors: ancestors(&model),
        };
        let n = problem.block();
        let step: Vec<f64> = (0..n * frames).map(|_| 0.03 * noise(&mut seed)).collect();
        let state = problem.retract(&start, &step);
        let (h, g) = problem.normal_equations(&state);
        assert_eq!(h.size(), n * frames);
        let eps = 1e-6;
        let mut worst = 0.0_f64;
        for unknown in 0..n * frames {
            let energy_at = |sign: f64| {
                let mut d = vec![0.0; n * frames];
                d[unknown] = sign * eps;
                problem.energy(&problem.retract(&state, &d))
            };
            let fd = (energy_at(1.0) - energy_at(-1.0)) / (2.0 * eps);
            let error = (fd - 2.0 * g[unknown]).abs();
            worst = worst.max(error / fd.abs().max(1.0));
            assert!(
                error < 1e-5 * fd.abs().max(1.0),
                "unknown {unknown} (frame {}, slot {}): {fd} vs {}",
                unknown / n,
                unknown % n,
                2.0 * g[unknown]
            );
        }
        println!("keypoint solve gradient: worst relative mismatch {worst:.2e}");
    }

    #[test]
    fn the_joint_solve_lowers_the_energy_and_handles_short_sequences() {
        let (model, sequence, observations, weights) = small_problem_inputs(3);
        let kw = KeypointWeights { noise: 0.03 };
        let (out, summary) =
            refine_with_keypoints(&model, &sequence, &observations, &weights, &kw).unwrap();
        assert!(summary.refine.energy_after < summary.refine.energy_before);
        assert!(summary.keypoint_distance_after < summary.keypoint_distance_before);
        assert!(out.pose.iter().all(|v| v.is_finite()));
        assert_eq!(summary.keypoints_used, 23);
        // One frame.
        let one = BodySequence::from_params(&[sequence.params(0)]).unwrap();
        let mut first = observations.clone();
        first.num_frames = 1;
        first.positions.truncate(23);
        first.confidence.truncate(23);
        let (out, _) = refine_with_keypoints(&model, &one, &first, &weights, &kw).unwrap();
        assert_eq!(out.num_frames, 1);
        // Mismatched frame counts, bad noise and NaN poses are errors.
        assert!(matches!(
            refine_with_keypoints(&model, &one, &observations, &weights, &kw),
            Err(KeypointError::FrameCount { .. })
        ));
        assert!(matches!(
            refine_with_keypoints(
                &model,
                &one,
                &first,
                &weights,
                &KeypointWeights { noise: 0.0 }
            ),
            Err(KeypointError::BadNoise(_))
        ));
        let mut nan = one.clone();
        nan.pose[5].x = f64::NAN;
        assert_eq!(
            refine_with_keypoints(&model, &nan, &first, &weights, &kw).unwrap_err(),
            KeypointError::Smooth(SmoothError::NotFinite { frame: 0 })
        );
    }

    /// The issue's acceptance test for keypoints mode: on the synthetic scene (exact ground
    /// truth, jittered fits, keypoints = true joints + 1 cm noise) the keypoint solve reduces
    /// the mean joint position error more than smoothing does, and reduces the template
    /// vertex velocity error.
    #[test]
    fn keypoints_beat_smoothing_on_the_synthetic_scene() {
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
        let keypoints = scene.keypoints_3d().unwrap().unwrap();
        let observations = KeypointObservations::new(&keypoints, model.num_joints()).unwrap();
        let fit_config = crate::FitConfig::default();
        let weights = fit_config.plan();
        let started = std::time::Instant::now();
        let (smoothed, _) = refine_sequence(&input, &weights).unwrap();
        let smooth_seconds = started.elapsed().as_secs_f64();
        let started = std::time::Instant::now();
        let (fitted, summary) = refine_with_keypoints(
            &model,
            &input,
            &observations,
            &weights,
            &KeypointWeights {
                noise: fit_config.keypoint_noise_m,
            },
        )
        .unwrap();
        let keypoint_seconds = started.elapsed().as_secs_f64();
        let truth_joints = joint_positions(&model, &truth).unwrap();
        let joint_error =
            |s: &BodySequence| mean_distance(&joint_positions(&model, s).unwrap(), &truth_joints);
        let (e_in, e_smooth, e_kp) = (
            joint_error(&input),
            joint_error(&smoothed),
            joint_error(&fitted),
        );
        let velocity = |s: &BodySequence| vertex_velocity_error(&model, s, &truth).unwrap();
        let (v_in, v_smooth, v_kp) = (velocity(&input), velocity(&smoothed), velocity(&fitted));
        println!(
            "synthetic scene, {} frames: mean joint error input {:.2} mm, smooth {:.2} mm, keypoints {:.2} mm; vertex velocity error input {:.3}, smooth {:.3}, keypoints {:.3} mm/frame; keypoint distance {:.2} -> {:.2} mm; {} iterations; smooth {:.2} s, keypoints {:.2} s",
            config.frames,
            e_in * 1e3,
            e_smooth * 1e3,
            e_kp * 1e3,
            v_in * 1e3,
            v_smooth * 1e3,
            v_kp * 1e3,
            summary.keypoint_distance_before * 1e3,
            summary.keypoint_distance_after * 1e3,
            summary.refine.max_iterations_used,
            smooth_seconds,
            keypoint_seconds,
        );
        assert!(
            e_smooth < e_in,
            "smoothing alone helps: {e_in} -> {e_smooth}"
        );
        assert!(e_kp < e_smooth, "keypoints help more: {e_smooth} -> {e_kp}");
        assert!(v_kp < 0.7 * v_in, "velocity error {v_in} -> {v_kp}");
    }
}
