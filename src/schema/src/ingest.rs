//! The ingest entry: one Zarr group written by the ingest stage from a multi-view capture or
//! the built-in synthetic scene. Each writer here sits beside its reader.
//!
//! Axes: `view` (ingested cameras), `frame` (the motion frame axis), `image` (ingested
//! (view, frame) pairs), `height`/`width` (the largest rescaled image), `rgb` = 3,
//! `row`/`col` = 3, `xyz` = 3, `hw` = 2, `coeff` = 5, `joint`, `vertex`, `face`, `corner` = 3,
//! `beta`, `expression`, `pose_feature` = 9 (J - 1), `keypoint`. Every array has these
//! `dimension_names`.
//!
//! World origin: ingest re-centres the dataset's world on the subject, so that a capture
//! far from its world's origin (geographic coordinates, a scene moved 10 km away) keeps its
//! millimetres in the f32 arithmetic of training and rendering. Attribute `world_offset`
//! (`[x, y, z]`, metres) is the point of the dataset's world that is this entry's origin:
//! the mean of the body fits' world translations over the frame axis, rounded to whole
//! metres (so a scene moved by whole metres stores the same arrays, and one near its
//! origin keeps its coordinates). Every world-space array below (camera extrinsics, body
//! world translations, 3D keypoints) is relative to it: add it to a position, or give a
//! camera `-world_offset` ([`Camera::with_origin_at`]), to return to the dataset's world.
//! Entries made before it existed lack it: their offset is zero. Entries derived from this
//! one (fit, motion, train) live in its world.
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
//! the recording's first frame (`seqavatar_schema::motion::FrameAxis`).
//! - `frame_source_id` i64 `(frame)`: the dataset's frame number.
//! - `frame_split` u8 `(frame)`: bit 0 = a training image uses it, bit 1 = a test image
//!   does, bit 2 = a held-out frame (`split.held_out_frames`: never trained on, every view
//!   has a test image of it); 0 = only the motion windows use it (no image ingested).
//!   Read with [`read_frame_split`], and `frame_interval` with [`read_frame_interval`].
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
//!   `mask/`, writes either. Read with [`read_garment_region`].
//!
//! Garment history (only the synthetic history scene, `dataset.scene: history`), per frame:
//! - `history_displacement_mm` f64 `(frame)`: RMS over the garment's particles of the
//!   simulated garment minus its static drape under the same pose (what the pose alone
//!   cannot explain), millimetres.
//! - `history_displacement_px` f64 `(frame)`: the same difference projected into every
//!   ingested view, RMS over particles and views, in pixels of the ingested images.
//! - `history_frame` u8 `(frame)`: 1 where `history_displacement_px` exceeds the attribute
//!   `history_frame_px` (1 px): the *history frames* eval scores separately.
//! - `garment_state` f64 `(frame, component)`: the exact state of the skirt's oscillator in
//!   the body's heading frame ([`GARMENT_STATE_COMPONENTS`]: hem deflection forward and
//!   across, their rates, twist and its rate; m, m/s, rad, rad/s), the input of the motion
//!   stage's `garment_oracle`.
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
//! `num_train_images`, `num_test_images`, `background` (`[0, 0, 0]`), `world_offset`
//! (above); `history_frame_px` with the garment history arrays.

use anyhow::Context;
use seqavatar_core::body::{BodyModel, BodyModelArrays, BodyParams};
use seqavatar_core::camera::{Camera, Intrinsics};
use seqavatar_core::glam::{DMat3, DVec3};
use seqavatar_engine::{ArrayWriter, Element, EntryReader, EntryWriter};

use serde::{Deserialize, Serialize};

/// The attribute holding the point of the dataset's world that is the entry's origin.
pub const WORLD_OFFSET_ATTRIBUTE: &str = "world_offset";

/// Sets [`WORLD_OFFSET_ATTRIBUTE`].
pub fn write_world_offset(out: &EntryWriter, offset: DVec3) -> anyhow::Result<()> {
    out.set_attribute(WORLD_OFFSET_ATTRIBUTE, serde_json::json!(offset.to_array()))
}

/// The entry's [`WORLD_OFFSET_ATTRIBUTE`]: zero when absent (an entry made before ingest
/// re-centred the world is in its dataset's world).
pub fn read_world_offset(entry: &EntryReader) -> anyhow::Result<DVec3> {
    let Some(value) = entry.attribute(WORLD_OFFSET_ATTRIBUTE) else {
        return Ok(DVec3::ZERO);
    };
    serde_json::from_value::<[f64; 3]>(value)
        .ok()
        .map(DVec3::from_array)
        .filter(|offset| offset.is_finite())
        .ok_or_else(|| {
            anyhow::anyhow!(
                "entry {}: attribute {WORLD_OFFSET_ATTRIBUTE} is not [x, y, z] in finite metres",
                entry.location()
            )
        })
}

/// Sets the attribute `frame_interval`: the frame axis's step in dataset frames.
pub fn write_frame_interval(out: &EntryWriter, interval: usize) -> anyhow::Result<()> {
    out.set_attribute("frame_interval", interval.into())
}

/// The entry's attribute `frame_interval`; missing or not a positive integer is an error naming
/// the entry.
pub fn read_frame_interval(entry: &EntryReader) -> anyhow::Result<u32> {
    let location = entry.location();
    let value = crate::attribute(entry, "frame_interval")?;
    value
        .as_u64()
        .filter(|&v| v >= 1 && v <= u64::from(u32::MAX))
        .map(|v| v as u32)
        .ok_or_else(|| {
            anyhow::anyhow!(
                "entry {location}: attribute `frame_interval` = {value} is not a positive integer"
            )
        })
}

