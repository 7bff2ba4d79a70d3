//! The body model arrays (validated once at construction) and per-frame body parameters.

use glam::DVec3;

/// Why body-model arrays were rejected. `field` names the array as SMPL's files name it.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BodyModelError {
    #[error("body model field `{field}`: expected {expected} values, got {got}")]
    Length {
        field: &'static str,
        expected: String,
        got: usize,
    },
    #[error("body model field `{field}` holds a value that is not finite (at flat index {index})")]
    NotFinite { field: &'static str, index: usize },
    #[error("body model has no {what}")]
    Empty { what: &'static str },
    #[error(
        "body model field `kintree_table`: joint {joint} has parent {parent}; parents must come before their children and joint 0 must be the only root"
    )]
    BadParent { joint: usize, parent: i64 },
    #[error("body model field `f`: face {face} refers to vertex {index} of {vertices}")]
    FaceIndex {
        face: usize,
        index: u32,
        vertices: usize,
    },
    #[error(
        "body model field `weights`: vertex {vertex} has weights summing to {sum} (expected 1)"
    )]
    WeightSum { vertex: usize, sum: f64 },
    #[error("body model field `weights`: vertex {vertex} has a negative weight {weight}")]
    NegativeWeight { vertex: usize, weight: f64 },
}

/// The plain arrays of a body model, row-major, as SMPL's dense `.npz` stores them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BodyModelArrays {
    /// `v_template`, (V, 3).
    pub template: Vec<[f64; 3]>,
    /// `f`, (F, 3) vertex indices.
    pub faces: Vec<[u32; 3]>,
    /// Parent of each joint, `-1` for the root (`kintree_table[0]`), (J).
    pub parents: Vec<i64>,
    /// `weights`, (V, J) skinning weights.
    pub weights: Vec<f64>,
    /// `J_regressor`, (J, V).
    pub joint_regressor: Vec<f64>,
    /// `shapedirs` (shape part), (V, 3, B).
    pub shape_dirs: Vec<f64>,
    pub num_betas: usize,
    /// `shapedirs` expression part of SMPL-X (or `exprdirs`), (V, 3, E); empty for SMPL.
    pub expression_dirs: Vec<f64>,
    pub num_expression: usize,
    /// `posedirs`, (V, 3, 9 (J - 1)), or empty for a model without pose blend shapes.
    /// Single precision: it is the largest array and skinning streams it every frame.
    pub pose_dirs: Vec<f32>,
}

/// A validated skinned body model. Construct with [`BodyModel::new`].
#[derive(Clone, Debug)]
pub struct BodyModel {
    pub(crate) arrays: BodyModelArrays,
    pub(crate) parents: Vec<Option<usize>>,
    /// Skinning weights per vertex, sparse: `skin_offsets[v]..skin_offsets[v + 1]` index
    /// `skin_joints` / `skin_weights`. Exact zeros are dropped; nothing else is.
    pub(crate) skin_offsets: Vec<u32>,
    pub(crate) skin_joints: Vec<u32>,
    pub(crate) skin_weights: Vec<f64>,
    /// Joint regressor rows, sparse, same layout over vertices.
    pub(crate) regressor_offsets: Vec<u32>,
    pub(crate) regressor_vertices: Vec<u32>,
    pub(crate) regressor_weights: Vec<f64>,
}

/// Tolerance on the sum of a vertex's skinning weights (files are often single precision).
const WEIGHT_SUM_TOLERANCE: f64 = 1e-3;

fn check_len<T>(
    field: &'static str,
    values: &[T],
    expected: usize,
    what: &str,
) -> Result<(), BodyModelError> {
    if values.len() != expected {
        return Err(BodyModelError::Length {
            field,
            expected: format!("{expected} ({what})"),
            got: values.len(),
        });
    }
    Ok(())
}

fn check_finite(
    field: &'static str,
    values: impl IntoIterator<Item = f64>,
) -> Result<(), BodyModelError> {
    match values.into_iter().position(|x| !x.is_finite()) {
        Some(index) => Err(BodyModelError::NotFinite { field, index }),
        None => Ok(()),
    }
}

