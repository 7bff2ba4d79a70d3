//! DNA-Rendering takes: a main `.smc` (HDF5) with JPEG-encoded images and an annotation
//! `.smc` with cameras, masks and SMPL-X fits (layout in `datasets.md`), read with the
//! pure-Rust [`crate::smc`] reader (size limits, strict UTF-8: see there).
//!
//! Conventions converted here:
//! - `Camera_Parameter/<NN>/RT` is camera-to-world: the world-to-camera rotation is `R^T`
//!   and the translation `-R^T c`. `K` has integer pixel centres ([`Camera::from_opencv`]
//!   adds 0.5); `D` is OpenCV's `(k1, k2, p1, p2, k3)`. `Color_Calibration` is not applied.
//! - Image sizes come from the camera groups' `resolution` attribute, `(height, width)`.
//! - Masks: the maximum over the decoded channels, soft values kept.
//! - SMPL-X: `fullpose` (N, 55, 3) is the pose in SMPL-X joint order; the model was built
//!   with `flat_hand_mean=False`, so the body model's mean hand pose (`hands_meanl`,
//!   `hands_meanr`) is added to joints 25..55 here, giving the rotations the model actually
//!   applies. `transl` is [`BodyParams::world_translation`] (no world rotation). `betas` and
//!   `expression` with a single row, or fewer rows than frames, are broadcast (the last row
//!   repeats) with a warning; extra rows are dropped with a warning. `scale` other than 1 is
//!   reported as a warning and not applied.
//! - `Keypoints_3D/keypoints3d` (optional), `(frames, K, 3)` or `(frames, K, 4)` with a
//!   confidence column (confidence 1 without one): carried as stored (world space, metres,
//!   as the SMPL-X fits; the dataset's own reader leaves the coordinate frame as a TODO). A
//!   keypoint with a non-finite coordinate or confidence gets confidence 0. Which body joint
//!   each keypoint measures is not documented (`datasets.md`, the dataset's reader), so none
//!   is mapped (every joint index is `None`): fit `mode: keypoints` refuses such an entry.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::{DMat3, DVec3};

use crate::body_model::load_fits_model;
use crate::common::{check_finite, decode_mask, decode_rgb, warn};
use crate::smc::SmcFile;
use crate::{BodyModelKind, DatasetReader, Keypoints3d, SourceCamera, SourceImage, Split};
use seqavatar_formats::npz;

/// The two camera groups of the main file.
const CAMERA_GROUPS: [&str; 2] = ["Camera_5mp", "Camera_12mp"];

/// An opened DNA-Rendering take.
pub struct DnaRendering {
    main_file: SmcFile,
    annot_file: SmcFile,
    cameras: Vec<SourceCamera>,
    /// Per camera: the main-file group holding its images.
    camera_groups: Vec<&'static str>,
    num_frames: usize,
    /// Per frame, before the hand mean is added.
    params: Vec<BodyParams>,
    body_model_path: Option<PathBuf>,
    /// SMPL-X mean hand pose (90 values), read from the body model file at open.
    hands_mean: Option<Vec<f64>>,
    /// `Keypoints_3D/keypoints3d`, when the annotation file has it.
    keypoints: Option<Keypoints3d>,
    pub gender: Option<String>,
    pub warnings: Vec<String>,
}

/// Where the annotation file of `main` is: `<part>_main/<take>.smc` ->
/// `<part>_annotations/<take>_annots.smc`, or `<take>_annots.smc` next to the main file.
pub fn annotation_candidates(main: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let (Some(dir), Some(stem)) = (main.parent(), main.file_stem().and_then(|s| s.to_str())) else {
        return out;
    };
    let name = format!("{stem}_annots.smc");
    if let Some(dir_name) = dir.file_name().and_then(|s| s.to_str())
        && let Some(part) = dir_name.strip_suffix("main")
    {
        out.push(dir.with_file_name(format!("{part}annotations")).join(&name));
    }
    out.push(dir.join(&name));
    out
}

/// A numeric dataset, checked finite.
fn read_f64s(file: &SmcFile, path: &str) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
    let (shape, values) = file.read_f64s(path)?;
    check_finite(&values, &file.context(&format!("dataset `{path}`")))?;
    Ok((shape, values))
}