/// The array `frame_split` (module docs: bits 0 train, 1 test, 2 held out), checked to be
/// `(frame)` with no other bit set; errors name the entry and the array.
pub fn read_frame_split(entry: &EntryReader) -> anyhow::Result<Vec<u8>> {
    let location = entry.location();
    let frames = entry.read::<i64>("frame_source_id")?.data.len();
    let split = entry.read::<u8>("frame_split")?;
    anyhow::ensure!(
        split.shape == [frames],
        "entry {location}: array `frame_split` has shape {:?}, expected ({frames}) (the frame axis)",
        split.shape
    );
    if let Some(bad) = split.data.iter().find(|&&bits| bits > 7) {
        anyhow::bail!("entry {location}: array `frame_split` holds {bad}, expected 0 .. 7");
    }
    Ok(split.data)
}

/// Writes the camera arrays of the ingested views: `cameras` are the rescaled,
/// distortion-free cameras, `source` the dataset's cameras they came from (for
/// `camera_source_distortion` and `camera_source_id`). [`read_cameras`] reads them back.
pub fn write_cameras(
    out: &EntryWriter,
    cameras: &[Camera],
    source: &[&SourceCamera],
) -> anyhow::Result<()> {
    anyhow::ensure!(
        cameras.len() == source.len(),
        "{} cameras for {} source cameras",
        cameras.len(),
        source.len()
    );
    let mut k: Vec<f64> = Vec::new();
    let mut r: Vec<f64> = Vec::new();
    let mut t: Vec<f64> = Vec::new();
    let mut size: Vec<u32> = Vec::new();
    let mut distortion: Vec<f64> = Vec::new();
    let mut ids: Vec<i64> = Vec::new();
    for (camera, source) in cameras.iter().zip(source) {
        k.extend(camera.k_matrix().iter().flatten().copied());
        let rt = camera.rotation.transpose();
        // Row-major R: rows of R are the columns of R^T.
        r.extend(
            rt.x_axis
                .to_array()
                .into_iter()
                .chain(rt.y_axis.to_array())
                .chain(rt.z_axis.to_array()),
        );
        t.extend(camera.translation.to_array());
        size.extend([camera.height, camera.width]);
        distortion.extend(source.camera.distortion);
        ids.push(source.id);
    }
    let v = cameras.len() as u64;
    out.write_whole("camera_K", &["view", "row", "col"], &[v, 3, 3], &k)?;
    out.write_whole("camera_R", &["view", "row", "col"], &[v, 3, 3], &r)?;
    out.write_whole("camera_t", &["view", "xyz"], &[v, 3], &t)?;
    out.write_whole("camera_image_size", &["view", "hw"], &[v, 2], &size)?;
    out.write_whole(
        "camera_source_distortion",
        &["view", "coeff"],
        &[v, 5],
        &distortion,
    )?;
    out.write_whole("camera_source_id", &["view"], &[v], &ids)?;
    Ok(())
}

/// Copies the camera arrays of [`write_cameras`] from `ingest` into `out` (train and motion
/// entries carry them); with `only_present`, the ones `ingest` lacks are left out.
pub fn copy_cameras(
    out: &EntryWriter,
    ingest: &EntryReader,
    only_present: bool,
) -> anyhow::Result<()> {
    fn copy<T: Element>(
        out: &EntryWriter,
        ingest: &EntryReader,
        name: &str,
        dims: &[&str],
    ) -> anyhow::Result<()> {
        let a = ingest.read::<T>(name)?;
        let shape: Vec<u64> = a.shape.iter().map(|&x| x as u64).collect();
        let chunk: Vec<u64> = shape.iter().map(|&x| x.max(1)).collect();
        out.write_array(name, dims, &shape, &chunk, &a.data)
    }
    for (name, dims) in [
        ("camera_K", &["view", "row", "col"][..]),
        ("camera_R", &["view", "row", "col"][..]),
        ("camera_t", &["view", "xyz"][..]),
        ("camera_image_size", &["view", "hw"][..]),
    ] {
        if only_present && !ingest.has_array(name) {
            continue;
        }
        if name == "camera_image_size" {
            copy::<u32>(out, ingest, name, dims)?;
        } else {
            copy::<f64>(out, ingest, name, dims)?;
        }
    }
    Ok(())
}

/// Reads the distortion-free cameras `camera_K`, `camera_R`, `camera_t`, `camera_image_size` of an entry.
pub fn read_cameras(entry: &EntryReader) -> anyhow::Result<Vec<Camera>> {
    let k = entry.read::<f64>("camera_K")?;
    let r = entry.read::<f64>("camera_R")?;
    let t = entry.read::<f64>("camera_t")?;
    let size = entry.read::<u32>("camera_image_size")?;
    let views = k.shape.first().copied().unwrap_or(0);
    let location = entry.location();
    for (name, shape, expected) in [
        ("camera_K", &k.shape, vec![views, 3, 3]),
        ("camera_R", &r.shape, vec![views, 3, 3]),
        ("camera_t", &t.shape, vec![views, 3]),
        ("camera_image_size", &size.shape, vec![views, 2]),
    ] {
        anyhow::ensure!(
            *shape == expected,
            "entry {location}: array `{name}` has shape {shape:?}, expected {expected:?}"
        );
    }
    (0..views)
        .map(|view| {
            let kk = &k.data[view * 9..view * 9 + 9];
            let rr = &r.data[view * 9..view * 9 + 9];
            let tt = &t.data[view * 3..view * 3 + 3];
            let hw = &size.data[view * 2..view * 2 + 2];
            let camera = Camera {
                width: hw[1],
                height: hw[0],
                intrinsics: Intrinsics {
                    fx: kk[0],
                    fy: kk[4],
                    cx: kk[2],
                    cy: kk[5],
                },
                rotation: DMat3::from_cols_array(&[
                    rr[0], rr[3], rr[6], rr[1], rr[4], rr[7], rr[2], rr[5], rr[8],
                ]),
                translation: DVec3::new(tt[0], tt[1], tt[2]),
                distortion: [0.0; 5],
            };
            camera
                .validate()
                .with_context(|| format!("entry {location}: camera of view {view}"))?;
            Ok(camera)
        })
        .collect()
}

