//! The `eval` stage's building blocks: image metrics (PSNR, SSIM, LPIPS with VGG16 and
//! AlexNet on the `cpu` and `gpu` backends), the paper's evaluation protocol, a strict
//! safetensors reader for the LPIPS weights, and report pictures (plots, contact sheets,
//! error maps) and Markdown tables.
//!
//! The stage kind itself is registered once it is wired end to end to the training stage's
//! avatar output; until then [`register`] adds nothing.

pub mod image;
pub mod lpips;
pub mod metrics;
pub mod report;
pub mod safetensors;

/// Adds this crate's stage kinds to the registry (none yet: see the crate docs).
pub fn register(_registry: &mut seqavatar_engine::Registry) {}
