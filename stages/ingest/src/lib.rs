//! The `ingest` stage: reads a multi-view capture (or generates the built-in synthetic scene)
//! and writes cameras, the frame axis and split, undistorted and rescaled images with masks,
//! per-frame body-model parameters and the body model itself.
//!
//! # Output schema (one Zarr group per entry)
//!
//! Axes: `view` (ingested cameras), `frame` (the motion frame axis), `image` (ingested
//! (view, frame) pairs), `height`/`width` (the largest rescaled image), `rgb` = 3,
//! `row`/`col` = 3, `xyz` = 3, `hw` = 2, `coeff` = 5, `joint`, `vertex`, `face`, `corner` = 3,
//! `beta`, `expression`, `pose_feature` = 9 (J - 1), `keypoint`. Every array has these
//! `dimension_names`.
//!
//! Cameras (after undistortion and rescaling; the images are distortion free):
//! - `camera_K` f64 `(view, row, col)`: intrinsics in the continuous pixel convention
//!   (ARCHITECTURE.md: pixel centres at `+0.5`).
//! - `camera_R` f64 `(view, row, col)`, `camera_t` f64 `(view, xyz)`: world-to-camera,
//!   `x_cam = R x + t`, metres, OpenCV axes.
//! - `camera_image_size` u32 `(view, hw)`: `[height, width]` of that view's images.
//! - `camera_source_distortion` f64 `(view, coeff)`: the capture's OpenCV `(k1,k2,p1,p2,k3)`,
//!   for provenance only; it is already removed from the images.
//! - `camera_source_id` i64 `(view)`: the dataset's camera id.
//!
//! Frames: the frame axis is an arithmetic sequence of dataset frames with step
//! `frame_interval` (attribute), from `past_frames` steps before the first used frame
//! (clamped at the sequence start) to the last used frame; attribute `first_frame_index` is
//! the dataset frame-list index of position 0, so position 0 is the recording's first frame
//! (on this axis) exactly when it is below `frame_interval`. The motion stage indexes the
//! axis directly: "frame t - l s" is position `t - l s`, clamped at 0 only when position 0 is
//! the recording's first frame (`seqavatar_motion::schema::FrameAxis`).
//! - `frame_source_id` i64 `(frame)`: the dataset's frame number.
//! - `frame_split` u8 `(frame)`: bit 0 = a training image uses it, bit 1 = a test image
//!   does, bit 2 = a held-out frame (`split.held_out_frames`: never trained on, every view
//!   has a test image of it); 0 = only the motion windows use it (no image ingested).
//!
//! Images (only those the split uses, one image per chunk):
//! - `images` u8 `(image, height, width, rgb)` and `masks` u8 `(image, height, width)`
//!   (0 background .. 255 foreground). A view smaller than the array is stored in the
//!   top-left corner, padded with zeros; crop with `camera_image_size`.
//! - `image_view` u32 `(image)`, `image_frame` u32 `(image)`: positions on the view and frame
//!   axes; `image_split` u8 `(image)`: 0 train, 1 test. Images are ordered train first, then
//!   test, each by view then frame, then the held-out frames' test images by view then frame.
//!   A (view, frame) in both splits is stored once, as train.
//!
//! Garment region (only where the dataset has one; eval scores it beside the whole image):
//! - `garment_masks` u8 `(image, height, width)`, chunked and padded as `masks` and resampled
//!   by the same samples: the garment's coverage of each pixel, 0 .. 255 (soft at edges,
//!   like `masks`; a pixel is in the region at 128 and above), never above `masks`.
//! - Attribute `garment_region`: where it came from: `synthetic_skirt` (the synthetic scene's
//!   skirt: the supersamples whose visible surface after the depth test is a skirt triangle)
//!   or `cihp_clothing` (ZJU-MoCap `mask_cihp/` part labels 5, 6, 7, 9, 11, 12: upper
//!   clothes, dress, coat, pants, scarf, skirt). No other dataset, nor ZJU-MoCap with
//!   `mask/`, writes either. Read with [`schema::read_garment_region`].
//!
//! Garment history (only the synthetic history scene, `dataset.scene: history`), per frame:
//! - `history_displacement_mm` f64 `(frame)`: RMS over the garment's particles of the
//!   simulated garment minus its static drape under the same pose (what the pose alone
//!   cannot explain), millimetres.
//! - `history_displacement_px` f64 `(frame)`: the same difference projected into every
//!   ingested view, RMS over particles and views, in pixels of the ingested images.
//! - `history_frame` u8 `(frame)`: 1 where `history_displacement_px` exceeds the attribute
//!   `history_frame_px` (1 px): the *history frames* eval scores separately.
//!
//! Body parameters per frame (the dataset's fits; for the synthetic scene, the jittered
//! copy), in [`seqavatar_core::body::BodyParams`] conventions:
//! - `body_pose` f64 `(frame, joint, xyz)`: local axis-angle per joint, root first
//!   (`body_pose[:, 0]` is SMPL's `global_orient`).
//! - `body_world_rotation` f64 `(frame, xyz)` axis-angle and `body_world_translation` f64
//!   `(frame, xyz)`: `world = R(rot) x + trans` applied after skinning (`Rh`, `Th`).
//! - `body_betas` f64 `(frame, beta)`; `body_expression` f64 `(frame, expression)` (only when
//!   the body model has expression components).
//! - Synthetic scene only: the same five arrays with the prefix `gt_` (`gt_body_pose`, ...)
//!   hold the exact parameters the images were rendered with.
//!
//! 3D keypoints (only where the dataset has them), rows on the frame axis:
//! - `keypoints_3d` f64 `(frame, keypoint, xyz)`: world space, metres.
//! - `keypoints_3d_confidence` f64 `(frame, keypoint)`: finite, `>= 0`; 0 marks a missing
//!   keypoint, whose position means nothing (it may be NaN: a source keypoint with a
//!   non-finite position is stored with confidence 0).
//! - Attribute `keypoints_3d_joints`: per keypoint, the index of the body-model joint it
//!   measures (the posed joint position `k_j` of [`seqavatar_core::body`]), or -1 where the
//!   dataset documents no correspondence.
//!
//! Sources: the synthetic scene writes every joint of the procedural body (keypoint `j` is
//! joint `j`): the ground-truth joint positions plus seeded Gaussian noise of
//! `dataset.jitter.keypoints_metres` per coordinate (a stream separate from the fit jitter),
//! confidence 1. DNA-Rendering writes `Keypoints_3D/keypoints3d` of the annotation file
//! (`(frames, K, 3)`, or `(frames, K, 4)` with a confidence column) as stored; its joint
//! correspondence is not documented, so every keypoint has joint -1.
//!
//! Body model (the arrays of [`seqavatar_core::body::BodyModelArrays`]):
//! - `body_model_template` f64 `(vertex, xyz)`, `body_model_faces` u32 `(face, corner)`,
//!   `body_model_parents` i64 `(joint)` (-1 for the root), `body_model_weights` f64
//!   `(vertex, joint)`, `body_model_joint_regressor` f64 `(joint, vertex)`,
//!   `body_model_shape_dirs` f64 `(vertex, xyz, beta)`, `body_model_expression_dirs` f64
//!   `(vertex, xyz, expression)` (only when present), `body_model_pose_dirs` f32
//!   `(vertex, xyz, pose_feature)` (only when the model has pose blend shapes).
//!
//! [`read_body_model`] and [`read_body_params`] read the body arrays back.
//!
//! Group attributes: `dataset` (the dataset kind), `body_model_kind` (`smpl`, `smplx` or
//! `procedural`), `frame_interval`, `resolution_scale`, `past_frames`, `first_frame_index`,
//! `num_train_images`, `num_test_images`, `background` (`[0, 0, 0]`); `history_frame_px`
//! with the garment history arrays.

pub mod config;
pub mod contact_sheet;
pub mod datasets;
/// The file formats, re-exported from the library crate `seqavatar-formats` so existing
/// `seqavatar_ingest::formats` paths keep working.
pub use seqavatar_formats as formats;
pub mod plan;
pub mod reader;
pub mod schema;
pub mod stage;
pub mod synthetic;

pub use config::IngestConfig;
pub use reader::{DatasetReader, GarmentRegion, Keypoints3d};
pub use schema::{read_body_model, read_body_params, read_cameras, read_keypoints_3d};
pub use stage::Ingest;

/// Adds the `ingest` stage kind to the registry.
pub fn register(registry: &mut seqavatar_engine::Registry) {
    registry.add(Box::new(stage::Ingest));
}
