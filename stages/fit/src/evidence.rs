//! Evidence that a fit matches the capture, and the per-track choice between a refined fit
//! and the input fit.
//!
//! Two measures, each only where the ingest entry has the data:
//! - **Silhouette IoU** per image: the posed body ([`BodyModel::forward`]) rasterized with
//!   the ingest stage's software rasterizer ([`seqavatar_datasets::synthetic::raster`]) into
//!   the image's camera, against the ingest mask (foreground: mask >= 128). Images are
//!   compared at most [`EVIDENCE_MAX_SIDE`] pixels on their longer side (masks resampled
//!   with the ingest stage's [`resample`]), which keeps the test cheap on full-size captures.
//! - **Keypoint error** per frame: the confidence-weighted distance between posed joints and
//!   the 3D keypoints that name a joint.
//!
//! [`choose_tracks`] tests every track (a joint's rotations, the world rotation, the
//! translation) in the context of the others, as they were refined together: the refined
//! fit against the same with only that track put back to the input. A track whose
//! refinement made the evidence worse (mean IoU lower, or keypoint error higher) keeps its
//! input fit.

use rayon::prelude::*;
use seqavatar_core::body::BodyModel;
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::DVec3;
use seqavatar_datasets::synthetic::raster::{EMPTY, rasterize};
use seqavatar_engine::EntryReader;
use seqavatar_formats::resample::{SourceImage, resample};

use crate::keypoints::KeypointObservations;
use seqavatar_schema::body::BodySequence;
use seqavatar_schema::fit::TrackVerdict;
use seqavatar_schema::ingest::ImageArrays;

/// Longest side, in pixels, at which silhouettes are compared.
pub const EVIDENCE_MAX_SIDE: u32 = 256;

/// One ingested image's mask, at the evidence resolution of its view.
#[derive(Clone, Debug)]
pub struct MaskImage {
    pub view: usize,
    pub frame: usize,
    /// Row-major, `true` = foreground.
    pub foreground: Vec<bool>,
}

/// The cameras (at evidence resolution) and masks of an ingest entry.
#[derive(Clone, Debug)]
pub struct Silhouettes {
    pub cameras: Vec<Camera>,
    pub images: Vec<MaskImage>,
}

/// The evidence resolution of a camera: scaled down so its longer side is at most
/// [`EVIDENCE_MAX_SIDE`].
pub fn evidence_camera(camera: &Camera) -> Camera {
    let side = camera.width.max(camera.height);
    if side <= EVIDENCE_MAX_SIDE {
        return camera.clone();
    }
    camera.rescaled(f64::from(EVIDENCE_MAX_SIDE) / f64::from(side))
}

