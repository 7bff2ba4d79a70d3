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
//! - `renders` and `error_maps` u8 `(image, height, width, rgb)`, one image per chunk, views
//!   smaller than the largest stored in the top-left corner (the ingest layout). Renders are
//!   after the protocol (background outside the bound box); error maps are the per-pixel mean
//!   absolute error in the "hot" colour map, white at `error_full_scale`.
//! - `contact_sheet` u8 `(sheet_height, sheet_width, rgb)`: ground truth | render | error.
//! - `speed_width`, `speed_height` u32 `(resolution)`, `speed_fps` f64 `(resolution)`.
//!
//! Attributes: `summary` (`sequence`, `means` = `MeanScores`, `subsets` =
//! `SubsetScores`: means on the ingest entry's history frames and other
//! frames, held-out cameras and held-out frames, each `null` when empty; `train_image_psnr` =
//! the train entry's `train_image_psnr_mean` (protocol PSNR on training images) or `null`;
//! `context_probes` = a list of `ProbeResult`: the scores with the
//! motion-history inputs zeroed and taken from frame `i + context_probe_offset`, and their
//! PSNR change per subset, empty for avatars without such inputs; `lpips` =
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
use seqavatar_engine::EntryReader;

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
    let count = entry.shape("renders")?.first().copied().unwrap_or(0) as usize;
    let views = entry.read::<u32>("image_view")?.data;
    let frames = entry.read::<u32>("image_frame")?.data;
    for index in 0..count {
        let (view, frame) = (
            views.get(index).copied().unwrap_or(0),
            frames.get(index).copied().unwrap_or(0),
        );
        save(
            read_rgb(entry, "renders", Some(index))?,
            format!("render_{index:03}_view{view}_frame{frame}.png"),
        )?;
        save(
            read_rgb(entry, "error_maps", Some(index))?,
            format!("error_{index:03}_view{view}_frame{frame}.png"),
        )?;
    }
    Ok(count)
}