/// The per-image arrays of an ingest entry: `image_view`, `image_frame` and `image_split`, and
/// the sizes of `images` and `masks` (and `garment_masks`), which [`ImageArrays::read`] checks
/// against each other and the cameras; the images are read one at a time.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageArrays {
    /// Per image, its positions on the `view` and `frame` axes and its split (0 train, 1 test).
    pub view: Vec<u32>,
    pub frame: Vec<u32>,
    pub split: Vec<u8>,
    /// Height and width of the stored images (the largest view).
    pub height: u64,
    pub width: u64,
    /// Per view, `[height, width]` (`camera_image_size`).
    view_size: Vec<[u64; 2]>,
}

/// `images`, `masks` and, where the dataset has a garment region, `garment_masks`, to fill.
pub type ImageWriters = (ArrayWriter<u8>, ArrayWriter<u8>, Option<ArrayWriter<u8>>);

impl ImageArrays {
    /// Creates the arrays of `count` images of up to `[height, width]`, one image per chunk
    /// (with `garment`, its attribute too); [`ImageArrays::write_index`] writes the rest.
    pub fn create(
        out: &EntryWriter,
        count: u64,
        [height, width]: [u64; 2],
        garment: Option<GarmentRegion>,
    ) -> anyhow::Result<ImageWriters> {
        let dims = ["image", "height", "width", "rgb"];
        let (shape, chunk) = ([count, height, width, 3], [1, height, width, 3]);
        let plane = |name| out.create_array::<u8>(name, &dims[..3], &shape[..3], &chunk[..3]);
        let images = out.create_array::<u8>("images", &dims, &shape, &chunk)?;
        let masks = plane("masks")?;
        if let Some(region) = garment {
            out.set_attribute(GARMENT_REGION_ATTRIBUTE, region.as_str().into())?;
        }
        Ok((
            images,
            masks,
            garment.map(|_| plane(GARMENT_MASKS)).transpose()?,
        ))
    }

    /// Writes `image_view`, `image_frame` and `image_split` of `(view, frame, split)` per image.
    pub fn write_index(out: &EntryWriter, images: &[(usize, usize, u8)]) -> anyhow::Result<()> {
        let n = images.len() as u64;
        let column =
            |name, values: Vec<u32>| out.write_array(name, &["image"], &[n], &[n.max(1)], &values);
        column("image_view", images.iter().map(|i| i.0 as u32).collect())?;
        column("image_frame", images.iter().map(|i| i.1 as u32).collect())?;
        let split: Vec<u8> = images.iter().map(|i| i.2).collect();
        out.write_array("image_split", &["image"], &[n], &[n.max(1)], &split)
    }

    /// Reads the per-image arrays and checks them: one length, views and frames the entry
    /// has, splits 0 or 1, `images` `(image, height, width, 3)` and `masks` of the same
    /// images, each image's view no larger than them. Errors name the entry and the array.
    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let location = entry.location();
        let (view, frame) = (
            entry.read::<u32>("image_view")?,
            entry.read::<u32>("image_frame")?,
        );
        let split = entry.read::<u8>("image_split")?;
        let count = view.data.len();
        for (name, shape) in [
            ("image_view", &view.shape),
            ("image_frame", &frame.shape),
            ("image_split", &split.shape),
        ] {
            anyhow::ensure!(
                *shape == [count],
                "entry {location}: array `{name}` has shape {shape:?}, expected ({count})"
            );
        }
        let (shape, masks) = (entry.shape("images")?, entry.shape("masks")?);
        anyhow::ensure!(
            shape.len() == 4 && shape[0] as usize == count && shape[3] == 3 && masks == shape[..3],
            "entry {location}: arrays `images` and `masks` have shapes {shape:?} and {masks:?}, expected ({count}, height, width, 3) and ({count}, height, width)"
        );
        let sizes = entry.read::<u32>("camera_image_size")?.data;
        let view_size: Vec<[u64; 2]> = sizes
            .chunks_exact(2)
            .map(|s| [s[0], s[1]].map(u64::from))
            .collect();
        let frames = entry.shape("frame_source_id")?.iter().product::<u64>();
        for (i, ((&v, &f), &s)) in view
            .data
            .iter()
            .zip(&frame.data)
            .zip(&split.data)
            .enumerate()
        {
            let (Some(&[h, w]), true) = (view_size.get(v as usize), u64::from(f) < frames) else {
                anyhow::bail!(
                    "entry {location}: image {i} names view {v} and frame {f}, but the entry has {} views and {frames} frames",
                    view_size.len()
                );
            };
            anyhow::ensure!(
                s <= 1,
                "entry {location}: `image_split` of image {i} is {s}, expected 0 or 1"
            );
            anyhow::ensure!(
                h <= shape[1] && w <= shape[2],
                "entry {location}: view {v} is {w}x{h} but `images` is {}x{}",
                shape[2],
                shape[1]
            );
        }
        let (height, width) = (shape[1], shape[2]);
        let (view, frame, split) = (view.data, frame.data, split.data);
        Ok(Self {
            view,
            frame,
            split,
            height,
            width,
            view_size,
        })
    }

    pub fn len(&self) -> usize {
        self.view.len()
    }

    pub fn is_empty(&self) -> bool {
        self.view.is_empty()
    }

    /// Image `index` of `images`, cropped to its view's size.
    pub fn image(&self, entry: &EntryReader, index: usize) -> anyhow::Result<image::RgbImage> {
        read_image(entry, "images", index, self.cropped(index))
    }

    /// Mask `index` of `masks`, cropped to its view's size.
    pub fn mask(&self, entry: &EntryReader, index: usize) -> anyhow::Result<image::GrayImage> {
        read_image(entry, "masks", index, self.cropped(index))
    }

    /// Mask `index` of [`GARMENT_MASKS`], cropped to its view's size.
    pub fn garment_mask(&self, entry: &EntryReader, i: usize) -> anyhow::Result<image::GrayImage> {
        read_image(entry, GARMENT_MASKS, i, self.cropped(i))
    }

    /// Image `index` and its mask as stored: the whole padded `height x width`.
    pub fn stored(
        &self,
        entry: &EntryReader,
        i: usize,
    ) -> anyhow::Result<(image::RgbImage, image::GrayImage)> {
        let size = [self.height, self.width];
        Ok((
            read_image(entry, "images", i, size)?,
            read_image(entry, "masks", i, size)?,
        ))
    }

    fn cropped(&self, index: usize) -> [u64; 2] {
        self.view_size[self.view[index] as usize]
    }
}

