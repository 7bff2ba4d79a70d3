//! Loads SMPL / SMPL-X body models from the dense `.npz` files people convert the official
//! `.pkl` models to (same keys: `v_template`, `f`, `kintree_table`, `weights`, `J_regressor`,
//! `shapedirs`, `posedirs`, SMPL-X also `hands_meanl`/`hands_meanr` and optionally
//! `exprdirs`).
//!
//! SMPL-X v1.1 keeps 300 shape and 100 expression components together in `shapedirs`
//! (400); v1.0 keeps 10 + 10 (20). A separate `exprdirs` array wins when present.

use std::path::Path;

use anyhow::{Context, bail};
use seqavatar_core::body::{BodyModel, BodyModelArrays};

use crate::BodyModelKind;
use crate::common::read_bytes;
use seqavatar_formats::{Value, npz};

/// A loaded body model with what the readers need beyond the arrays.
#[derive(Clone, Debug)]
pub struct LoadedBodyModel {
    pub model: BodyModel,
    pub kind: BodyModelKind,
    /// SMPL-X `hands_meanl` then `hands_meanr` (90 values: 30 joint rotations), the mean hand
    /// pose that SMPL-X adds to the fitted hand pose when built with `flat_hand_mean=False`.
    pub hands_mean: Option<Vec<f64>>,
}

/// How many components to keep (fits use 10 betas and 10 expression coefficients).
#[derive(Clone, Copy, Debug)]
pub struct ComponentLimits {
    pub max_betas: usize,
    pub max_expression: usize,
}

impl Default for ComponentLimits {
    fn default() -> Self {
        Self {
            max_betas: 10,
            max_expression: 10,
        }
    }
}

/// Loads a dense `.npz` body model: 24 joints is SMPL, 55 is SMPL-X.
pub fn load_body_model_npz(
    path: &Path,
    limits: ComponentLimits,
) -> anyhow::Result<LoadedBodyModel> {
    let bytes = read_bytes(path)?;
    let arrays =
        npz::read(&bytes).with_context(|| format!("{}: not a readable .npz", path.display()))?;
    let npz = NpzArrays {
        arrays: &arrays,
        file: path.display(),
    };
    let file = &npz.file;

    let (shape, template) = npz.shaped("v_template", &[None, Some(3)])?;
    let num_vertices = shape[0];
    let (kind, parents) = npz.kinematic_tree()?;
    let num_joints = parents.len();
    let faces = npz.faces()?;
    let (_, weights) = npz.shaped("weights", &[Some(num_vertices), Some(num_joints)])?;
    let (_, joint_regressor) =
        npz.shaped("J_regressor", &[Some(num_joints), Some(num_vertices)])?;
    let dirs = npz.shape_and_expression_dirs(kind, num_vertices, limits)?;
    let pose_dirs = npz.pose_dirs(num_vertices, num_joints)?;
    let hands_mean = npz.hands_mean(kind)?;
    let model = BodyModel::new(BodyModelArrays {
        template: template
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        faces,
        parents,
        weights,
        joint_regressor,
        shape_dirs: dirs.shape_dirs,
        num_betas: dirs.num_betas,
        expression_dirs: dirs.expression_dirs,
        num_expression: dirs.num_expression,
        pose_dirs,
    })
    .with_context(|| format!("{file}: invalid body model"))?;
    Ok(LoadedBodyModel {
        model,
        kind,
        hands_mean,
    })
}

/// The body model a file-based dataset's fits refer to: the ingest config's `body_model:`
/// file, which must be an SMPL model, or SMPL-X for `kind` [`BodyModelKind::Smplx`].
pub fn load_fits_model(
    path: Option<&Path>,
    dataset: &str,
    kind: BodyModelKind,
) -> anyhow::Result<(BodyModel, BodyModelKind)> {
    let (name, joints) = match kind {
        BodyModelKind::Smplx => ("SMPL-X", 55),
        _ => ("SMPL", 24),
    };
    let path = path.with_context(|| {
        format!(
            "{dataset} needs the {name} model: set `body_model:` in the ingest config to a dense \
             {name} .npz (v_template, f, kintree_table, weights, J_regressor, shapedirs, posedirs)"
        )
    })?;
    let loaded = load_body_model_npz(path, ComponentLimits::default())?;
    anyhow::ensure!(
        loaded.kind == kind,
        "{}: {dataset} fits are {name} ({joints} joints) but this model is {}",
        path.display(),
        loaded.kind.as_str()
    );
    Ok((loaded.model, loaded.kind))
}

