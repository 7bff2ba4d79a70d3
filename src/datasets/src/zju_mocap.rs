//! ZJU-MoCap (`CoreView_XXX/`): `annots.npy` cameras and image lists, SMPL fits in
//! `new_params/` (or `params/`), images `Camera_B*/NNNNNN.jpg`, masks in `mask_cihp/` (or
//! `mask/`) mirroring the image paths as `.png`.
//!
//! Conventions converted here:
//! - `annots.npy` `cams.T` is in millimetres: divided by 1000. `R`, `T` are world-to-camera.
//!   `K` has integer pixel centres: [`Camera::from_opencv`] adds 0.5.
//! - The fits state world vertices as `SMPL(poses, shapes) R(Rh)^T + Th` on row vectors,
//!   which is `R(Rh) x + Th` on column vectors: `Rh` is [`BodyParams::world_rotation`] and `Th`
//!   [`BodyParams::world_translation`] unchanged; `poses[0..3]` is the root's local rotation.
//! - Mask files store labels (0/1, or a part id for `mask_cihp`): any non-zero is foreground
//!   (255).
//! - With `mask_cihp/`, the garment region of an image is the union of the CIHP clothing
//!   labels [`CIHP_GARMENT_LABELS`] (255 inside, 0 outside); a file holding a value above 19
//!   (no CIHP label) loads with an empty garment region and a warning naming it. `mask/` has no part labels, so no garment region.
//! - A frame's number is its image file stem (`000123.jpg` -> 123); fits are
//!   `new_params/<number>.npy`.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::{DMat3, DVec3};

use crate::body_model::load_fits_model;
use crate::common::{
    Field, image_size, join_relative, read_mask, read_npy, read_rgb, trailing_number,
};
use crate::{BodyModelKind, DatasetReader, GarmentRegion, SourceCamera, SourceImage, Split};
use seqavatar_formats::Value;

/// Frames used by the 3DGS-Avatar split, per sequence number (docs/method.md).
const SPLIT_FRAMES: [(i64, usize); 6] = [
    (377, 570),
    (386, 540),
    (387, 540),
    (392, 556),
    (393, 658),
    (394, 475),
];

/// The clothing labels of the 20-class CIHP / LIP part set of ZJU-MoCap's `mask_cihp/`
/// parses: 5 upper clothes, 6 dress, 7 coat, 9 pants, 11 scarf, 12 skirt. Not 10 (torso skin
/// in ZJU-MoCap's parses), nor the accessories hat, glove, sunglasses, socks and shoes.
pub const CIHP_GARMENT_LABELS: [u8; 6] = [5, 6, 7, 9, 11, 12];

/// The largest CIHP part label (20 classes, 0 background).
const CIHP_MAX_LABEL: u8 = 19;

/// The garment region of a CIHP part-label image: 255 where the label is clothing
/// ([`CIHP_GARMENT_LABELS`]), else 0.
pub fn cihp_garment_mask(labels: &image::GrayImage) -> image::GrayImage {
    let mut region = labels.clone();
    for value in region.iter_mut() {
        *value = if CIHP_GARMENT_LABELS.contains(value) {
            255
        } else {
            0
        };
    }
    region
}

/// Test views are every view but the first, test frames every 30th (docs/method.md).
const TEST_FRAME_STEP: usize = 30;

/// An opened ZJU-MoCap sequence.
pub struct ZjuMocap {
    root: PathBuf,
    cameras: Vec<SourceCamera>,
    /// Per frame, per camera: the image path relative to the root.
    images: Vec<Vec<String>>,
    frame_ids: Vec<i64>,
    params_dir: PathBuf,
    mask_dir: PathBuf,
    body_model_path: Option<PathBuf>,
    sequence_number: Option<i64>,
}

impl ZjuMocap {
    /// Opens `root` (the `CoreView_XXX` folder). `body_model` is the SMPL dense `.npz`.
    pub fn open(root: &Path, body_model: Option<&Path>) -> anyhow::Result<Self> {
        let annots_path = root.join("annots.npy");
        let annots = read_npy(&annots_path)?;
        let annots_field = Field::root(&annots_path, &annots);
        let cams = CameraLists::read(&annots_field)?;
        let num_cameras = cams.k.len();
        let images = image_lists(&annots_field, num_cameras)?;
        let frame_ids = images
            .iter()
            .enumerate()
            .map(|(f, names)| {
                let stem = Path::new(&names[0])
                    .file_stem()
                    .and_then(|s| s.to_str())
                    .unwrap_or_default();
                // Sequences whose file names are not numbers (313, 315) use the list index.
                stem.parse::<i64>().unwrap_or(f as i64)
            })
            .collect();
        let cameras = (0..num_cameras)
            .map(|c| cams.camera(root, &images, c))
            .collect::<anyhow::Result<Vec<_>>>()?;

        let params_dir = first_folder(root, ["new_params", "params"], " (SMPL fits)")?;
        let mask_dir = first_folder(root, ["mask_cihp", "mask"], "")?;
        let sequence_number = root
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(trailing_number);
        Ok(Self {
            root: root.to_owned(),
            cameras,
            images,
            frame_ids,
            params_dir,
            mask_dir,
            body_model_path: body_model.map(Path::to_owned),
            sequence_number,
        })
    }

