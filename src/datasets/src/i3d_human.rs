//! I3D-Human (`<root>/<ID>-train/`, `<ID>-novelview/`, `<ID>-novelpose/`), the HumanNeRF-style
//! layout Dyco uses: per folder `cameras.pkl` and `mesh_infos.pkl` keyed by image name
//! (`frame_{:06d}_view_{:02d}`), `frameid_pose.pkl` (list by frame number), `images/` and
//! `masks/` (`<name>.png`, non-zero = foreground).
//!
//! The reader merges the three folders: its cameras are every view id found (sorted), its
//! frame list every frame number from 0 to the last one any file mentions, so that the frame
//! list index is the frame number and the motion stage's "t - l s" is a plain subtraction.
//!
//! Conventions converted here:
//! - `intrinsics` has integer pixel centres: [`Camera::from_opencv`] adds 0.5.
//!   `extrinsics` is a 4 x 4 world-to-camera matrix in metres.
//! - Fits: `Rh`, `Th` are [`BodyParams::world_rotation`]/`world_translation` (world =
//!   `R(Rh) x + Th`); `poses` (72) are the local joint rotations, root first. A frame without
//!   a `mesh_infos.pkl` entry takes its fit from `frameid_pose.pkl`, whose `poses` (23, 3)
//!   leave out the root (taken as zero, which is what the HumanNeRF preprocessing stores in
//!   `poses[0:3]` since it moves the global orientation into `Rh`). Betas are zero.
//! - The body model is SMPL (from the ingest config's `body_model`).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::{DMat3, DVec3};

use crate::body_model::load_fits_model;
use crate::common::{Field, image_size, read_mask, read_pickle, read_rgb, warn};
use crate::{BodyModelKind, DatasetReader, FrameRange, SourceCamera, SourceImage, Split};
use seqavatar_formats::Value;

/// The Dyco split: (sequence, train view ids, test view ids, frame interval) (docs/method.md).
const SPLITS: [(&str, &[i64], &[i64], usize); 4] = [
    ("ID1_1", &[1, 3, 6, 8], &[2, 4, 7, 9], 1),
    ("ID1_2", &[0, 2, 5, 7], &[1, 6, 8, 9], 1),
    ("ID2_1", &[1, 3, 5, 7, 9], &[2, 4, 6, 10], 3),
    ("ID3_1", &[1, 3, 5, 7, 9], &[2, 4, 6, 8, 10], 3),
];

/// The sub-folders of a sequence, in the order the reader looks for an image.
const PARTS: [&str; 3] = ["train", "novelview", "novelpose"];

/// The existing sub-folders of sequence `sequence` under `root` with their index in
/// [`PARTS`]: every file the reader reads lies in one of them.
pub fn sequence_folders(root: &Path, sequence: &str) -> Vec<(usize, PathBuf)> {
    PARTS
        .iter()
        .enumerate()
        .map(|(i, part)| (i, root.join(format!("{sequence}-{part}"))))
        .filter(|(_, p)| p.is_dir())
        .collect()
}

/// Where one image lives.
#[derive(Clone, Debug)]
struct ImageRef {
    folder: PathBuf,
    name: String,
}

/// An opened I3D-Human sequence.
pub struct I3dHuman {
    root: PathBuf,
    sequence: String,
    cameras: Vec<SourceCamera>,
    num_frames: usize,
    /// (frame number, camera index) -> image.
    images: HashMap<(usize, usize), ImageRef>,
    /// Frame number -> fit.
    params: BTreeMap<usize, BodyParams>,
    /// Frame numbers with training-folder images, per camera index.
    train_frames: BTreeSet<usize>,
    /// Frame numbers with novel-view-folder images.
    test_frames: BTreeSet<usize>,
    body_model_path: Option<PathBuf>,
    pub warnings: Vec<String>,
}

/// `frame_000012_view_03` -> (12, 3).
fn parse_name(name: &str) -> Option<(usize, i64)> {
    let rest = name.strip_prefix("frame_")?;
    let (frame, view) = rest.split_once("_view_")?;
    if frame.len() > 9 || view.len() > 9 {
        return None;
    }
    Some((frame.parse().ok()?, view.parse().ok()?))
}

fn dict_items<'a>(file: &Path, value: &'a Value) -> anyhow::Result<&'a [(Value, Value)]> {
    value.as_dict().with_context(|| {
        format!(
            "{}: expected a dict keyed by image name, found {value}",
            file.display()
        )
    })
}