/// Image `index` of the array `name` (`(image, height, width)`, or with a last axis of
/// channels): its top-left `height x width` pixels.
fn read_image<P: image::Pixel<Subpixel = u8>>(
    entry: &EntryReader,
    name: &str,
    index: usize,
    [height, width]: [u64; 2],
) -> anyhow::Result<image::ImageBuffer<P, Vec<u8>>> {
    let channels = u64::from(P::CHANNEL_COUNT);
    let rank = if channels == 1 { 3 } else { 4 };
    let (start, shape) = ([index as u64, 0, 0, 0], [1, height, width, channels]);
    let data = entry
        .read_region::<u8>(name, &start[..rank], &shape[..rank])?
        .data;
    image::ImageBuffer::from_raw(width as u32, height as u32, data).ok_or_else(|| {
        anyhow::anyhow!(
            "entry {}: array `{name}`: image {index} has the wrong size",
            entry.location()
        )
    })
}

/// Writes `keypoints_3d`, `keypoints_3d_confidence` and the `keypoints_3d_joints` attribute
/// (lib.rs schema). A keypoint with a non-finite position gets confidence 0; a negative or
/// non-finite confidence, or a joint the model does not have, is an error naming the frame
/// (row) and keypoint.
pub fn write_keypoints_3d(
    out: &EntryWriter,
    keypoints: &Keypoints3d,
    model: &BodyModel,
) -> anyhow::Result<()> {
    let k = keypoints.num_keypoints();
    let n = keypoints.num_frames();
    anyhow::ensure!(k > 0, "no keypoints");
    for (i, joint) in keypoints.joints.iter().enumerate() {
        if let Some(j) = joint {
            anyhow::ensure!(
                *j < model.num_joints(),
                "keypoint {i} names joint {j}; the body model has {} joints",
                model.num_joints()
            );
        }
    }
    let mut confidence = keypoints.confidence.clone();
    for (i, (c, p)) in confidence.iter_mut().zip(&keypoints.positions).enumerate() {
        anyhow::ensure!(
            c.is_finite() && *c >= 0.0,
            "confidence {c} of frame {} keypoint {} is not a finite non-negative number",
            i / k,
            i % k
        );
        if !p.is_finite() {
            *c = 0.0;
        }
    }
    let positions: Vec<f64> = keypoints
        .positions
        .iter()
        .flat_map(|p| p.to_array())
        .collect();
    let (n64, k64) = (n as u64, k as u64);
    let chunk = n64.clamp(1, 1024);
    out.write_array(
        "keypoints_3d",
        &["frame", "keypoint", "xyz"],
        &[n64, k64, 3],
        &[chunk, k64, 3],
        &positions,
    )?;
    out.write_array(
        "keypoints_3d_confidence",
        &["frame", "keypoint"],
        &[n64, k64],
        &[chunk, k64],
        &confidence,
    )?;
    let joints: Vec<i64> = keypoints
        .joints
        .iter()
        .map(|j| j.map_or(-1, |j| j as i64))
        .collect();
    out.set_attribute("keypoints_3d_joints", serde_json::to_value(joints)?)?;
    Ok(())
}