    /// Whether the masks are `mask_cihp/` part labels (else `mask/`, 0/1).
    fn part_labels(&self) -> bool {
        self.mask_dir
            .file_name()
            .is_some_and(|name| name == "mask_cihp")
    }

    /// The fits file of a frame-list index.
    fn params_path(&self, frame: usize) -> PathBuf {
        self.params_dir
            .join(format!("{}.npy", self.frame_ids[frame]))
    }
}

/// The first of the folders `names` under `root` that exists; `what` ends the error.
fn first_folder(root: &Path, names: [&str; 2], what: &str) -> anyhow::Result<PathBuf> {
    let [first, second] = names;
    names
        .iter()
        .map(|d| root.join(d))
        .find(|d| d.is_dir())
        .with_context(|| {
            format!(
                "{}: neither `{first}/` nor `{second}/` exists{what}",
                root.display()
            )
        })
}

/// The per-camera lists of `annots.npy` `cams` (`K`, `R`, `T`, optional `D`), of one length.
struct CameraLists<'a> {
    annots_path: &'a Path,
    k: &'a [Value],
    r: &'a [Value],
    t: &'a [Value],
    d: Option<&'a [Value]>,
}

impl<'a> CameraLists<'a> {
    /// Reads `cams` and checks that it lists at least one camera, the same in every list.
    fn read(annots_field: &Field<'a>) -> anyhow::Result<Self> {
        let annots_path = annots_field.file;
        let cams = annots_field.get("cams", "cams")?;
        let ks = cams.get("K", "cams.K")?.sequence()?;
        let rs = cams.get("R", "cams.R")?.sequence()?;
        let ts = cams.get("T", "cams.T")?.sequence()?;
        let ds = match cams.value.get("D") {
            Some(_) => Some(cams.get("D", "cams.D")?.sequence()?),
            None => None,
        };
        let num_cameras = ks.len();
        if num_cameras == 0 {
            bail!("{}: field `cams.K` lists no camera", annots_path.display());
        }
        for (name, list) in [("cams.R", rs.len()), ("cams.T", ts.len())]
            .into_iter()
            .chain(ds.map(|d| ("cams.D", d.len())))
        {
            if list != num_cameras {
                bail!(
                    "{}: field `{name}` has {list} cameras but `cams.K` has {num_cameras}",
                    annots_path.display()
                );
            }
        }
        Ok(Self {
            annots_path,
            k: ks,
            r: rs,
            t: ts,
            d: ds,
        })
    }

    /// Camera `c`, sized by its first image (`images[0][c]`), numbered by its image folder.
    fn camera(
        &self,
        root: &Path,
        images: &[Vec<String>],
        c: usize,
    ) -> anyhow::Result<SourceCamera> {
        let annots_path = self.annots_path;
        let at = |name: &str| format!("{name}[{c}]");
        let [k_path, r_path, t_path, d_path] = ["cams.K", "cams.R", "cams.T", "cams.D"].map(at);
        let field = |path, value| Field {
            file: annots_path,
            path,
            value,
        };
        let k = field(&k_path, &self.k[c]).matrix3()?;
        let r = field(&r_path, &self.r[c]).matrix3()?;
        let t = field(&t_path, &self.t[c]).finite_f64s(3)?;
        let distortion = match self.d {
            Some(ds) => field(&d_path, &ds[c]).distortion()?,
            None => [0.0; 5],
        };
        let first_image = join_relative(root, &images[0][c], annots_path, "ims[0].ims")?;
        let (width, height) = image_size(&first_image)?;
        let rotation = DMat3::from_cols_array_2d(&r).transpose();
        let translation = DVec3::new(t[0], t[1], t[2]) / 1000.0;
        let camera = Camera::from_opencv(width, height, k, rotation, translation, distortion)
            .with_context(|| format!("{}: camera {c} (`cams.*[{c}]`)", annots_path.display()))?;
        let dir_name = Path::new(&images[0][c])
            .parent()
            .and_then(|p| p.to_str())
            .unwrap_or_default();
        let id = trailing_number(dir_name).unwrap_or(c as i64 + 1);
        Ok(SourceCamera { id, camera })
    }
}