fn key_name<'a>(file: &Path, key: &'a Value) -> anyhow::Result<(&'a str, usize, i64)> {
    let name = key
        .as_str()
        .with_context(|| format!("{}: key {key} is not an image name", file.display()))?;
    let (frame, view) = parse_name(name).with_context(|| {
        format!(
            "{}: key {name:?} is not of the form frame_NNNNNN_view_NN",
            file.display()
        )
    })?;
    Ok((name, frame, view))
}

fn camera_from_entry(
    file: &Path,
    name: &str,
    entry: &Value,
    size: (u32, u32),
) -> anyhow::Result<Camera> {
    let path_k = format!("{name}.intrinsics");
    let path_e = format!("{name}.extrinsics");
    let path_d = format!("{name}.distortions");
    let field = Field {
        file,
        path: name,
        value: entry,
    };
    let k = field.get("intrinsics", &path_k)?.matrix3()?;
    let e = field.get("extrinsics", &path_e)?.finite_f64s(16)?;
    let distortion = match entry.get("distortions") {
        Some(Value::None) | None => [0.0; 5],
        Some(_) => field.get("distortions", &path_d)?.distortion()?,
    };
    let rotation = DMat3::from_cols_array(&[e[0], e[4], e[8], e[1], e[5], e[9], e[2], e[6], e[10]]);
    let translation = DVec3::new(e[3], e[7], e[11]);
    Camera::from_opencv(size.0, size.1, k, rotation, translation, distortion)
        .with_context(|| format!("{}: camera `{name}`", file.display()))
}

/// The fit `name` (`Rh`, `Th`, `poses`): `mesh_infos.pkl` holds 72 pose values, root first;
/// `frameid_pose.pkl` 69, without the root (then zero).
fn params_from_fit(
    file: &Path,
    name: &str,
    entry: &Value,
    pose_values: usize,
) -> anyhow::Result<BodyParams> {
    let field = Field {
        file,
        path: name,
        value: entry,
    };
    let [p_rh, p_th, p_poses] = ["Rh", "Th", "poses"].map(|key| format!("{name}.{key}"));
    let rh = field.get("Rh", &p_rh)?.finite_f64s(3)?;
    let th = field.get("Th", &p_th)?.finite_f64s(3)?;
    let poses = field.get("poses", &p_poses)?.finite_f64s(pose_values)?;
    let mut pose = if pose_values == 72 {
        Vec::new()
    } else {
        vec![DVec3::ZERO]
    };
    pose.extend(poses.chunks_exact(3).map(|c| DVec3::new(c[0], c[1], c[2])));
    Ok(BodyParams {
        pose,
        betas: Vec::new(),
        expression: Vec::new(),
        world_rotation: DVec3::new(rh[0], rh[1], rh[2]),
        world_translation: DVec3::new(th[0], th[1], th[2]),
    })
}

impl I3dHuman {
    /// Opens sequence `sequence` (e.g. `ID1_1`) under `root`.
    pub fn open(root: &Path, sequence: &str, body_model: Option<&Path>) -> anyhow::Result<Self> {
        let folders = sequence_folders(root, sequence);
        if folders.is_empty() {
            bail!(
                "I3D-Human: no folder {0}-train, {0}-novelview or {0}-novelpose under {1}",
                sequence,
                root.display()
            );
        }
        let mut scan = SequenceScan::default();
        for (part, folder) in &folders {
            scan.read_cameras(*part, folder)?;
            scan.read_mesh_infos(folder)?;
            let pose_path = folder.join("frameid_pose.pkl");
            if scan.frameid_pose.is_none() && pose_path.is_file() {
                let value = read_pickle(&pose_path)?;
                scan.frameid_pose = Some((pose_path, value));
            }
        }
        scan.fill_from_frameid_pose()?;
        let SequenceScan {
            views,
            images_by_id,
            params,
            train_frames,
            test_frames,
            warnings,
            ..
        } = scan;
        let ids: Vec<i64> = views.keys().copied().collect();
        let cameras: Vec<SourceCamera> = views
            .into_iter()
            .map(|(id, (camera, _))| SourceCamera { id, camera })
            .collect();
        let mut images = HashMap::new();
        for (frame, view, image) in images_by_id {
            let index = ids
                .binary_search(&view)
                .expect("view ids come from the same files");
            images.entry((frame, index)).or_insert(image);
        }
        let last_image = images.keys().map(|&(f, _)| f).max();
        let last_param = params.keys().copied().max();
        let num_frames = last_image.max(last_param).map_or(0, |f| f + 1);
        if num_frames == 0 {
            bail!("I3D-Human {sequence}: the sequence lists no frame");
        }
        Ok(Self {
            root: root.to_owned(),
            sequence: sequence.to_owned(),
            cameras,
            num_frames,
            images,
            params,
            train_frames,
            test_frames,
            body_model_path: body_model.map(Path::to_owned),
            warnings,
        })
    }
}

