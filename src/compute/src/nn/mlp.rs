//! A stack of dense layers on `cpu`: skip concatenation, cached activations, initialisation.
//!
//! Layer `l` reads the output of layer `l - 1` (layer 0 reads the network input); a layer
//! marked `skip_input` reads `concat(previous output, network input)` in that column order,
//! as the LBS-offset network (`63 -> 128 -> 128 -> 128`, then `concat(128, 63) = 191 -> 128
//! -> J`) does. Several output heads of one trunk (e.g. `512 -> 3, 4, 3`) are one layer with
//! the heads' widths summed: PyTorch initialises each head from its fan-in alone, which is
//! the same for the merged layer.

use super::init::{Rng, kaiming_uniform};
use super::linear::{
    Activation, InputGrad, InputPart, LinearGrads, LinearShape, linear_backward, linear_forward,
};
use super::scalar::NnScalar;
use super::{NnError, check_len};

/// One layer of an [`MlpSpec`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct MlpLayerSpec {
    /// Output width.
    pub out_features: usize,
    /// Activation after the bias.
    pub activation: Activation,
    /// Whether the network input is concatenated after the previous layer's output.
    pub skip_input: bool,
}

impl MlpLayerSpec {
    /// A plain layer (no skip).
    pub fn new(out_features: usize, activation: Activation) -> Self {
        MlpLayerSpec {
            out_features,
            activation,
            skip_input: false,
        }
    }

    /// A layer that also reads the network input.
    pub fn with_skip(out_features: usize, activation: Activation) -> Self {
        MlpLayerSpec {
            out_features,
            activation,
            skip_input: true,
        }
    }
}

/// The architecture of an [`Mlp`].
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct MlpSpec {
    /// Width of the network input.
    pub in_features: usize,
    /// The layers, first to last.
    pub layers: Vec<MlpLayerSpec>,
}

impl MlpSpec {
    /// The shape of every layer, after checking the architecture.
    pub fn shapes(&self) -> Result<Vec<LinearShape>, NnError> {
        if self.in_features == 0 || self.layers.is_empty() {
            return Err(NnError::Shape {
                operand: "mlp spec".into(),
                message: format!(
                    "needs in_features > 0 and at least one layer (got {} and {} layers)",
                    self.in_features,
                    self.layers.len()
                ),
            });
        }
        let mut previous = self.in_features;
        let mut shapes = Vec::with_capacity(self.layers.len());
        for (index, layer) in self.layers.iter().enumerate() {
            if layer.out_features == 0 {
                return Err(NnError::Shape {
                    operand: format!("mlp layer {index}"),
                    message: "out_features must be positive".into(),
                });
            }
            if index == 0 && layer.skip_input {
                return Err(NnError::Shape {
                    operand: "mlp layer 0".into(),
                    message:
                        "the first layer already reads the input; skip_input is for later layers"
                            .into(),
                });
            }
            let in_features = previous
                + if layer.skip_input {
                    self.in_features
                } else {
                    0
                };
            shapes.push(LinearShape {
                in_features,
                out_features: layer.out_features,
                activation: layer.activation,
            });
            previous = layer.out_features;
        }
        Ok(shapes)
    }

    /// Width of the network output.
    pub fn out_features(&self) -> usize {
        self.layers.last().map_or(0, |layer| layer.out_features)
    }
}

/// The parameters (or their gradients) of one layer.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerParams<T> {
    /// The layer's shape.
    pub shape: LinearShape,
    /// `in x out`, row-major.
    pub weight: Vec<T>,
    /// `out`.
    pub bias: Vec<T>,
}

impl<T: NnScalar> LayerParams<T> {
    /// All-zero parameters of the given shape.
    pub fn zeros(shape: LinearShape) -> Self {
        LayerParams {
            shape,
            weight: vec![T::ZERO; shape.weight_len()],
            bias: vec![T::ZERO; shape.out_features],
        }
    }
}

/// A dense network on `cpu`.
#[derive(Clone, Debug, PartialEq)]
pub struct Mlp<T> {
    spec: MlpSpec,
    /// The layers' parameters, first to last.
    pub layers: Vec<LayerParams<T>>,
}