/// Rows of a per-frame array: `rows` values each, broadcast or truncated to `frames` rows.
fn per_frame(
    values: Vec<f64>,
    shape: &[usize],
    width: usize,
    frames: usize,
    what: &str,
    warnings: &mut Vec<String>,
) -> anyhow::Result<Vec<Vec<f64>>> {
    if width == 0 || !values.len().is_multiple_of(width) || values.is_empty() {
        bail!("{what} has shape {shape:?}; expected (frames, {width})");
    }
    let mut rows: Vec<Vec<f64>> = values.chunks_exact(width).map(<[f64]>::to_vec).collect();
    if rows.len() < frames {
        warn(
            warnings,
            format!(
                "{what} has {} rows for {frames} frames: repeating the last row for frames {}..{frames}",
                rows.len(),
                rows.len()
            ),
        );
        let last = rows.last().expect("non-empty").clone();
        rows.resize(frames, last);
    } else if rows.len() > frames {
        warn(
            warnings,
            format!(
                "{what} has {} rows for {frames} frames: ignoring the extra rows",
                rows.len()
            ),
        );
        rows.truncate(frames);
    }
    Ok(rows)
}

/// Reads one member array of an `.npz` without loading the others.
fn npz_member(path: &Path, name: &str) -> anyhow::Result<Option<Vec<f64>>> {
    let bytes = crate::common::read_bytes(path)?;
    let entries =
        npz::list(&bytes).with_context(|| format!("{}: not a readable .npz", path.display()))?;
    let Some(entry) = entries.iter().find(|e| e.name == format!("{name}.npy")) else {
        return Ok(None);
    };
    let value = npz::read_member(&bytes, entry)
        .with_context(|| format!("{}: member `{name}`", path.display()))?;
    let (_, values) = value
        .to_f64_array()
        .with_context(|| format!("{}: member `{name}` is not numeric", path.display()))?;
    Ok(Some(values))
}

/// Parses `Keypoints_3D/keypoints3d` values of shape `shape` into the first `frames` rows
/// (module docs); `what` names the file and dataset in errors.
pub fn parse_keypoints(
    shape: &[usize],
    values: &[f64],
    frames: usize,
    what: &str,
) -> anyhow::Result<Keypoints3d> {
    let [rows, count, width] = shape[..] else {
        bail!("{what} has shape {shape:?}; expected (frames, keypoints, 3 or 4)");
    };
    if count == 0 || !(width == 3 || width == 4) || values.len() != rows * count * width {
        bail!("{what} has shape {shape:?}; expected (frames, keypoints, 3 or 4)");
    }
    if rows < frames {
        bail!("{what} has {rows} frames but the main file has {frames}");
    }
    let mut positions = Vec::with_capacity(frames * count);
    let mut confidence = Vec::with_capacity(frames * count);
    for point in values.chunks_exact(width).take(frames * count) {
        let p = DVec3::new(point[0], point[1], point[2]);
        let c = if width == 4 { point[3] } else { 1.0 };
        let i = positions.len();
        if c.is_finite() && c < 0.0 {
            bail!(
                "{what}: frame {} keypoint {} has negative confidence {c}",
                i / count,
                i % count
            );
        }
        positions.push(p);
        confidence.push(if p.is_finite() && c.is_finite() {
            c
        } else {
            0.0
        });
    }
    Ok(Keypoints3d {
        joints: vec![None; count],
        positions,
        confidence,
    })
}