/// What [`I3dHuman::open`] gathers from the folders of a sequence, in folder order.
#[derive(Default)]
struct SequenceScan {
    /// view id -> (camera, source file and key for messages)
    views: BTreeMap<i64, (Camera, String)>,
    /// (frame, view id, image) of every image.
    images_by_id: Vec<(usize, i64, ImageRef)>,
    params: BTreeMap<usize, BodyParams>,
    /// Whether a `mesh_infos.pkl` fit has a non-zero root rotation.
    nonzero_root: bool,
    /// The first `frameid_pose.pkl` found, and its path.
    frameid_pose: Option<(PathBuf, Value)>,
    train_frames: BTreeSet<usize>,
    test_frames: BTreeSet<usize>,
    warnings: Vec<String>,
}

impl SequenceScan {
    /// The cameras and images of `folder`'s `cameras.pkl`; a view keeps its first camera (a
    /// later, different one is a warning).
    fn read_cameras(&mut self, part: usize, folder: &Path) -> anyhow::Result<()> {
        let cameras_path = folder.join("cameras.pkl");
        let cameras_value = read_pickle(&cameras_path)?;
        for (key, entry) in dict_items(&cameras_path, &cameras_value)? {
            let (name, frame, view) = key_name(&cameras_path, key)?;
            let image = ImageRef {
                folder: folder.to_owned(),
                name: name.to_owned(),
            };
            match self.views.entry(view) {
                std::collections::btree_map::Entry::Vacant(slot) => {
                    let image_path = folder.join("images").join(format!("{name}.png"));
                    let size = image_size(&image_path)?;
                    let camera = camera_from_entry(&cameras_path, name, entry, size)?;
                    slot.insert((camera, format!("{} `{name}`", cameras_path.display())));
                }
                std::collections::btree_map::Entry::Occupied(known) => {
                    let (first, origin) = known.get();
                    let camera =
                        camera_from_entry(&cameras_path, name, entry, (first.width, first.height))?;
                    if !same_camera(first, &camera) {
                        warn(
                            &mut self.warnings,
                            format!(
                                "{}: camera `{name}` of view {view} differs from {origin}, which the reader uses",
                                cameras_path.display()
                            ),
                        );
                    }
                }
            }
            match part {
                0 => {
                    self.train_frames.insert(frame);
                }
                1 => {
                    self.test_frames.insert(frame);
                }
                _ => {}
            }
            self.images_by_id.push((frame, view, image));
        }
        Ok(())
    }

    /// The fits of `folder`'s `mesh_infos.pkl`; a frame keeps its first fit.
    fn read_mesh_infos(&mut self, folder: &Path) -> anyhow::Result<()> {
        let mesh_path = folder.join("mesh_infos.pkl");
        let mesh_value = read_pickle(&mesh_path)?;
        for (key, entry) in dict_items(&mesh_path, &mesh_value)? {
            let (name, frame, _) = key_name(&mesh_path, key)?;
            let p = params_from_fit(&mesh_path, name, entry, 72)?;
            self.nonzero_root |= p.pose[0] != DVec3::ZERO;
            self.params.entry(frame).or_insert(p);
        }
        Ok(())
    }

    /// Frames without a `mesh_infos.pkl` fit take theirs from `frameid_pose.pkl`.
    fn fill_from_frameid_pose(&mut self) -> anyhow::Result<()> {
        let Some((path, value)) = &self.frameid_pose else {
            return Ok(());
        };
        let list = Field::root(path, value).sequence()?;
        let mut filled = 0;
        for (index, entry) in list.iter().enumerate() {
            if let std::collections::btree_map::Entry::Vacant(slot) = self.params.entry(index) {
                slot.insert(params_from_fit(path, &format!("[{index}]"), entry, 69)?);
                filled += 1;
            }
        }
        if filled > 0 && self.nonzero_root {
            warn(
                &mut self.warnings,
                format!(
                    "{}: {filled} frames take their fit from this file, which has no root rotation (taken as zero) while mesh_infos.pkl has non-zero root rotations",
                    path.display()
                ),
            );
        }
        Ok(())
    }
}

/// Whether two cameras have the same intrinsic matrix and extrinsics, to a relative 1e-6.
fn same_camera(a: &Camera, b: &Camera) -> bool {
    let close = |x: f64, y: f64| (x - y).abs() <= 1e-6 * (1.0 + x.abs().max(y.abs()));
    let entries = |c: &Camera| {
        c.k_matrix()
            .into_iter()
            .flatten()
            .chain(c.rotation.to_cols_array())
            .chain(c.translation.to_array())
    };
    entries(a).zip(entries(b)).all(|(x, y)| close(x, y))
}