/// Activations of one forward pass, kept for the backward pass, plus gradient scratch.
#[derive(Clone, Debug, Default)]
pub struct MlpCache<T> {
    rows: usize,
    outputs: Vec<Vec<T>>,
    grad_current: Vec<T>,
    grad_previous: Vec<T>,
}

impl<T> MlpCache<T> {
    /// An empty cache; buffers grow on first use and are reused afterwards.
    pub fn new() -> Self {
        MlpCache {
            rows: 0,
            outputs: Vec::new(),
            grad_current: Vec::new(),
            grad_previous: Vec::new(),
        }
    }

    /// The output of layer `index` of the last forward pass (`rows x out`).
    pub fn layer_output(&self, index: usize) -> Option<&[T]> {
        self.outputs.get(index).map(Vec::as_slice)
    }

    /// The network output of the last forward pass.
    pub fn output(&self) -> Option<&[T]> {
        self.outputs.last().map(Vec::as_slice)
    }

    /// Rows of the last forward pass.
    pub fn rows(&self) -> usize {
        self.rows
    }
}

impl<T: NnScalar> Mlp<T> {
    /// PyTorch-default initialisation (see [`kaiming_uniform`]), layers in order.
    pub fn new(spec: MlpSpec, rng: &mut Rng) -> Result<Self, NnError> {
        Self::with_init(spec, rng, |_, layer, rng| {
            kaiming_uniform(
                rng,
                layer.shape.in_features,
                &mut layer.weight,
                &mut layer.bias,
            )
        })
    }

    /// Custom initialisation: `init(layer_index, layer, rng)` fills each layer in order, e.g.
    /// PyTorch default for all but a last layer drawn from `U(-1e-5, 1e-5)` with zero bias
    /// (the body-pose refiner).
    pub fn with_init(
        spec: MlpSpec,
        rng: &mut Rng,
        mut init: impl FnMut(usize, &mut LayerParams<T>, &mut Rng),
    ) -> Result<Self, NnError> {
        let shapes = spec.shapes()?;
        let mut layers: Vec<LayerParams<T>> = shapes.into_iter().map(LayerParams::zeros).collect();
        for (index, layer) in layers.iter_mut().enumerate() {
            init(index, layer, rng);
        }
        Ok(Mlp { spec, layers })
    }

    /// Wraps existing parameters (e.g. loaded from a checkpoint), checking every length.
    pub fn from_layers(spec: MlpSpec, layers: Vec<LayerParams<T>>) -> Result<Self, NnError> {
        let shapes = spec.shapes()?;
        if shapes.len() != layers.len() {
            return Err(NnError::Shape {
                operand: "mlp layers".into(),
                message: format!("spec has {} layers, got {}", shapes.len(), layers.len()),
            });
        }
        for (index, (shape, layer)) in shapes.iter().zip(&layers).enumerate() {
            if *shape != layer.shape {
                return Err(NnError::Shape {
                    operand: format!("mlp layer {index}"),
                    message: format!("spec shape {shape:?}, parameters have {:?}", layer.shape),
                });
            }
            check_len(
                &format!("mlp layer {index} weight"),
                shape.weight_len(),
                layer.weight.len(),
            )?;
            check_len(
                &format!("mlp layer {index} bias"),
                shape.out_features,
                layer.bias.len(),
            )?;
        }
        Ok(Mlp { spec, layers })
    }

    /// The architecture.
    pub fn spec(&self) -> &MlpSpec {
        &self.spec
    }

    /// Zero gradients shaped like the parameters.
    pub fn zero_grads(&self) -> Vec<LayerParams<T>> {
        self.layers
            .iter()
            .map(|layer| LayerParams::zeros(layer.shape))
            .collect()
    }

    /// Total number of trainable values.
    pub fn parameter_count(&self) -> usize {
        self.layers
            .iter()
            .map(|layer| layer.weight.len() + layer.bias.len())
            .sum()
    }