/// The annotation file found next to `main` ([`annotation_candidates`]).
fn find_annotations(main: &Path) -> anyhow::Result<PathBuf> {
    let candidates = annotation_candidates(main);
    candidates
        .iter()
        .find(|c| c.is_file())
        .cloned()
        .with_context(|| {
            format!(
                "{}: the annotation file is missing (looked for {}); DNA-Rendering needs both \
             the main and the annotation .smc",
                main.display(),
                candidates
                    .iter()
                    .map(|c| c.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })
}

/// The two files of a take, as the steps of [`DnaRendering::open`] read them.
struct TakeFiles<'a> {
    main_file: &'a SmcFile,
    annot_file: &'a SmcFile,
}

/// The cameras of a take that have images, and the frames they all hold.
struct TakeCameras {
    cameras: Vec<SourceCamera>,
    /// The main-file group (`Camera_5mp`, `Camera_12mp`) of each camera.
    camera_groups: Vec<&'static str>,
    num_frames: usize,
}

impl TakeFiles<'_> {
    /// Cameras: every calibrated camera that has images in the main file.
    fn cameras(&self, warnings: &mut Vec<String>) -> anyhow::Result<TakeCameras> {
        let (main, annotations) = (self.main_file.path(), self.annot_file.path());
        let mut ids: Vec<(i64, String)> = self
            .annot_file
            .members("Camera_Parameter")?
            .into_iter()
            .filter_map(|name| name.parse::<i64>().ok().map(|id| (id, name)))
            .collect();
        ids.sort();
        let mut cameras = Vec::new();
        let mut camera_groups = Vec::new();
        let mut num_frames: Option<usize> = None;
        for (id, key) in ids {
            let mut found = None;
            for group_name in CAMERA_GROUPS {
                if self.main_file.has_group(&format!("{group_name}/{id}"))? {
                    found = Some(group_name);
                    break;
                }
            }
            let Some(group_name) = found else {
                warn(
                    warnings,
                    format!(
                        "{}: camera {key} is calibrated but has no images in {}",
                        annotations.display(),
                        main.display()
                    ),
                );
                continue;
            };
            let (width, height) = self.resolution(group_name)?;
            let frames = self
                .main_file
                .members(&format!("{group_name}/{id}/color"))?
                .len();
            num_frames = Some(num_frames.map_or(frames, |n| n.min(frames)));
            let camera = self.calibration(&key, width, height)?;
            cameras.push(SourceCamera { id, camera });
            camera_groups.push(group_name);
        }
        if cameras.is_empty() {
            bail!(
                "{}: no camera in `Camera_Parameter` has images in the main file",
                annotations.display()
            );
        }
        let num_frames = num_frames.unwrap_or(0);
        if num_frames == 0 {
            bail!("{}: the cameras hold no frame", main.display());
        }
        Ok(TakeCameras {
            cameras,
            camera_groups,
            num_frames,
        })
    }

    /// The image size (width, height) of a camera group's `resolution` attribute.
    fn resolution(&self, group_name: &str) -> anyhow::Result<(u32, u32)> {
        let main = self.main_file.path();
        let resolution = self
            .main_file
            .f64s_attr(group_name, "resolution")?
            .with_context(|| {
                format!(
                    "{}: group `{group_name}` has no attribute `resolution`",
                    main.display()
                )
            })?;
        let [height, width] = resolution[..] else {
            bail!(
                "{}: group `{group_name}` attribute `resolution` must be (height, width)",
                main.display()
            );
        };
        let pixels = |v: f64| {
            (v.fract() == 0.0 && (0.0..=f64::from(u32::MAX)).contains(&v)).then_some(v as u32)
        };
        let (Some(width), Some(height)) = (pixels(width), pixels(height)) else {
            bail!(
                "{}: group `{group_name}` attribute `resolution` {resolution:?} is not two pixel \
                 counts",
                main.display()
            );
        };
        Ok((width, height))
    }

    /// The camera of `Camera_Parameter/<key>` (`K`, `D`, camera-to-world `RT`).
    fn calibration(&self, key: &str, width: u32, height: u32) -> anyhow::Result<Camera> {
        let annotations = self.annot_file.path();
        let prefix = format!("Camera_Parameter/{key}");
        let (_, k) = read_f64s(self.annot_file, &format!("{prefix}/K"))?;
        let (_, d) = read_f64s(self.annot_file, &format!("{prefix}/D"))?;
        let (_, rt) = read_f64s(self.annot_file, &format!("{prefix}/RT"))?;
        if k.len() != 9 || rt.len() != 16 || d.len() < 4 || d.len() > 5 {
            bail!(
                "{}: `{prefix}`: K must be 3x3, RT 4x4 and D 5 values; got {}, {}, {} values",
                annotations.display(),
                k.len(),
                rt.len(),
                d.len()
            );
        }
        let mut distortion = [0.0; 5];
        distortion[..d.len()].copy_from_slice(&d);
        // Camera-to-world: rotation columns are the camera axes in world coordinates.
        let cam_to_world = DMat3::from_cols_array(&[
            rt[0], rt[4], rt[8], rt[1], rt[5], rt[9], rt[2], rt[6], rt[10],
        ]);
        let centre = DVec3::new(rt[3], rt[7], rt[11]);
        let rotation = cam_to_world.transpose();
        let translation = -(rotation * centre);
        let kk = [[k[0], k[1], k[2]], [k[3], k[4], k[5]], [k[6], k[7], k[8]]];
        Camera::from_opencv(width, height, kk, rotation, translation, distortion)
            .with_context(|| format!("{}: `{prefix}`", annotations.display()))
    }

    /// The SMPL-X fits of the first `num_frames` frames (`SMPLx/*`).
    fn smplx_params(
        &self,
        num_frames: usize,
        warnings: &mut Vec<String>,
    ) -> anyhow::Result<Vec<BodyParams>> {
        let (annotations, annot_file) = (self.annot_file.path(), self.annot_file);
        if !annot_file.has_group("SMPLx")? {
            bail!(
                "{}: missing group `SMPLx` (fits exist for parts 1 and 2 only)",
                annotations.display()
            );
        }
        let (pose_shape, fullpose) = read_f64s(annot_file, "SMPLx/fullpose")?;
        if fullpose.len() % 165 != 0 {
            bail!(
                "{}: dataset `SMPLx/fullpose` has shape {pose_shape:?}; expected (frames, 55, 3)",
                annotations.display()
            );
        }
        let pose_frames = fullpose.len() / 165;
        if pose_frames < num_frames {
            bail!(
                "{}: dataset `SMPLx/fullpose` has {pose_frames} frames but the main file has {num_frames}",
                annotations.display()
            );
        }
        let file_what = |path: &str| format!("{} dataset `{path}`", annotations.display());
        let (transl_shape, transl) = read_f64s(annot_file, "SMPLx/transl")?;
        if transl.len() / 3 < num_frames || transl.len() % 3 != 0 {
            bail!(
                "{}: dataset `SMPLx/transl` has shape {transl_shape:?}; expected ({num_frames}, 3)",
                annotations.display()
            );
        }
        // Coefficients per frame, as wide as the dataset's last axis.
        let mut per_frame_rows = |path: &str| {
            let (shape, values) = read_f64s(annot_file, path)?;
            let width = *shape.last().unwrap_or(&0);
            per_frame(
                values,
                &shape,
                width,
                num_frames,
                &file_what(path),
                warnings,
            )
        };
        let betas = per_frame_rows("SMPLx/betas")?;
        let expression = if annot_file.has_dataset("SMPLx/expression")? {
            per_frame_rows("SMPLx/expression")?
        } else {
            vec![Vec::new(); num_frames]
        };
        if annot_file.has_dataset("SMPLx/scale")? {
            let (_, scale) = read_f64s(annot_file, "SMPLx/scale")?;
            if scale.iter().any(|s| (s - 1.0).abs() > 1e-6) {
                warn(
                    warnings,
                    format!(
                        "{}: SMPL-X scale {scale:?} is not applied (the body model has no scale)",
                        file_what("SMPLx/scale")
                    ),
                );
            }
        }
        Ok((0..num_frames)
            .map(|f| BodyParams {
                pose: fullpose[f * 165..(f + 1) * 165]
                    .chunks_exact(3)
                    .map(|c| DVec3::new(c[0], c[1], c[2]))
                    .collect(),
                betas: betas[f].clone(),
                expression: expression[f].clone(),
                world_rotation: DVec3::ZERO,
                world_translation: DVec3::new(transl[3 * f], transl[3 * f + 1], transl[3 * f + 2]),
            })
            .collect())
    }

    /// The 3D keypoints of the first `num_frames` frames, when the take has them.
    fn keypoints(&self, num_frames: usize) -> anyhow::Result<Option<Keypoints3d>> {
        if !self.annot_file.has_dataset("Keypoints_3D/keypoints3d")? {
            return Ok(None);
        }
        // Not checked finite: a missing keypoint is NaN (module docs).
        let (shape, values) = self.annot_file.read_f64s("Keypoints_3D/keypoints3d")?;
        let what = format!(
            "{} dataset `Keypoints_3D/keypoints3d`",
            self.annot_file.path().display()
        );
        Ok(Some(parse_keypoints(&shape, &values, num_frames, &what)?))
    }
}

