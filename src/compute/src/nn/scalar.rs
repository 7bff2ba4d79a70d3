//! The float trait the `cpu` network code is generic over: the crate's [`Scalar`] plus the
//! trigonometric functions of the positional encoding.
//!
//! Only `f32` and `f64` implement it, which are also the float types `gemm` accepts.

use crate::scalar::Scalar;

/// A [`Scalar`] with sine and cosine: `f32` or `f64`.
pub trait NnScalar: Scalar {
    /// Sine.
    fn sin(self) -> Self;
    /// Cosine.
    fn cos(self) -> Self;
}

impl NnScalar for f32 {
    #[inline]
    fn sin(self) -> Self {
        f32::sin(self)
    }
    #[inline]
    fn cos(self) -> Self {
        f32::cos(self)
    }
}

impl NnScalar for f64 {
    #[inline]
    fn sin(self) -> Self {
        f64::sin(self)
    }
    #[inline]
    fn cos(self) -> Self {
        f64::cos(self)
    }
}
