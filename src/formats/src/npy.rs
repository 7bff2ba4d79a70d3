//! The numpy `.npy` format (versions 1 to 3): numeric arrays, and object arrays, whose data
//! is a pickle read by the safe [`super::pickle`] reader.

use super::dtype::{DType, Kind};
use super::pickle::{self, ArrayError, PickleError, checked_product, numeric_array};
use super::value::{ArrayData, Value};
use super::{BadLimit, Budget, Limits, MAX_ARRAY_BYTES_VAR, MAX_FILE_BYTES_VAR, OverBudget};

/// Why an `.npy` byte string was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NpyError {
    #[error("not an .npy file (the magic string \\x93NUMPY is missing)")]
    NotNpy,
    #[error("unsupported .npy format version {major}.{minor}")]
    UnsupportedVersion { major: u8, minor: u8 },
    #[error("truncated .npy file: {0}")]
    Truncated(String),
    #[error("bad .npy header: {0}")]
    BadHeader(String),
    #[error("unsupported .npy data type: {0}")]
    Dtype(String),
    #[error("object array data: {0}")]
    Pickle(#[from] PickleError),
    #[error("{0}")]
    TooLarge(OverBudget),
    #[error("object array pickle holds {found}, but the header says shape {shape:?}")]
    ObjectMismatch { found: String, shape: Vec<usize> },
    #[error(
        "the header declares shape {shape:?} of {dtype}, {bytes} bytes decoded: over the \
         {limit}-byte limit (raise the limit per array with {MAX_ARRAY_BYTES_VAR}, per file \
         with {MAX_FILE_BYTES_VAR})"
    )]
    ArrayTooLarge {
        shape: Vec<usize>,
        dtype: String,
        bytes: usize,
        limit: usize,
    },
    #[error(transparent)]
    Limit(#[from] BadLimit),
}

/// The parsed header of an `.npy` file.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyHeader {
    pub dtype: DType,
    pub fortran_order: bool,
    pub shape: Vec<usize>,
    /// Byte offset of the data.
    pub data_offset: usize,
}

/// Reads an `.npy` file's bytes: a numeric array as [`Value::Array`], an object array as the
/// array the pickle holds (use [`Value::unwrap_object_scalar`] for `np.save` of a dict).
/// The declared array must fit the [`Limits::from_env`] (see [`super`]).
pub fn read(bytes: &[u8]) -> Result<Value, NpyError> {
    read_with(bytes, &Limits::from_env()?)
}

/// [`read`] within explicit limits.
pub fn read_with(bytes: &[u8], limits: &Limits) -> Result<Value, NpyError> {
    let header = read_header(bytes)?;
    let mut file = Budget::with_limit(limits.max_file_bytes);
    decode_within(bytes, &header, limits, &mut file)
}

/// The bytes a numeric array of this header takes in the file after the header, and in
/// memory once decoded (twice for a Fortran-order reorder, which copies); `None` for object
/// arrays, whose pickle has no declared size.
pub fn declared_sizes(header: &NpyHeader) -> Result<Option<(usize, usize)>, NpyError> {
    if header.dtype.kind == Kind::Object {
        return Ok(None);
    }
    let overflow = || NpyError::BadHeader(format!("shape {:?} overflows", header.shape));
    let count = checked_product(&header.shape).ok_or_else(overflow)?;
    let stored = count
        .checked_mul(header.dtype.itemsize)
        .ok_or_else(overflow)?;
    let copies = if header.fortran_order && header.shape.len() > 1 {
        2
    } else {
        1
    };
    let decoded = header
        .dtype
        .decoded_bytes(count)
        .and_then(|n| n.checked_mul(copies))
        .ok_or_else(overflow)?;
    Ok(Some((stored, decoded)))
}

/// Refuses a header whose declared array exceeds the per-array limit or what is left of
/// the per-file limit (`file_left`).
pub fn check_declared(
    header: &NpyHeader,
    limits: &Limits,
    file_left: usize,
) -> Result<(), NpyError> {
    if let Some((_, decoded)) = declared_sizes(header)? {
        let limit = limits.max_array_bytes.min(file_left);
        if decoded > limit {
            return Err(NpyError::ArrayTooLarge {
                shape: header.shape.clone(),
                dtype: header.dtype.descr(),
                bytes: decoded,
                limit,
            });
        }
    }
    Ok(())
}

