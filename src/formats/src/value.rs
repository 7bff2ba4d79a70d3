//! Values decoded from Python pickles and numpy files: a small owned tree of dicts, lists,
//! scalars and numpy arrays, plus typed accessors that the dataset readers use.

use std::fmt;

/// A Python value as far as the dataset files need: everything else is rejected at decode time.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<Value>),
    Tuple(Vec<Value>),
    /// A `dict` or `OrderedDict`, in insertion order.
    Dict(Vec<(Value, Value)>),
    Set(Vec<Value>),
    Array(NpArray),
}

/// A numpy array in C (row-major) order. Fortran-ordered and big-endian inputs are converted
/// on load, so `data` is always the logical element sequence.
#[derive(Clone, Debug, PartialEq)]
pub struct NpArray {
    /// The numpy type string the array was stored with, e.g. `<f8`, for messages.
    pub dtype: String,
    pub shape: Vec<usize>,
    pub data: ArrayData,
}

/// Element storage. Integer kinds up to 32 bits and `int64` widen to `i64`; `float16` widens
/// to `f32`.
#[derive(Clone, Debug, PartialEq)]
pub enum ArrayData {
    Bool(Vec<bool>),
    U8(Vec<u8>),
    I64(Vec<i64>),
    U64(Vec<u64>),
    F32(Vec<f32>),
    F64(Vec<f64>),
    /// Fixed-width unicode (`<U..`), trailing NULs removed.
    Str(Vec<String>),
    /// Fixed-width bytes (`|S..`), trailing NULs removed.
    Bytes(Vec<Vec<u8>>),
    /// Object arrays (`|O`): each element is any pickled value.
    Object(Vec<Value>),
}

