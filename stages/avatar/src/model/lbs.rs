//! LBS-weight offsets: the network `encoding 63 -> 128 -> 128 -> 128, skip concat(128, 63) ->
//! 128 -> J` (input encoding detached from the positions) and the one place where offsets
//! become skinning weights, `softmax(log(w_template + 1e-9) + offset)`, with its backward.

use seqavatar_compute::nn::linear::InputGrad;
use seqavatar_compute::nn::{Activation, NnScalar, Rng, positional_encoding_forward};

use super::dense::{Dense, Init, part};
use super::{ModelError, NetworkConfig, NetworkGroup, Widths, check_finite, check_input};

/// Added to the template weights before the logarithm (the reference's value).
pub const LOG_WEIGHT_EPSILON: f64 = 1e-9;

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
    if joints == 0 || !template.len().is_multiple_of(joints) {
        return Err(ModelError::Input {
            field: "lbs template weights".into(),
            message: format!(
                "{} values is not a whole number of rows of {joints} joints",
                template.len()
            ),
        });
    }
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
    let epsilon = S::from_f64(LOG_WEIGHT_EPSILON);
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
    if joints == 0 || !weights.len().is_multiple_of(joints) {
        return Err(ModelError::Input {
            field: "lbs weights".into(),
            message: format!(
                "{} values is not a whole number of rows of {joints} joints",
                weights.len()
            ),
        });
    }
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
    rows: usize,
    encoding: Vec<S>,
    /// Outputs of the five layers (the last are the offsets).
    outputs: Vec<Vec<S>>,
}

impl<S> LbsOffsetsCache<S> {
    /// Number of rows of the forward pass.
    pub fn rows(&self) -> usize {
        self.rows
    }
}

/// The LBS-offset network's layers.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct LbsOffsetNet<S> {
    pub(crate) layers: [Dense<S>; 5],
    widths: Widths,
}

impl<S: NnScalar> LbsOffsetNet<S> {
    pub(crate) fn new(config: &NetworkConfig, rng: &mut Rng) -> Self {
        let widths = config.widths;
        let encoding = widths.encoding_width();
        let hidden = widths.lbs_hidden;
        let group = NetworkGroup::LbsOffsets;
        let relu = Activation::Relu;
        let mut dense = |index: usize, input: usize, output: usize, activation: Activation| {
            Dense::new(
                format!("lbs_offsets.{index}"),
                group,
                input,
                output,
                activation,
                Init::PytorchDefault,
                rng,
            )
        };
        let layers = [
            dense(0, encoding, hidden, relu),
            dense(1, hidden, hidden, relu),
            dense(2, hidden, hidden, relu),
            dense(3, hidden + encoding, hidden, relu),
            dense(4, hidden, config.skinning_joints, Activation::Identity),
        ];
        LbsOffsetNet { layers, widths }
    }

    pub(crate) fn forward(&self, xyz: &[S]) -> Result<(Vec<S>, LbsOffsetsCache<S>), ModelError> {
        if !xyz.len().is_multiple_of(3) {
            return Err(ModelError::Input {
                field: "lbs xyz".into(),
                message: format!("{} values is not a whole number of 3-vectors", xyz.len()),
            });
        }
        check_finite("lbs xyz", xyz)?;
        let n = xyz.len() / 3;
        let encoding_width = self.widths.encoding_width();
        let hidden = self.widths.lbs_hidden;
        let mut cache = LbsOffsetsCache {
            rows: n,
            encoding: vec![S::ZERO; n * encoding_width],
            outputs: vec![Vec::new(); 5],
        };
        positional_encoding_forward(self.widths.encoding(), xyz, n, 3, &mut cache.encoding)?;
        let (encoding, outputs) = (&cache.encoding, &mut cache.outputs);
        for index in 0..5 {
            let (before, rest) = outputs.split_at_mut(index);
            let out = &mut rest[0];
            match index {
                0 => self.layers[0].forward(&[part(encoding, encoding_width)], n, out)?,
                3 => self.layers[3].forward(
                    &[part(&before[2], hidden), part(encoding, encoding_width)],
                    n,
                    out,
                )?,
                _ => self.layers[index].forward(&[part(&before[index - 1], hidden)], n, out)?,
            }
        }
        let offsets = cache.outputs[4].clone();
        Ok((offsets, cache))
    }

    pub(crate) fn backward(
        &mut self,
        cache: &LbsOffsetsCache<S>,
        d_offsets: &[S],
    ) -> Result<(), ModelError> {
        let n = cache.rows;
        let joints = self.layers[4].out_features();
        check_input("d_offsets", n * joints, d_offsets.len())?;
        let encoding_width = self.widths.encoding_width();
        let hidden = self.widths.lbs_hidden;
        let mut d_current = d_offsets.to_vec();
        let mut d_previous = vec![S::ZERO; n * hidden];
        for index in (0..5).rev() {
            let output = &cache.outputs[index];
            match index {
                0 => self.layers[0].backward(
                    &[part(&cache.encoding, encoding_width)],
                    n,
                    output,
                    &mut d_current,
                    &mut [InputGrad::Skip],
                )?,
                // The encoding is detached: its gradient is not wanted.
                3 => self.layers[3].backward(
                    &[
                        part(&cache.outputs[2], hidden),
                        part(&cache.encoding, encoding_width),
                    ],
                    n,
                    output,
                    &mut d_current,
                    &mut [InputGrad::Write(&mut d_previous), InputGrad::Skip],
                )?,
                _ => self.layers[index].backward(
                    &[part(&cache.outputs[index - 1], hidden)],
                    n,
                    output,
                    &mut d_current,
                    &mut [InputGrad::Write(&mut d_previous)],
                )?,
            }
            std::mem::swap(&mut d_current, &mut d_previous);
            d_previous.resize(n * hidden, S::ZERO);
        }
        Ok(())
    }
}