/// Per frame, per camera: the image paths of `ims[].ims` (one per camera).
fn image_lists(annots_field: &Field<'_>, num_cameras: usize) -> anyhow::Result<Vec<Vec<String>>> {
    let annots_path = annots_field.file;
    let ims = annots_field.get("ims", "ims")?.sequence()?;
    if ims.is_empty() {
        bail!("{}: field `ims` lists no frame", annots_path.display());
    }
    let mut images = Vec::with_capacity(ims.len());
    for (f, frame) in ims.iter().enumerate() {
        let path = format!("ims[{f}].ims");
        let frame_field = Field {
            file: annots_path,
            path: "ims[]",
            value: frame,
        };
        let list = frame_field.get("ims", &path)?.sequence()?;
        if list.len() != num_cameras {
            bail!(
                "{}: field `{path}` has {} images but there are {num_cameras} cameras",
                annots_path.display(),
                list.len()
            );
        }
        let names = list
            .iter()
            .map(|v| {
                v.as_str().map(str::to_owned).with_context(|| {
                    format!(
                        "{}: field `{path}` holds {v}, not a path",
                        annots_path.display()
                    )
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        images.push(names);
    }
    Ok(images)
}

/// Reads one ZJU/EasyMocap fits dict (`poses`, `Rh`, `Th`, `shapes`) into body parameters.
pub fn read_smpl_params(path: &Path) -> anyhow::Result<BodyParams> {
    let value = read_npy(path)?;
    let root = Field::root(path, &value);
    let poses = root.get("poses", "poses")?.finite_f64s(72)?;
    let rh = root.get("Rh", "Rh")?.finite_f64s(3)?;
    let th = root.get("Th", "Th")?.finite_f64s(3)?;
    let shapes = root.get("shapes", "shapes")?.finite_array()?.1;
    Ok(BodyParams {
        pose: poses.chunks_exact(3).map(DVec3::from_slice).collect(),
        betas: shapes,
        expression: Vec::new(),
        world_rotation: DVec3::new(rh[0], rh[1], rh[2]),
        world_translation: DVec3::new(th[0], th[1], th[2]),
    })
}

impl DatasetReader for ZjuMocap {
    fn describe(&self) -> String {
        format!("ZJU-MoCap {}", self.root.display())
    }

    fn cameras(&self) -> &[SourceCamera] {
        &self.cameras
    }

    fn num_frames(&self) -> usize {
        self.images.len()
    }

    fn frame_id(&self, frame: usize) -> i64 {
        self.frame_ids[frame]
    }

    fn default_split(&self) -> Split {
        let used = SPLIT_FRAMES
            .iter()
            .find(|(n, _)| Some(*n) == self.sequence_number)
            .map_or(self.num_frames(), |&(_, frames)| frames)
            .min(self.num_frames());
        Split::first_frames(
            vec![0],
            (1..self.cameras.len()).collect(),
            Some(used),
            TEST_FRAME_STEP,
        )
    }

    fn body_model(&self) -> anyhow::Result<(BodyModel, BodyModelKind)> {
        load_fits_model(
            self.body_model_path.as_deref(),
            "ZJU-MoCap",
            BodyModelKind::Smpl,
        )
    }

    fn body_params(&self, frame: usize) -> anyhow::Result<BodyParams> {
        read_smpl_params(&self.params_path(frame))
    }

    fn read_image(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage> {
        Ok(self.read_image_with_garment(view, frame)?.0)
    }

    /// The CIHP clothing labels, when the masks are `mask_cihp/` part labels.
    fn garment_region(&self) -> Option<GarmentRegion> {
        self.part_labels().then_some(GarmentRegion::CihpClothing)
    }

    fn read_image_with_garment(
        &self,
        view: usize,
        frame: usize,
    ) -> anyhow::Result<(SourceImage, Option<image::GrayImage>)> {
        let relative = &self.images[frame][view];
        let annots = self.root.join("annots.npy");
        let image_path = join_relative(&self.root, relative, &annots, "ims")?;
        let camera = &self.cameras[view].camera;
        let rgb = read_rgb(&image_path, (camera.width, camera.height))?;
        let mask_path =
            join_relative(&self.mask_dir, relative, &annots, "ims")?.with_extension("png");
        // `mask/` stores the 0/1 foreground mask, `mask_cihp/` part labels.
        let labels = read_mask(&mask_path, !self.part_labels(), rgb.dimensions())?;
        if !self.part_labels() {
            return Ok((SourceImage { rgb, mask: labels }, None));
        }
        // A file that is no label image (a 0/255 matte, a palette written as grey) still
        // loads: its non-zero pixels are the person, and its garment region is empty (eval
        // counts such images apart), said here with the file's name.
        let non_labels = labels.iter().filter(|l| **l > CIHP_MAX_LABEL).count();
        let garment = if non_labels > 0 {
            eprintln!(
                "[ingest] warning: {}: {non_labels} pixels hold values above \
                 {CIHP_MAX_LABEL}, which are no CIHP part labels; the image's garment region \
                 is left empty",
                mask_path.display()
            );
            image::GrayImage::new(labels.width(), labels.height())
        } else {
            cihp_garment_mask(&labels)
        };
        let mut mask = labels;
        for value in mask.iter_mut() {
            if *value != 0 {
                *value = 255;
            }
        }
        Ok((SourceImage { rgb, mask }, Some(garment)))
    }
}
