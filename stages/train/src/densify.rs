//! Per-Gaussian state and 3DGS adaptive density control (clone, split, prune), carrying every
//! per-Gaussian quantity along: parameters, their Adam moments, template KNN rows and the
//! view-space gradient statistics.
//!
//! Rules (docs/method.md, "Densification", the standard 3DGS ones):
//! - average view-space gradient `accum / count >= grad_threshold` selects a Gaussian;
//! - small ones (`max scale <= percent_dense x extent`) are cloned (an exact copy);
//! - large ones are split into 2 Gaussians sampled from the Gaussian itself
//!   (`x + R (s * n)`, `n ~ N(0, I)`) with scales divided by `0.8 x 2`; the original is removed;
//! - Gaussians with opacity `< min_opacity` are pruned; no growth beyond `max_gaussians`;
//! - new Gaussians get zero Adam moments (as 3DGS appends zeros to the optimiser state);
//!   the gradient statistics of every Gaussian restart from zero afterwards.

use rayon::prelude::*;
use seqavatar_core::glam::DVec3;
use seqavatar_core::rotation::quat_wxyz_to_matrix;

use crate::rng::Rng;

/// What happens to a column when Gaussians are added.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Growth {
    /// The new Gaussian copies its parent's row (parameters, KNN rows).
    Inherit,
    /// The new Gaussian starts at zero (optimiser moments, statistics).
    Zero,
}

/// One per-Gaussian quantity: `width` values per Gaussian.
#[derive(Clone, Debug, PartialEq)]
pub struct Column {
    pub name: String,
    pub width: usize,
    pub growth: Growth,
    pub values: Vec<f64>,
}

/// Names of the columns the density control needs.
pub mod names {
    pub const POSITION: &str = "xyz";
    pub const LOG_SCALE: &str = "log_scale";
    pub const ROTATION: &str = "rotation";
    pub const OPACITY_LOGIT: &str = "opacity";
    pub const GRAD_ACCUM: &str = "grad_accum";
    pub const GRAD_COUNT: &str = "grad_count";
}

/// All per-Gaussian state as named columns of equal length.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianState {
    pub columns: Vec<Column>,
}

/// Why a state operation was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum StateError {
    #[error("column `{0}` is missing")]
    Missing(String),
    #[error(
        "column `{name}` has {len} values, not a multiple of width {width} for {count} Gaussians"
    )]
    BadLength {
        name: String,
        len: usize,
        width: usize,
        count: usize,
    },
    #[error("column `{0}` exists twice")]
    Duplicate(String),
}

impl GaussianState {
    /// Number of Gaussians (0 without columns).
    pub fn len(&self) -> usize {
        self.columns
            .first()
            .map_or(0, |c| c.values.len() / c.width.max(1))
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Adds a column; checks its length against the others.
    pub fn add(
        &mut self,
        name: &str,
        width: usize,
        growth: Growth,
        values: Vec<f64>,
    ) -> Result<(), StateError> {
        if self.columns.iter().any(|c| c.name == name) {
            return Err(StateError::Duplicate(name.to_owned()));
        }
        let count = if self.columns.is_empty() {
            values.len() / width.max(1)
        } else {
            self.len()
        };
        if width == 0 || values.len() != count * width {
            return Err(StateError::BadLength {
                name: name.to_owned(),
                len: values.len(),
                width,
                count,
            });
        }
        self.columns.push(Column {
            name: name.to_owned(),
            width,
            growth,
            values,
        });
        Ok(())
    }

    pub fn column(&self, name: &str) -> Result<&Column, StateError> {
        self.columns
            .iter()
            .find(|c| c.name == name)
            .ok_or_else(|| StateError::Missing(name.to_owned()))
    }

    pub fn column_mut(&mut self, name: &str) -> Result<&mut Column, StateError> {
        self.columns
            .iter_mut()
            .find(|c| c.name == name)
            .ok_or_else(|| StateError::Missing(name.to_owned()))
    }

    pub fn values(&self, name: &str) -> Result<&[f64], StateError> {
        Ok(&self.column(name)?.values)
    }

    pub fn values_mut(&mut self, name: &str) -> Result<&mut Vec<f64>, StateError> {
        Ok(&mut self.column_mut(name)?.values)
    }

    /// Keeps only the Gaussians whose flag is true (order preserved).
    pub fn retain(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.len(), "retain mask length");
        for column in &mut self.columns {
            let w = column.width;
            let old = std::mem::take(&mut column.values);
            column.values = old
                .chunks_exact(w)
                .zip(keep)
                .filter(|(_, k)| **k)
                .flat_map(|(row, _)| row.iter().copied())
                .collect();
        }
    }

