//! Safe readers for the file formats the datasets use: pickles (with numpy arrays, dtypes,
//! scalars and OrderedDicts), `.npy`, `.npz`, JPEG/PNG images ([`images`]) and 3D Gaussian
//! Splatting PLY files ([`ply`]). They execute nothing, accept only known globals and never
//! allocate more than the input can justify.
//!
//! # Memory limits
//!
//! Every reader checks what it is about to allocate against a budget before allocating:
//!
//! - pickle, `.npy` and `.npz`: the decoded values of one file (the inflated members of an
//!   archive included) may take at most [`decode_budget`]`(file size)` bytes: [`EXPANSION`]
//!   times the file's size plus [`SLACK`], never more than [`MAX_DECODED_BYTES`]. A deflate
//!   bomb, an archive whose members overlap, or a `|S1` array of many one-byte strings (24
//!   bytes of `Vec` per element) is refused before it allocates. Parser scratch (the pickle
//!   machine's objects, the zip directory) comes on top; [`PEAK_LIMIT_FACTOR`] times the
//!   budget bounds the whole peak, and `tests/allocation.rs` measures it with a counting
//!   allocator on crafted files.
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
pub mod value;

pub use value::{ArrayData, NpArray, Value};

/// Decoded bytes allowed per byte of input.
pub const EXPANSION: usize = 32;
/// Decoded bytes allowed on top of [`EXPANSION`] times the input, for small files with
/// well-compressed members.
pub const SLACK: usize = 32 << 20;
/// The most decoded bytes any one file may produce (4 GiB).
pub const MAX_DECODED_BYTES: usize = 4 << 30;
/// The peak allocation of a reader is at most this many times its [`decode_budget`].
pub const PEAK_LIMIT_FACTOR: usize = 2;

/// The decoded-bytes budget of a file of `input_len` bytes (module docs).
pub fn decode_budget(input_len: usize) -> usize {
    input_len
        .saturating_mul(EXPANSION)
        .saturating_add(SLACK)
        .min(MAX_DECODED_BYTES)
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
     corrupt or a decompression bomb; see seqavatar_ingest::formats for the limits)"
)]
pub struct OverBudget {
    pub limit: usize,
}

impl Budget {
    /// The budget of a file of `input_len` bytes: [`decode_budget`].
    pub fn for_input(input_len: usize) -> Self {
        Self::with_limit(decode_budget(input_len))
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
