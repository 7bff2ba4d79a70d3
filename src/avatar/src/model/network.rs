//! The `cpu` interpreter of a [`NetworkSpec`], generic over f32 (production) and f64 (the
//! oracle of the finite-difference tests): one forward and one backward for every network.
//!
//! Values are stored per block (`L` blocks for a per-Gaussian window, else one). The backward
//! walks the layers in reverse; the first contribution to a value's gradient writes it, later
//! ones (a value read by several layers or window elements) add to it, in reverse layer
//! order and ascending window element.

use seqavatar_compute::nn::linear::{InputGrad, LinearGrads};
use seqavatar_compute::nn::{
    Activation, InputPart, LinearShape, NnScalar, Rng, linear_backward, linear_forward,
    positional_encoding_backward, positional_encoding_forward,
};

use super::ModelError;
use super::dense::Dense;
use super::spec::{NetworkSpec, Part, Value, window_blocks};

/// One network's parameters (one [`Dense`] per layer of its description).
#[derive(Clone, Debug, PartialEq)]
pub struct Network<S> {
    spec: NetworkSpec,
    pub(crate) layers: Vec<Dense<S>>,
}

/// The values of one forward pass, for its backward.
#[derive(Clone, Debug, Default)]
pub struct Activations<S> {
    rows: usize,
    /// The output layer.
    output: usize,
    /// Per input, its (encoded) blocks.
    inputs: Vec<Vec<Vec<S>>>,
    /// Per layer, its output blocks.
    outputs: Vec<Vec<Vec<S>>>,
    /// Per layer, the per-frame bias of a per-Gaussian layer that reads per-frame values.
    frame_bias: Vec<Option<Vec<S>>>,
}

impl<S> Activations<S> {
    /// Number of Gaussians of the forward pass (0 when no input is per Gaussian).
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// The network's output (the output layer's values; empty for a default value).
    pub fn output(&self) -> &[S] {
        self.outputs
            .get(self.output)
            .and_then(|blocks| blocks.first())
            .map_or(&[][..], Vec::as_slice)
    }

    /// The column blocks `parts` of one product's input.
    fn parts(&self, parts: &[Part]) -> Vec<InputPart<'_, S>> {
        parts
            .iter()
            .map(|part| InputPart {
                data: part.pick::<Vec<S>>(&self.inputs, &self.outputs),
                cols: part.cols,
            })
            .collect()
    }
}

/// The per-Gaussian and per-frame shapes of a layer whose per-frame inputs are folded into a
/// per-frame bias (`rows_in` leading weight rows, the rest per frame).
pub(crate) fn folded_shapes(shape: LinearShape, rows_in: usize) -> (LinearShape, LinearShape) {
    (
        LinearShape {
            in_features: rows_in,
            ..shape
        },
        LinearShape {
            in_features: shape.in_features - rows_in,
            activation: Activation::Identity,
            ..shape
        },
    )
}

/// The input-gradient sinks of taken gradient buffers: skip, write (first contribution) or
/// add.
fn sinks<S>(buffers: &mut [Option<(Vec<S>, bool)>]) -> Vec<InputGrad<'_, S>> {
    buffers
        .iter_mut()
        .map(|b| match b {
            None => InputGrad::Skip,
            Some((buffer, true)) => InputGrad::Accumulate(&mut buffer[..]),
            Some((buffer, false)) => InputGrad::Write(&mut buffer[..]),
        })
        .collect()
}

/// Takes a reusable buffer of `len` zeros from `pool`.
fn scratch<S: NnScalar>(pool: &mut Vec<Vec<S>>, len: usize) -> Vec<S> {
    let mut buffer = pool.pop().unwrap_or_default();
    buffer.clear();
    buffer.resize(len, S::ZERO);
    buffer
}

impl<S: NnScalar> Network<S> {
    /// The layers of `spec` (checked), drawn from `rng` in layer order.
    pub fn new(spec: NetworkSpec, rng: &mut Rng) -> Result<Self, ModelError> {
        spec.validate()?;
        let layers = (0..spec.layers.len())
            .map(|index| {
                let shape = spec.shape(index);
                Dense::new(
                    spec.parameter_name(index),
                    spec.group,
                    shape.in_features,
                    shape.out_features,
                    shape.activation,
                    spec.layers[index].init,
                    rng,
                )
            })
            .collect();
        Ok(Network { spec, layers })
    }

    pub fn spec(&self) -> &NetworkSpec {
        &self.spec
    }

