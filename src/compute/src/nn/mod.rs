//! Dense layers, positional encoding and Adam for the SeqAvatar networks, on `cpu` and `gpu`.
//!
//! The networks are small ReLU MLPs applied to every Gaussian (up to ~100k rows), so the
//! one heavy operation is a matrix product with a fused bias and activation, and its
//! backward. Conventions shared by both backends:
//!
//! - Matrices are row-major. A layer's input `X` is `rows x in`, its weight `W` is
//!   `in x out` (the transpose of a PyTorch `nn.Linear.weight`), its bias `b` has `out`
//!   entries and its output is `Y = act(X W + b)`.
//! - A layer may read its input from several matrices side by side (a concatenation along
//!   columns that is never materialised): input part `p` multiplies the rows of `W` that
//!   follow those of the parts before it. Skip connections and the SeqAvatar trunk input
//!   `concat(63, 32, 32, 96)` use this.
//! - The ReLU derivative is taken from the layer output (`Y > 0`), so backward needs only
//!   the cached outputs, never the pre-activations.
//! - Weight and bias gradients are accumulated (`+=`), so several batches or several uses of
//!   a layer sum up; the caller zeroes them before a step.
//!
//! Modules:
//! - [`scalar`]: the float trait the `cpu` code is generic over (the crate `Scalar` + sin/cos).
//! - [`linear`]: the `cpu` layer forward and backward on `gemm`.
//! - [`init`]: the seeded PRNG and PyTorch-default initialisation.
//! - [`encoding`]: NeRF positional encoding, forward and backward.
//! - [`adam`]: Adam with parameter groups and learning-rate schedules.
//! - [`gpu`]: the WGSL kernels (`shaders/nn_*.wgsl`) for all of the above: f32, and where
//!   the adapter has tensor cores and [`Precision::Mixed`] asks for them, dense-layer
//!   products with f16 operands and f32 accumulation.

pub mod adam;
pub mod encoding;
pub mod gpu;
pub mod init;
pub mod linear;
pub mod scalar;

pub use adam::{Adam, AdamConfig, AdamState, LrSchedule, ParamGroup};
pub use encoding::{PositionalEncoding, positional_encoding_backward, positional_encoding_forward};
pub use init::{Rng, kaiming_uniform, uniform_fill};
pub use linear::{Activation, InputPart, LinearShape, linear_backward, linear_forward};
pub use scalar::NnScalar;

/// The `precision:` setting of the train and eval configs: how the dense layers' matrix
/// products run on the `gpu` backend (`cpu` ignores it and always runs f32). Spelled `f32`
/// or `mixed`; resolved once, when the networks' gpu kernels are made
/// ([`gpu::NnGpu::for_context`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// f32 operands and accumulation everywhere (`nn_matmul.wgsl`): the reference.
    F32,
    /// f16 operands with f32 accumulation on tensor cores where the adapter has them
    /// (`nn_matmul_coop.wgsl`), else f32. Parameters, their gradients' accumulation
    /// buffers and the Adam state stay f32 either way.
    #[default]
    Mixed,
}

impl std::fmt::Display for Precision {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        formatter.write_str(match self {
            Self::F32 => "f32",
            Self::Mixed => "mixed",
        })
    }
}

/// Errors of the dense-network operations: every one names the operand it is about.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NnError {
    /// A buffer does not have the length its shape implies.
    #[error("{operand}: expected {expected} elements, got {actual}")]
    Length {
        /// Which operand (e.g. `"layer 2 weight"`).
        operand: String,
        /// The length the shape implies.
        expected: usize,
        /// The length that was passed.
        actual: usize,
    },
    /// A shape is inconsistent with itself or with another operand.
    #[error("{operand}: {message}")]
    Shape {
        /// Which operand.
        operand: String,
        /// What is wrong.
        message: String,
    },
    /// A hyper-parameter is out of its valid range.
    #[error("{field}: {message}")]
    Config {
        /// Which field (e.g. `"adam.beta1"`).
        field: String,
        /// What is wrong.
        message: String,
    },
    /// The GPU device cannot hold or address an operand.
    #[error("gpu: {0}")]
    Gpu(String),
}

/// Checks that `data` has `expected` elements, naming `operand` otherwise.
pub(crate) fn check_len(operand: &str, expected: usize, actual: usize) -> Result<(), NnError> {
    if expected == actual {
        Ok(())
    } else {
        Err(NnError::Length {
            operand: operand.to_owned(),
            expected,
            actual,
        })
    }
}
