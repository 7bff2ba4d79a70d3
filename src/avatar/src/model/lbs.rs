//! LBS-weight offsets: the cache of the network `encoding 63 -> 128 -> 128 -> 128, skip
//! concat(128, 63) -> 128 -> J` (input encoding detached from the positions; described by
//! [`NetworkSpec::lbs_offsets`](super::spec::NetworkSpec::lbs_offsets)) and the one place
//! where offsets become skinning weights, `softmax(log(w_template + 1e-9) + offset)`, with
//! its backward.

use seqavatar_compute::nn::NnScalar;

use super::network::Activations;
use super::{ModelError, check_input};

/// An error unless `len` values are a whole number of rows of `joints`.
fn check_rows(field: &str, len: usize, joints: usize) -> Result<(), ModelError> {
    if joints == 0 || !len.is_multiple_of(joints) {
        return Err(ModelError::Input {
            field: field.into(),
            message: format!("{len} values is not a whole number of rows of {joints} joints"),
        });
    }
    Ok(())
}

/// Skinning weights `softmax(log(template + 1e-9) + offsets)` per row (`n x J` each).
///
/// `template` holds the template weights of each Gaussian's nearest template vertex; they
/// must be finite and non-negative (an error names the first bad entry).
pub fn blend_weights<S: NnScalar>(
    template: &[S],
    offsets: &[S],
    joints: usize,
) -> Result<Vec<S>, ModelError> {
    check_input("lbs offsets", template.len(), offsets.len())?;
    check_rows("lbs template weights", template.len(), joints)?;
    if let Some(index) = template
        .iter()
        .position(|w| !(w.is_finite() && *w >= S::ZERO))
    {
        return Err(ModelError::Input {
            field: "lbs template weights".into(),
            message: format!(
                "entry {index} (row {}, joint {}) is {}, expected finite and >= 0",
                index / joints,
                index % joints,
                template[index]
            ),
        });
    }
    let epsilon = S::from_f64(crate::skinning::WEIGHT_LOG_EPS);
    let mut weights = vec![S::ZERO; template.len()];
    for ((w_row, t_row), o_row) in weights
        .chunks_exact_mut(joints)
        .zip(template.chunks_exact(joints))
        .zip(offsets.chunks_exact(joints))
    {
        let mut max = -S::MAX;
        for ((w, &t), &o) in w_row.iter_mut().zip(t_row).zip(o_row) {
            *w = (t + epsilon).ln() + o;
            max = max.max(*w);
        }
        let mut sum = S::ZERO;
        for w in w_row.iter_mut() {
            *w = (*w - max).exp();
            sum += *w;
        }
        for w in w_row.iter_mut() {
            *w /= sum;
        }
    }
    Ok(weights)
}

/// Backward of [`blend_weights`]: `dL/d(offsets) = w * (g - sum_j w_j g_j)` per row, from the
/// forward's `weights` and `g = dL/d(weights)`.
pub fn blend_weights_backward<S: NnScalar>(
    weights: &[S],
    d_weights: &[S],
    joints: usize,
) -> Result<Vec<S>, ModelError> {
    check_input("lbs weight gradient", weights.len(), d_weights.len())?;
    check_rows("lbs weights", weights.len(), joints)?;
    let mut d_offsets = vec![S::ZERO; weights.len()];
    for ((d_row, w_row), g_row) in d_offsets
        .chunks_exact_mut(joints)
        .zip(weights.chunks_exact(joints))
        .zip(d_weights.chunks_exact(joints))
    {
        let dot: S = w_row.iter().zip(g_row).map(|(&w, &g)| w * g).sum();
        for ((d, &w), &g) in d_row.iter_mut().zip(w_row).zip(g_row) {
            *d = w * (g - dot);
        }
    }
    Ok(d_offsets)
}

/// The offset network's activations for its backward.
#[derive(Clone, Debug, Default)]
pub struct LbsOffsetsCache<S> {
    pub(crate) activations: Activations<S>,
}

impl<S> LbsOffsetsCache<S> {
    /// Number of rows of the forward pass.
    pub fn rows(&self) -> usize {
        self.activations.rows()
    }
}