impl ArrayData {
    pub fn len(&self) -> usize {
        match self {
            ArrayData::Bool(v) => v.len(),
            ArrayData::U8(v) => v.len(),
            ArrayData::I64(v) => v.len(),
            ArrayData::U64(v) => v.len(),
            ArrayData::F32(v) => v.len(),
            ArrayData::F64(v) => v.len(),
            ArrayData::Str(v) => v.len(),
            ArrayData::Bytes(v) => v.len(),
            ArrayData::Object(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes the elements occupy (vector storage, and each string's header and text), what
    /// a copy allocates; object elements count their `Value` headers only.
    pub fn footprint(&self) -> usize {
        use std::mem::size_of;
        match self {
            ArrayData::Bool(v) => v.len(),
            ArrayData::U8(v) => v.len(),
            ArrayData::I64(v) => 8 * v.len(),
            ArrayData::U64(v) => 8 * v.len(),
            ArrayData::F32(v) => 4 * v.len(),
            ArrayData::F64(v) => 8 * v.len(),
            ArrayData::Str(v) => v.iter().map(|s| size_of::<String>() + s.len()).sum(),
            ArrayData::Bytes(v) => v.iter().map(|b| size_of::<Vec<u8>>() + b.len()).sum(),
            ArrayData::Object(v) => size_of::<Value>() * v.len(),
        }
    }

    /// Elements as `f64` when the kind is numeric or boolean.
    pub fn to_f64(&self) -> Option<Vec<f64>> {
        Some(match self {
            ArrayData::Bool(v) => v.iter().map(|&b| f64::from(u8::from(b))).collect(),
            ArrayData::U8(v) => v.iter().map(|&x| f64::from(x)).collect(),
            ArrayData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::U64(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::F32(v) => v.iter().map(|&x| f64::from(x)).collect(),
            ArrayData::F64(v) => v.clone(),
            ArrayData::Str(_) | ArrayData::Bytes(_) | ArrayData::Object(_) => return None,
        })
    }
}

impl NpArray {
    /// Number of elements (the product of the shape).
    pub fn len(&self) -> usize {
        self.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

impl Value {
    /// The Python-side name of this value's type, for error messages.
    pub fn type_name(&self) -> &'static str {
        match self {
            Value::None => "None",
            Value::Bool(_) => "bool",
            Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Bytes(_) => "bytes",
            Value::List(_) => "list",
            Value::Tuple(_) => "tuple",
            Value::Dict(_) => "dict",
            Value::Set(_) => "set",
            Value::Array(_) => "ndarray",
        }
    }

    /// The items of a dict.
    pub fn as_dict(&self) -> Option<&[(Value, Value)]> {
        match self {
            Value::Dict(items) => Some(items),
            _ => None,
        }
    }

    /// The items of a list or a tuple, or of a one-dimensional object array.
    pub fn as_sequence(&self) -> Option<&[Value]> {
        match self {
            Value::List(items) | Value::Tuple(items) => Some(items),
            Value::Array(NpArray {
                shape,
                data: ArrayData::Object(items),
                ..
            }) if shape.len() == 1 => Some(items),
            _ => None,
        }
    }

    pub fn as_str(&self) -> Option<&str> {
        match self {
            Value::Str(s) => Some(s),
            _ => None,
        }
    }

    /// Looks a string key up in a dict (keys stored as `bytes` match too, as Python 2 writes
    /// them).
    pub fn get(&self, key: &str) -> Option<&Value> {
        self.as_dict()?.iter().find_map(|(k, v)| match k {
            Value::Str(s) if s == key => Some(v),
            Value::Bytes(b) if b == key.as_bytes() => Some(v),
            _ => None,
        })
    }

    /// `np.save` of a dict stores a zero-dimensional object array holding the dict: this
    /// returns the held value for such arrays and the value itself otherwise.
    pub fn unwrap_object_scalar(&self) -> &Value {
        match self {
            Value::Array(NpArray {
                shape,
                data: ArrayData::Object(items),
                ..
            }) if shape.is_empty() && items.len() == 1 => &items[0],
            other => other,
        }
    }

    /// A numeric value as a flat `f64` array with its shape: numpy arrays, Python numbers
    /// (shape `[]`) and rectangular nested lists/tuples of numbers. `None` otherwise.
    pub fn to_f64_array(&self) -> Option<(Vec<usize>, Vec<f64>)> {
        match self {
            Value::Array(a) => Some((a.shape.clone(), a.data.to_f64()?)),
            Value::Int(i) => Some((vec![], vec![*i as f64])),
            Value::Float(f) => Some((vec![], vec![*f])),
            Value::Bool(b) => Some((vec![], vec![f64::from(u8::from(*b))])),
            Value::List(items) | Value::Tuple(items) => {
                let mut inner_shape: Option<Vec<usize>> = None;
                let mut data = Vec::new();
                for item in items {
                    let (shape, values) = item.to_f64_array()?;
                    match &inner_shape {
                        None => inner_shape = Some(shape),
                        Some(s) if *s == shape => {}
                        Some(_) => return None,
                    }
                    data.extend(values);
                }
                let mut shape = vec![items.len()];
                shape.extend(inner_shape.unwrap_or_default());
                Some((shape, data))
            }
            _ => None,
        }
    }
}

impl fmt::Display for Value {
    /// A short description for error messages (never the full contents).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Value::Array(a) => write!(f, "ndarray(dtype {}, shape {:?})", a.dtype, a.shape),
            Value::Str(s) if s.len() <= 40 => write!(f, "str {s:?}"),
            Value::Int(i) => write!(f, "int {i}"),
            Value::Float(x) => write!(f, "float {x}"),
            Value::List(v) | Value::Tuple(v) | Value::Set(v) => {
                write!(f, "{} of {} items", self.type_name(), v.len())
            }
            Value::Dict(v) => write!(f, "dict of {} items", v.len()),
            other => f.write_str(other.type_name()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nested_lists_become_arrays_and_ragged_lists_do_not() {
        let v = Value::List(vec![
            Value::Tuple(vec![Value::Int(1), Value::Float(2.5)]),
            Value::List(vec![Value::Bool(true), Value::Int(-4)]),
        ]);
        assert_eq!(
            v.to_f64_array(),
            Some((vec![2, 2], vec![1.0, 2.5, 1.0, -4.0]))
        );
        let ragged = Value::List(vec![Value::List(vec![Value::Int(1)]), Value::Int(2)]);
        assert_eq!(ragged.to_f64_array(), None);
        assert_eq!(Value::List(vec![]).to_f64_array(), Some((vec![0], vec![])));
    }

    #[test]
    fn dict_lookup_accepts_python2_byte_keys() {
        let d = Value::Dict(vec![
            (Value::Bytes(b"K".to_vec()), Value::Int(1)),
            (Value::Str("R".into()), Value::Int(2)),
        ]);
        assert_eq!(d.get("K"), Some(&Value::Int(1)));
        assert_eq!(d.get("R"), Some(&Value::Int(2)));
        assert_eq!(d.get("T"), None);
        assert_eq!(Value::Int(3).get("K"), None);
    }
}