/// The arrays of a body model `.npz`, with the file named in errors.
struct NpzArrays<'a> {
    arrays: &'a [(String, Value)],
    file: std::path::Display<'a>,
}

/// The shape and expression blend shapes kept (at most `ComponentLimits` of each).
struct ShapeAndExpressionDirs {
    shape_dirs: Vec<f64>,
    num_betas: usize,
    expression_dirs: Vec<f64>,
    num_expression: usize,
}

impl NpzArrays<'_> {
    /// Shape and values (as f64) of array `key`, which must be present.
    fn get(&self, key: &str) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
        let file = &self.file;
        let value = self
            .arrays
            .iter()
            .find(|(name, _)| name == key)
            .map(|(_, v)| v)
            .with_context(|| format!("{file}: missing array `{key}`"))?;
        array_f64(value).with_context(|| format!("{file}: array `{key}`"))
    }

    /// [`NpzArrays::get`] of an array whose shape is `expected` (`None`: any extent).
    fn shaped(
        &self,
        key: &str,
        expected: &[Option<usize>],
    ) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
        let (shape, values) = self.get(key)?;
        let file = &self.file;
        let ok = shape.len() == expected.len()
            && shape
                .iter()
                .zip(expected)
                .all(|(&s, e)| e.is_none_or(|e| e == s));
        if !ok {
            let want: Vec<String> = expected
                .iter()
                .map(|e| e.map_or_else(|| "N".to_owned(), |n| n.to_string()))
                .collect();
            bail!(
                "{file}: array `{key}` has shape {shape:?}; expected ({})",
                want.join(", ")
            );
        }
        Ok((shape, values))
    }

    fn has(&self, key: &str) -> bool {
        self.arrays.iter().any(|(name, _)| name == key)
    }

    /// The model kind (from the joint count) and each joint's parent (-1 for the root), from
    /// `kintree_table`.
    fn kinematic_tree(&self) -> anyhow::Result<(BodyModelKind, Vec<i64>)> {
        let file = &self.file;
        let (shape, kintree) = self.shaped("kintree_table", &[Some(2), None])?;
        let num_joints = shape[1];
        let kind = match num_joints {
            24 => BodyModelKind::Smpl,
            55 => BodyModelKind::Smplx,
            n => {
                bail!(
                    "{file}: array `kintree_table` has {n} joints; expected 24 (SMPL) or 55 (SMPL-X)"
                )
            }
        };
        let mut parents = Vec::with_capacity(num_joints);
        for j in 0..num_joints {
            if kintree[num_joints + j] != j as f64 {
                bail!(
                    "{file}: array `kintree_table` row 1 must list the joints 0..{num_joints} in order"
                );
            }
            // The root's parent is stored as -1 or as 2^32 - 1 (unsigned).
            let parent = kintree[j];
            parents.push(if j == 0 { -1 } else { parent as i64 });
        }
        Ok((kind, parents))
    }

    /// The triangles of `f`, as vertex indices.
    fn faces(&self) -> anyhow::Result<Vec<[u32; 3]>> {
        let file = &self.file;
        let (_, faces) = self.shaped("f", &[None, Some(3)])?;
        faces
            .chunks_exact(3)
            .map(|c| {
                let index = |x: f64| {
                    if x >= 0.0 && x < u32::MAX as f64 && x.fract() == 0.0 {
                        Ok(x as u32)
                    } else {
                        Err(anyhow::anyhow!(
                            "{file}: array `f` holds {x}, not a vertex index"
                        ))
                    }
                };
                Ok([index(c[0])?, index(c[1])?, index(c[2])?])
            })
            .collect::<anyhow::Result<Vec<_>>>()
    }

    /// The shape blend shapes of `shapedirs`, and the expression ones of `exprdirs` or (SMPL-X
    /// without it) of the tail of `shapedirs`.
    fn shape_and_expression_dirs(
        &self,
        kind: BodyModelKind,
        num_vertices: usize,
        limits: ComponentLimits,
    ) -> anyhow::Result<ShapeAndExpressionDirs> {
        let (shape, shapedirs) = self.shaped("shapedirs", &[Some(num_vertices), Some(3), None])?;
        let components = shape[2];
        let (num_shape, expression_in_shapedirs) = match (kind, self.has("exprdirs"), components) {
            (BodyModelKind::Smplx, false, 400) => (300, 100),
            (BodyModelKind::Smplx, false, 20) => (10, 10),
            _ => (components, 0),
        };
        let num_betas = num_shape.min(limits.max_betas);
        let shape_dirs = take_components(&shapedirs, components, 0, num_betas);
        let (expression_dirs, num_expression) = if self.has("exprdirs") {
            let (shape, exprdirs) =
                self.shaped("exprdirs", &[Some(num_vertices), Some(3), None])?;
            let n = shape[2].min(limits.max_expression);
            (take_components(&exprdirs, shape[2], 0, n), n)
        } else {
            let n = expression_in_shapedirs.min(limits.max_expression);
            (take_components(&shapedirs, components, num_shape, n), n)
        };
        Ok(ShapeAndExpressionDirs {
            shape_dirs,
            num_betas,
            expression_dirs,
            num_expression,
        })
    }

    /// The pose blend shapes of `posedirs` (empty when absent).
    fn pose_dirs(&self, num_vertices: usize, num_joints: usize) -> anyhow::Result<Vec<f32>> {
        let file = &self.file;
        if !self.has("posedirs") {
            return Ok(Vec::new());
        }
        let (shape, posedirs) = self.get("posedirs")?;
        let features = 9 * (num_joints - 1);
        if posedirs.len() != num_vertices * 3 * features {
            bail!(
                "{file}: array `posedirs` has shape {shape:?}; expected ({num_vertices}, 3, {features})"
            );
        }
        Ok(posedirs.iter().map(|&x| x as f32).collect())
    }

    /// SMPL-X's mean hand pose (`hands_meanl` then `hands_meanr`), when the file has it.
    fn hands_mean(&self, kind: BodyModelKind) -> anyhow::Result<Option<Vec<f64>>> {
        let file = &self.file;
        if kind == BodyModelKind::Smplx && self.has("hands_meanl") && self.has("hands_meanr") {
            let (_, left) = self.get("hands_meanl")?;
            let (_, right) = self.get("hands_meanr")?;
            if left.len() != 45 || right.len() != 45 {
                bail!("{file}: arrays `hands_meanl`/`hands_meanr` must hold 45 values each");
            }
            Ok(Some(left.into_iter().chain(right).collect()))
        } else {
            Ok(None)
        }
    }
}

fn array_f64(value: &Value) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
    match value {
        Value::Array(a) => Ok((
            a.shape.clone(),
            a.data
                .to_f64()
                .with_context(|| format!("dtype {} is not numeric", a.dtype))?,
        )),
        other => bail!("expected a numeric array, found {other}"),
    }
}

/// Components `first..first + count` of a `(V, 3, total)` array, as `(V, 3, count)`.
fn take_components(dirs: &[f64], total: usize, first: usize, count: usize) -> Vec<f64> {
    if total == 0 || count == 0 {
        return Vec::new();
    }
    dirs.chunks_exact(total)
        .flat_map(|row| row[first..first + count].iter().copied())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_are_sliced_from_the_last_axis() {
        // (V=1, 3, 4): row r holds r*10 + c.
        let dirs: Vec<f64> = (0..3)
            .flat_map(|r| (0..4).map(move |c| f64::from(r * 10 + c)))
            .collect();
        assert_eq!(
            take_components(&dirs, 4, 1, 2),
            vec![1.0, 2.0, 11.0, 12.0, 21.0, 22.0]
        );
        assert!(take_components(&dirs, 4, 0, 0).is_empty());
    }
}
