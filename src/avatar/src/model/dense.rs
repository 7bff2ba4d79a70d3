//! One named dense layer with its gradient buffers: the building block of every network here.
//!
//! The maths is `seqavatar_compute::nn::linear` (`Y = act(concat(parts) W + b)`, `W: in x out`
//! row-major, gradients accumulated); this type only owns the parameters, their gradients and
//! the stable name under which checkpoints store them.

use seqavatar_compute::nn::linear::{InputGrad, LinearGrads};
use seqavatar_compute::nn::{
    Activation, InputPart, LinearShape, NnError, NnScalar, Rng, kaiming_uniform, linear_backward,
    linear_forward, uniform_fill,
};

use super::NetworkGroup;

/// A dense layer `Y = act(X W + b)` with accumulated gradients.
#[derive(Clone, Debug, PartialEq)]
pub struct Dense<S> {
    /// Stable name, e.g. `non_rigid.trunk.0`; parameters are `{name}.weight` and `{name}.bias`.
    pub name: String,
    /// The optimiser group the layer belongs to.
    pub group: NetworkGroup,
    /// Input width, output width and activation.
    pub shape: LinearShape,
    /// `in x out`, row-major (the transpose of a PyTorch `nn.Linear.weight`).
    pub weight: Vec<S>,
    /// `out`.
    pub bias: Vec<S>,
    /// Gradient of `weight`, accumulated.
    pub d_weight: Vec<S>,
    /// Gradient of `bias`, accumulated.
    pub d_bias: Vec<S>,
}

/// How a layer's parameters are drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Init {
    /// PyTorch's `nn.Linear` default: weight and bias from `U(-1/sqrt(in), 1/sqrt(in))`.
    PytorchDefault,
    /// Weight from `U(-bound, bound)`, bias zero (the pose refiner's last layer).
    SmallUniform(f64),
}

impl<S: NnScalar> Dense<S> {
    /// A layer drawn from `rng` with the given initialisation.
    pub fn new(
        name: impl Into<String>,
        group: NetworkGroup,
        in_features: usize,
        out_features: usize,
        activation: Activation,
        init: Init,
        rng: &mut Rng,
    ) -> Self {
        let shape = LinearShape {
            in_features,
            out_features,
            activation,
        };
        let mut weight = vec![S::ZERO; shape.weight_len()];
        let mut bias = vec![S::ZERO; out_features];
        match init {
            Init::PytorchDefault => kaiming_uniform(rng, in_features, &mut weight, &mut bias),
            Init::SmallUniform(bound) => uniform_fill(rng, &mut weight, bound),
        }
        Dense {
            name: name.into(),
            group,
            shape,
            d_weight: vec![S::ZERO; weight.len()],
            d_bias: vec![S::ZERO; bias.len()],
            weight,
            bias,
        }
    }

    pub fn out_features(&self) -> usize {
        self.shape.out_features
    }

    /// `output = act(concat(parts) W + b)` over `rows` rows; `output` is resized.
    pub fn forward(
        &self,
        parts: &[InputPart<'_, S>],
        rows: usize,
        output: &mut Vec<S>,
    ) -> Result<(), NnError> {
        output.resize(rows * self.shape.out_features, S::ZERO);
        linear_forward(self.shape, &self.weight, &self.bias, parts, rows, output)
    }

    /// Backward of [`Dense::forward`]: accumulates the parameter gradients, writes or adds the
    /// input gradients per `d_parts`. `d_output` (`dL/dY`) is masked in place.
    pub fn backward(
        &mut self,
        parts: &[InputPart<'_, S>],
        rows: usize,
        output: &[S],
        d_output: &mut [S],
        d_parts: &mut [InputGrad<'_, S>],
    ) -> Result<(), NnError> {
        linear_backward(
            self.shape,
            &self.weight,
            parts,
            rows,
            output,
            d_output,
            LinearGrads {
                weight: &mut self.d_weight,
                bias: &mut self.d_bias,
                inputs: d_parts,
            },
        )
    }

    pub fn zero_grad(&mut self) {
        self.d_weight.fill(S::ZERO);
        self.d_bias.fill(S::ZERO);
    }
}
