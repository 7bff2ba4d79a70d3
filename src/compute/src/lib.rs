//! Compute backends and the operations that run on them.
//!
//! Two backends implement one set of operations: `cpu` (plain Rust, rayon, `gemm`; generic
//! over f32/f64 so gradients are checked in f64) and `gpu` (WGSL kernels from `shaders/` run
//! through wgpu on a hardware adapter). Every operation is one Rust item with both
//! implementations side by side and one parity test.
//!
//! - [`backend`]: device selection (`auto | cpu | gpu`), the wgpu context, buffers, limits,
//!   float-atomic detection.
//! - [`splat`]: differentiable Gaussian splatting (projection, SH colour, tile binning and
//!   sort, compositing, backward), the benchmark scene and the render-only entry point.
//! - [`nn`]: dense layers (matrix products with fused bias and activation), their backward,
//!   and Adam, for the SeqAvatar networks.

pub mod backend;
pub mod nn;
pub mod scalar;
pub mod splat;