/// The SMPL-X mean hand pose of the body model file at `path` (`hands_meanl` then
/// `hands_meanr`); without it (a warning) the hand poses are used as they are.
fn hands_mean(path: &Path, warnings: &mut Vec<String>) -> anyhow::Result<Option<Vec<f64>>> {
    let left = npz_member(path, "hands_meanl")?;
    let right = npz_member(path, "hands_meanr")?;
    Ok(match (left, right) {
        (Some(l), Some(r)) if l.len() == 45 && r.len() == 45 => {
            Some(l.into_iter().chain(r).collect())
        }
        _ => {
            warn(
                warnings,
                format!(
                    "{}: no 45-value `hands_meanl`/`hands_meanr`; the DNA-Rendering hand poses are used without the SMPL-X mean hand pose",
                    path.display()
                ),
            );
            None
        }
    })
}

impl DnaRendering {
    /// Opens a take from its main file; the annotation file is `annotations` or found next
    /// to the main file ([`annotation_candidates`]).
    pub fn open(
        main: &Path,
        annotations: Option<&Path>,
        body_model: Option<&Path>,
    ) -> anyhow::Result<Self> {
        let mut warnings = Vec::new();
        let annotations = match annotations {
            Some(a) => a.to_owned(),
            None => find_annotations(main)?,
        };
        let main_file = SmcFile::open(main)?;
        let annot_file = SmcFile::open(&annotations)?;
        let gender = main_file.string_attr("", "gender")?;
        let take = TakeFiles {
            main_file: &main_file,
            annot_file: &annot_file,
        };
        let TakeCameras {
            cameras,
            camera_groups,
            num_frames,
        } = take.cameras(&mut warnings)?;
        let params = take.smplx_params(num_frames, &mut warnings)?;
        let keypoints = take.keypoints(num_frames)?;
        let hands_mean = match body_model {
            Some(path) => hands_mean(path, &mut warnings)?,
            None => None,
        };
        Ok(Self {
            main_file,
            annot_file,
            cameras,
            camera_groups,
            num_frames,
            params,
            body_model_path: body_model.map(Path::to_owned),
            hands_mean,
            keypoints,
            gender,
            warnings,
        })
    }
}