/// The smallest range (start, end, step) that covers `frames` if they are evenly spaced.
fn frame_range(frames: &BTreeSet<usize>, fallback_step: usize) -> FrameRange {
    let list: Vec<usize> = frames.iter().copied().collect();
    let step = match list.as_slice() {
        [] | [_] => fallback_step.max(1),
        [a, b, ..] => {
            let step = b - a;
            if list.windows(2).all(|w| w[1] - w[0] == step) {
                step
            } else {
                fallback_step.max(1)
            }
        }
    };
    FrameRange {
        start: list.first().copied().unwrap_or(0),
        end: list.last().map(|l| l + 1),
        step,
    }
}

impl DatasetReader for I3dHuman {
    fn describe(&self) -> String {
        format!("I3D-Human {} {}", self.root.display(), self.sequence)
    }

    fn cameras(&self) -> &[SourceCamera] {
        &self.cameras
    }

    fn num_frames(&self) -> usize {
        self.num_frames
    }

    fn default_split(&self) -> Split {
        let ids: Vec<i64> = self.cameras.iter().map(|c| c.id).collect();
        let index_of = |views: &[i64]| -> Vec<usize> {
            views
                .iter()
                .filter_map(|v| ids.binary_search(v).ok())
                .collect()
        };
        let table = SPLITS.iter().find(|(name, ..)| *name == self.sequence);
        let interval = table.map_or(1, |t| t.3);
        let train_frames = frame_range(&self.train_frames, interval);
        let test_frames = frame_range(&self.test_frames, train_frames.step);
        let (train_views, test_views) = match table {
            Some(&(_, train, test, _)) => (index_of(train), index_of(test)),
            None => {
                let with = |frames: &BTreeSet<usize>| -> BTreeSet<usize> {
                    self.images
                        .keys()
                        .filter(|(f, _)| frames.contains(f))
                        .map(|&(_, v)| v)
                        .collect()
                };
                let train = with(&self.train_frames);
                let test: Vec<usize> = with(&self.test_frames)
                    .difference(&train)
                    .copied()
                    .collect();
                (train.into_iter().collect(), test)
            }
        };
        let test_views = if self.test_frames.is_empty() {
            Vec::new()
        } else {
            test_views
        };
        Split {
            train_views,
            test_views,
            frame_interval: train_frames.step,
            train_frames,
            test_frames,
            held_out_frames: None,
        }
    }

    fn body_model(&self) -> anyhow::Result<(BodyModel, BodyModelKind)> {
        load_fits_model(
            self.body_model_path.as_deref(),
            "I3D-Human",
            BodyModelKind::Smpl,
        )
    }

    fn body_params(&self, frame: usize) -> anyhow::Result<BodyParams> {
        self.params.get(&frame).cloned().with_context(|| {
            format!(
                "I3D-Human {}: frame {frame} has no fit in mesh_infos.pkl or frameid_pose.pkl",
                self.sequence
            )
        })
    }

    fn read_image(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage> {
        let image = self.images.get(&(frame, view)).with_context(|| {
            format!(
                "I3D-Human {}: no image of view {} at frame {frame} in {}",
                self.sequence,
                self.cameras[view].id,
                PARTS.map(|p| format!("{}-{p}", self.sequence)).join(", ")
            )
        })?;
        let file = |dir: &str| image.folder.join(dir).join(format!("{}.png", image.name));
        let camera = &self.cameras[view].camera;
        let rgb = read_rgb(&file("images"), (camera.width, camera.height))?;
        let mask = read_mask(&file("masks"), true, rgb.dimensions())?;
        Ok(SourceImage { rgb, mask })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_names_parse() {
        assert_eq!(parse_name("frame_000012_view_03"), Some((12, 3)));
        assert_eq!(parse_name("frame_12_view_x"), None);
        assert_eq!(parse_name("view_03"), None);
    }

    #[test]
    fn evenly_spaced_frames_give_their_step() {
        let frames: BTreeSet<usize> = [3, 6, 9].into_iter().collect();
        assert_eq!(
            frame_range(&frames, 1),
            FrameRange {
                start: 3,
                end: Some(10),
                step: 3
            }
        );
        let uneven: BTreeSet<usize> = [0, 1, 3].into_iter().collect();
        assert_eq!(frame_range(&uneven, 1).step, 1);
    }
}
