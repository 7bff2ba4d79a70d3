//! The train entry: the trained avatar, written and read by `seqavatar_avatar`'s
//! `TrainedAvatar` (which owns the model the arrays describe), and the run's record.
//!
//! The avatar:
//! - `gaussian_xyz` f64 `(gaussian, xyz)`: canonical (big-pose) centres, metres.
//! - `gaussian_sh` f64 `(gaussian, coeff, rgb)`: 16 SH coefficients per channel (degree 3
//!   storage; the attribute `sh_degree` says how many are active).
//! - `gaussian_opacity` f64 `(gaussian)`: opacity logits (activated with a sigmoid).
//! - `gaussian_log_scale` f64 `(gaussian, xyz)`; `gaussian_rotation` f64 `(gaussian, wxyz)`.
//! - The body model arrays of the ingest schema (`body_model_*`), so that the entry renders
//!   on its own.
//! - `network/<name>` f64: network parameters by their stable names (when the motion context
//!   or the refiners use networks), the f32 values the networks train and render with.
//!
//! Attributes: `avatar` (the `AvatarConfig`), `sh_degree`, `scales` (raw temporal
//! scales fed to the networks, largest first), `sequence_length`, `background`,
//! `body_model_kind`, `extent`, `motion_joints` (with networks). The train stage adds its
//! own `config` (the resolved train config, which nothing here reads).
//!
//! The run: the attribute `config` (the resolved train config), and
//! - `loss_<name>` f64 `(iteration)` for `total`, `l1`, `mask_mse`, `dssim`, `lpips`
//!   (unweighted, 0 when the LPIPS loss is off), `aiap`, `psnr` (train PSNR inside the bound
//!   box) and `gaussians` (count after the iteration);
//! - `camera_K`, `camera_R`, `camera_t`, `camera_image_size`: the ingest entry's cameras
//!   (ingest resolution; training rescales them by `resolution_scale`);
//! - `test_psnr` f64 `(image)`: held-out PSNR per test image (docs/method.md protocol), with
//!   `test_image` u32 `(image)` the ingest image index;
//! - attributes `wall_seconds`, `iterations_per_second` (of the last session when resumed),
//!   `resumed_from`, `final_train_psnr` (mean over the last tenth of the iterations),
//!   `test_psnr_mean`, `backend`, `gaussians`;
//! - attributes `train_image_psnr_mean` (the held-out protocol's PSNR on up to
//!   64 training images spread over the training split, next to
//!   `test_psnr_mean`: the gap is memorisation), `train_image_psnr_images`, `input_rms`
//!   (`InputRms`: RMS of each non-rigid input block over the training
//!   frames) and `first_layer_norms` (a list of `BlockNorm`: first-layer
//!   weight norms per input block).
//!
//! [`PlannedTrain`]: what the entry will hold, as far as the stage's config determines it when
//! the pipeline loads.

use serde::{Deserialize, Serialize};

/// The plan of a train entry (the stage's `planned` hook).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlannedTrain {
    /// The avatar's motion context, as named in the train config (`motion_context`).
    pub motion_context: String,
    /// Whether rendering the avatar reads the motion entry (skeleton-motion context).
    pub renders_from_motion_entry: bool,
}

impl PlannedTrain {
    /// The plan of a train input as a downstream stage's load-time check sees it.
    pub fn of(input: &seqavatar_engine::StageInput<'_>) -> Result<Self, String> {
        crate::ingest::planned_of(input)
    }
}