impl DatasetReader for DnaRendering {
    fn describe(&self) -> String {
        format!(
            "DNA-Rendering {} (gender {})",
            self.main_file.path().display(),
            self.gender.as_deref().unwrap_or("unknown")
        )
    }

    fn cameras(&self) -> &[SourceCamera] {
        &self.cameras
    }

    fn num_frames(&self) -> usize {
        self.num_frames
    }

    fn default_split(&self) -> Split {
        let index_of = |ids: &mut dyn Iterator<Item = i64>| -> Vec<usize> {
            ids.filter_map(|id| self.cameras.iter().position(|c| c.id == id))
                .collect()
        };
        let train_end = 100.min(self.num_frames);
        Split::first_frames(
            index_of(&mut (0..=46).step_by(2)),
            index_of(&mut (48..=58).step_by(2)),
            Some(train_end),
            5,
        )
    }

    fn body_model(&self) -> anyhow::Result<(BodyModel, BodyModelKind)> {
        load_fits_model(
            self.body_model_path.as_deref(),
            "DNA-Rendering",
            BodyModelKind::Smplx,
        )
    }

    fn body_params(&self, frame: usize) -> anyhow::Result<BodyParams> {
        let mut params = self
            .params
            .get(frame)
            .cloned()
            .with_context(|| format!("DNA-Rendering: frame {frame} of {}", self.num_frames))?;
        if let Some(mean) = &self.hands_mean {
            for (joint, m) in params.pose[25..55].iter_mut().zip(mean.chunks_exact(3)) {
                *joint += DVec3::new(m[0], m[1], m[2]);
            }
        }
        Ok(params)
    }