/// Reads the arrays written by [`write_keypoints_3d`]; `None` when the entry has none.
/// Errors name the entry and the array or attribute.
pub fn read_keypoints_3d(entry: &EntryReader) -> anyhow::Result<Option<Keypoints3d>> {
    if !entry.has_array("keypoints_3d") {
        return Ok(None);
    }
    let location = entry.location();
    let positions = entry.read::<f64>("keypoints_3d")?;
    anyhow::ensure!(
        positions.shape.len() == 3 && positions.shape[2] == 3,
        "entry {location}: array keypoints_3d has shape {:?}, expected (frame, keypoint, 3)",
        positions.shape
    );
    let (n, k) = (positions.shape[0], positions.shape[1]);
    let confidence = entry.read::<f64>("keypoints_3d_confidence")?;
    anyhow::ensure!(
        confidence.shape == [n, k],
        "entry {location}: array keypoints_3d_confidence has shape {:?}, expected ({n}, {k})",
        confidence.shape
    );
    let joints = entry.attribute("keypoints_3d_joints").ok_or_else(|| {
        anyhow::anyhow!("entry {location}: attribute keypoints_3d_joints is missing")
    })?;
    let joints: Vec<i64> = serde_json::from_value(joints).map_err(|e| {
        anyhow::anyhow!(
            "entry {location}: attribute keypoints_3d_joints is not a list of integers: {e}"
        )
    })?;
    anyhow::ensure!(
        joints.len() == k,
        "entry {location}: attribute keypoints_3d_joints has {} entries for {k} keypoints",
        joints.len()
    );
    let joints = joints
        .into_iter()
        .enumerate()
        .map(|(i, j)| match j {
            -1 => Ok(None),
            j if j >= 0 => Ok(Some(j as usize)),
            j => Err(anyhow::anyhow!(
                "entry {location}: attribute keypoints_3d_joints[{i}] is {j} (a joint index or -1)"
            )),
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Some(Keypoints3d {
        joints,
        positions: positions
            .data
            .chunks_exact(3)
            .map(|c| DVec3::new(c[0], c[1], c[2]))
            .collect(),
        confidence: confidence.data,
    }))
}

/// Writes `<prefix>_pose`, `_world_rotation`, `_world_translation`, `_betas` and (when the
/// model has them) `_expression`, zero-padding coefficients to the model's counts.
pub fn write_body_params(
    out: &EntryWriter,
    prefix: &str,
    params: &[BodyParams],
    model: &BodyModel,
) -> anyhow::Result<()> {
    let n = params.len() as u64;
    let j = model.num_joints() as u64;
    let pose: Vec<f64> = params
        .iter()
        .flat_map(|p| p.pose.iter().flat_map(|v| v.to_array()))
        .collect();
    out.write_whole(
        &format!("{prefix}_pose"),
        &["frame", "joint", "xyz"],
        &[n, j, 3],
        &pose,
    )?;
    let rotation: Vec<f64> = params
        .iter()
        .flat_map(|p| p.world_rotation.to_array())
        .collect();
    out.write_whole(
        &format!("{prefix}_world_rotation"),
        &["frame", "xyz"],
        &[n, 3],
        &rotation,
    )?;
    let translation: Vec<f64> = params
        .iter()
        .flat_map(|p| p.world_translation.to_array())
        .collect();
    out.write_whole(
        &format!("{prefix}_world_translation"),
        &["frame", "xyz"],
        &[n, 3],
        &translation,
    )?;
    let padded = |values: &[f64], count: usize| {
        let mut row = values.to_vec();
        row.resize(count, 0.0);
        row
    };
    let b = model.num_betas();
    if b > 0 {
        let betas: Vec<f64> = params.iter().flat_map(|p| padded(&p.betas, b)).collect();
        out.write_whole(
            &format!("{prefix}_betas"),
            &["frame", "beta"],
            &[n, b as u64],
            &betas,
        )?;
    }
    let e = model.num_expression();
    if e > 0 {
        let expression: Vec<f64> = params
            .iter()
            .flat_map(|p| padded(&p.expression, e))
            .collect();
        out.write_whole(
            &format!("{prefix}_expression"),
            &["frame", "expression"],
            &[n, e as u64],
            &expression,
        )?;
    }
    Ok(())
}

/// Reads per-frame body parameters written by [`write_body_params`] (`prefix` = `body` or
/// `gt_body`).
pub fn read_body_params(entry: &EntryReader, prefix: &str) -> anyhow::Result<Vec<BodyParams>> {
    let pose = entry.read::<f64>(&format!("{prefix}_pose"))?;
    anyhow::ensure!(
        pose.shape.len() == 3 && pose.shape[2] == 3,
        "array {prefix}_pose has shape {:?}, expected (frame, joint, 3)",
        pose.shape
    );
    let (n, j) = (pose.shape[0], pose.shape[1]);
    let rotation = entry.read::<f64>(&format!("{prefix}_world_rotation"))?;
    let translation = entry.read::<f64>(&format!("{prefix}_world_translation"))?;
    for (name, array) in [
        ("world_rotation", &rotation),
        ("world_translation", &translation),
    ] {
        anyhow::ensure!(
            array.shape == [n, 3],
            "array {prefix}_{name} has shape {:?}, expected ({n}, 3)",
            array.shape
        );
    }
    let optional = |name: &str| -> anyhow::Result<(usize, Vec<f64>)> {
        let full = format!("{prefix}_{name}");
        if !entry.has_array(&full) {
            return Ok((0, Vec::new()));
        }
        let array = entry.read::<f64>(&full)?;
        anyhow::ensure!(
            array.shape.len() == 2 && array.shape[0] == n,
            "array {full} has shape {:?}, expected ({n}, K)",
            array.shape
        );
        Ok((array.shape[1], array.data))
    };
    let (b, betas) = optional("betas")?;
    let (e, expression) = optional("expression")?;
    let v3 = |data: &[f64], i: usize| DVec3::new(data[3 * i], data[3 * i + 1], data[3 * i + 2]);
    Ok((0..n)
        .map(|f| BodyParams {
            pose: (0..j).map(|k| v3(&pose.data, f * j + k)).collect(),
            betas: betas[f * b..(f + 1) * b].to_vec(),
            expression: expression[f * e..(f + 1) * e].to_vec(),
            world_rotation: v3(&rotation.data, f),
            world_translation: v3(&translation.data, f),
        })
        .collect())
}

/// Writes the `body_model_*` arrays.
pub fn write_body_model(out: &EntryWriter, model: &BodyModel) -> anyhow::Result<()> {
    let a = model.arrays();
    let v = model.num_vertices() as u64;
    let j = model.num_joints() as u64;
    let f = a.faces.len() as u64;
    let template: Vec<f64> = a.template.iter().flatten().copied().collect();
    out.write_whole(
        "body_model_template",
        &["vertex", "xyz"],
        &[v, 3],
        &template,
    )?;
    let faces: Vec<u32> = a.faces.iter().flatten().copied().collect();
    out.write_array(
        "body_model_faces",
        &["face", "corner"],
        &[f, 3],
        &[f.max(1), 3],
        &faces,
    )?;
    out.write_whole("body_model_parents", &["joint"], &[j], &a.parents)?;
    out.write_whole(
        "body_model_weights",
        &["vertex", "joint"],
        &[v, j],
        &a.weights,
    )?;
    out.write_whole(
        "body_model_joint_regressor",
        &["joint", "vertex"],
        &[j, v],
        &a.joint_regressor,
    )?;
    if a.num_betas > 0 {
        let b = a.num_betas as u64;
        out.write_whole(
            "body_model_shape_dirs",
            &["vertex", "xyz", "beta"],
            &[v, 3, b],
            &a.shape_dirs,
        )?;
    }
    if a.num_expression > 0 {
        let e = a.num_expression as u64;
        out.write_whole(
            "body_model_expression_dirs",
            &["vertex", "xyz", "expression"],
            &[v, 3, e],
            &a.expression_dirs,
        )?;
    }
    if !a.pose_dirs.is_empty() {
        let p = 9 * (j - 1);
        // Chunked by vertex blocks: SMPL-X's pose_dirs are 60 MB.
        let block = v.min(2048);
        out.write_array(
            "body_model_pose_dirs",
            &["vertex", "xyz", "pose_feature"],
            &[v, 3, p],
            &[block, 3, p],
            &a.pose_dirs,
        )?;
    }
    Ok(())
}

/// Reads the body model written by [`write_body_model`] and validates it.
pub fn read_body_model(entry: &EntryReader) -> anyhow::Result<BodyModel> {
    let has = |name: &str| entry.has_array(name);
    let template = entry.read::<f64>("body_model_template")?;
    anyhow::ensure!(
        template.shape.len() == 2 && template.shape[1] == 3,
        "array body_model_template has shape {:?}, expected (vertex, 3)",
        template.shape
    );
    let faces = entry.read::<u32>("body_model_faces")?;
    let parents = entry.read::<i64>("body_model_parents")?;
    // Blend shapes and their count (the last axis), or none where the array is absent.
    let blend_shapes = |name: &str| -> anyhow::Result<(Vec<f64>, usize)> {
        if !has(name) {
            return Ok((Vec::new(), 0));
        }
        let a = entry.read::<f64>(name)?;
        let count = a.shape.last().copied();
        let count = count.ok_or_else(|| anyhow::anyhow!("array {name} is zero-dimensional"))?;
        Ok((a.data, count))
    };
    let (shape_dirs, num_betas) = blend_shapes("body_model_shape_dirs")?;
    let (expression_dirs, num_expression) = blend_shapes("body_model_expression_dirs")?;
    let pose_dirs = if has("body_model_pose_dirs") {
        entry.read::<f32>("body_model_pose_dirs")?.data
    } else {
        Vec::new()
    };
    anyhow::ensure!(
        faces.data.len() % 3 == 0,
        "array body_model_faces is not (face, 3)"
    );
    let arrays = BodyModelArrays {
        template: template
            .data
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        faces: faces
            .data
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
        parents: parents.data,
        weights: entry.read::<f64>("body_model_weights")?.data,
        joint_regressor: entry.read::<f64>("body_model_joint_regressor")?.data,
        shape_dirs,
        num_betas,
        expression_dirs,
        num_expression,
        pose_dirs,
    };
    BodyModel::new(arrays)
        .with_context(|| format!("body model arrays of entry {}", entry.location()))
}

/// The entry's `body_model_kind` attribute (ingest and train entries); `unknown` where absent.
pub fn read_body_model_kind(entry: &EntryReader) -> String {
    let kind = entry.attribute("body_model_kind");
    kind.and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| "unknown".to_owned())
}