impl Silhouettes {
    /// Reads the cameras and every image's mask of an ingest entry; `None` when it has no
    /// images. Errors name the entry and the array.
    pub fn read(ingest: &EntryReader) -> anyhow::Result<Option<Self>> {
        let location = ingest.location();
        let source_cameras = seqavatar_schema::ingest::read_cameras(ingest)?;
        let arrays = ImageArrays::read(ingest)?;
        if arrays.is_empty() {
            return Ok(None);
        }
        let cameras: Vec<Camera> = source_cameras.iter().map(evidence_camera).collect();
        let images = (0..arrays.len())
            .into_par_iter()
            .map(|i| -> anyhow::Result<MaskImage> {
                let view = arrays.view[i] as usize;
                let source = &source_cameras[view];
                let (w, h) = (source.width, source.height);
                let source_image = SourceImage {
                    rgb: image::RgbImage::new(w, h),
                    mask: arrays.mask(ingest, i)?,
                };
                // `read_cameras` gives distortion-free cameras: only the size changes.
                let (_, mask) = resample(&source_image, source, &cameras[view])
                    .map_err(|e| anyhow::anyhow!("entry {location}: mask of image {i}: {e}"))?;
                Ok(MaskImage {
                    view,
                    frame: arrays.frame[i] as usize,
                    foreground: mask.iter().map(|&m| m >= 128).collect(),
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(Some(Self { cameras, images }))
    }

    /// IoU of the posed body's silhouette and the mask of every image whose frame is in
    /// `posed` (`posed[frame]`: world vertices, or `None` to skip the image: `NaN`).
    pub fn iou(&self, faces: &[[u32; 3]], posed: &[Option<Vec<DVec3>>]) -> Vec<f64> {
        self.images
            .par_iter()
            .map(
                |image| match posed.get(image.frame).and_then(Option::as_ref) {
                    Some(vertices) => {
                        let buffer = rasterize(&self.cameras[image.view], vertices, faces);
                        silhouette_iou(&buffer.triangle, &image.foreground)
                    }
                    None => f64::NAN,
                },
            )
            .collect()
    }

    /// Mean of per-image values over the images of each view (`NaN` for a view with none).
    pub fn per_view_mean(&self, values: &[f64]) -> Vec<f64> {
        let mut sum = vec![0.0; self.cameras.len()];
        let mut count = vec![0usize; self.cameras.len()];
        for (image, value) in self.images.iter().zip(values) {
            sum[image.view] += value;
            count[image.view] += 1;
        }
        sum.iter()
            .zip(&count)
            .map(|(s, &c)| if c == 0 { f64::NAN } else { s / c as f64 })
            .collect()
    }
}

/// Intersection over union of the covered samples of a visibility buffer and a mask; 1
/// when both are empty.
pub fn silhouette_iou(triangle: &[u32], foreground: &[bool]) -> f64 {
    let (mut intersection, mut union) = (0usize, 0usize);
    for (&t, &m) in triangle.iter().zip(foreground) {
        let body = t != EMPTY;
        intersection += usize::from(body && m);
        union += usize::from(body || m);
    }
    if union == 0 {
        1.0
    } else {
        intersection as f64 / union as f64
    }
}

/// Confidence-weighted keypoint distance of one frame from its posed joints: `(sum of
/// c d, sum of c)`.
pub fn frame_keypoint_distance(
    observations: &KeypointObservations,
    frame: usize,
    joints: &[DVec3],
) -> (f64, f64) {
    let k = observations.per_frame();
    let (mut distance, mut weight) = (0.0, 0.0);
    for i in 0..k {
        let c = observations.confidence[frame * k + i];
        if c == 0.0 {
            continue;
        }
        let d = (joints[observations.joints[i]] - observations.positions[frame * k + i]).length();
        distance += c * d;
        weight += c;
    }
    (distance, weight)
}

/// The evidence a fit is judged by.
pub struct EvidenceSources<'a> {
    pub model: &'a BodyModel,
    pub silhouettes: Option<&'a Silhouettes>,
    pub keypoints: Option<&'a KeypointObservations>,
}

/// Evidence of one sequence.
#[derive(Clone, Debug, PartialEq)]
pub struct Evidence {
    /// Per ingested image (empty without silhouettes).
    pub iou: Vec<f64>,
    /// Per frame `(sum of c d, sum of c)` (empty without keypoints).
    pub keypoints: Vec<(f64, f64)>,
}

impl Evidence {
    /// Mean IoU over all images (`None` without silhouettes).
    pub fn mean_iou(&self) -> Option<f64> {
        (!self.iou.is_empty()).then(|| self.iou.iter().sum::<f64>() / self.iou.len() as f64)
    }

    /// Mean keypoint distance, metres (`None` without keypoints).
    pub fn keypoint_error(&self) -> Option<f64> {
        if self.keypoints.is_empty() {
            return None;
        }
        let (d, w) = self
            .keypoints
            .iter()
            .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
        Some(if w > 0.0 { d / w } else { 0.0 })
    }
}

impl EvidenceSources<'_> {
    /// Whether there is anything to judge by.
    pub fn any(&self) -> bool {
        self.silhouettes.is_some() || self.keypoints.is_some()
    }

    /// Evidence of the frames marked in `frames` (all when `None`); the others are left at
    /// `NaN` / zero weight.
    fn measure(
        &self,
        sequence: &BodySequence,
        frames: Option<&[bool]>,
    ) -> anyhow::Result<Evidence> {
        let wanted = |t: usize| frames.is_none_or(|f| f[t]);
        let posed: Vec<Option<(Vec<DVec3>, Vec<DVec3>)>> = (0..sequence.num_frames)
            .into_par_iter()
            .map(|t| -> anyhow::Result<_> {
                if !wanted(t) {
                    return Ok(None);
                }
                let posed = self
                    .model
                    .forward(&sequence.params(t))
                    .map_err(|e| anyhow::anyhow!("frame {t}: {e}"))?;
                Ok(Some((posed.vertices, posed.joints)))
            })
            .collect::<anyhow::Result<_>>()?;
        let iou = match self.silhouettes {
            Some(s) => {
                let vertices: Vec<Option<Vec<DVec3>>> = posed
                    .iter()
                    .map(|p| p.as_ref().map(|(v, _)| v.clone()))
                    .collect();
                s.iou(self.model.faces(), &vertices)
            }
            None => Vec::new(),
        };
        let keypoints = match self.keypoints {
            Some(k) => posed
                .iter()
                .enumerate()
                .map(|(t, p)| match p {
                    Some((_, joints)) => frame_keypoint_distance(k, t, joints),
                    None => (0.0, 0.0),
                })
                .collect(),
            None => Vec::new(),
        };
        Ok(Evidence { iou, keypoints })
    }

    /// Evidence of a whole sequence.
    pub fn evidence(&self, sequence: &BodySequence) -> anyhow::Result<Evidence> {
        self.measure(sequence, None)
    }
}

/// The tracks of a sequence: joint rotations `0..J`, the world rotation `J`, the
/// translation `J + 1`.
pub fn track_name(track: usize, num_joints: usize) -> String {
    match track.checked_sub(num_joints) {
        None => format!("joint {track}"),
        Some(0) => "world rotation".to_owned(),
        Some(_) => "translation".to_owned(),
    }
}

/// Copies track `track` of `from` into `to`.
fn copy_track(to: &mut BodySequence, from: &BodySequence, track: usize) {
    let j = to.num_joints;
    for t in 0..to.num_frames {
        if track < j {
            to.pose[t * j + track] = from.pose[t * j + track];
        } else if track == j {
            to.world_rotation[t] = from.world_rotation[t];
        } else {
            to.world_translation[t] = from.world_translation[t];
        }
    }
}

/// Frames where track `track` differs between two sequences.
fn changed_frames(a: &BodySequence, b: &BodySequence, track: usize) -> Vec<bool> {
    let j = a.num_joints;
    (0..a.num_frames)
        .map(|t| {
            if track < j {
                a.pose[t * j + track] != b.pose[t * j + track]
            } else if track == j {
                a.world_rotation[t] != b.world_rotation[t]
            } else {
                a.world_translation[t] != b.world_translation[t]
            }
        })
        .collect()
}

/// Judges each track of `refined` in the context of the others (module docs): the refined
/// sequence against the same with only that track put back to `input`. Returns the refined
/// sequence with every track whose refinement made the evidence worse put back, and a
/// verdict per track. The shape (betas, expression) of `refined` is kept: it is shared per
/// subject, not a track.
pub fn choose_tracks(
    sources: &EvidenceSources<'_>,
    input: &BodySequence,
    refined: &BodySequence,
) -> anyhow::Result<(BodySequence, Vec<TrackVerdict>)> {
    let j = input.num_joints;
    let refined_evidence = sources.evidence(refined)?;
    let num_images = refined_evidence.iou.len().max(1) as f64;
    let total_weight: f64 = refined_evidence.keypoints.iter().map(|k| k.1).sum();
    let mut output = refined.clone();
    let mut verdicts = Vec::with_capacity(j + 2);
    for track in 0..j + 2 {
        let frames = changed_frames(input, refined, track);
        if !frames.contains(&true) {
            verdicts.push(TrackVerdict {
                iou_change: 0.0,
                keypoint_change: 0.0,
                kept_input: false,
            });
            continue;
        }
        let mut without = refined.clone();
        copy_track(&mut without, input, track);
        let evidence = sources.measure(&without, Some(&frames))?;
        // What refining this track changed: refined minus refined-without-it.
        let iou_change: f64 = refined_evidence
            .iou
            .iter()
            .zip(&evidence.iou)
            .filter(|(_, b)| !b.is_nan())
            .map(|(a, b)| a - b)
            .sum::<f64>()
            / num_images;
        let keypoint_change = if total_weight > 0.0 {
            refined_evidence
                .keypoints
                .iter()
                .zip(&evidence.keypoints)
                .zip(&frames)
                .filter(|(_, changed)| **changed)
                .map(|((a, b), _)| a.0 - b.0)
                .sum::<f64>()
                / total_weight
        } else {
            0.0
        };
        let kept_input = iou_change < 0.0 || keypoint_change > 0.0;
        if kept_input {
            copy_track(&mut output, input, track);
        }
        verdicts.push(TrackVerdict {
            iou_change,
            keypoint_change,
            kept_input,
        });
    }
    Ok((output, verdicts))
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::body::BodyParams;
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_core::camera::Intrinsics;
    use seqavatar_schema::ingest::Keypoints3d;

    #[test]
    fn iou_of_known_coverage() {
        // Body on samples 0 and 2, mask on 0 and 1: 1 shared of 3 covered.
        let iou = silhouette_iou(&[0, EMPTY, 1, EMPTY], &[true, true, false, false]);
        assert!((iou - 1.0 / 3.0).abs() < 1e-15);
        assert_eq!(silhouette_iou(&[EMPTY; 3], &[false; 3]), 1.0);
        assert_eq!(silhouette_iou(&[5; 2], &[true; 2]), 1.0);
        assert_eq!(silhouette_iou(&[5, 5], &[false, false]), 0.0);
        assert_eq!(track_name(3, 24), "joint 3");
        assert_eq!(track_name(24, 24), "world rotation");
        assert_eq!(track_name(25, 24), "translation");
    }

    /// A small capture of a known body: two cameras, masks drawn from the true fits, and
    /// keypoints at the true joints.
    fn capture(model: &BodyModel, truth: &BodySequence) -> (Silhouettes, KeypointObservations) {
        let intrinsics = Intrinsics {
            fx: 60.0,
            fy: 60.0,
            cx: 24.0,
            cy: 32.0,
        };
        let centre = DVec3::new(0.0, 0.9, 0.0);
        let cameras: Vec<Camera> = [DVec3::new(0.0, 1.0, 3.0), DVec3::new(3.0, 1.0, 0.5)]
            .into_iter()
            .map(|eye| Camera::look_at(48, 64, intrinsics, eye, centre, DVec3::Y))
            .collect();
        let mut images = Vec::new();
        let mut positions = Vec::new();
        for frame in 0..truth.num_frames {
            let posed = model.forward(&truth.params(frame)).unwrap();
            for (view, camera) in cameras.iter().enumerate() {
                let buffer = rasterize(camera, &posed.vertices, model.faces());
                images.push(MaskImage {
                    view,
                    frame,
                    foreground: buffer.triangle.iter().map(|&t| t != EMPTY).collect(),
                });
            }
            positions.extend(posed.joints);
        }
        let j = model.num_joints();
        let keypoints = Keypoints3d {
            joints: (0..j).map(Some).collect(),
            confidence: vec![1.0; positions.len()],
            positions,
        };
        (
            Silhouettes { cameras, images },
            KeypointObservations::new(&keypoints, j).unwrap(),
        )
    }

    /// Refining one track toward the truth is taken; bending another away from it, or
    /// shifting the translation, keeps the input, by either kind of evidence alone.
    #[test]
    fn worse_tracks_keep_their_input_and_better_ones_are_taken() {
        let model = procedural_body(0.04);
        let frames = 3;
        let params: Vec<BodyParams> = (0..frames)
            .map(|t| {
                let mut p = model.zero_params();
                p.pose[1] = DVec3::new(-0.3 + 0.2 * t as f64, 0.0, 0.0);
                p.pose[16] = DVec3::new(0.0, 0.0, -0.9);
                p.pose[17] = DVec3::new(0.0, 0.0, 0.9);
                p.world_translation = DVec3::new(0.05 * t as f64, 0.0, 0.0);
                p
            })
            .collect();
        let truth = BodySequence::from_params(&params).unwrap();
        let (silhouettes, keypoints) = capture(&model, &truth);
        // The input fit: the right elbow (joint 19) off by 0.5 rad.
        let mut input = truth.clone();
        for t in 0..frames {
            input.pose[t * 24 + 19] = DVec3::new(0.0, 0.5, 0.5);
        }
        // The refinement repairs the elbow, bends the left knee (joint 4) and shifts the body.
        let mut refined = truth.clone();
        for t in 0..frames {
            refined.pose[t * 24 + 4] = DVec3::new(0.8, 0.0, 0.0);
            refined.world_translation[t].x += 0.06;
        }
        for (silhouettes, keypoints) in [
            (Some(&silhouettes), None),
            (None, Some(&keypoints)),
            (Some(&silhouettes), Some(&keypoints)),
        ] {
            let sources = EvidenceSources {
                model: &model,
                silhouettes,
                keypoints,
            };
            let (output, verdicts) = choose_tracks(&sources, &input, &refined).unwrap();
            assert_eq!(verdicts.len(), 26);
            let kept: Vec<usize> = (0..26).filter(|&k| verdicts[k].kept_input).collect();
            assert_eq!(kept, vec![4, 25], "{verdicts:?}");
            assert!(!verdicts[19].kept_input);
            for t in 0..frames {
                assert_eq!(output.pose[t * 24 + 19], truth.pose[t * 24 + 19]);
                assert_eq!(output.pose[t * 24 + 4], input.pose[t * 24 + 4]);
                assert_eq!(output.world_translation[t], input.world_translation[t]);
            }
            if silhouettes.is_some() {
                assert!(verdicts[19].iou_change > 0.0 && verdicts[4].iou_change < 0.0);
                let before = sources.evidence(&input).unwrap().mean_iou().unwrap();
                let after = sources.evidence(&output).unwrap().mean_iou().unwrap();
                assert!(after > before && after == 1.0, "{before} -> {after}");
            } else {
                assert!(verdicts[19].keypoint_change < 0.0 && verdicts[4].keypoint_change > 0.0);
                let error = sources.evidence(&output).unwrap().keypoint_error().unwrap();
                assert!(error < 1e-12, "{error}");
            }
        }
    }
}
