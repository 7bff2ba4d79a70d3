//! The float trait the `cpu` network code is generic over: the crate's [`Scalar`] plus the
//! trigonometric functions of the positional encoding.
//!
//! Only `f32` and `f64` implement it, which are also the float types `gemm` accepts.

use crate::scalar::Scalar;

/// A [`Scalar`] with sine and cosine: `f32` or `f64`.
pub trait NnScalar: Scalar {
    fn sin(self) -> Self;
    fn cos(self) -> Self;
}

macro_rules! impl_nn_scalar {
    ($($t:ty),+) => {$(
        impl NnScalar for $t {
            #[inline]
            fn sin(self) -> Self {
                <$t>::sin(self)
            }
            #[inline]
            fn cos(self) -> Self {
                <$t>::cos(self)
            }
        }
    )+};
}

impl_nn_scalar!(f32, f64);