/// The per-image garment masks (lib.rs schema), `uint8` 0..255 `(image, height, width)`
/// chunked as `masks`; written only where the dataset has a garment region.
pub const GARMENT_MASKS: &str = "garment_masks";
/// The attribute naming where [`GARMENT_MASKS`] came from ([`GarmentRegion::as_str`]).
pub const GARMENT_REGION_ATTRIBUTE: &str = "garment_region";

/// Where the entry's garment masks came from; `None` when the entry has none (its dataset has
/// no garment region, or it was made before ingest version 5). The array without the
/// attribute (or the other way round), an unknown attribute value, or a `garment_masks`
/// shape other than that of `masks` is an error naming the entry.
pub fn read_garment_region(entry: &EntryReader) -> anyhow::Result<Option<GarmentRegion>> {
    let location = entry.location();
    let attribute = entry.attribute(GARMENT_REGION_ATTRIBUTE);
    let region = match (entry.has_array(GARMENT_MASKS), attribute) {
        (false, None) => return Ok(None),
        (true, Some(value)) => serde_json::from_value::<GarmentRegion>(value.clone()).map_err(|_| {
            anyhow::anyhow!(
                "entry {location}: attribute `{GARMENT_REGION_ATTRIBUTE}` is {value}, expected \"synthetic_skirt\" or \"cihp_clothing\""
            )
        })?,
        (true, None) => anyhow::bail!(
            "entry {location}: array `{GARMENT_MASKS}` without the attribute `{GARMENT_REGION_ATTRIBUTE}`"
        ),
        (false, Some(_)) => anyhow::bail!(
            "entry {location}: attribute `{GARMENT_REGION_ATTRIBUTE}` without the array `{GARMENT_MASKS}`"
        ),
    };
    let (garment, masks) = (entry.shape(GARMENT_MASKS)?, entry.shape("masks")?);
    anyhow::ensure!(
        garment == masks,
        "entry {location}: array `{GARMENT_MASKS}` has shape {garment:?}, expected that of `masks` {masks:?}"
    );
    Ok(Some(region))
}

