//! What a training run reads from its input entries: cameras and images of the ingest entry
//! (rescaled by `resolution_scale`), per-frame body parameters (of the fit entry when there
//! is one, else of the ingest entry), the body rig, and the motion entry's per-(frame, scale)
//! arrays from which every training window is a gather.

use anyhow::Context;
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::DVec3;
use seqavatar_engine::EntryReader;
use seqavatar_formats::resample::{SourceImage, resample};
use seqavatar_schema::ingest::{
    ImageArrays, read_body_model, read_body_model_kind, read_body_params,
};

use seqavatar_avatar::rig::BodyRig;
use seqavatar_schema::motion::MotionTrack;

use crate::losses::{Rect, bound_box};

/// One ingested image, resampled to the training resolution.
#[derive(Clone, Debug)]
pub struct ImageRecord {
    pub view: usize,
    pub frame: usize,
    /// 0 train, 1 test.
    pub split: u8,
    /// `H x W x 3` bytes.
    pub rgb: Vec<u8>,
    /// `H x W` bytes, 255 = foreground.
    pub mask: Vec<u8>,
    /// The padded foreground bounding box; `None` for an empty mask.
    pub bound: Option<Rect>,
}

impl ImageRecord {
    /// The training target: the image composited with its mask onto `background`,
    /// `m c + (1 - m) b` per channel with `c = rgb / 255` and `m = mask / 255`, so that
    /// whatever the camera saw behind the person is replaced by the colour the avatar is
    /// rendered on.
    pub fn colour_on(&self, background: [f64; 3]) -> Vec<f64> {
        self.rgb
            .chunks_exact(3)
            .zip(&self.mask)
            .flat_map(|(pixel, &mask)| {
                let m = f64::from(mask) / 255.0;
                [0, 1, 2].map(|c| m * (f64::from(pixel[c]) / 255.0) + (1.0 - m) * background[c])
            })
            .collect()
    }

    /// Mask in `[0, 1]` as f64.
    pub fn mask_f64(&self) -> Vec<f64> {
        self.mask.iter().map(|&b| f64::from(b) / 255.0).collect()
    }
}

/// The cameras of an entry (the ingest schema's reader, re-exported for this crate's users).
pub use seqavatar_schema::ingest::read_cameras;

/// Everything a run reads, in memory.
#[derive(Clone, Debug)]
pub struct TrainingData {
    /// Cameras at the training resolution, one per view.
    pub cameras: Vec<Camera>,
    pub images: Vec<ImageRecord>,
    /// Body parameters per frame.
    pub params: Vec<BodyParams>,
    pub rig: BodyRig,
    pub motion: MotionTrack,
    /// Extent of the camera rig (docs/method.md: 1.1 x the largest distance of a training camera
    /// from their centroid).
    pub extent: f64,
    /// The body model kind attribute of the ingest entry.
    pub body_model_kind: String,
}

/// The body parameters (of `params_entry`), the body model (of `ingest`) and the motion
/// track, checked against each other.
fn read_body_and_motion(
    ingest: &EntryReader,
    params_entry: &EntryReader,
    motion: &EntryReader,
) -> anyhow::Result<(Vec<BodyParams>, BodyModel, MotionTrack)> {
    let params = read_body_params(params_entry, "body")?;
    let model = read_body_model(ingest)?;
    let motion_track = MotionTrack::read(motion)?;
    anyhow::ensure!(
        motion_track.num_frames == params.len(),
        "entry {}: {} motion frames, but entry {} has body parameters for {} frames",
        motion.location(),
        motion_track.num_frames,
        params_entry.location(),
        params.len()
    );
    anyhow::ensure!(
        motion_track.num_vertices == model.num_vertices()
            && motion_track.body_joints() == model.num_joints(),
        "entry {}: motion arrays have {} vertices and {} joints, the body model {} and {}",
        motion.location(),
        motion_track.num_vertices,
        motion_track.body_joints(),
        model.num_vertices(),
        model.num_joints()
    );
    for (i, p) in params.iter().enumerate() {
        model.check_params(p).with_context(|| {
            format!(
                "entry {}: body parameters of frame {i}",
                params_entry.location()
            )
        })?;
    }
    Ok((params, model, motion_track))
}

impl TrainingData {
    /// The bound box of image `index` grown by `padding` pixels and clipped to its camera's
    /// image; `None` for an image without foreground.
    pub fn padded_bound(&self, index: usize, padding: usize) -> Option<Rect> {
        let record = &self.images[index];
        let camera = &self.cameras[record.view];
        record.bound.map(|bound| {
            crate::run::pad_rect(
                bound,
                padding,
                camera.width as usize,
                camera.height as usize,
            )
        })
    }

