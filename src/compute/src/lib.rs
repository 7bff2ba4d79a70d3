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
//!   sort, compositing, backward) and the benchmark scene.
//! - [`nn`]: dense layers (matrix products with fused bias and activation), their backward,
//!   and Adam, for the SeqAvatar networks.
//! - [`lpips`]: the LPIPS perceptual distance (VGG16, AlexNet trunks), used by evaluation as a
//!   metric and by training as a loss; [`image`] is its float image, [`safetensors`] the
//!   strict reader of its weights files.
//! - [`memory`]: keeps the allocator from returning training's short-lived buffers to the
//!   kernel every iteration (glibc thresholds), called once by the binaries.
//! - [`ssim`]: SSIM with its exact gradient (f64), the training loss's and eval's metric.

pub mod backend;
pub mod image;
pub mod lpips;
pub mod memory;
pub mod nn;
pub mod safetensors;
pub mod scalar;
pub mod splat;
pub mod ssim;
