//! In-memory n-dimensional arrays and the element types the cache stores.

use zarrs::array::builder::ArrayBuilderFillValue;
use zarrs::array::{DataType, data_type};

mod sealed {
    pub trait Sealed {}
}

/// An element type storable in a cache array.
pub trait Element:
    zarrs::array::Element
    + zarrs::array::ElementOwned
    + Copy
    + Send
    + Sync
    + PartialEq
    + std::fmt::Debug
    + Default
    + 'static
    + sealed::Sealed
{
    /// The Zarr v3 data type name (`float32`, `uint8`, ...).
    const DTYPE: &'static str;
    /// The Zarr data type.
    fn zarr_data_type() -> DataType;
    /// The fill value used for chunks that were never written (zero).
    fn fill_value() -> ArrayBuilderFillValue;
    /// The value as `f64`, for statistics.
    fn to_f64(self) -> f64;
}

macro_rules! impl_element {
    ($type:ty, $name:literal, $constructor:ident) => {
        impl sealed::Sealed for $type {}
        impl Element for $type {
            const DTYPE: &'static str = $name;
            fn zarr_data_type() -> DataType {
                data_type::$constructor()
            }
            fn fill_value() -> ArrayBuilderFillValue {
                ArrayBuilderFillValue::from(<$type>::default())
            }
            fn to_f64(self) -> f64 {
                self as f64
            }
        }
    };
}

impl_element!(u8, "uint8", uint8);
impl_element!(u16, "uint16", uint16);
impl_element!(u32, "uint32", uint32);
impl_element!(u64, "uint64", uint64);
impl_element!(i32, "int32", int32);
impl_element!(i64, "int64", int64);
impl_element!(f32, "float32", float32);
impl_element!(f64, "float64", float64);

/// A row-major (C order) n-dimensional array.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray<T> {
    pub shape: Vec<usize>,
    pub data: Vec<T>,
}

impl<T> NdArray<T> {
    /// An array of `shape` holding `data` in row-major order; the length must match.
    pub fn new(shape: Vec<usize>, data: Vec<T>) -> anyhow::Result<Self> {
        let expected = checked_product(&shape)
            .ok_or_else(|| anyhow::anyhow!("array shape {shape:?} overflows usize"))?;
        anyhow::ensure!(
            expected == data.len(),
            "array shape {shape:?} needs {expected} elements, got {}",
            data.len()
        );
        Ok(Self { shape, data })
    }

    pub fn len(&self) -> usize {
        self.data.len()
    }

    /// Whether the array has no elements.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// Row-major offset of `index`, or `None` when it has the wrong rank or is out of bounds.
    pub fn offset(&self, index: &[usize]) -> Option<usize> {
        if index.len() != self.shape.len() {
            return None;
        }
        let mut offset = 0usize;
        for (&position, &extent) in index.iter().zip(&self.shape) {
            if position >= extent {
                return None;
            }
            offset = offset * extent + position;
        }
        Some(offset)
    }

    /// The element at `index`, or `None` when out of bounds.
    pub fn get(&self, index: &[usize]) -> Option<&T> {
        self.offset(index).map(|offset| &self.data[offset])
    }
}

/// The product of `values`, or `None` on overflow.
pub(crate) fn checked_product(values: &[usize]) -> Option<usize> {
    values
        .iter()
        .try_fold(1usize, |product, &value| product.checked_mul(value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_are_row_major() {
        let array = NdArray::new(vec![2, 3, 4], (0..24).collect::<Vec<i32>>()).unwrap();
        assert_eq!(array.offset(&[1, 2, 3]), Some(23));
        assert_eq!(array.get(&[1, 0, 2]), Some(&14));
        assert_eq!(array.get(&[2, 0, 0]), None);
        assert_eq!(array.get(&[0, 0]), None);
    }

    #[test]
    fn length_must_match_shape() {
        let error = NdArray::new(vec![2, 2], vec![1u8, 2, 3]).unwrap_err();
        assert!(error.to_string().contains("needs 4 elements, got 3"));
        assert!(NdArray::new(vec![usize::MAX, 3], Vec::<u8>::new()).is_err());
        let empty = NdArray::new(vec![0, 5], Vec::<f32>::new()).unwrap();
        assert!(empty.is_empty());
    }
}
