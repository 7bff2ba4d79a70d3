//! DNA-Rendering `.smc` files (HDF5, as h5py writes them) read with the pure-Rust
//! `hdf5-reader` crate: no system HDF5 library is linked.
//!
//! `hdf5-reader` was chosen over `hdf5-pure` (both read every layout h5py writes: contiguous,
//! compact, chunked, gzip and shuffle; variable- and fixed-length strings; zero-padded group
//! names) because it is read-only, bounds its reads, and refuses invalid UTF-8 in a string
//! where `hdf5-pure` replaces it silently.
//!
//! Strictness on top of the crate, so that a small or damaged file cannot exhaust the machine
//! or pass wrong values:
//! - A dataset is read only after its declared size is checked, before anything is allocated
//!   for it, against [`MAX_DATASET_BYTES`] and against what the file can hold: its own length
//!   for unfiltered layouts, [`MAX_DEFLATE_RATIO`] times that for chunked (possibly
//!   compressed) ones. Object headers are capped at [`MAX_OBJECT_HEADER_BYTES`].
//! - Strings are decoded as strict UTF-8; anything else is an error naming the file and the
//!   attribute.
//! - Numbers are converted to `f64` from the stored type (1-8 byte integers, 4 or 8 byte
//!   floats, either byte order); other types are errors naming the dataset.
//!
//! Every error names the file and the object (`path`, attribute).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use hdf5_reader::{ByteOrder, Datatype, Hdf5File, OpenOptions};

/// Largest dataset read, in bytes once decoded (256 MiB: a DNA-Rendering 12 MP JPEG is a few
/// MB, the annotation arrays are kilobytes).
pub const MAX_DATASET_BYTES: u64 = 256 << 20;

/// Largest ratio of decoded to stored bytes accepted for a chunked dataset (deflate's
/// maximum is about 1032:1).
pub const MAX_DEFLATE_RATIO: u64 = 1032;

/// Largest object header (a DNA-Rendering header is a few hundred bytes).
pub const MAX_OBJECT_HEADER_BYTES: usize = 1 << 20;

/// An opened `.smc` (HDF5) file.
pub struct SmcFile {
    path: PathBuf,
    file: Hdf5File,
    len: u64,
}

fn options() -> OpenOptions {
    OpenOptions::default()
        .with_max_read_bytes(MAX_DATASET_BYTES as usize)
        .with_max_chunk_bytes(MAX_DATASET_BYTES as usize)
        .with_max_object_header_bytes(MAX_OBJECT_HEADER_BYTES)
}

/// `"<file>: <what>"`.
fn at(path: &Path, what: &str) -> String {
    format!("{}: {what}", path.display())
}