/// A frame is a *history frame* when its garment's history-only displacement exceeds this
/// many pixels RMS (ingested resolution).
pub const HISTORY_FRAME_PX: f64 = 1.0;

/// Values per frame of `garment_state`: the history scene's skirt oscillator in the body's
/// heading frame, `[forward, across, forward rate, across rate, twist, twist rate]` (hem
/// deflection in metres and metres per second, twist in radians and radians per second).
pub const GARMENT_STATE_COMPONENTS: usize = 6;

/// The garment's history-only displacement per frame (lib.rs schema: `history_*` arrays) and
/// the exact state of its dynamics (`garment_state`).
#[derive(Clone, Debug, PartialEq)]
pub struct GarmentHistoryArrays {
    /// RMS over particles of simulated minus static drape, millimetres.
    pub millimetres: Vec<f64>,
    /// RMS over particles and ingested views of the projected difference, pixels.
    pub pixels: Vec<f64>,
    /// `pixels > HISTORY_FRAME_PX`.
    pub frames: Vec<bool>,
    /// Per frame, the garment's dynamic state ([`GARMENT_STATE_COMPONENTS`] values).
    pub states: Vec<[f64; GARMENT_STATE_COMPONENTS]>,
}

/// Writes `history_displacement_mm`, `history_displacement_px` and `history_frame`, and the
/// attribute `history_frame_px` (the threshold).
pub fn write_garment_history(
    out: &EntryWriter,
    history: &GarmentHistoryArrays,
) -> anyhow::Result<()> {
    let n = history.millimetres.len();
    anyhow::ensure!(
        history.pixels.len() == n && history.frames.len() == n && history.states.len() == n,
        "garment history: {} mm, {} px, {} flags, {} states",
        n,
        history.pixels.len(),
        history.frames.len(),
        history.states.len()
    );
    let n = n as u64;
    let chunk = [n.max(1)];
    out.write_array(
        "history_displacement_mm",
        &["frame"],
        &[n],
        &chunk,
        &history.millimetres,
    )?;
    out.write_array(
        "history_displacement_px",
        &["frame"],
        &[n],
        &chunk,
        &history.pixels,
    )?;
    let flags: Vec<u8> = history.frames.iter().map(|&f| u8::from(f)).collect();
    out.write_array("history_frame", &["frame"], &[n], &chunk, &flags)?;
    out.set_attribute("history_frame_px", HISTORY_FRAME_PX.into())?;
    let states: Vec<f64> = history.states.iter().flatten().copied().collect();
    let components = GARMENT_STATE_COMPONENTS as u64;
    out.write_array(
        "garment_state",
        &["frame", "component"],
        &[n, components],
        &[n.max(1), components],
        &states,
    )?;
    Ok(())
}

/// Reads the arrays of [`write_garment_history`]; `None` when the entry has none (only the
/// synthetic history scene writes them). Errors name the entry and the array.
pub fn read_garment_history(entry: &EntryReader) -> anyhow::Result<Option<GarmentHistoryArrays>> {
    if !entry.has_array("history_frame") {
        return Ok(None);
    }
    let location = entry.location();
    let frames = entry.read::<i64>("frame_source_id")?.data.len();
    let millimetres = entry.read::<f64>("history_displacement_mm")?;
    let pixels = entry.read::<f64>("history_displacement_px")?;
    let flags = entry.read::<u8>("history_frame")?;
    let states = entry.read::<f64>("garment_state")?;
    for (name, shape) in [
        ("history_displacement_mm", &millimetres.shape),
        ("history_displacement_px", &pixels.shape),
        ("history_frame", &flags.shape),
    ] {
        anyhow::ensure!(
            *shape == [frames],
            "entry {location}: array `{name}` has shape {shape:?}, expected ({frames}) (the frame axis)"
        );
    }
    anyhow::ensure!(
        states.shape == [frames, GARMENT_STATE_COMPONENTS],
        "entry {location}: array `garment_state` has shape {:?}, expected ({frames}, {GARMENT_STATE_COMPONENTS})",
        states.shape
    );
    if let Some(bad) = flags.data.iter().find(|f| **f > 1) {
        anyhow::bail!("entry {location}: array `history_frame` holds {bad}, expected 0 or 1");
    }
    if let Some(bad) = states.data.iter().position(|v| !v.is_finite()) {
        anyhow::bail!(
            "entry {location}: array `garment_state` has a non-finite value at frame {}",
            bad / GARMENT_STATE_COMPONENTS
        );
    }
    Ok(Some(GarmentHistoryArrays {
        millimetres: millimetres.data,
        pixels: pixels.data,
        frames: flags.data.iter().map(|&f| f == 1).collect(),
        states: states
            .data
            .chunks_exact(GARMENT_STATE_COMPONENTS)
            .map(|c| std::array::from_fn(|k| c[k]))
            .collect(),
    }))
}