    /// Appends one Gaussian per parent index, following each column's growth rule, then
    /// overrides the given columns with explicit rows.
    fn append_children(&mut self, parents: &[usize], overrides: &[(&str, Vec<f64>)]) {
        for column in &mut self.columns {
            let w = column.width;
            if let Some((_, rows)) = overrides.iter().find(|(n, _)| *n == column.name) {
                assert_eq!(rows.len(), parents.len() * w);
                column.values.extend_from_slice(rows);
                continue;
            }
            match column.growth {
                Growth::Inherit => {
                    for &p in parents {
                        let row: Vec<f64> = column.values[p * w..(p + 1) * w].to_vec();
                        column.values.extend(row);
                    }
                }
                Growth::Zero => column
                    .values
                    .extend(std::iter::repeat_n(0.0, parents.len() * w)),
            }
        }
    }

    /// Adds one visibility's view-space gradient norms (`N`) for the Gaussians marked visible.
    pub fn accumulate_gradient_stats(
        &mut self,
        grad_norms: &[f64],
        visible: &[bool],
    ) -> Result<(), StateError> {
        let n = self.len();
        assert_eq!(grad_norms.len(), n);
        assert_eq!(visible.len(), n);
        {
            let accum = self.values_mut(names::GRAD_ACCUM)?;
            for i in 0..n {
                if visible[i] {
                    accum[i] += grad_norms[i];
                }
            }
        }
        let count = self.values_mut(names::GRAD_COUNT)?;
        for i in 0..n {
            if visible[i] {
                count[i] += 1.0;
            }
        }
        Ok(())
    }
}

/// Thresholds of the density control.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensifySettings {
    pub grad_threshold: f64,
    pub percent_dense: f64,
    /// Scene extent in metres.
    pub extent: f64,
    pub min_opacity: f64,
    pub max_gaussians: usize,
}

