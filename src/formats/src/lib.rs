//! Safe readers for the file formats the datasets use: pickles (with numpy arrays, dtypes,
//! scalars and OrderedDicts), `.npy`, `.npz`, JPEG/PNG images ([`images`]) and 3D Gaussian
//! Splatting PLY files ([`ply`]). They execute nothing, accept only known globals and never
//! allocate more than the input can justify.
//!
//! # Memory limits
//!
//! Every reader checks what it is about to allocate against a limit before allocating:
//!
//! - `.npy` and `.npz`: the limits apply to what a file *declares*, never to how well it
//!   compresses. Each array's decoded size comes from its header's shape and dtype and may
//!   be at most [`Limits::max_array_bytes`] (default [`DEFAULT_MAX_ARRAY_BYTES`], environment
//!   variable [`MAX_ARRAY_BYTES_VAR`]); the arrays of one file together at most
//!   [`Limits::max_file_bytes`] (default [`DEFAULT_MAX_FILE_BYTES`], [`MAX_FILE_BYTES_VAR`]).
//!   An `.npz` member's header is inflated first; the size it declares must equal the size
//!   the zip directory records, and inflating stops one byte past it (more or less data is
//!   an error). A deflate bomb that declares its size is refused before inflating; one that
//!   lies is stopped at the declared size. A `|S1` array of many one-byte strings is charged
//!   24 bytes of `Vec` per element.
//! - pickles (and `.npy` object arrays, whose data is a pickle): nothing is compressed, but
//!   small opcodes build large values, so the values may take at most [`decode_budget`]`(size)`
//!   bytes: [`EXPANSION`] times the pickle's size plus [`SLACK`], within the per-file limit.
//!   Parser scratch (the pickle machine's objects, the zip directory) comes on top;
//!   [`PEAK_LIMIT_FACTOR`] times the limit bounds the whole peak, and `src/formats/tests/bombs.rs`
//!   measures it with a counting allocator on crafted files.
//! - images: see [`images`]: the header's size is checked against the camera and against
//!   [`images::MAX_IMAGE_PIXELS`] before decoding, and decoding allocates at most
//!   [`images::MAX_BYTES_PER_PIXEL`] bytes per pixel.
//! - PLY: the declared vertex count times the record size must equal the bytes after the
//!   header before anything is allocated, and the decoded cloud is smaller than those bytes.

pub mod dtype;
pub mod images;
pub mod npy;
pub mod npz;
pub mod pickle;
pub mod ply;
pub mod resample;
pub mod value;

pub use value::{ArrayData, NpArray, Value};

/// Decoded bytes allowed per byte of a pickle.
pub const EXPANSION: usize = 32;
/// Decoded bytes allowed on top of [`EXPANSION`] times a pickle's size.
pub const SLACK: usize = 32 << 20;
/// The default of [`Limits::max_array_bytes`]: 512 MiB (a float64 SMPL-X blend-shape array
/// is about 120 MB).
pub const DEFAULT_MAX_ARRAY_BYTES: usize = 512 << 20;
/// The default of [`Limits::max_file_bytes`]: 1 GiB.
pub const DEFAULT_MAX_FILE_BYTES: usize = 1 << 30;
/// Environment variable overriding [`DEFAULT_MAX_ARRAY_BYTES`] (bytes, or with a `K`, `M`
/// or `G` suffix for KiB, MiB, GiB).
pub const MAX_ARRAY_BYTES_VAR: &str = "SEQAVATAR_MAX_ARRAY_BYTES";
/// Environment variable overriding [`DEFAULT_MAX_FILE_BYTES`] (same syntax).
pub const MAX_FILE_BYTES_VAR: &str = "SEQAVATAR_MAX_FILE_BYTES";
/// The peak allocation of a reader is at most this many times its limit (the inflated
/// member and its decoded array are alive together).
pub const PEAK_LIMIT_FACTOR: usize = 2;