    fn keypoints_3d(&self) -> anyhow::Result<Option<Keypoints3d>> {
        Ok(self.keypoints.clone())
    }

    fn read_image(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage> {
        let id = self.cameras[view].id;
        let image_path = format!("{}/{id}/color/{frame}", self.camera_groups[view]);
        let bytes = self.main_file.read_bytes(&image_path)?;
        let source = format!("{} dataset `{image_path}`", self.main_file.path().display());
        let camera = &self.cameras[view].camera;
        let rgb = decode_rgb(&bytes, &source, (camera.width, camera.height))?;
        let mask_path = format!("Mask/{id}/mask/{frame}");
        let mask_bytes = self.annot_file.read_bytes(&mask_path)?;
        let mask_source = format!("{} dataset `{mask_path}`", self.annot_file.path().display());
        let mask = decode_mask(&mask_bytes, &mask_source, false, rgb.dimensions())?;
        Ok(SourceImage { rgb, mask })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keypoints_parse_with_and_without_confidence() {
        let values = [
            1.0,
            2.0,
            3.0,
            0.9, //
            f64::NAN,
            0.0,
            0.0,
            0.8, //
            4.0,
            5.0,
            6.0,
            f64::NAN, //
            7.0,
            8.0,
            9.0,
            0.5, //
            0.0,
            0.0,
            0.0,
            0.0, //
            0.0,
            0.0,
            0.0,
            0.0,
        ];
        let k = parse_keypoints(&[3, 2, 4], &values, 2, "f `K`").unwrap();
        assert_eq!(k.joints, vec![None, None]);
        assert_eq!(k.num_frames(), 2);
        assert_eq!(k.confidence, vec![0.9, 0.0, 0.0, 0.5]);
        assert_eq!(k.positions[3], DVec3::new(7.0, 8.0, 9.0));
        let k = parse_keypoints(&[1, 1, 3], &[1.0, 2.0, 3.0], 1, "f").unwrap();
        assert_eq!(k.confidence, vec![1.0]);
        let e = parse_keypoints(&[1, 2, 5], &[0.0; 10], 1, "f `K`").unwrap_err();
        assert!(e.to_string().contains("f `K` has shape [1, 2, 5]"), "{e}");
        let e = parse_keypoints(&[1, 1, 3], &[0.0; 3], 2, "f").unwrap_err();
        assert!(
            e.to_string().contains("1 frames but the main file has 2"),
            "{e}"
        );
        let e = parse_keypoints(
            &[1, 2, 4],
            &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0],
            1,
            "f",
        )
        .unwrap_err();
        assert!(e.to_string().contains("frame 0 keypoint 1"), "{e}");
    }

    #[test]
    fn annotation_file_names() {
        let c = annotation_candidates(Path::new("/d/dna_rendering_part1_main/0007_04.smc"));
        assert_eq!(
            c,
            vec![
                PathBuf::from("/d/dna_rendering_part1_annotations/0007_04_annots.smc"),
                PathBuf::from("/d/dna_rendering_part1_main/0007_04_annots.smc"),
            ]
        );
    }

    #[test]
    fn per_frame_rows_broadcast_and_truncate_with_warnings() {
        let mut warnings = Vec::new();
        let rows = per_frame(vec![1.0, 2.0], &[1, 2], 2, 3, "betas", &mut warnings).unwrap();
        assert_eq!(rows, vec![vec![1.0, 2.0]; 3]);
        assert_eq!(warnings.len(), 1);
        let rows = per_frame(vec![1.0, 2.0, 3.0, 4.0], &[2, 2], 2, 1, "x", &mut warnings).unwrap();
        assert_eq!(rows, vec![vec![1.0, 2.0]]);
        assert_eq!(warnings.len(), 2);
        assert!(per_frame(vec![1.0; 3], &[3], 2, 1, "x", &mut warnings).is_err());
        assert!(per_frame(vec![], &[0, 2], 2, 1, "x", &mut warnings).is_err());
    }
}
