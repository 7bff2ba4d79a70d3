//! The eval entry: the scores of a trained avatar's renders of the ingest entry's test
//! images, the renders, error maps and contact sheet, and the rendering speed. Written by the
//! eval stage; `pipeline report` and the viewer read its attributes.
//!
//! Output arrays (axis `image` = the scored test images, in ingest order):
//! - `psnr`, `ssim` f64 `(image)`; `lpips_vgg`, `lpips_alex` f64 `(image)` only when the
//!   matching weights file is configured (LPIPS is never reported as a number otherwise).
//! - Only where the ingest entry has `garment_masks` (seqavatar_evaluation::region): `garment_pixels` u32
//!   `(image)` (pixels in the garment region), `garment_psnr`, `garment_ssim` f64 `(image)`
//!   and, with their weights, `garment_lpips_vgg`, `garment_lpips_alex` f64 `(image)`; NaN
//!   where the region is empty (such images are left out of the region means).
//! - `image_index` u32 `(image)` (position on the ingest `image` axis), `image_view`,
//!   `image_frame` u32 `(image)`, `render_seconds` f64 `(image)` (whole render path).
//!   These columns, each one chunk, are [`PerImageScores`].
//! - `renders` and `error_maps` u8 `(image, height, width, rgb)`, one image per chunk, views
//!   smaller than the largest stored in the top-left corner (the ingest layout). Renders are
//!   after the protocol (background outside the bound box); error maps are the per-pixel mean
//!   absolute error in the "hot" colour map, white at `error_full_scale`.
//! - `contact_sheet` u8 `(sheet_height, sheet_width, rgb)`: ground truth | render | error
//!   ([`write_contact_sheet`]).
//! - `speed_width`, `speed_height` u32 `(resolution)`, `speed_fps` f64 `(resolution)`.
//!
//! Attributes: `summary` (`sequence`, `means` = `MeanScores`, `subsets` =
//! `SubsetScores`: means on the ingest entry's history frames and other
//! frames, held-out cameras and held-out frames, each `null` when empty; `train_image_psnr` =
//! the train entry's `train_image_psnr_mean` (protocol PSNR on training images) or `null`;
//! `context_probes` = a list of `ProbeResult`: the scores with the
//! motion-history inputs zeroed and taken from frame `i + context_probe_offset`, and their
//! PSNR change per subset (`psnr_change`, with `psnr_change.garment` the same changes on the
//! garment region where there is one), empty for avatars without such inputs; `lpips` =
//! `"unavailable"` or the nets used, `backend`; `garment_region` = the ingest entry's
//! `garment_region` (`synthetic_skirt`, `cihp_clothing`) or `null` (no garment region for
//! this dataset), and then `means.garment` and each subset's `garment` =
//! `RegionMeans` (`images`, `empty_images`, `psnr`, `ssim`, `lpips_vgg`,
//! `lpips_alex`); `garment_lpips` = how region LPIPS is taken
//! (`REGION_LPIPS_METHOD`) or `null`), `speed` (a list of `SpeedRow`),
//! `mean_table` (Markdown), `garment_table` (Markdown: per subset, the whole-image figures
//! beside the garment region's, or "garment region: not available for this dataset").

use std::path::Path;

use anyhow::Context as _;
use seqavatar_engine::{Element, EntryReader, EntryWriter};

/// The kind name in pipeline files.
pub const EVAL_KIND: &str = "eval";
/// Entry attribute holding the sequence name, the means and the LPIPS availability.
pub const SUMMARY_ATTRIBUTE: &str = "summary";
/// Entry attribute holding the garment-region table (Markdown)
/// or the sentence that the dataset has no garment region.
pub const GARMENT_TABLE_ATTRIBUTE: &str = "garment_table";
/// Entry attribute holding the rendering speed rows.
pub const SPEED_ATTRIBUTE: &str = "speed";
/// Train-entry attribute with the protocol PSNR on training images.
pub const TRAIN_IMAGE_PSNR_ATTRIBUTE: &str = "train_image_psnr_mean";

/// The field `key` of the entry's [`SUMMARY_ATTRIBUTE`] as a `T`, read from `null` where the
/// attribute or the field is absent; errors name the entry and the field.
pub fn read_summary_field<T: serde::de::DeserializeOwned>(
    entry: &EntryReader,
    key: &str,
) -> anyhow::Result<T> {
    let summary = entry.attribute(SUMMARY_ATTRIBUTE);
    let field = summary.and_then(|summary| summary.get(key).cloned());
    serde_json::from_value(field.unwrap_or_default()).with_context(|| {
        format!(
            "eval entry {}: attribute {SUMMARY_ATTRIBUTE}.{key}",
            entry.location()
        )
    })
}