/// One camera of a capture as the dataset calibrates it: full resolution, OpenCV
/// distortion, continuous pixel convention (built with [`Camera::from_opencv`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SourceCamera {
    /// The dataset's own camera id (ZJU `Camera_B<id>`, DNA `"<id>"`, I3D `view_<id>`).
    pub id: i64,
    pub camera: Camera,
}

/// 3D keypoints of every frame of a dataset's frame list (`frame`-major), in world space,
/// metres. A keypoint whose position is not finite is missing: [`write_keypoints_3d`] stores
/// it with confidence 0.
#[derive(Clone, Debug, PartialEq)]
pub struct Keypoints3d {
    /// Per keypoint, the body joint it measures; `None` where the dataset does not document
    /// the correspondence.
    pub joints: Vec<Option<usize>>,
    /// `(frame, keypoint)` positions.
    pub positions: Vec<seqavatar_core::glam::DVec3>,
    /// `(frame, keypoint)` confidence, finite and non-negative; 0 = missing.
    pub confidence: Vec<f64>,
}

impl Keypoints3d {
    pub fn num_keypoints(&self) -> usize {
        self.joints.len()
    }

    /// Number of frames (rows).
    pub fn num_frames(&self) -> usize {
        self.positions.len() / self.num_keypoints().max(1)
    }
}

/// Where a dataset's garment region comes from: the ingest entry's `garment_region`
/// attribute, written with the `garment_masks` array (lib.rs schema).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GarmentRegion {
    /// The synthetic scene's skirt: the pixels whose visible surface is a skirt triangle.
    SyntheticSkirt,
    /// ZJU-MoCap `mask_cihp/` part labels: the union of the clothing labels
    /// (`CIHP_GARMENT_LABELS` of the ZJU-MoCap reader).
    CihpClothing,
}

impl GarmentRegion {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::SyntheticSkirt => "synthetic_skirt",
            Self::CihpClothing => "cihp_clothing",
        }
    }
}

/// What an ingest entry will hold, as far as the stage's config determines it when the
/// pipeline loads (the stage's `planned` hook), for the stages downstream to check then.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlannedIngest {
    /// The images of the split, where the config determines them (the synthetic scene);
    /// `None` for file-based datasets, whose split comes from their files.
    pub images: Option<IngestImages>,
    /// Why the entry will hold no test image, where the config already says so.
    pub no_test_images: Option<String>,
}

/// The images an ingest entry holds, or will hold: how many (training and test) and the
/// largest view's size, and where the figures come from (for messages: the config fields
/// of a plan, or the entry).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IngestImages {
    pub count: u64,
    pub width: u64,
    pub height: u64,
    pub source: String,
}

impl IngestImages {
    /// From the entry's image arrays ([`ImageArrays`]), before any image is read.
    pub fn of_entry(entry: &EntryReader) -> anyhow::Result<Self> {
        let arrays = ImageArrays::read(entry)?;
        let (count, width, height) = (arrays.len() as u64, arrays.width, arrays.height);
        let source = format!("entry {}", entry.location());
        Ok(Self {
            count,
            width,
            height,
            source,
        })
    }
}

impl PlannedIngest {
    /// The plan of an ingest input as a downstream stage's load-time check sees it.
    pub fn of(input: &seqavatar_engine::StageInput<'_>) -> Result<Self, String> {
        planned_of(input)
    }
}

/// Reads a stage input's plan as `T`; `Null` (no plan) is `T::default()`.
pub(crate) fn planned_of<T: Default + serde::de::DeserializeOwned>(
    input: &seqavatar_engine::StageInput<'_>,
) -> Result<T, String> {
    if input.planned.is_null() {
        return Ok(T::default());
    }
    serde_json::from_value(input.planned.clone())
        .map_err(|e| format!("input {} ({}): its plan: {e}", input.name, input.kind))
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_engine::LocalStore;

    fn write(out: &EntryWriter, case: &str) -> anyhow::Result<()> {
        let (ids, split): (&[i64], &[u8]) = match case {
            "good" => (&[10, 12, 14], &[0, 1, 7]),
            "short" => (&[10, 12, 14], &[0, 1]),
            _ => (&[10, 12], &[1, 9]),
        };
        let frames = ids.len() as u64;
        out.write_array("frame_source_id", &["frame"], &[frames], &[frames], ids)?;
        let n = split.len() as u64;
        out.write_array("frame_split", &["frame"], &[n], &[n], split)?;
        match case {
            "good" => write_frame_interval(out, 2),
            "short" => out.set_attribute("frame_interval", 0.into()),
            _ => Ok(()),
        }
    }

    #[test]
    fn frame_split_and_interval_read_back_or_name_the_entry_and_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let good = crate::testing::entry(&store, write, "good");
        assert_eq!(read_frame_interval(&good).unwrap(), 2);
        assert_eq!(read_frame_split(&good).unwrap(), [0, 1, 7]);
        let short = crate::testing::entry(&store, write, "short");
        let bits = crate::testing::entry(&store, write, "bits");
        for (entry, error, expected) in [
            (
                &short,
                read_frame_interval(&short).unwrap_err(),
                "attribute `frame_interval` = 0 is not a positive integer",
            ),
            (
                &short,
                read_frame_split(&short).unwrap_err(),
                "array `frame_split` has shape [2], expected (3)",
            ),
            (
                &bits,
                read_frame_interval(&bits).unwrap_err(),
                "attribute `frame_interval` is missing",
            ),
            (
                &bits,
                read_frame_split(&bits).unwrap_err(),
                "array `frame_split` holds 9, expected 0 .. 7",
            ),
        ] {
            let message = format!("{error:#}");
            assert!(
                message.contains(expected) && message.contains(entry.location()),
                "{message}"
            );
        }
    }
}
