//! The floating-point scalar trait (`f32`, `f64`) that generic numeric code is written against.
//!
//! Production runs in `f32`; gradient checks run the very same code in `f64` so that central
//! finite differences are accurate. The trait is deliberately small: arithmetic, the handful
//! of elementary functions the operations need, and conversions through `f64`.

use std::fmt::{Debug, Display};
use std::iter::Sum;
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Sub, SubAssign};

use seqavatar_core::matmul::MatmulScalar;

/// A real floating-point number: `f32` or `f64` (both multiply through
/// `seqavatar_core::matmul`).
pub trait Scalar:
    Copy
    + MatmulScalar
    + Send
    + Sync
    + Default
    + Debug
    + Display
    + PartialEq
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + DivAssign
    + Sum
    + 'static
{
    const ZERO: Self;
    const ONE: Self;
    const MAX: Self;
    const EPSILON: Self;

    /// Nearest representable value (rounds when narrowing to `f32`).
    fn from_f64(value: f64) -> Self;
    fn to_f64(self) -> f64;
    /// Exact conversion of a small integer (pixel coordinates, counts).
    fn from_u32(value: u32) -> Self {
        Self::from_f64(f64::from(value))
    }
    fn exp(self) -> Self;
    fn ln(self) -> Self;
    fn sqrt(self) -> Self;
    fn abs(self) -> Self;
    fn ceil(self) -> Self;
    fn floor(self) -> Self;
    /// IEEE `maxNum`: a NaN argument loses to a number.
    fn max(self, other: Self) -> Self;
    /// IEEE `minNum`: a NaN argument loses to a number.
    fn min(self, other: Self) -> Self;
    /// `max(lo, min(hi, self))`; `lo <= hi` is the caller's responsibility.
    fn clamp(self, lo: Self, hi: Self) -> Self {
        self.min(hi).max(lo)
    }
    fn is_finite(self) -> bool;
    fn is_nan(self) -> bool;
    /// The value rounded to `f32` (for sort keys shared with the `f32` GPU backend).
    fn to_f32(self) -> f32 {
        self.to_f64() as f32
    }
}

macro_rules! impl_scalar {
    (@delegate $t:ty: $($name:ident),+ -> $out:ty) => {$(
        #[inline(always)]
        fn $name(self) -> $out {
            <$t>::$name(self)
        }
    )+};
    ($t:ty) => {
        impl Scalar for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            const MAX: Self = <$t>::MAX;
            const EPSILON: Self = <$t>::EPSILON;

            #[inline(always)]
            fn from_f64(value: f64) -> Self {
                value as $t
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                f64::from(self)
            }
            impl_scalar!(@delegate $t: exp, ln, sqrt, abs, ceil, floor -> Self);
            impl_scalar!(@delegate $t: is_finite, is_nan -> bool);
            #[inline(always)]
            fn max(self, other: Self) -> Self {
                <$t>::max(self, other)
            }
            #[inline(always)]
            fn min(self, other: Self) -> Self {
                <$t>::min(self, other)
            }
        }
    };
}

impl_scalar!(f32);
impl_scalar!(f64);

#[cfg(test)]
mod tests {
    use super::*;

    fn generic_round_trip<S: Scalar>(x: f64) -> f64 {
        let s = S::from_f64(x);
        (s * S::ONE + S::ZERO).sqrt().ln().exp().to_f64()
    }

    #[test]
    fn both_precisions_agree_on_elementary_functions() {
        let x = 2.75;
        assert!((generic_round_trip::<f64>(x) - x.sqrt()).abs() < 1e-14);
        assert!((generic_round_trip::<f32>(x) - x.sqrt()).abs() < 1e-6);
        assert_eq!(f32::from_u32(16_777_216), 16_777_216.0);
    }

    #[test]
    fn min_max_ignore_nan_and_clamp_orders_bounds() {
        assert_eq!(Scalar::max(f32::NAN, 1.0), 1.0);
        assert_eq!(Scalar::min(2.0_f64, f64::NAN), 2.0);
        assert_eq!(Scalar::clamp(5.0_f64, -1.0, 1.0), 1.0);
        assert_eq!(Scalar::clamp(-5.0_f32, -1.0, 1.0), -1.0);
        assert!(!Scalar::is_finite(f32::INFINITY));
        assert!(Scalar::is_nan(f64::NAN));
    }
}
