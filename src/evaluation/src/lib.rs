//! The evaluation protocol on trained avatars, shared by the eval stage, `pipeline render`,
//! `pipeline export`, `pipeline report` and the viewer: image metrics (PSNR, SSIM, LPIPS with
//! VGG16 and AlexNet on the `cpu` and `gpu` backends), the paper's protocol applied to
//! renders of a trained avatar, rendering speed, novel-pose animation and run reports.
//!
//! - [`evaluate`]: scoring renders (protocol, metrics, error maps, contact sheet, speed).
//! - [`avatar_render`]: the trained avatar as a renderer, and the avatar/entry checks.
//! - [`animate`]: `pipeline render` (novel poses from another sequence or a pose file);
//!   [`export`]: `pipeline export`.
//! - [`pipeline_report`]: `pipeline report`; [`ablation`]: its seed-averaged ablation table.
//! - [`subsets`]: scores on the history frames and per protocol (held-out cameras, frames).
//! - [`region`]: PSNR, SSIM and LPIPS on the garment region (the ingest `garment_masks`).
//! - [`context_probe`]: the PSNR change with the motion context zeroed or from another frame.
//! - [`scores`], [`metrics`], [`report`], [`testset`]: building blocks.

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
pub mod scores;
pub mod subsets;
pub mod testset;