    /// Reads the entries. `params_entry` is the fit entry if the pipeline has one, else the
    /// ingest entry.
    pub fn read(
        ingest: &EntryReader,
        params_entry: &EntryReader,
        motion: &EntryReader,
        resolution_scale: f64,
    ) -> anyhow::Result<Self> {
        let location = ingest.location();
        let source_cameras = read_cameras(ingest)?;
        let cameras: Vec<Camera> = source_cameras
            .iter()
            .map(|c| c.rescaled(resolution_scale))
            .collect();
        let arrays = ImageArrays::read(ingest)?;
        let (params, model, motion_track) = read_body_and_motion(ingest, params_entry, motion)?;
        let rig = BodyRig::new(model)?;
        // Image `i`, resampled to its training camera, with its mask's bound box.
        let record = |i: usize| -> anyhow::Result<ImageRecord> {
            let (view, frame) = (arrays.view[i] as usize, arrays.frame[i] as usize);
            anyhow::ensure!(
                frame < params.len(),
                "entry {location}: image {i} names frame {frame}, but there are {} frames",
                params.len()
            );
            let source = &source_cameras[view];
            let source_image = SourceImage {
                rgb: arrays.image(ingest, i)?,
                mask: arrays.mask(ingest, i)?,
            };
            let target = &cameras[view];
            let (rgb, mask) = resample(&source_image, source, target)
                .with_context(|| format!("entry {location}: resampling image {i}"))?;
            let mask_f: Vec<f64> = mask.iter().map(|&b| f64::from(b) / 255.0).collect();
            let bound = bound_box(&mask_f, target.width as usize, target.height as usize, 0);
            Ok(ImageRecord {
                view,
                frame,
                split: arrays.split[i],
                rgb,
                mask,
                bound,
            })
        };
        let images = (0..arrays.len())
            .map(record)
            .collect::<anyhow::Result<Vec<_>>>()?;
        let train_views: Vec<usize> = {
            let mut v: Vec<usize> = images
                .iter()
                .filter(|r| r.split == 0)
                .map(|r| r.view)
                .collect();
            v.sort_unstable();
            v.dedup();
            v
        };
        anyhow::ensure!(
            !train_views.is_empty(),
            "entry {location}: no training images"
        );
        let extent = camera_extent(train_views.iter().map(|&v| &cameras[v]));
        let body_model_kind = read_body_model_kind(ingest);
        Ok(Self {
            cameras,
            images,
            params,
            rig,
            motion: motion_track,
            extent,
            body_model_kind,
        })
    }

    /// Indices into `images` of one split.
    pub fn split(&self, split: u8) -> Vec<usize> {
        (0..self.images.len())
            .filter(|&i| self.images[i].split == split)
            .collect()
    }
}

/// 1.1 x the largest distance of a camera centre from the centroid (at least 1 cm, so that
/// one camera still has a scale).
pub fn camera_extent<'a>(cameras: impl Iterator<Item = &'a Camera>) -> f64 {
    let centres: Vec<DVec3> = cameras.map(|c| c.center()).collect();
    let centroid = centres.iter().copied().sum::<DVec3>() / centres.len().max(1) as f64;
    let radius = centres
        .iter()
        .map(|c| (*c - centroid).length())
        .fold(0.0, f64::max);
    (1.1 * radius).max(0.01)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::camera::Intrinsics;

    #[test]
    fn targets_are_composited_with_their_mask() {
        // Four pixels: foreground, background, 20 % and 60 % coverage; values worked out
        // by hand (m c + (1 - m) b).
        let record = ImageRecord {
            view: 0,
            frame: 0,
            split: 0,
            rgb: vec![255, 0, 51, 90, 180, 12, 255, 255, 255, 0, 102, 255],
            mask: vec![255, 0, 51, 153],
            bound: None,
        };
        let background = [0.0, 0.5, 1.0];
        let expected = [
            [1.0, 0.0, 0.2],
            [0.0, 0.5, 1.0],
            [0.2, 0.6, 1.0],
            [0.0, 0.44, 1.0],
        ];
        let got = record.colour_on(background);
        assert_eq!(got.len(), 12);
        for (pixel, want) in got.chunks_exact(3).zip(expected) {
            for (g, w) in pixel.iter().zip(want) {
                assert!((g - w).abs() < 1e-12, "{pixel:?} vs {want:?}");
            }
        }
        // On black, the foreground keeps its colour premultiplied by the mask.
        let black = record.colour_on([0.0; 3]);
        assert_eq!(&black[3..6], &[0.0; 3]);
        assert!((black[9 + 1] - 0.6 * 0.4).abs() < 1e-12);
    }

    #[test]
    fn extent_of_a_ring_is_its_radius_times_1_1() {
        let cams: Vec<Camera> = (0..6)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 6.0;
                Camera::look_at(
                    64,
                    64,
                    Intrinsics {
                        fx: 50.0,
                        fy: 50.0,
                        cx: 32.0,
                        cy: 32.0,
                    },
                    DVec3::new(3.0 * a.cos(), 1.0, 3.0 * a.sin()),
                    DVec3::ZERO,
                    DVec3::Y,
                )
            })
            .collect();
        let e = camera_extent(cams.iter());
        assert!((e - 3.3).abs() < 1e-9, "{e}");
    }
}