    /// Forward over `rows` rows of `input` (`rows x in`); the output is `cache.output()`.
    pub fn forward<'c>(
        &self,
        input: &[T],
        rows: usize,
        cache: &'c mut MlpCache<T>,
    ) -> Result<&'c [T], NnError> {
        check_len("mlp input", rows * self.spec.in_features, input.len())?;
        cache.rows = rows;
        cache.outputs.resize_with(self.layers.len(), Vec::new);
        for index in 0..self.layers.len() {
            let layer = &self.layers[index];
            let (before, rest) = cache.outputs.split_at_mut(index);
            let output = &mut rest[0];
            output.resize(rows * layer.shape.out_features, T::ZERO);
            let parts = self.input_parts(index, input, before);
            linear_forward(
                layer.shape,
                &layer.weight,
                &layer.bias,
                &parts,
                rows,
                output,
            )?;
        }
        Ok(cache.outputs.last().map(Vec::as_slice).unwrap_or_default())
    }

    /// The input parts of layer `index`, given the outputs of the layers before it.
    fn input_parts<'a>(
        &self,
        index: usize,
        input: &'a [T],
        previous_outputs: &'a [Vec<T>],
    ) -> Vec<InputPart<'a, T>> {
        let in_features = self.spec.in_features;
        if index == 0 {
            return vec![InputPart {
                data: input,
                cols: in_features,
            }];
        }
        let previous = InputPart {
            data: previous_outputs[index - 1].as_slice(),
            cols: self.layers[index - 1].shape.out_features,
        };
        if self.spec.layers[index].skip_input {
            vec![
                previous,
                InputPart {
                    data: input,
                    cols: in_features,
                },
            ]
        } else {
            vec![previous]
        }
    }

    /// Backward of the last [`forward`](Self::forward) (whose `input` must be passed again).
    ///
    /// `d_output` holds `dL/d(output)` and is used as scratch. Parameter gradients are
    /// accumulated into `grads`; `d_input`, when given, is overwritten with `dL/d(input)`.
    pub fn backward(
        &self,
        input: &[T],
        cache: &mut MlpCache<T>,
        d_output: &mut [T],
        grads: &mut [LayerParams<T>],
        mut d_input: Option<&mut [T]>,
    ) -> Result<(), NnError> {
        let rows = cache.rows;
        let in_features = self.spec.in_features;
        check_len("mlp input", rows * in_features, input.len())?;
        check_len(
            "mlp output gradient",
            rows * self.spec.out_features(),
            d_output.len(),
        )?;
        if cache.outputs.len() != self.layers.len() {
            return Err(NnError::Shape {
                operand: "mlp cache".into(),
                message: "backward needs a forward pass of this network first".into(),
            });
        }
        if grads.len() != self.layers.len() {
            return Err(NnError::Shape {
                operand: "mlp gradients".into(),
                message: format!("{} layers, network has {}", grads.len(), self.layers.len()),
            });
        }
        if let Some(buffer) = d_input.as_deref_mut() {
            check_len("mlp input gradient", rows * in_features, buffer.len())?;
            buffer.fill(T::ZERO);
        }
        let MlpCache {
            outputs,
            grad_current,
            grad_previous,
            ..
        } = cache;
        for index in (0..self.layers.len()).rev() {
            let layer = &self.layers[index];
            let grad = &mut grads[index];
            check_len(
                &format!("mlp layer {index} weight gradient"),
                layer.weight.len(),
                grad.weight.len(),
            )?;
            let parts = self.input_parts(index, input, outputs);
            let d_layer_output: &mut [T] = if index + 1 == self.layers.len() {
                &mut *d_output
            } else {
                &mut grad_current[..rows * layer.shape.out_features]
            };
            let mut d_parts: Vec<InputGrad<'_, T>> = Vec::with_capacity(2);
            if index == 0 {
                d_parts.push(match d_input.as_deref_mut() {
                    Some(buffer) => InputGrad::Accumulate(buffer),
                    None => InputGrad::Skip,
                });
            } else {
                let width = self.layers[index - 1].shape.out_features;
                grad_previous.resize(grad_previous.len().max(rows * width), T::ZERO);
                d_parts.push(InputGrad::Write(&mut grad_previous[..rows * width]));
                if self.spec.layers[index].skip_input {
                    d_parts.push(match d_input.as_deref_mut() {
                        Some(buffer) => InputGrad::Accumulate(buffer),
                        None => InputGrad::Skip,
                    });
                }
            }
            linear_backward(
                layer.shape,
                &layer.weight,
                &parts,
                rows,
                &outputs[index],
                d_layer_output,
                LinearGrads {
                    weight: &mut grad.weight,
                    bias: &mut grad.bias,
                },
                &mut d_parts,
            )?;
            drop(d_parts);
            std::mem::swap(grad_current, grad_previous);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::init::uniform_fill;

    /// The LBS-offset shape in miniature: 3 -> 5 -> 4, skip concat (4 + 3) -> 6 -> 2.
    fn skip_spec() -> MlpSpec {
        MlpSpec {
            in_features: 3,
            layers: vec![
                MlpLayerSpec::new(5, Activation::Relu),
                MlpLayerSpec::new(4, Activation::Relu),
                MlpLayerSpec::with_skip(6, Activation::Relu),
                MlpLayerSpec::new(2, Activation::Identity),
            ],
        }
    }

    #[test]
    fn shapes_follow_the_skip_concatenation() {
        let shapes = skip_spec().shapes().unwrap();
        let widths: Vec<_> = shapes
            .iter()
            .map(|s| (s.in_features, s.out_features))
            .collect();
        assert_eq!(widths, [(3, 5), (5, 4), (7, 6), (6, 2)]);
        let bad = MlpSpec {
            in_features: 3,
            layers: vec![MlpLayerSpec::with_skip(2, Activation::Relu)],
        };
        assert!(
            bad.shapes()
                .unwrap_err()
                .to_string()
                .contains("mlp layer 0")
        );
    }

    /// Forward by hand: explicit concatenation and the naive product.
    fn naive_forward(mlp: &Mlp<f64>, input: &[f64], rows: usize) -> Vec<f64> {
        let n_in = mlp.spec().in_features;
        let mut current: Vec<f64> = input.to_vec();
        let mut width = n_in;
        for (index, layer) in mlp.layers.iter().enumerate() {
            let (layer_in, data) = if mlp.spec().layers[index].skip_input {
                let mut joined = Vec::new();
                for r in 0..rows {
                    joined.extend_from_slice(&current[r * width..(r + 1) * width]);
                    joined.extend_from_slice(&input[r * n_in..(r + 1) * n_in]);
                }
                (width + n_in, joined)
            } else {
                (width, current.clone())
            };
            let out = layer.shape.out_features;
            let mut next = vec![0.0; rows * out];
            for r in 0..rows {
                for j in 0..out {
                    let mut sum = layer.bias[j];
                    for i in 0..layer_in {
                        sum += data[r * layer_in + i] * layer.weight[i * out + j];
                    }
                    next[r * out + j] = layer.shape.activation.apply(sum);
                }
            }
            current = next;
            width = out;
        }
        current
    }

    #[test]
    fn forward_matches_explicit_concatenation() {
        let mut rng = Rng::new(9);
        let mlp = Mlp::<f64>::new(skip_spec(), &mut rng).unwrap();
        let rows = 17;
        let mut input = vec![0.0; rows * 3];
        uniform_fill(&mut rng, &mut input, 2.0);
        let mut cache = MlpCache::new();
        let output = mlp.forward(&input, rows, &mut cache).unwrap().to_vec();
        let expected = naive_forward(&mlp, &input, rows);
        for (a, b) in output.iter().zip(&expected) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
    }

    #[test]
    fn backward_matches_finite_differences_with_skip() {
        let mut rng = Rng::new(21);
        let mlp = Mlp::<f64>::new(skip_spec(), &mut rng).unwrap();
        let rows = 4;
        let mut input = vec![0.0; rows * 3];
        uniform_fill(&mut rng, &mut input, 2.0);
        let mut probe = vec![0.0; rows * 2];
        uniform_fill(&mut rng, &mut probe, 1.0);
        let loss = |net: &Mlp<f64>, x: &[f64]| -> f64 {
            let mut cache = MlpCache::new();
            let y = net.forward(x, rows, &mut cache).unwrap();
            y.iter().zip(&probe).map(|(a, b)| a * b).sum()
        };

        let mut cache = MlpCache::new();
        mlp.forward(&input, rows, &mut cache).unwrap();
        let mut grads = mlp.zero_grads();
        let mut d_output = probe.clone();
        let mut d_input = vec![f64::NAN; input.len()];
        mlp.backward(
            &input,
            &mut cache,
            &mut d_output,
            &mut grads,
            Some(&mut d_input),
        )
        .unwrap();

        let h = 1e-6;
        let tolerance = 1e-6;
        for (l, layer) in mlp.layers.iter().enumerate() {
            for i in 0..layer.weight.len() {
                let (mut plus, mut minus) = (mlp.clone(), mlp.clone());
                plus.layers[l].weight[i] += h;
                minus.layers[l].weight[i] -= h;
                let fd = (loss(&plus, &input) - loss(&minus, &input)) / (2.0 * h);
                let g = grads[l].weight[i];
                assert!((g - fd).abs() < tolerance, "layer {l} dW[{i}] {g} vs {fd}");
            }
            for j in 0..layer.bias.len() {
                let (mut plus, mut minus) = (mlp.clone(), mlp.clone());
                plus.layers[l].bias[j] += h;
                minus.layers[l].bias[j] -= h;
                let fd = (loss(&plus, &input) - loss(&minus, &input)) / (2.0 * h);
                let g = grads[l].bias[j];
                assert!((g - fd).abs() < tolerance, "layer {l} db[{j}] {g} vs {fd}");
            }
        }
        for i in 0..input.len() {
            let (mut plus, mut minus) = (input.clone(), input.clone());
            plus[i] += h;
            minus[i] -= h;
            let fd = (loss(&mlp, &plus) - loss(&mlp, &minus)) / (2.0 * h);
            assert!(
                (d_input[i] - fd).abs() < tolerance,
                "dX[{i}] {} vs {fd}",
                d_input[i]
            );
        }

        // A second backward accumulates parameter gradients: exactly twice the first.
        let first = grads.clone();
        mlp.forward(&input, rows, &mut cache).unwrap();
        let mut d_output = probe.clone();
        mlp.backward(&input, &mut cache, &mut d_output, &mut grads, None)
            .unwrap();
        for (a, b) in grads.iter().zip(&first) {
            for (x, y) in a.weight.iter().zip(&b.weight) {
                assert!((x - 2.0 * y).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn custom_init_sets_the_last_layer() {
        let spec = MlpSpec {
            in_features: 69,
            layers: vec![
                MlpLayerSpec::new(128, Activation::Relu),
                MlpLayerSpec::new(128, Activation::Relu),
                MlpLayerSpec::new(69, Activation::Identity),
            ],
        };
        let last = spec.layers.len() - 1;
        let mlp = Mlp::<f32>::with_init(spec, &mut Rng::new(0), |index, layer, rng| {
            if index == last {
                uniform_fill(rng, &mut layer.weight, 1e-5);
                layer.bias.fill(0.0);
            } else {
                kaiming_uniform(
                    rng,
                    layer.shape.in_features,
                    &mut layer.weight,
                    &mut layer.bias,
                );
            }
        })
        .unwrap();
        let max_last = mlp.layers[last]
            .weight
            .iter()
            .fold(0.0f32, |m, x| m.max(x.abs()));
        assert!(max_last <= 1e-5 && max_last > 0.0);
        assert!(mlp.layers[last].bias.iter().all(|&b| b == 0.0));
        let max_first = mlp.layers[0]
            .weight
            .iter()
            .fold(0.0f32, |m, x| m.max(x.abs()));
        assert!(max_first > 0.1 && max_first <= 1.0 / 69f32.sqrt());
        assert_eq!(
            mlp.parameter_count(),
            69 * 128 + 128 + 128 * 128 + 128 + 128 * 69 + 69
        );
    }

    #[test]
    fn from_layers_rejects_wrong_lengths() {
        let spec = MlpSpec {
            in_features: 2,
            layers: vec![MlpLayerSpec::new(3, Activation::Relu)],
        };
        let mut layer = LayerParams::<f32>::zeros(spec.shapes().unwrap()[0]);
        layer.bias.pop();
        let error = Mlp::from_layers(spec, vec![layer]).unwrap_err();
        assert_eq!(
            error,
            NnError::Length {
                operand: "mlp layer 0 bias".into(),
                expected: 3,
                actual: 2
            }
        );
    }
}
