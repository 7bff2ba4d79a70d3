//! The `eval` stage: image metrics (PSNR, SSIM, LPIPS with VGG16 and AlexNet on the `cpu` and
//! `gpu` backends), the paper's evaluation protocol applied to renders of a trained avatar,
//! rendering speed, novel-pose animation (`pipeline render`) and run reports
//! (`pipeline report`), plus a strict safetensors reader for the LPIPS weights.
//!
//! - [`stage`]: the `eval` stage kind and its output schema.
//! - [`evaluate`]: scoring renders (protocol, metrics, error maps, contact sheet, speed).
//! - [`avatar_render`]: the trained avatar as a renderer, and the avatar/entry checks.
//! - [`animate`]: `pipeline render` (novel poses from another sequence or a pose file).
//! - [`pipeline_report`]: `pipeline report`; [`ablation`]: its seed-averaged ablation table.
//! - [`subsets`]: scores on the history frames and per protocol (held-out cameras, frames).
//! - [`region`]: PSNR, SSIM and LPIPS on the garment region (the ingest `garment_masks`).
//! - [`context_probe`]: the PSNR change with the motion context zeroed or from another frame.
//! - [`metrics`], [`report`], [`testset`]: building blocks.
//! - [`lpips`], [`image`], [`safetensors`]: re-exported from `seqavatar_compute`, where LPIPS
//!   lives so that training can use it as a loss too.

pub mod ablation;
pub mod animate;
pub mod avatar_render;
pub mod context_probe;
pub mod evaluate;
pub mod export;
pub mod metrics;
pub mod pipeline_report;
pub mod region;
pub mod report;
pub mod stage;
pub mod subsets;
pub mod testset;

pub use seqavatar_compute::{image, lpips, safetensors};

/// Adds the `eval` stage kind to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(stage::EvalStage));
}