/// The per-image columns (module docs: axis `image`, one chunk each), written in one piece by
/// the eval stage; [`PerImageScores::read`] checks every column has one length.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PerImageScores {
    /// `psnr`, `ssim`, `lpips_vgg`, `lpips_alex`.
    pub whole: ScoreColumns,
    /// `garment_pixels` and `garment_psnr`, ...; only where ingest has a garment region.
    pub garment: Option<(Vec<u32>, ScoreColumns)>,
    pub render_seconds: Vec<f64>,
    /// Positions on the ingest `image`, `view` and `frame` axes.
    pub image_index: Vec<u32>,
    pub image_view: Vec<u32>,
    pub image_frame: Vec<u32>,
}

/// One region's score columns; each LPIPS column only with its weights (NaN where missing).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ScoreColumns {
    pub psnr: Vec<f64>,
    pub ssim: Vec<f64>,
    pub lpips_vgg: Option<Vec<f64>>,
    pub lpips_alex: Option<Vec<f64>>,
}

const WHOLE: [&str; 4] = ["psnr", "ssim", "lpips_vgg", "lpips_alex"];
const GARMENT: [&str; 4] = [
    "garment_psnr",
    "garment_ssim",
    "garment_lpips_vgg",
    "garment_lpips_alex",
];

impl ScoreColumns {
    /// Writes the present columns of `n` images as `names` (psnr, ssim, vgg, alex).
    fn write(&self, out: &EntryWriter, names: [&str; 4], n: [u64; 1]) -> anyhow::Result<()> {
        let (vgg, alex) = (self.lpips_vgg.as_ref(), self.lpips_alex.as_ref());
        let columns = [Some(&self.psnr), Some(&self.ssim), vgg, alex];
        for (name, values) in names.into_iter().zip(columns) {
            if let Some(values) = values {
                out.write_whole(name, &["image"], &n, values)?;
            }
        }
        Ok(())
    }

    fn read(entry: &EntryReader, names: [&str; 4], n: usize) -> anyhow::Result<Self> {
        let [psnr, ssim, vgg, alex] = names;
        let optional = |name| match entry.has_array(name) {
            true => read_column(entry, name, n).map(Some),
            false => Ok(None),
        };
        Ok(Self {
            psnr: read_column(entry, psnr, n)?,
            ssim: read_column(entry, ssim, n)?,
            lpips_vgg: optional(vgg)?,
            lpips_alex: optional(alex)?,
        })
    }
}

/// The array `name` of shape `(n)`, or an error naming the entry and the array.
fn read_column<T: Element>(entry: &EntryReader, name: &str, n: usize) -> anyhow::Result<Vec<T>> {
    let array = entry.read::<T>(name)?;
    anyhow::ensure!(
        array.shape == [n],
        "entry {}: array `{name}` has shape {:?}, expected ({n})",
        entry.location(),
        array.shape
    );
    Ok(array.data)
}

impl PerImageScores {
    pub fn write(&self, out: &EntryWriter) -> anyhow::Result<()> {
        let n = [self.image_index.len() as u64];
        let u32s = |name, values: &[u32]| out.write_whole(name, &["image"], &n, values);
        self.whole.write(out, WHOLE, n)?;
        if let Some((pixels, scores)) = &self.garment {
            u32s("garment_pixels", pixels)?;
            scores.write(out, GARMENT, n)?;
        }
        out.write_whole("render_seconds", &["image"], &n, &self.render_seconds)?;
        u32s("image_index", &self.image_index)?;
        u32s("image_view", &self.image_view)?;
        u32s("image_frame", &self.image_frame)
    }

    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let n = entry.shape("image_index")?.iter().product::<u64>() as usize;
        let garment = match entry.has_array("garment_pixels") {
            true => Some((
                read_column(entry, "garment_pixels", n)?,
                ScoreColumns::read(entry, GARMENT, n)?,
            )),
            false => None,
        };
        Ok(Self {
            whole: ScoreColumns::read(entry, WHOLE, n)?,
            garment,
            render_seconds: read_column(entry, "render_seconds", n)?,
            image_index: read_column(entry, "image_index", n)?,
            image_view: read_column(entry, "image_view", n)?,
            image_frame: read_column(entry, "image_frame", n)?,
        })
    }
}

/// Writes `contact_sheet`, read back with [`read_rgb`].
pub fn write_contact_sheet(out: &EntryWriter, sheet: &image::RgbImage) -> anyhow::Result<()> {
    let shape = [sheet.height(), sheet.width(), 3].map(u64::from);
    let dims = ["sheet_height", "sheet_width", "rgb"];
    out.write_whole("contact_sheet", &dims, &shape, sheet.as_raw())
}