/// What one densification step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DensifyReport {
    pub cloned: usize,
    pub split: usize,
    pub pruned: usize,
    pub count: usize,
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// One 3DGS densify-and-prune step.
pub fn densify_and_prune(
    state: &mut GaussianState,
    settings: &DensifySettings,
    rng: &mut Rng,
) -> Result<DensifyReport, StateError> {
    let n = state.len();
    let accum = state.values(names::GRAD_ACCUM)?;
    let count = state.values(names::GRAD_COUNT)?;
    let mean_grad: Vec<f64> = (0..n)
        .map(|i| {
            if count[i] > 0.0 {
                accum[i] / count[i]
            } else {
                0.0
            }
        })
        .collect();
    let log_scale = state.values(names::LOG_SCALE)?;
    let max_scale: Vec<f64> = log_scale
        .chunks_exact(3)
        .map(|s| s.iter().cloned().fold(f64::NEG_INFINITY, f64::max).exp())
        .collect();
    let size_limit = settings.percent_dense * settings.extent;
    let selected: Vec<bool> = mean_grad
        .iter()
        .map(|g| g.is_finite() && *g >= settings.grad_threshold)
        .collect();
    let mut report = DensifyReport::default();

    // Growth budget: each clone adds one Gaussian, each split adds one net.
    let mut budget = settings.max_gaussians.saturating_sub(n);
    let mut clones = Vec::new();
    let mut splits = Vec::new();
    for i in 0..n {
        if !selected[i] || budget == 0 {
            continue;
        }
        if max_scale[i] <= size_limit {
            clones.push(i);
        } else {
            splits.push(i);
        }
        budget -= 1;
    }
    // Split children: sampled positions and shrunken scales, drawn in a fixed order.
    let positions = state.values(names::POSITION)?;
    let rotations = state.values(names::ROTATION)?;
    let mut child_parents = Vec::with_capacity(clones.len() + 2 * splits.len());
    let mut child_xyz = Vec::new();
    let mut child_scale = Vec::new();
    for &p in &clones {
        child_parents.push(p);
        child_xyz.extend_from_slice(&positions[3 * p..3 * p + 3]);
        child_scale.extend_from_slice(&log_scale[3 * p..3 * p + 3]);
    }
    for &p in &splits {
        let r = quat_wxyz_to_matrix([
            rotations[4 * p],
            rotations[4 * p + 1],
            rotations[4 * p + 2],
            rotations[4 * p + 3],
        ]);
        let s: Vec<f64> = log_scale[3 * p..3 * p + 3]
            .iter()
            .map(|v| v.exp())
            .collect();
        for _ in 0..2 {
            let sample = DVec3::new(
                s[0] * rng.normal(),
                s[1] * rng.normal(),
                s[2] * rng.normal(),
            );
            let x = DVec3::new(positions[3 * p], positions[3 * p + 1], positions[3 * p + 2])
                + r * sample;
            child_parents.push(p);
            child_xyz.extend(x.to_array());
            child_scale.extend(s.iter().map(|v| (v / (0.8 * 2.0)).ln()));
        }
    }
    report.cloned = clones.len();
    report.split = splits.len();
    state.append_children(
        &child_parents,
        &[
            (names::POSITION, child_xyz),
            (names::LOG_SCALE, child_scale),
        ],
    );

    // Remove split originals and transparent Gaussians.
    let total = state.len();
    let opacity = state.values(names::OPACITY_LOGIT)?;
    let mut keep: Vec<bool> = (0..total)
        .map(|i| sigmoid(opacity[i]) >= settings.min_opacity)
        .collect();
    let transparent = keep.iter().filter(|k| !**k).count();
    for &p in &splits {
        keep[p] = false;
    }
    let removed = keep.iter().filter(|k| !**k).count();
    report.pruned = transparent.min(removed);
    state.retain(&keep);
    for name in [names::GRAD_ACCUM, names::GRAD_COUNT] {
        state
            .values_mut(name)?
            .par_iter_mut()
            .for_each(|v| *v = 0.0);
    }
    report.count = state.len();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four Gaussians: 0 small and busy (clone), 1 large and busy (split), 2 quiet,
    /// 3 transparent (prune). Extra columns check that everything is carried along.
    fn state() -> GaussianState {
        let mut s = GaussianState::default();
        s.add(
            names::POSITION,
            3,
            Growth::Inherit,
            vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 3.0, 0.0, 0.0],
        )
        .unwrap();
        let small = 0.001f64.ln();
        let large = 0.2f64.ln();
        s.add(
            names::LOG_SCALE,
            3,
            Growth::Inherit,
            vec![
                small, small, small, large, small, small, small, small, small, small, small, small,
            ],
        )
        .unwrap();
        s.add(
            names::ROTATION,
            4,
            Growth::Inherit,
            [1.0, 0.0, 0.0, 0.0].repeat(4),
        )
        .unwrap();
        s.add(
            names::OPACITY_LOGIT,
            1,
            Growth::Inherit,
            vec![0.0, 1.0, 2.0, -10.0],
        )
        .unwrap();
        s.add("xyz/adam_m", 3, Growth::Zero, vec![1.0; 12]).unwrap();
        s.add(
            "knn_template",
            2,
            Growth::Inherit,
            vec![10.0, 11.0, 20.0, 21.0, 30.0, 31.0, 40.0, 41.0],
        )
        .unwrap();
        s.add(
            names::GRAD_ACCUM,
            1,
            Growth::Zero,
            vec![3e-4 * 2.0, 5e-4, 1e-5, 1e-5],
        )
        .unwrap();
        s.add(names::GRAD_COUNT, 1, Growth::Zero, vec![2.0, 1.0, 1.0, 1.0])
            .unwrap();
        s
    }

    fn settings(max: usize) -> DensifySettings {
        DensifySettings {
            grad_threshold: 2e-4,
            percent_dense: 0.01,
            extent: 1.0,
            min_opacity: 0.005,
            max_gaussians: max,
        }
    }

    #[test]
    fn clone_split_prune_carry_every_column() {
        let mut s = state();
        let mut rng = Rng::new(1);
        let report = densify_and_prune(&mut s, &settings(1000), &mut rng).unwrap();
        assert_eq!(
            report,
            DensifyReport {
                cloned: 1,
                split: 1,
                pruned: 1,
                count: 5
            }
        );
        // Survivors keep their order: 0, 2, then the clone of 0, then two children of 1.
        let knn = s.values("knn_template").unwrap();
        assert_eq!(
            knn,
            &[10.0, 11.0, 30.0, 31.0, 10.0, 11.0, 20.0, 21.0, 20.0, 21.0]
        );
        let m = s.values("xyz/adam_m").unwrap();
        assert_eq!(&m[..6], &[1.0; 6]);
        assert_eq!(&m[6..], &[0.0; 9]);
        let xyz = s.values(names::POSITION).unwrap();
        assert_eq!(&xyz[6..9], &[0.0, 0.0, 0.0]);
        // Split children: scale / 1.6, positions near the parent along its long axis.
        let ls = s.values(names::LOG_SCALE).unwrap();
        for child in [3, 4] {
            assert!((ls[3 * child] - (0.2f64 / 1.6).ln()).abs() < 1e-12);
            assert!((xyz[3 * child] - 1.0).abs() < 1.0 && (xyz[3 * child + 1]).abs() < 0.01);
        }
        assert_eq!(
            s.values(names::OPACITY_LOGIT).unwrap(),
            &[0.0, 2.0, 0.0, 1.0, 1.0]
        );
        assert!(
            s.values(names::GRAD_ACCUM)
                .unwrap()
                .iter()
                .all(|v| *v == 0.0)
        );
        assert!(
            s.values(names::GRAD_COUNT)
                .unwrap()
                .iter()
                .all(|v| *v == 0.0)
        );
    }

    #[test]
    fn growth_stops_at_the_limit_but_pruning_continues() {
        let mut s = state();
        let report = densify_and_prune(&mut s, &settings(4), &mut Rng::new(1)).unwrap();
        assert_eq!(
            report,
            DensifyReport {
                cloned: 0,
                split: 0,
                pruned: 1,
                count: 3
            }
        );
        let mut s = state();
        let report = densify_and_prune(&mut s, &settings(5), &mut Rng::new(1)).unwrap();
        assert_eq!((report.cloned, report.split, report.count), (1, 0, 4));
    }

    #[test]
    fn statistics_and_errors() {
        let mut s = state();
        s.accumulate_gradient_stats(&[1.0, 2.0, 3.0, 4.0], &[true, false, true, false])
            .unwrap();
        assert_eq!(s.values(names::GRAD_COUNT).unwrap(), &[3.0, 1.0, 2.0, 1.0]);
        assert!(matches!(
            s.add("bad", 3, Growth::Zero, vec![0.0; 5]),
            Err(StateError::BadLength { .. })
        ));
        assert!(matches!(
            s.add("xyz", 3, Growth::Zero, vec![0.0; 12]),
            Err(StateError::Duplicate(_))
        ));
        assert!(matches!(s.values("nope"), Err(StateError::Missing(_))));
        // Unseen Gaussians (count 0) are never selected, and NaN statistics are ignored.
        let mut s = state();
        s.values_mut(names::GRAD_COUNT).unwrap()[0] = 0.0;
        s.values_mut(names::GRAD_ACCUM).unwrap()[1] = f64::NAN;
        let report = densify_and_prune(&mut s, &settings(1000), &mut Rng::new(1)).unwrap();
        assert_eq!((report.cloned, report.split), (0, 0));
    }
}
