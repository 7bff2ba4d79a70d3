//! A small, strict reader (and writer, for tests and fixtures) of the safetensors format.
//!
//! Layout: an 8-byte little-endian header length `n`, `n` bytes of UTF-8 JSON, then the raw
//! little-endian data. The JSON maps each tensor name to `{"dtype", "shape", "data_offsets":
//! [begin, end]}` (offsets relative to the start of the data); the optional `__metadata__`
//! key maps strings to strings. Untrusted files are validated completely before any tensor is
//! handed out: the header length, the JSON, every dtype, shape and offset pair, overflow of
//! `product(shape) * dtype size`, offsets inside the data and tensors that overlap. Every
//! error names the file and the tensor or field at fault.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The largest JSON header accepted (the format's own limit is 100 MB).
const MAX_HEADER_BYTES: u64 = 100 * 1024 * 1024;

/// Element types this reader understands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    U8,
    F16,
    BF16,
    F32,
    F64,
}

impl Dtype {
    fn parse(text: &str) -> Option<Self> {
        [Self::U8, Self::F16, Self::BF16, Self::F32, Self::F64]
            .into_iter()
            .find(|dtype| dtype.name() == text)
    }

    /// The name used in the header.
    pub fn name(self) -> &'static str {
        match self {
            Self::U8 => "U8",
            Self::F16 => "F16",
            Self::BF16 => "BF16",
            Self::F32 => "F32",
            Self::F64 => "F64",
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Self::U8 => 1,
            Self::F16 | Self::BF16 => 2,
            Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

/// Why a safetensors file could not be read; every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum SafetensorsError {
    // The cause is in the message, so it is not also a `source` (chains would repeat it).
    #[error("{path}: cannot read: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{path}: not a safetensors file: {message}")]
    Header { path: PathBuf, message: String },
    #[error("{path}: tensor {tensor:?}: {message}")]
    Tensor {
        path: PathBuf,
        tensor: String,
        message: String,
    },
    #[error("{path}: no tensor named {tensor:?}")]
    Missing { path: PathBuf, tensor: String },
}

/// One tensor's description in the header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorInfo {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// Byte range inside the data section.
    pub begin: usize,
    pub end: usize,
}

/// A whole safetensors file held in memory, validated.
#[derive(Debug)]
pub struct SafetensorsFile {
    path: PathBuf,
    tensors: BTreeMap<String, TensorInfo>,
    metadata: BTreeMap<String, String>,
    data: Vec<u8>,
}