impl BodyModel {
    /// Validates the arrays (sizes, finiteness, tree order, face indices, weights) and
    /// precomputes the sparse skinning and regressor tables.
    pub fn new(arrays: BodyModelArrays) -> Result<Self, BodyModelError> {
        let num_vertices = arrays.template.len();
        let num_joints = arrays.parents.len();
        if num_vertices == 0 {
            return Err(BodyModelError::Empty {
                what: "vertices (`v_template`)",
            });
        }
        if num_joints == 0 {
            return Err(BodyModelError::Empty {
                what: "joints (`kintree_table`)",
            });
        }
        check_finite("v_template", arrays.template.iter().flatten().copied())?;
        let mut parents = Vec::with_capacity(num_joints);
        for (joint, &parent) in arrays.parents.iter().enumerate() {
            let parent_index = match (joint, parent) {
                (0, -1) => None,
                (j, p) if p >= 0 && (p as usize) < j => Some(p as usize),
                _ => return Err(BodyModelError::BadParent { joint, parent }),
            };
            parents.push(parent_index);
        }
        for (face, corners) in arrays.faces.iter().enumerate() {
            if let Some(&index) = corners.iter().find(|&&i| i as usize >= num_vertices) {
                return Err(BodyModelError::FaceIndex {
                    face,
                    index,
                    vertices: num_vertices,
                });
            }
        }
        let vj = format!("V={num_vertices} x J={num_joints}");
        check_len("weights", &arrays.weights, num_vertices * num_joints, &vj)?;
        check_finite("weights", arrays.weights.iter().copied())?;
        let jv = format!("J={num_joints} x V={num_vertices}");
        check_len(
            "J_regressor",
            &arrays.joint_regressor,
            num_vertices * num_joints,
            &jv,
        )?;
        check_finite("J_regressor", arrays.joint_regressor.iter().copied())?;
        let shape = format!("V={num_vertices} x 3 x B={}", arrays.num_betas);
        check_len(
            "shapedirs",
            &arrays.shape_dirs,
            num_vertices * 3 * arrays.num_betas,
            &shape,
        )?;
        check_finite("shapedirs", arrays.shape_dirs.iter().copied())?;
        let expr = format!("V={num_vertices} x 3 x E={}", arrays.num_expression);
        check_len(
            "exprdirs",
            &arrays.expression_dirs,
            num_vertices * 3 * arrays.num_expression,
            &expr,
        )?;
        check_finite("exprdirs", arrays.expression_dirs.iter().copied())?;
        if !arrays.pose_dirs.is_empty() {
            let features = 9 * (num_joints - 1);
            let pose = format!("V={num_vertices} x 3 x 9(J-1)={features}, or none");
            check_len(
                "posedirs",
                &arrays.pose_dirs,
                num_vertices * 3 * features,
                &pose,
            )?;
            check_finite("posedirs", arrays.pose_dirs.iter().map(|&x| x as f64))?;
        }

        let mut skin_offsets = Vec::with_capacity(num_vertices + 1);
        let mut skin_joints = Vec::new();
        let mut skin_weights = Vec::new();
        skin_offsets.push(0u32);
        for vertex in 0..num_vertices {
            let row = &arrays.weights[vertex * num_joints..(vertex + 1) * num_joints];
            let mut sum = 0.0;
            for (joint, &weight) in row.iter().enumerate() {
                if weight < 0.0 {
                    return Err(BodyModelError::NegativeWeight { vertex, weight });
                }
                if weight != 0.0 {
                    skin_joints.push(joint as u32);
                    skin_weights.push(weight);
                    sum += weight;
                }
            }
            if (sum - 1.0).abs() > WEIGHT_SUM_TOLERANCE {
                return Err(BodyModelError::WeightSum { vertex, sum });
            }
            skin_offsets.push(skin_joints.len() as u32);
        }
        let mut regressor_offsets = Vec::with_capacity(num_joints + 1);
        let mut regressor_vertices = Vec::new();
        let mut regressor_weights = Vec::new();
        regressor_offsets.push(0u32);
        for joint in 0..num_joints {
            let row = &arrays.joint_regressor[joint * num_vertices..(joint + 1) * num_vertices];
            for (vertex, &weight) in row.iter().enumerate() {
                if weight != 0.0 {
                    regressor_vertices.push(vertex as u32);
                    regressor_weights.push(weight);
                }
            }
            regressor_offsets.push(regressor_vertices.len() as u32);
        }
        Ok(Self {
            arrays,
            parents,
            skin_offsets,
            skin_joints,
            skin_weights,
            regressor_offsets,
            regressor_vertices,
            regressor_weights,
        })
    }

    /// The arrays the model was built from (for writing it out again).
    pub fn arrays(&self) -> &BodyModelArrays {
        &self.arrays
    }

    pub fn num_vertices(&self) -> usize {
        self.arrays.template.len()
    }

    pub fn num_joints(&self) -> usize {
        self.parents.len()
    }

    pub fn num_betas(&self) -> usize {
        self.arrays.num_betas
    }

    pub fn num_expression(&self) -> usize {
        self.arrays.num_expression
    }

    /// True when the model has pose-dependent blend shapes (`posedirs`).
    pub fn has_pose_dirs(&self) -> bool {
        !self.arrays.pose_dirs.is_empty()
    }

    pub fn parents(&self) -> &[Option<usize>] {
        &self.parents
    }

    pub fn faces(&self) -> &[[u32; 3]] {
        &self.arrays.faces
    }