    /// Evaluates the network on `inputs` (one slice per input block of the description, in
    /// its order and layout); the output is [`Activations::output`] of the result.
    pub fn forward(&self, inputs: &[&[S]]) -> Result<Activations<S>, ModelError> {
        let spec = &self.spec;
        let n = spec.check_inputs(inputs)?;
        let window = spec.window;
        let mut cache = Activations {
            rows: n,
            output: spec.output,
            inputs: Vec::with_capacity(inputs.len()),
            outputs: Vec::with_capacity(self.layers.len()),
            frame_bias: Vec::with_capacity(self.layers.len()),
        };
        for (input, data) in spec.inputs.iter().zip(inputs) {
            let raw = match input.rows {
                super::spec::Rows::GaussianWindow => window_blocks(data, window, input.width),
                _ => vec![data.to_vec()],
            };
            let blocks = match input.encoding {
                None => raw,
                Some(encoding) => {
                    let rows = input.rows.block_rows(n, window);
                    let mut encoded = Vec::with_capacity(raw.len());
                    for block in &raw {
                        let mut out = vec![S::ZERO; rows * input.value_width()];
                        positional_encoding_forward(encoding, block, rows, input.width, &mut out)?;
                        encoded.push(out);
                    }
                    encoded
                }
            };
            cache.inputs.push(blocks);
        }
        for (index, layer) in self.layers.iter().enumerate() {
            let rows_space = spec.layers[index].rows;
            let rows = rows_space.block_rows(n, window);
            let mut blocks = Vec::new();
            let mut frame_bias = None;
            for call in 0..rows_space.calls(window) {
                let plan = spec.plan(index, call);
                let parts = cache.parts(&plan.rows);
                let mut out = Vec::new();
                if plan.frame.is_empty() {
                    layer.forward(&parts, rows, &mut out)?;
                } else {
                    let width = layer.out_features();
                    let (rows_shape, frame_shape) = folded_shapes(layer.shape, plan.rows_in());
                    let (rows_weight, frame_weight) = layer.weight.split_at(plan.rows_in() * width);
                    let frame_parts = cache.parts(&plan.frame);
                    let mut bias = vec![S::ZERO; width];
                    linear_forward(
                        frame_shape,
                        frame_weight,
                        &layer.bias,
                        &frame_parts,
                        1,
                        &mut bias,
                    )?;
                    out = vec![S::ZERO; rows * width];
                    linear_forward(rows_shape, rows_weight, &bias, &parts, rows, &mut out)?;
                    frame_bias = Some(bias);
                }
                blocks.push(out);
            }
            cache.outputs.push(blocks);
            cache.frame_bias.push(frame_bias);
        }
        Ok(cache)
    }