/// The absolute caps on what one file may decode to (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// The most bytes one decoded array may take.
    pub max_array_bytes: usize,
    /// The most bytes the decoded arrays of one file may take together.
    pub max_file_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_array_bytes: DEFAULT_MAX_ARRAY_BYTES,
            max_file_bytes: DEFAULT_MAX_FILE_BYTES,
        }
    }
}

/// An environment variable holds no valid size.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{var}={value:?} is not a size in bytes (examples: 1073741824, 800M, 2G)")]
pub struct BadLimit {
    pub var: &'static str,
    pub value: String,
}

impl Limits {
    /// The defaults, overridden by [`MAX_ARRAY_BYTES_VAR`] and [`MAX_FILE_BYTES_VAR`].
    pub fn from_env() -> Result<Self, BadLimit> {
        let mut limits = Self::default();
        for (var, field) in [
            (MAX_ARRAY_BYTES_VAR, &mut limits.max_array_bytes),
            (MAX_FILE_BYTES_VAR, &mut limits.max_file_bytes),
        ] {
            if let Some(value) = std::env::var_os(var) {
                let value = value.to_string_lossy().into_owned();
                *field = parse_size(&value).ok_or(BadLimit { var, value })?;
            }
        }
        Ok(limits)
    }
}

/// `123`, `800K`, `800M`, `2G` (binary multiples) as bytes.
pub fn parse_size(text: &str) -> Option<usize> {
    let text = text.trim();
    let (digits, shift) = match text.char_indices().last()? {
        (at, 'k' | 'K') => (&text[..at], 10),
        (at, 'm' | 'M') => (&text[..at], 20),
        (at, 'g' | 'G') => (&text[..at], 30),
        _ => (text, 0),
    };
    let n: usize = digits.trim().parse().ok()?;
    n.checked_mul(1usize.checked_shl(shift)?)
        .filter(|&bytes| bytes > 0)
}

/// The decoded-bytes budget of a pickle of `input_len` bytes (module docs), before the
/// per-file limit.
pub fn decode_budget(input_len: usize) -> usize {
    input_len.saturating_mul(EXPANSION).saturating_add(SLACK)
}

/// Bytes a reader may still allocate for decoded values.
#[derive(Clone, Debug)]
pub struct Budget {
    left: usize,
    limit: usize,
}

/// A reader needed more memory than its [`Budget`] allows.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error(
    "decoding needs more than the {limit}-byte memory limit for this file (the file is \
     corrupt or too large: see the Limits section of the README for the limits and how to \
     raise them)"
)]
pub struct OverBudget {
    pub limit: usize,
}

impl Budget {
    /// The budget of a pickle of `input_len` bytes: [`decode_budget`], within the per-file
    /// limit.
    pub fn for_pickle(input_len: usize, limits: &Limits) -> Self {
        Self::with_limit(decode_budget(input_len).min(limits.max_file_bytes))
    }

    pub fn with_limit(limit: usize) -> Self {
        Self { left: limit, limit }
    }

    /// Takes `bytes` from the budget, or fails without changing it.
    pub fn charge(&mut self, bytes: usize) -> Result<(), OverBudget> {
        self.left = self
            .left
            .checked_sub(bytes)
            .ok_or(OverBudget { limit: self.limit })?;
        Ok(())
    }

    /// Bytes still available.
    pub fn left(&self) -> usize {
        self.left
    }

    pub fn limit(&self) -> usize {
        self.limit
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_suffixes() {
        assert_eq!(parse_size("1024"), Some(1024));
        assert_eq!(parse_size("800M"), Some(800 << 20));
        assert_eq!(parse_size(" 2g "), Some(2 << 30));
        assert_eq!(parse_size("3K"), Some(3 << 10));
        for bad in ["", "0", "-1", "M", "1.5G", "12 bytes"] {
            assert_eq!(parse_size(bad), None, "{bad}");
        }
    }
}