/// Decodes the array of `bytes` (a whole `.npy`, whose `header` was read) within the
/// per-array limit, charging its decoded values to `file` (an `.npz` archive shares one
/// among its members) before they are allocated.
pub fn decode_within(
    bytes: &[u8],
    header: &NpyHeader,
    limits: &Limits,
    file: &mut Budget,
) -> Result<Value, NpyError> {
    check_declared(header, limits, file.left())?;
    let data = &bytes[header.data_offset..];
    let Some((needed, _)) = declared_sizes(header)? else {
        // An object array: a pickle, whose values may expand (see `super`).
        let limit = super::decode_budget(data.len())
            .min(limits.max_array_bytes)
            .min(file.left());
        let mut budget = Budget::with_limit(limit);
        let (value, _) = pickle::load_prefix_within(data, &mut budget)?;
        file.charge(limit - budget.left())
            .map_err(NpyError::TooLarge)?;
        let matches = match &value {
            Value::Array(a) => a.shape == header.shape && matches!(a.data, ArrayData::Object(_)),
            _ => false,
        };
        if !matches {
            return Err(NpyError::ObjectMismatch {
                found: value.to_string(),
                shape: header.shape.clone(),
            });
        }
        return Ok(value);
    };
    if data.len() < needed {
        return Err(NpyError::Truncated(format!(
            "shape {:?} of {} needs {} data bytes, the file has {}",
            header.shape,
            header.dtype.descr(),
            needed,
            data.len()
        )));
    }
    let array = numeric_array(
        &header.dtype,
        header.shape.clone(),
        header.fortran_order,
        &data[..needed],
        file,
    )
    .map_err(|e| match e {
        ArrayError::Invalid(message) => NpyError::Dtype(message),
        ArrayError::OverBudget(e) => NpyError::TooLarge(e),
    })?;
    Ok(Value::Array(array))
}

/// Parses the magic string, version and header dictionary.
pub fn read_header(bytes: &[u8]) -> Result<NpyHeader, NpyError> {
    if bytes.len() < 8 || &bytes[..6] != b"\x93NUMPY" {
        return Err(NpyError::NotNpy);
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (header_len, start) = match major {
        1 => {
            let b = bytes
                .get(8..10)
                .ok_or_else(|| NpyError::Truncated("header length".into()))?;
            (usize::from(u16::from_le_bytes([b[0], b[1]])), 10usize)
        }
        2 | 3 => {
            let b = bytes
                .get(8..12)
                .ok_or_else(|| NpyError::Truncated("header length".into()))?;
            let n = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            (
                usize::try_from(n).map_err(|_| NpyError::Truncated("header".into()))?,
                12,
            )
        }
        _ => return Err(NpyError::UnsupportedVersion { major, minor }),
    };
    let end = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| {
            NpyError::Truncated(format!(
                "the header is {header_len} bytes, the file has {}",
                bytes.len() - start
            ))
        })?;
    let raw = &bytes[start..end];
    let text: String = if major == 3 {
        std::str::from_utf8(raw)
            .map_err(|_| NpyError::BadHeader("header is not UTF-8".into()))?
            .to_owned()
    } else {
        raw.iter().map(|&b| char::from(b)).collect()
    };
    let literal = Literal::parse(&text).map_err(NpyError::BadHeader)?;
    let Literal::Dict(entries) = literal else {
        return Err(NpyError::BadHeader("the header is not a dict".into()));
    };
    let field = |name: &str| {
        entries
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v)
            .ok_or_else(|| NpyError::BadHeader(format!("missing key '{name}'")))
    };
    let dtype = match field("descr")? {
        Literal::Str(s) => DType::parse(s).map_err(NpyError::Dtype)?,
        _ => {
            return Err(NpyError::Dtype(
                "structured dtypes (a list descr) are not supported".into(),
            ));
        }
    };
    let fortran_order = match field("fortran_order")? {
        Literal::Bool(b) => *b,
        _ => return Err(NpyError::BadHeader("'fortran_order' is not a bool".into())),
    };
    let shape = match field("shape")? {
        Literal::Tuple(items) => items
            .iter()
            .map(|item| match item {
                Literal::Int(n) => usize::try_from(*n)
                    .map_err(|_| NpyError::BadHeader(format!("negative dimension {n}"))),
                _ => Err(NpyError::BadHeader("'shape' holds a non-integer".into())),
            })
            .collect::<Result<Vec<_>, _>>()?,
        _ => return Err(NpyError::BadHeader("'shape' is not a tuple".into())),
    };
    Ok(NpyHeader {
        dtype,
        fortran_order,
        shape,
        data_offset: end,
    })
}

/// The Python literals an `.npy` header uses.
#[derive(Debug, PartialEq)]
enum Literal {
    Str(String),
    Int(i64),
    Bool(bool),
    None,
    Tuple(Vec<Literal>),
    List(Vec<Literal>),
    Dict(Vec<(String, Literal)>),
}

impl Literal {
    fn parse(text: &str) -> Result<Literal, String> {
        let mut parser = LiteralParser {
            chars: text.as_bytes(),
            pos: 0,
            depth: 0,
        };
        let value = parser.value()?;
        parser.skip_space();
        if parser.pos != parser.chars.len() {
            return Err(format!("unexpected text after the dict at {}", parser.pos));
        }
        Ok(value)
    }
}

struct LiteralParser<'a> {
    chars: &'a [u8],
    pos: usize,
    depth: usize,
}