    /// Template vertex `v` (`v_template`).
    pub fn template_vertex(&self, vertex: usize) -> DVec3 {
        DVec3::from_array(self.arrays.template[vertex])
    }

    /// The skinning weights of one vertex as `(joint, weight)` pairs (zeros omitted).
    pub fn vertex_weights(&self, vertex: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let range = self.skin_offsets[vertex] as usize..self.skin_offsets[vertex + 1] as usize;
        self.skin_joints[range.clone()]
            .iter()
            .zip(&self.skin_weights[range])
            .map(|(&j, &w)| (j as usize, w))
    }

    /// Parameters of the rest pose: zero pose, zero shape, no world transform.
    pub fn zero_params(&self) -> BodyParams {
        BodyParams {
            pose: vec![DVec3::ZERO; self.num_joints()],
            betas: vec![0.0; self.num_betas()],
            expression: vec![0.0; self.num_expression()],
            world_rotation: DVec3::ZERO,
            world_translation: DVec3::ZERO,
        }
    }

    /// Checks that `params` fit this model: one rotation per joint, no more shape or
    /// expression coefficients than the model has (fewer are padded with zeros, as SMPL
    /// does when a file holds 300 components and a fit uses 10), all finite.
    pub fn check_params(&self, params: &BodyParams) -> Result<(), BodyParamsError> {
        if params.pose.len() != self.num_joints() {
            return Err(BodyParamsError::PoseLength {
                expected: self.num_joints(),
                got: params.pose.len(),
            });
        }
        if params.betas.len() > self.num_betas() {
            return Err(BodyParamsError::TooManyCoefficients {
                field: "betas",
                max: self.num_betas(),
                got: params.betas.len(),
            });
        }
        if params.expression.len() > self.num_expression() {
            return Err(BodyParamsError::TooManyCoefficients {
                field: "expression",
                max: self.num_expression(),
                got: params.expression.len(),
            });
        }
        let all = params
            .pose
            .iter()
            .flat_map(|v| v.to_array())
            .chain(params.betas.iter().copied())
            .chain(params.expression.iter().copied())
            .chain(params.world_rotation.to_array())
            .chain(params.world_translation.to_array());
        if all.into_iter().any(|x| !x.is_finite()) {
            return Err(BodyParamsError::NotFinite);
        }
        let rotations = params
            .pose
            .iter()
            .enumerate()
            .map(|(joint, v)| {
                (
                    if joint == 0 {
                        "global_orient"
                    } else {
                        "body_pose"
                    },
                    *v,
                )
            })
            .chain(std::iter::once(("Rh", params.world_rotation)));
        for (field, rotation) in rotations {
            let angle = rotation.length();
            if angle > MAX_ROTATION_RADIANS {
                return Err(BodyParamsError::Absurd {
                    field,
                    value: angle,
                    limit: MAX_ROTATION_RADIANS,
                    unit: "rad",
                });
            }
        }
        let distance = params.world_translation.length();
        if distance > MAX_TRANSLATION_METRES {
            return Err(BodyParamsError::Absurd {
                field: "transl",
                value: distance,
                limit: MAX_TRANSLATION_METRES,
                unit: "m",
            });
        }
        Ok(())
    }
}

/// The largest axis-angle rotation accepted (radians): any rotation is at most pi, so a
/// larger one is a unit error or garbage, and far larger ones lose all precision.
pub const MAX_ROTATION_RADIANS: f64 = 1e3;
/// The largest world translation accepted (metres).
pub const MAX_TRANSLATION_METRES: f64 = 1e4;

/// Per-frame parameters of a body model.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyParams {
    /// Local axis-angle rotation of every joint, root first (`pose[0]` = SMPL `global_orient`).
    pub pose: Vec<DVec3>,
    /// Shape coefficients (may be shorter than the model's; missing ones are zero).
    pub betas: Vec<f64>,
    /// Expression coefficients (SMPL-X); may be shorter than the model's.
    pub expression: Vec<f64>,
    /// Axis-angle rotation about the world origin applied after skinning (`Rh`).
    pub world_rotation: DVec3,
    /// Translation applied after skinning and the world rotation (`Th`, SMPL-X `transl`).
    pub world_translation: DVec3,
}

/// Why body parameters do not fit a model.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BodyParamsError {
    #[error("pose has {got} joint rotations, the body model has {expected} joints")]
    PoseLength { expected: usize, got: usize },
    #[error("{field} has {got} coefficients, the body model has only {max}")]
    TooManyCoefficients {
        field: &'static str,
        max: usize,
        got: usize,
    },
    #[error("a body parameter is not finite")]
    NotFinite,
    #[error("{field} has magnitude {value:e} {unit}, beyond the {limit:e} {unit} accepted")]
    Absurd {
        field: &'static str,
        value: f64,
        limit: f64,
        unit: &'static str,
    },
}