impl SafetensorsFile {
    /// Reads and validates `path`, a regular file (a device such as `/dev/zero` or a FIFO
    /// would never end or would block: refused from its metadata).
    pub fn read(path: &Path) -> Result<Self, SafetensorsError> {
        let io = |error| SafetensorsError::Io {
            path: path.to_owned(),
            error,
        };
        if !std::fs::metadata(path).map_err(io)?.is_file() {
            return Err(io(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "not a regular file (a device, FIFO, socket or folder): only regular files \
                 can be read",
            )));
        }
        let bytes = std::fs::read(path).map_err(io)?;
        Self::parse(path, bytes)
    }

    /// Validates the bytes of a file; `path` is only used in error messages.
    pub fn parse(path: &Path, mut bytes: Vec<u8>) -> Result<Self, SafetensorsError> {
        let header_error = |message: String| SafetensorsError::Header {
            path: path.to_owned(),
            message,
        };
        let Some(length_bytes) = bytes.get(..8) else {
            return Err(header_error(format!(
                "{} bytes, shorter than the 8-byte header length",
                bytes.len()
            )));
        };
        let header_len = u64::from_le_bytes(length_bytes.try_into().expect("8 bytes"));
        if header_len > MAX_HEADER_BYTES {
            return Err(header_error(format!(
                "header length {header_len} exceeds the limit of {MAX_HEADER_BYTES} bytes"
            )));
        }
        let header_end = 8 + header_len as usize;
        if header_end > bytes.len() {
            return Err(header_error(format!(
                "header length {header_len} runs past the end of the {}-byte file",
                bytes.len()
            )));
        }
        let header: serde_json::Value = serde_json::from_slice(&bytes[8..header_end])
            .map_err(|error| header_error(format!("header is not valid JSON: {error}")))?;
        let serde_json::Value::Object(entries) = header else {
            return Err(header_error("header is not a JSON object".to_owned()));
        };
        let data_len = bytes.len() - header_end;
        let mut tensors = BTreeMap::new();
        let mut metadata = BTreeMap::new();
        for (name, value) in entries {
            if name == "__metadata__" {
                let serde_json::Value::Object(pairs) = value else {
                    return Err(header_error("__metadata__ is not an object".to_owned()));
                };
                for (key, value) in pairs {
                    let serde_json::Value::String(text) = value else {
                        return Err(header_error(format!("__metadata__.{key} is not a string")));
                    };
                    metadata.insert(key, text);
                }
                continue;
            }
            let info = parse_tensor_info(&value, data_len).map_err(|message| {
                SafetensorsError::Tensor {
                    path: path.to_owned(),
                    tensor: name.clone(),
                    message,
                }
            })?;
            tensors.insert(name, info);
        }
        // Tensors must not overlap (the format also forbids holes, but a hole is harmless).
        let mut ranges: Vec<(&String, &TensorInfo)> = tensors.iter().collect();
        ranges.sort_by_key(|(_, info)| (info.begin, info.end));
        for pair in ranges.windows(2) {
            let ((first_name, first), (second_name, second)) = (pair[0], pair[1]);
            if second.begin < first.end {
                return Err(SafetensorsError::Tensor {
                    path: path.to_owned(),
                    tensor: (*second_name).clone(),
                    message: format!(
                        "data_offsets [{}, {}] overlap those of {first_name:?} [{}, {}]",
                        second.begin, second.end, first.begin, first.end
                    ),
                });
            }
        }
        bytes.drain(..header_end);
        Ok(Self {
            path: path.to_owned(),
            tensors,
            metadata,
            data: bytes,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Tensor names in sorted order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.tensors.keys().map(String::as_str)
    }

    pub fn info(&self, name: &str) -> Option<&TensorInfo> {
        self.tensors.get(name)
    }

    /// The `__metadata__` map.
    pub fn metadata(&self) -> &BTreeMap<String, String> {
        &self.metadata
    }

    fn require(&self, name: &str) -> Result<&TensorInfo, SafetensorsError> {
        self.tensors
            .get(name)
            .ok_or_else(|| SafetensorsError::Missing {
                path: self.path.clone(),
                tensor: name.to_owned(),
            })
    }

    fn tensor_error(&self, name: &str, message: String) -> SafetensorsError {
        SafetensorsError::Tensor {
            path: self.path.clone(),
            tensor: name.to_owned(),
            message,
        }
    }

    /// Tensor `name` as f32 values (from F16, BF16, F32 or F64) after checking its shape.
    /// F64 values beyond the f32 range are an error, not infinities.
    pub fn f32_tensor(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, SafetensorsError> {
        let info = self.require(name)?;
        if info.shape != shape {
            return Err(
                self.tensor_error(name, format!("shape {:?}, expected {shape:?}", info.shape))
            );
        }
        let raw = &self.data[info.begin..info.end];
        let values: Vec<f32> = match info.dtype {
            Dtype::F32 => raw
                .chunks_exact(4)
                .map(|chunk| f32::from_le_bytes(chunk.try_into().expect("4 bytes")))
                .collect(),
            Dtype::F64 => {
                let mut values = Vec::with_capacity(raw.len() / 8);
                for chunk in raw.chunks_exact(8) {
                    let value = f64::from_le_bytes(chunk.try_into().expect("8 bytes"));
                    if value.is_finite() && value.abs() > f64::from(f32::MAX) {
                        return Err(self
                            .tensor_error(name, format!("F64 value {value} does not fit in f32")));
                    }
                    values.push(value as f32);
                }
                values
            }
            Dtype::F16 => raw
                .chunks_exact(2)
                .map(|chunk| f16_to_f32(u16::from_le_bytes([chunk[0], chunk[1]])))
                .collect(),
            Dtype::BF16 => raw
                .chunks_exact(2)
                .map(|chunk| {
                    f32::from_bits(u32::from(u16::from_le_bytes([chunk[0], chunk[1]])) << 16)
                })
                .collect(),
            Dtype::U8 => {
                return Err(self.tensor_error(name, "dtype U8, expected a float dtype".to_owned()));
            }
        };
        if let Some(position) = values.iter().position(|value| !value.is_finite()) {
            return Err(self.tensor_error(
                name,
                format!("element {position} is not finite ({})", values[position]),
            ));
        }
        Ok(values)
    }

    /// Tensor `name` as f64 values (F32 or F64 only) with its shape, for fixtures.
    pub fn f64_tensor(&self, name: &str) -> Result<(Vec<f64>, Vec<usize>), SafetensorsError> {
        let info = self.require(name)?;
        let raw = &self.data[info.begin..info.end];
        let values = match info.dtype {
            Dtype::F64 => raw
                .chunks_exact(8)
                .map(|chunk| f64::from_le_bytes(chunk.try_into().expect("8 bytes")))
                .collect(),
            Dtype::F32 => raw
                .chunks_exact(4)
                .map(|chunk| f64::from(f32::from_le_bytes(chunk.try_into().expect("4 bytes"))))
                .collect(),
            other => {
                return Err(
                    self.tensor_error(name, format!("dtype {}, expected F32 or F64", other.name()))
                );
            }
        };
        Ok((values, info.shape.clone()))
    }

    /// Tensor `name` as bytes (U8 only) with its shape.
    pub fn u8_tensor(&self, name: &str) -> Result<(&[u8], Vec<usize>), SafetensorsError> {
        let info = self.require(name)?;
        if info.dtype != Dtype::U8 {
            return Err(
                self.tensor_error(name, format!("dtype {}, expected U8", info.dtype.name()))
            );
        }
        Ok((&self.data[info.begin..info.end], info.shape.clone()))
    }
}

fn parse_tensor_info(value: &serde_json::Value, data_len: usize) -> Result<TensorInfo, String> {
    let object = value.as_object().ok_or("entry is not a JSON object")?;
    let dtype_text = object
        .get("dtype")
        .and_then(|dtype| dtype.as_str())
        .ok_or("field dtype is missing or not a string")?;
    let dtype = Dtype::parse(dtype_text).ok_or_else(|| {
        format!("field dtype: unsupported {dtype_text:?} (expected U8, F16, BF16, F32 or F64)")
    })?;
    let shape_values = object
        .get("shape")
        .and_then(|shape| shape.as_array())
        .ok_or("field shape is missing or not an array")?;
    let mut shape = Vec::with_capacity(shape_values.len());
    for extent in shape_values {
        let extent = extent
            .as_u64()
            .and_then(|extent| usize::try_from(extent).ok())
            .ok_or_else(|| format!("field shape: {extent} is not a non-negative integer"))?;
        shape.push(extent);
    }
    let offsets = object
        .get("data_offsets")
        .and_then(|offsets| offsets.as_array())
        .filter(|offsets| offsets.len() == 2)
        .ok_or("field data_offsets is missing or not a pair")?;
    let offset = |index: usize| {
        offsets[index]
            .as_u64()
            .and_then(|offset| usize::try_from(offset).ok())
            .ok_or_else(|| {
                format!(
                    "field data_offsets: {} is not a non-negative integer",
                    offsets[index]
                )
            })
    };
    let (begin, end) = (offset(0)?, offset(1)?);
    if begin > end || end > data_len {
        return Err(format!(
            "field data_offsets [{begin}, {end}] is not a range inside the {data_len}-byte data"
        ));
    }
    let bytes = shape
        .iter()
        .try_fold(dtype.size(), |bytes, &extent| bytes.checked_mul(extent))
        .ok_or("field shape: element count overflows")?;
    if bytes != end - begin {
        return Err(format!(
            "shape {shape:?} of {} needs {bytes} bytes but data_offsets span {}",
            dtype.name(),
            end - begin
        ));
    }
    Ok(TensorInfo {
        dtype,
        shape,
        begin,
        end,
    })
}

/// IEEE binary16 to f32 (exact: every f16 is an f32).
fn f16_to_f32(bits: u16) -> f32 {
    let sign = u32::from(bits >> 15) << 31;
    let exponent = u32::from((bits >> 10) & 0x1f);
    let mantissa = u32::from(bits & 0x3ff);
    let magnitude = match (exponent, mantissa) {
        (0, 0) => 0,
        // Subnormal: mantissa * 2^-24, exact in f32.
        (0, _) => {
            let value = mantissa as f32 * 2f32.powi(-24);
            return if sign != 0 { -value } else { value };
        }
        (0x1f, 0) => 0x7f80_0000,
        (0x1f, _) => 0x7fc0_0000 | (mantissa << 13),
        _ => ((exponent + 127 - 15) << 23) | (mantissa << 13),
    };
    f32::from_bits(sign | magnitude)
}

/// Writes tensors (name, dtype, shape, little-endian bytes) and metadata as a safetensors
/// file: the fixture scripts' counterpart, used by tests.
pub fn write(
    path: &Path,
    tensors: &[(&str, Dtype, &[usize], &[u8])],
    metadata: &BTreeMap<String, String>,
) -> std::io::Result<()> {
    let mut header = serde_json::Map::new();
    if !metadata.is_empty() {
        header.insert(
            "__metadata__".to_owned(),
            serde_json::to_value(metadata).map_err(std::io::Error::other)?,
        );
    }
    let mut data = Vec::new();
    for (name, dtype, shape, bytes) in tensors {
        let begin = data.len();
        data.extend_from_slice(bytes);
        header.insert(
            (*name).to_owned(),
            serde_json::json!({
                "dtype": dtype.name(),
                "shape": shape,
                "data_offsets": [begin, data.len()],
            }),
        );
    }
    let mut json =
        serde_json::to_vec(&serde_json::Value::Object(header)).map_err(std::io::Error::other)?;
    // Pad the header with spaces to 8 bytes so the data is aligned, as the reference writer does.
    while json.len() % 8 != 0 {
        json.push(b' ');
    }
    let mut file = Vec::with_capacity(8 + json.len() + data.len());
    file.extend_from_slice(&(json.len() as u64).to_le_bytes());
    file.extend_from_slice(&json);
    file.extend_from_slice(&data);
    std::fs::write(path, file)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f32_bytes(values: &[f32]) -> Vec<u8> {
        values
            .iter()
            .flat_map(|value| value.to_le_bytes())
            .collect()
    }

    fn file_bytes(header: &str, data: &[u8]) -> Vec<u8> {
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend_from_slice(header.as_bytes());
        bytes.extend_from_slice(data);
        bytes
    }

    fn parse_error(bytes: Vec<u8>) -> String {
        SafetensorsFile::parse(Path::new("w.safetensors"), bytes)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn round_trips_every_dtype() {
        let folder = tempfile::tempdir().unwrap();
        let path = folder.path().join("t.safetensors");
        let weights = [1.5_f32, -2.0, 0.25, 3.0e-3, 7.0, -0.0];
        let doubles: Vec<u8> = [1.0e-300_f64, 2.5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        // f16: 1.0 = 0x3c00, -2.0 = 0xc000, smallest subnormal 2^-24 = 0x0001, 65504 = 0x7bff.
        let halves: Vec<u8> = [0x3c00_u16, 0xc000, 0x0001, 0x7bff, 0x8001]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        // bf16 of 1.0 is 0x3f80, of -3.0 is 0xc040.
        let brains: Vec<u8> = [0x3f80_u16, 0xc040]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let mut metadata = BTreeMap::new();
        metadata.insert("seed".to_owned(), "7".to_owned());
        write(
            &path,
            &[
                ("w", Dtype::F32, &[2, 3], &f32_bytes(&weights)),
                ("d", Dtype::F64, &[2], &doubles),
                ("h", Dtype::F16, &[5], &halves),
                ("b", Dtype::BF16, &[2], &brains),
                ("u", Dtype::U8, &[3], &[1, 2, 255]),
            ],
            &metadata,
        )
        .unwrap();
        let file = SafetensorsFile::read(&path).unwrap();
        assert_eq!(file.names().collect::<Vec<_>>(), ["b", "d", "h", "u", "w"]);
        assert_eq!(file.metadata()["seed"], "7");
        assert_eq!(file.f32_tensor("w", &[2, 3]).unwrap(), weights);
        assert_eq!(
            file.f64_tensor("d").unwrap(),
            (vec![1.0e-300, 2.5], vec![2])
        );
        assert_eq!(
            file.f32_tensor("h", &[5]).unwrap(),
            [1.0, -2.0, 2f32.powi(-24), 65504.0, -(2f32.powi(-24))]
        );
        assert_eq!(file.f32_tensor("b", &[2]).unwrap(), [1.0, -3.0]);
        assert_eq!(file.u8_tensor("u").unwrap(), (&[1_u8, 2, 255][..], vec![3]));
        let error = file.f32_tensor("w", &[3, 2]).unwrap_err().to_string();
        assert!(
            error.contains("t.safetensors") && error.contains("\"w\"") && error.contains("[2, 3]"),
            "{error}"
        );
        let error = file.f32_tensor("missing", &[1]).unwrap_err().to_string();
        assert!(error.contains("no tensor named \"missing\""), "{error}");
        let error = file.f32_tensor("u", &[3]).unwrap_err().to_string();
        assert!(error.contains("U8"), "{error}");
    }

    #[test]
    fn f16_conversion_matches_the_ieee_definition_for_every_finite_pattern() {
        for bits in 0..=u16::MAX {
            let exponent = (bits >> 10) & 0x1f;
            if exponent == 0x1f {
                let value = f16_to_f32(bits);
                assert!(if bits & 0x3ff == 0 {
                    value.is_infinite()
                } else {
                    value.is_nan()
                });
                continue;
            }
            let mantissa = f64::from(bits & 0x3ff);
            let magnitude = if exponent == 0 {
                mantissa * 2f64.powi(-24)
            } else {
                (1.0 + mantissa / 1024.0) * 2f64.powi(i32::from(exponent) - 15)
            };
            let expected = if bits >> 15 == 1 {
                -magnitude
            } else {
                magnitude
            };
            let value = f16_to_f32(bits);
            assert_eq!(f64::from(value), expected, "bits {bits:#06x}");
            assert_eq!(
                value.is_sign_negative(),
                bits >> 15 == 1,
                "bits {bits:#06x}"
            );
        }
    }

    #[test]
    fn rejects_malformed_files_with_the_field_named() {
        let data = f32_bytes(&[1.0, 2.0]);
        let with = |header: &str| file_bytes(header, &data);
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (vec![1, 2, 3], "shorter than the 8-byte header length"),
            (u64::MAX.to_le_bytes().to_vec(), "exceeds the limit"),
            (file_bytes("{", &[])[..9].to_vec(), "not valid JSON"),
            (
                {
                    let mut b = 100_u64.to_le_bytes().to_vec();
                    b.extend_from_slice(b"{}");
                    b
                },
                "runs past the end",
            ),
            (file_bytes("[1]", &[]), "not a JSON object"),
            (with(r#"{"w": 3}"#), "entry is not a JSON object"),
            (
                with(r#"{"w": {"shape": [2], "data_offsets": [0, 8]}}"#),
                "field dtype",
            ),
            (
                with(r#"{"w": {"dtype": "I64", "shape": [1], "data_offsets": [0, 8]}}"#),
                "unsupported \"I64\"",
            ),
            (
                with(r#"{"w": {"dtype": "F32", "shape": [-2], "data_offsets": [0, 8]}}"#),
                "field shape",
            ),
            (
                with(r#"{"w": {"dtype": "F32", "shape": [2]}}"#),
                "field data_offsets",
            ),
            (
                with(r#"{"w": {"dtype": "F32", "shape": [2], "data_offsets": [0, 16]}}"#),
                "inside the 8-byte data",
            ),
            (
                with(r#"{"w": {"dtype": "F32", "shape": [2], "data_offsets": [8, 0]}}"#),
                "not a range",
            ),
            (
                with(r#"{"w": {"dtype": "F32", "shape": [3], "data_offsets": [0, 8]}}"#),
                "needs 12 bytes",
            ),
            (
                with(
                    r#"{"w": {"dtype": "F32", "shape": [4294967296, 4294967296, 4], "data_offsets": [0, 8]}}"#,
                ),
                "overflows",
            ),
            (
                with(
                    r#"{"a": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}, "b": {"dtype": "F32", "shape": [1], "data_offsets": [4, 8]}}"#,
                ),
                "overlap",
            ),
            (
                file_bytes(r#"{"__metadata__": {"k": 1}}"#, &[]),
                "__metadata__.k",
            ),
        ];
        for (bytes, expected) in cases {
            let error = parse_error(bytes);
            assert!(error.contains("w.safetensors"), "{error}");
            assert!(error.contains(expected), "expected {expected:?} in {error}");
        }
    }

    #[test]
    fn rejects_non_finite_and_out_of_range_values() {
        let nan = file_bytes(
            r#"{"w": {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}}"#,
            &f32_bytes(&[1.0, f32::NAN]),
        );
        let file = SafetensorsFile::parse(Path::new("n.safetensors"), nan).unwrap();
        let error = file.f32_tensor("w", &[2]).unwrap_err().to_string();
        assert!(error.contains("element 1 is not finite"), "{error}");
        let huge: Vec<u8> = 1.0e300_f64.to_le_bytes().to_vec();
        let file = SafetensorsFile::parse(
            Path::new("h.safetensors"),
            file_bytes(
                r#"{"w": {"dtype": "F64", "shape": [1], "data_offsets": [0, 8]}}"#,
                &huge,
            ),
        )
        .unwrap();
        let error = file.f32_tensor("w", &[1]).unwrap_err().to_string();
        assert!(error.contains("does not fit in f32"), "{error}");
    }

    #[test]
    fn every_truncation_of_a_valid_file_is_an_error_or_a_smaller_valid_file() {
        let folder = tempfile::tempdir().unwrap();
        let path = folder.path().join("t.safetensors");
        write(
            &path,
            &[("w", Dtype::F32, &[3], &f32_bytes(&[1.0, 2.0, 3.0]))],
            &BTreeMap::new(),
        )
        .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        for cut in 0..bytes.len() {
            assert!(
                SafetensorsFile::parse(&path, bytes[..cut].to_vec()).is_err(),
                "cut {cut}"
            );
        }
        assert!(SafetensorsFile::parse(&path, bytes).is_ok());
    }
}