impl LiteralParser<'_> {
    fn skip_space(&mut self) {
        while self.pos < self.chars.len() && self.chars[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_space();
        self.chars.get(self.pos).copied()
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.peek() == Some(c) {
            self.pos += 1;
            Ok(())
        } else {
            Err(format!("expected '{}' at {}", char::from(c), self.pos))
        }
    }

    fn value(&mut self) -> Result<Literal, String> {
        self.depth += 1;
        if self.depth > 32 {
            return Err("header literal nests too deeply".into());
        }
        let value = match self.peek().ok_or("unexpected end of header")? {
            b'{' => {
                self.pos += 1;
                let mut entries = Vec::new();
                while self.peek() != Some(b'}') {
                    let Literal::Str(key) = self.value()? else {
                        return Err("dict keys must be strings".into());
                    };
                    self.expect(b':')?;
                    entries.push((key, self.value()?));
                    if self.peek() == Some(b',') {
                        self.pos += 1;
                    } else {
                        break;
                    }
                }
                self.expect(b'}')?;
                Literal::Dict(entries)
            }
            open @ (b'(' | b'[') => {
                self.pos += 1;
                let close = if open == b'(' { b')' } else { b']' };
                let mut items = Vec::new();
                while self.peek() != Some(close) {
                    items.push(self.value()?);
                    if self.peek() == Some(b',') {
                        self.pos += 1;
                    } else {
                        break;
                    }
                }
                self.expect(close)?;
                if open == b'(' {
                    Literal::Tuple(items)
                } else {
                    Literal::List(items)
                }
            }
            quote @ (b'\'' | b'"') => {
                self.pos += 1;
                let start = self.pos;
                while self.pos < self.chars.len() && self.chars[self.pos] != quote {
                    if self.chars[self.pos] == b'\\' {
                        return Err("escapes in header strings are not supported".into());
                    }
                    self.pos += 1;
                }
                if self.pos >= self.chars.len() {
                    return Err("unterminated string in header".into());
                }
                let s = String::from_utf8_lossy(&self.chars[start..self.pos]).into_owned();
                self.pos += 1;
                Literal::Str(s)
            }
            _ => {
                let start = self.pos;
                while self.pos < self.chars.len()
                    && (self.chars[self.pos].is_ascii_alphanumeric()
                        || matches!(self.chars[self.pos], b'-' | b'_' | b'+'))
                {
                    self.pos += 1;
                }
                let word = std::str::from_utf8(&self.chars[start..self.pos])
                    .map_err(|_| "bad header text")?;
                match word {
                    "True" => Literal::Bool(true),
                    "False" => Literal::Bool(false),
                    "None" => Literal::None,
                    // numpy writes `3L` in headers made by Python 2.
                    w => Literal::Int(
                        w.trim_end_matches('L')
                            .parse()
                            .map_err(|_| format!("unexpected {w:?} at {start}"))?,
                    ),
                }
            }
        };
        self.depth -= 1;
        Ok(value)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::value::NpArray;

    fn npy(header: &str, data: &[u8]) -> Vec<u8> {
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend((header.len() as u16).to_le_bytes());
        out.extend(header.as_bytes());
        out.extend(data);
        out
    }

    #[test]
    fn reads_a_handmade_array() {
        let data: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let bytes = npy(
            "{'descr': '<f4', 'fortran_order': True, 'shape': (2, 3), }",
            &data,
        );
        let v = read(&bytes).unwrap();
        assert_eq!(
            v,
            Value::Array(NpArray {
                dtype: "<f4".into(),
                shape: vec![2, 3],
                data: ArrayData::F32(vec![1.0, 3.0, 5.0, 2.0, 4.0, 6.0]),
            })
        );
    }

    #[test]
    fn header_errors_are_specific() {
        assert_eq!(read(b"hello"), Err(NpyError::NotNpy));
        let short = npy(
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4,), }",
            &[0; 8],
        );
        assert!(matches!(read(&short), Err(NpyError::Truncated(_))));
        let huge = npy(
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4611686018427387904, 4), }",
            &[],
        );
        assert!(matches!(read(&huge), Err(NpyError::BadHeader(_))));
        let structured = npy(
            "{'descr': [('a', '<f8')], 'fortran_order': False, 'shape': (1,), }",
            &[0; 8],
        );
        assert!(matches!(read(&structured), Err(NpyError::Dtype(_))));
        let no_shape = npy("{'descr': '<f8', 'fortran_order': False}", &[]);
        assert_eq!(
            read(&no_shape),
            Err(NpyError::BadHeader("missing key 'shape'".into()))
        );
    }

    #[test]
    fn literal_parser_handles_python_spellings() {
        assert_eq!(
            Literal::parse("{'a': (), \"b\": (3,), 'c': (2L, 1), 'd': None}").unwrap(),
            Literal::Dict(vec![
                ("a".into(), Literal::Tuple(vec![])),
                ("b".into(), Literal::Tuple(vec![Literal::Int(3)])),
                (
                    "c".into(),
                    Literal::Tuple(vec![Literal::Int(2), Literal::Int(1)])
                ),
                ("d".into(), Literal::None),
            ])
        );
        assert!(Literal::parse("{'a': (1, 2}").is_err());
        assert!(Literal::parse(&"(".repeat(100)).is_err());
    }
}