impl SmcFile {
    /// Opens `path` (reads only the superblock now; objects are read on demand).
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        let len = std::fs::metadata(path)
            .with_context(|| at(path, "cannot open"))?
            .len();
        let file = Hdf5File::open_with_options(path, options())
            .with_context(|| at(path, "cannot open as HDF5 (.smc)"))?;
        Ok(Self {
            path: path.to_owned(),
            file,
            len,
        })
    }

    /// Opens an in-memory file; `name` stands for its path in errors.
    pub fn from_bytes(bytes: &[u8], name: &Path) -> anyhow::Result<Self> {
        let file = Hdf5File::from_bytes_with_options(bytes, options())
            .with_context(|| at(name, "cannot open as HDF5 (.smc)"))?;
        Ok(Self {
            path: name.to_owned(),
            file,
            len: bytes.len() as u64,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// `"<file>: <what>"`, for errors about this file.
    pub fn context(&self, what: &str) -> String {
        at(&self.path, what)
    }

    fn group(&self, path: &str) -> anyhow::Result<hdf5_reader::group::Group> {
        if path.is_empty() || path == "/" {
            return self
                .file
                .root_group()
                .with_context(|| self.context("cannot read the root group"));
        }
        self.file
            .group(path)
            .with_context(|| self.context(&format!("missing group `{path}`")))
    }

    fn dataset(&self, path: &str) -> anyhow::Result<hdf5_reader::Dataset> {
        self.file
            .dataset(path)
            .with_context(|| self.context(&format!("missing dataset `{path}`")))
    }

    /// Whether the group `path` exists. Missing objects (at any level) give `false`; a
    /// damaged file is an error.
    pub fn has_group(&self, path: &str) -> anyhow::Result<bool> {
        self.exists(path, true)
    }

    /// Whether the dataset `path` exists (as [`SmcFile::has_group`]).
    pub fn has_dataset(&self, path: &str) -> anyhow::Result<bool> {
        self.exists(path, false)
    }

    fn exists(&self, path: &str, group: bool) -> anyhow::Result<bool> {
        let (parent, name) = path.rsplit_once('/').unwrap_or(("", path));
        if !parent.is_empty() && !self.has_group(parent)? {
            return Ok(false);
        }
        let (groups, datasets) = self.member_names(parent)?;
        Ok(if group { groups } else { datasets }
            .iter()
            .any(|member| member == name))
    }

    /// Names of the groups and of the datasets in the group `path`.
    fn member_names(&self, path: &str) -> anyhow::Result<(Vec<String>, Vec<String>)> {
        self.group(path)?
            .member_names()
            .with_context(|| self.context(&format!("cannot list group `{path}`")))
    }

    /// Names of the members (groups and datasets) of the group `path`.
    pub fn members(&self, path: &str) -> anyhow::Result<Vec<String>> {
        let (mut groups, datasets) = self.member_names(path)?;
        groups.extend(datasets);
        Ok(groups)
    }

    /// The decoded bytes of the dataset `path` and its shape, after the size checks (module
    /// docs).
    fn raw(&self, path: &str) -> anyhow::Result<(Vec<usize>, Datatype, Vec<u8>)> {
        let dataset = self.dataset(path)?;
        let what = |w: &str| self.context(&format!("dataset `{path}` {w}"));
        let shape: Vec<usize> = dataset
            .shape()
            .iter()
            .map(|&d| usize::try_from(d))
            .collect::<Result<_, _>>()
            .map_err(|_| anyhow::anyhow!("{}", what("has a dimension beyond usize")))?;
        let element = dataset
            .raw_element_size()
            .with_context(|| what("has an unreadable datatype"))? as u64;
        let declared = shape
            .iter()
            .try_fold(element, |acc, &d| acc.checked_mul(d as u64))
            .unwrap_or(u64::MAX);
        let holdable = if dataset.chunks().is_some() {
            self.len.saturating_mul(MAX_DEFLATE_RATIO)
        } else {
            self.len
        };
        if declared > MAX_DATASET_BYTES || declared > holdable {
            bail!(what(&format!(
                "declares shape {shape:?} ({declared} bytes), more than the file ({} bytes) \
                     can hold or the {MAX_DATASET_BYTES}-byte limit of one dataset",
                self.len
            )));
        }
        let bytes = dataset
            .read_raw_bytes()
            .with_context(|| what("cannot be read"))?;
        Ok((shape, dataset.dtype().clone(), bytes))
    }

    /// The 1-byte integer dataset `path` (JPEG or PNG bytes).
    pub fn read_bytes(&self, path: &str) -> anyhow::Result<Vec<u8>> {
        let (_, dtype, bytes) = self.raw(path)?;
        match dtype {
            Datatype::FixedPoint { size: 1, .. } => Ok(bytes),
            other => bail!(self.context(&format!(
                "dataset `{path}` holds {} values, not bytes",
                describe(&other)
            ))),
        }
    }

    /// The numeric dataset `path` as `f64` values (row-major) and its shape.
    pub fn read_f64s(&self, path: &str) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
        let (shape, dtype, bytes) = self.raw(path)?;
        let values =
            to_f64s(&dtype, &bytes).with_context(|| self.context(&format!("dataset `{path}`")))?;
        Ok((shape, values))
    }

    fn attribute(
        &self,
        object: &str,
        name: &str,
    ) -> anyhow::Result<Option<hdf5_reader::Attribute>> {
        let attributes = self
            .group(object)?
            .attributes()
            .with_context(|| self.context(&format!("cannot read the attributes of `{object}`")))?;
        Ok(attributes.into_iter().find(|a| a.name == name))
    }

    /// The string attribute `name` of the group `object` (`""` for the root); `None` when it
    /// is absent. Invalid UTF-8 or a non-string value is an error naming the attribute.
    pub fn string_attr(&self, object: &str, name: &str) -> anyhow::Result<Option<String>> {
        let Some(attribute) = self.attribute(object, name)? else {
            return Ok(None);
        };
        attribute.read_string().map(Some).with_context(|| {
            self.context(&format!(
                "attribute `{name}` of `{}` is not a valid UTF-8 string",
                display_object(object)
            ))
        })
    }

    /// The numeric attribute `name` of the group `object` as `f64` values; `None` when it is
    /// absent.
    pub fn f64s_attr(&self, object: &str, name: &str) -> anyhow::Result<Option<Vec<f64>>> {
        let Some(attribute) = self.attribute(object, name)? else {
            return Ok(None);
        };
        to_f64s(&attribute.datatype, &attribute.raw_data)
            .map(Some)
            .with_context(|| {
                self.context(&format!(
                    "attribute `{name}` of `{}`",
                    display_object(object)
                ))
            })
    }
}

fn display_object(object: &str) -> &str {
    if object.is_empty() { "/" } else { object }
}

fn describe(dtype: &Datatype) -> String {
    match dtype {
        Datatype::FixedPoint { size, signed, .. } => {
            format!(
                "{}{}",
                if *signed { "int" } else { "uint" },
                8 * u32::from(*size)
            )
        }
        Datatype::FloatingPoint { size, .. } => format!("float{}", 8 * u32::from(*size)),
        Datatype::String { .. } | Datatype::VarLen { .. } => "string".to_owned(),
        _ => "non-numeric".to_owned(),
    }
}

/// Converts stored numbers to `f64`: 1, 2, 4 or 8 byte integers and 4 or 8 byte floats in
/// either byte order. 64-bit integers beyond 2^53 round to the nearest `f64`.
pub fn to_f64s(dtype: &Datatype, bytes: &[u8]) -> anyhow::Result<Vec<f64>> {
    let (size, order) = match dtype {
        Datatype::FixedPoint {
            size, byte_order, ..
        }
        | Datatype::FloatingPoint { size, byte_order } => (usize::from(*size), *byte_order),
        other => bail!("holds {} values, not numbers", describe(other)),
    };
    let valid = match dtype {
        Datatype::FloatingPoint { .. } => matches!(size, 4 | 8),
        _ => matches!(size, 1 | 2 | 4 | 8),
    };
    if !valid || !bytes.len().is_multiple_of(size) {
        bail!(
            "has an unsupported {size}-byte {} type ({} bytes of data)",
            describe(dtype),
            bytes.len()
        );
    }
    let big = matches!(order, ByteOrder::BigEndian);
    Ok(bytes
        .chunks_exact(size)
        .map(|element| {
            let mut word = [0u8; 8];
            if big {
                word[8 - size..].copy_from_slice(element);
            } else {
                word[..size].copy_from_slice(element);
            }
            let bits = if big {
                u64::from_be_bytes(word)
            } else {
                u64::from_le_bytes(word)
            };
            match dtype {
                Datatype::FloatingPoint { .. } if size == 4 => {
                    f64::from(f32::from_bits(bits as u32))
                }
                Datatype::FloatingPoint { .. } => f64::from_bits(bits),
                Datatype::FixedPoint { signed: true, .. } => {
                    // Sign-extend from `size` bytes.
                    let shift = 64 - 8 * size as u32;
                    ((bits << shift) as i64 >> shift) as f64
                }
                _ => bits as f64,
            }
        })
        .collect())
}

/// Most objects [`SmcFile::walk`] visits, and deepest group nesting.
const MAX_WALK_OBJECTS: usize = 100_000;
const MAX_WALK_DEPTH: usize = 32;

impl SmcFile {
    /// Visits every group (depth first, `""` = root) and calls `group` with its path and
    /// `dataset` with each dataset path. Errors after [`MAX_WALK_OBJECTS`] objects or
    /// [`MAX_WALK_DEPTH`] levels.
    pub fn walk(
        &self,
        mut group: impl FnMut(&str) -> anyhow::Result<()>,
        mut dataset: impl FnMut(&str) -> anyhow::Result<()>,
    ) -> anyhow::Result<usize> {
        let mut visited = 0;
        let mut stack = vec![(String::new(), 0usize)];
        while let Some((path, depth)) = stack.pop() {
            visited += 1;
            if depth > MAX_WALK_DEPTH || visited > MAX_WALK_OBJECTS {
                bail!(self.context(&format!(
                    "more than {MAX_WALK_DEPTH} group levels or {MAX_WALK_OBJECTS} objects"
                )));
            }
            group(&path)?;
            let (groups, datasets) = self.member_names(&path)?;
            for name in datasets {
                visited += 1;
                dataset(&join(&path, &name))?;
            }
            for name in groups.into_iter().rev() {
                stack.push((join(&path, &name), depth + 1));
            }
        }
        Ok(visited)
    }
}

/// Reads every group, dataset and attribute of an in-memory file (for the fuzz target and
/// the damaged-file tests): the number of objects visited, or the first error.
pub fn read_all(bytes: &[u8]) -> anyhow::Result<usize> {
    let file = SmcFile::from_bytes(bytes, Path::new("<memory>"))?;
    file.walk(
        |path| {
            for attribute in file
                .group(path)?
                .attributes()
                .with_context(|| file.context(&format!("attributes of `{path}`")))?
            {
                let _ = attribute.read_string();
                let _ = to_f64s(&attribute.datatype, &attribute.raw_data);
            }
            Ok(())
        },
        |path| {
            let (_, dtype, data) = file.raw(path)?;
            let _ = to_f64s(&dtype, &data);
            Ok(())
        },
    )
}

fn join(parent: &str, name: &str) -> String {
    if parent.is_empty() {
        name.to_owned()
    } else {
        format!("{parent}/{name}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn le(size: u8, signed: bool) -> Datatype {
        Datatype::FixedPoint {
            size,
            signed,
            byte_order: ByteOrder::LittleEndian,
        }
    }

    #[test]
    fn numbers_convert_from_every_stored_type() {
        // Independent encodings: Rust's own to_*_bytes of known values.
        let f32s: Vec<u8> = [1.5f32, -2.25]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let float4 = Datatype::FloatingPoint {
            size: 4,
            byte_order: ByteOrder::LittleEndian,
        };
        assert_eq!(to_f64s(&float4, &f32s).unwrap(), vec![1.5, -2.25]);
        let f64s: Vec<u8> = [0.1f64, -3e300]
            .iter()
            .flat_map(|v| v.to_be_bytes())
            .collect();
        let float8_be = Datatype::FloatingPoint {
            size: 8,
            byte_order: ByteOrder::BigEndian,
        };
        assert_eq!(to_f64s(&float8_be, &f64s).unwrap(), vec![0.1, -3e300]);
        let i16s: Vec<u8> = [-300i16, 7].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(to_f64s(&le(2, true), &i16s).unwrap(), vec![-300.0, 7.0]);
        let i32s_be: Vec<u8> = [-5i32, 1 << 30]
            .iter()
            .flat_map(|v| v.to_be_bytes())
            .collect();
        let int4_be = Datatype::FixedPoint {
            size: 4,
            signed: true,
            byte_order: ByteOrder::BigEndian,
        };
        assert_eq!(
            to_f64s(&int4_be, &i32s_be).unwrap(),
            vec![-5.0, f64::from(1 << 30)]
        );
        assert_eq!(to_f64s(&le(1, false), &[255, 0]).unwrap(), vec![255.0, 0.0]);
        assert_eq!(to_f64s(&le(1, true), &[255, 1]).unwrap(), vec![-1.0, 1.0]);
        let i64s: Vec<u8> = [i64::MIN, 42]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        assert_eq!(
            to_f64s(&le(8, true), &i64s).unwrap(),
            vec![i64::MIN as f64, 42.0]
        );
        let u64s: Vec<u8> = u64::MAX.to_le_bytes().to_vec();
        assert_eq!(
            to_f64s(&le(8, false), &u64s).unwrap(),
            vec![u64::MAX as f64]
        );
        // Bad sizes and non-numeric types are errors.
        assert!(to_f64s(&le(3, true), &[0; 6]).is_err());
        assert!(to_f64s(&le(4, true), &[0; 6]).is_err());
        let float2 = Datatype::FloatingPoint {
            size: 2,
            byte_order: ByteOrder::LittleEndian,
        };
        assert!(to_f64s(&float2, &[0; 2]).is_err());
    }

    #[test]
    fn garbage_is_an_error_naming_the_file() {
        let e = SmcFile::from_bytes(b"not an hdf5 file at all", Path::new("x.smc"))
            .err()
            .unwrap();
        assert!(
            format!("{e:#}").starts_with("x.smc: cannot open as HDF5"),
            "{e:#}"
        );
        assert!(read_all(&[]).is_err());
    }
}