/// An RGB image array of an eval entry: the whole array, or image `index` of a stack.
pub fn read_rgb(
    entry: &EntryReader,
    name: &str,
    index: Option<usize>,
) -> anyhow::Result<image::RgbImage> {
    let shape = entry.shape(name)?;
    let (data, height, width) = match index {
        None => {
            anyhow::ensure!(
                shape.len() == 3 && shape[2] == 3,
                "array \"{name}\" has shape {shape:?}, expected (height, width, 3)"
            );
            (entry.read::<u8>(name)?.data, shape[0], shape[1])
        }
        Some(index) => {
            anyhow::ensure!(
                shape.len() == 4 && shape[3] == 3,
                "array \"{name}\" has shape {shape:?}, expected (image, height, width, 3)"
            );
            anyhow::ensure!(
                (index as u64) < shape[0],
                "index {index}: array \"{name}\" has {} images",
                shape[0]
            );
            let region = entry.read_region::<u8>(
                name,
                &[index as u64, 0, 0, 0],
                &[1, shape[1], shape[2], 3],
            )?;
            (region.data, shape[1], shape[2])
        }
    };
    image::RgbImage::from_raw(width as u32, height as u32, data)
        .ok_or_else(|| anyhow::anyhow!("array \"{name}\": size does not match its data"))
}

/// Writes the PNGs of an eval entry into `folder` (`contact_sheet.png`, `render_NNN.png`,
/// `error_NNN.png`); returns how many test images were written.
pub fn export_pngs(entry: &EntryReader, folder: &Path) -> anyhow::Result<usize> {
    let save = |image: image::RgbImage, name: String| -> anyhow::Result<()> {
        let path = folder.join(name);
        image
            .save(&path)
            .with_context(|| format!("cannot write {}", path.display()))
    };
    save(
        read_rgb(entry, "contact_sheet", None)?,
        "contact_sheet.png".to_owned(),
    )?;
    let columns = PerImageScores::read(entry)?;
    let (views, frames) = (&columns.image_view, &columns.image_frame);
    for (index, (view, frame)) in views.iter().zip(frames).enumerate() {
        save(
            read_rgb(entry, "renders", Some(index))?,
            format!("render_{index:03}_view{view}_frame{frame}.png"),
        )?;
        save(
            read_rgb(entry, "error_maps", Some(index))?,
            format!("error_{index:03}_view{view}_frame{frame}.png"),
        )?;
    }
    Ok(views.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_engine::LocalStore;

    fn scores(garment: bool) -> PerImageScores {
        let columns = |psnr: f64| ScoreColumns {
            psnr: vec![psnr, psnr + 1.0],
            ssim: vec![0.5, 0.25],
            lpips_vgg: Some(vec![0.125, 0.0625]),
            lpips_alex: None,
        };
        PerImageScores {
            whole: columns(30.0),
            garment: garment.then(|| (vec![7, 0], columns(20.0))),
            render_seconds: vec![0.5, 0.75],
            image_index: vec![3, 4],
            image_view: vec![1, 1],
            image_frame: vec![0, 2],
        }
    }

    fn write(out: &EntryWriter, case: &str) -> anyhow::Result<()> {
        match case {
            "whole" => scores(false).write(out),
            "garment" => scores(true).write(out),
            _ => {
                out.write_array("image_index", &["image"], &[2], &[2], &[3u32, 4])?;
                out.write_array("psnr", &["image"], &[3], &[3], &[1.0, 2.0, 3.0])
            }
        }
    }

    #[test]
    fn per_image_scores_read_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        for garment in [false, true] {
            let case = if garment { "garment" } else { "whole" };
            let entry = crate::testing::entry(&store, write, case);
            assert_eq!(PerImageScores::read(&entry).unwrap(), scores(garment));
            let mut names = entry.array_names();
            names.sort();
            let mut expected = vec![
                "image_frame",
                "image_index",
                "image_view",
                "lpips_vgg",
                "psnr",
                "render_seconds",
                "ssim",
            ];
            if garment {
                let garment = ["garment_lpips_vgg", "garment_pixels", "garment_psnr"];
                expected.extend(garment.into_iter().chain(["garment_ssim"]));
            }
            expected.sort();
            assert_eq!(names, expected);
            assert_eq!(entry.shape("psnr").unwrap(), [2]);
            assert_eq!(entry.dtype("image_view").unwrap(), "uint32");
            assert_eq!(entry.dtype("render_seconds").unwrap(), "float64");
        }
        let damaged = crate::testing::entry(&store, write, "damaged");
        let message = format!("{:#}", PerImageScores::read(&damaged).unwrap_err());
        assert!(
            message.contains("array `psnr` has shape [3], expected (2)")
                && message.contains(damaged.location()),
            "{message}"
        );
    }
}