    /// Backward of [`Network::forward`] from the gradient of the output: accumulates the
    /// parameter gradients and returns, per input block, its gradient (`Some` for inputs
    /// whose description asks for it, through their encoding).
    pub fn backward(
        &mut self,
        cache: &Activations<S>,
        d_output: &[S],
    ) -> Result<Vec<Option<Vec<S>>>, ModelError> {
        let spec = &self.spec;
        let window = spec.window;
        let n = cache.rows;
        let fits = cache.output == spec.output
            && cache.inputs.len() == spec.inputs.len()
            && cache.outputs.len() == spec.layers.len()
            && (0..spec.layers.len()).all(|j| {
                cache.outputs[j].len() == spec.layers[j].rows.calls(window)
                    && cache.outputs[j].iter().all(|b| {
                        b.len() == spec.layers[j].rows.block_rows(n, window) * spec.layers[j].out
                    })
            });
        if !fits {
            return Err(ModelError::Input {
                field: format!("{} cache", spec.prefix),
                message: "does not come from this network's forward pass".into(),
            });
        }
        let output = &cache.outputs[spec.output][0];
        super::check_input(
            &format!("{} output gradient", spec.prefix),
            output.len(),
            d_output.len(),
        )?;
        let mut pool: Vec<Vec<S>> = Vec::new();
        // Per value, per block: its gradient once something has written it.
        let mut d_inputs: Vec<Vec<Option<Vec<S>>>> = spec
            .inputs
            .iter()
            .map(|i| vec![None; i.rows.calls(window)])
            .collect();
        let mut d_outputs: Vec<Vec<Option<Vec<S>>>> = spec
            .layers
            .iter()
            .map(|l| vec![None; l.rows.calls(window)])
            .collect();
        d_outputs[spec.output][0] = Some(d_output.to_vec());
        for index in (0..self.layers.len()).rev() {
            let rows_space = spec.layers[index].rows;
            let rows = rows_space.block_rows(n, window);
            let layer = &mut self.layers[index];
            for call in 0..rows_space.calls(window) {
                let plan = spec.plan(index, call);
                let mut d_out = d_outputs[index][call]
                    .take()
                    .ok_or_else(|| ModelError::Input {
                        field: spec.parameter_name(index),
                        message: "no gradient reached this layer".into(),
                    })?;
                let wants = |part: &Part| match part.value {
                    Value::Input(i) => spec.inputs[i].gradient,
                    Value::Layer(_) => true,
                };
                // Take the gradient buffers of the parts out (write the first contribution).
                let mut take = |parts: &[Part]| -> Vec<Option<(Vec<S>, bool)>> {
                    parts
                        .iter()
                        .map(|part| {
                            if !wants(part) {
                                return None;
                            }
                            let slot = match part.value {
                                Value::Input(i) => &mut d_inputs[i][part.block],
                                Value::Layer(j) => &mut d_outputs[j][part.block],
                            };
                            let block_rows = spec.value_rows(part.value).block_rows(n, window);
                            let len = block_rows * spec.value_width(part.value);
                            Some(match slot.take() {
                                Some(buffer) => (buffer, true),
                                None => (scratch(&mut pool, len), false),
                            })
                        })
                        .collect()
                };
                let mut rows_d = take(&plan.rows);
                let mut frame_d = take(&plan.frame);
                let parts = cache.parts(&plan.rows);
                let out = &cache.outputs[index][call];
                if plan.frame.is_empty() {
                    layer.backward(&parts, rows, out, &mut d_out, &mut sinks(&mut rows_d))?;
                } else {
                    let width = layer.out_features();
                    let split = plan.rows_in() * width;
                    let (rows_shape, frame_shape) = folded_shapes(layer.shape, plan.rows_in());
                    let frame_bias = cache.frame_bias[index].as_deref().unwrap_or_default();
                    let frame_parts = cache.parts(&plan.frame);
                    let Dense {
                        weight,
                        d_weight,
                        d_bias,
                        ..
                    } = layer;
                    let (rows_weight, frame_weight) = weight.split_at(split);
                    let (d_rows_weight, d_frame_weight) = d_weight.split_at_mut(split);
                    let mut d_frame_bias = vec![S::ZERO; width];
                    linear_backward(
                        rows_shape,
                        rows_weight,
                        &parts,
                        rows,
                        out,
                        &mut d_out,
                        LinearGrads {
                            weight: d_rows_weight,
                            bias: &mut d_frame_bias,
                            inputs: &mut sinks(&mut rows_d),
                        },
                    )?;
                    linear_backward(
                        frame_shape,
                        frame_weight,
                        &frame_parts,
                        1,
                        frame_bias,
                        &mut d_frame_bias,
                        LinearGrads {
                            weight: d_frame_weight,
                            bias: d_bias,
                            inputs: &mut sinks(&mut frame_d),
                        },
                    )?;
                }
                pool.push(d_out);
                // Put the written gradients back.
                for (part, buffer) in plan.rows.iter().chain(&plan.frame).zip(
                    rows_d
                        .into_iter()
                        .chain(frame_d)
                        .map(|b| b.map(|(buffer, _)| buffer)),
                ) {
                    if let Some(buffer) = buffer {
                        match part.value {
                            Value::Input(i) => d_inputs[i][part.block] = Some(buffer),
                            Value::Layer(j) => d_outputs[j][part.block] = Some(buffer),
                        }
                    }
                }
            }
        }
        let mut gradients = Vec::with_capacity(spec.inputs.len());
        for (index, input) in spec.inputs.iter().enumerate() {
            if !input.gradient {
                gradients.push(None);
                continue;
            }
            let rows = input.rows.block_rows(n, window);
            let d_value = d_inputs[index][0]
                .take()
                .unwrap_or_else(|| vec![S::ZERO; rows * input.value_width()]);
            let gradient = match input.encoding {
                None => d_value,
                Some(encoding) => {
                    let mut d_raw = vec![S::ZERO; rows * input.width];
                    positional_encoding_backward(
                        encoding,
                        &cache.inputs[index][0],
                        &d_value,
                        rows,
                        input.width,
                        &mut d_raw,
                    )?;
                    d_raw
                }
            };
            gradients.push(Some(gradient));
        }
        Ok(gradients)
    }
}
