//! Scoring a set of renders against the test split: the paper protocol per image (metrics.rs),
//! LPIPS when weights are configured, error maps, the contact sheet, per-image metric arrays
//! and the per-sequence mean table. The renders come from any [`ViewRenderer`]; the eval stage
//! plugs in the trained avatar.

use std::time::Instant;

use image::RgbImage;
use seqavatar_core::camera::Camera;

use crate::metrics::{Mask, PreparedPair, Protocol, psnr_ssim};
use crate::region::{RegionMeans, RegionScore, region_lpips_crop, region_psnr, region_ssim};
use crate::scores::{ImageScore, MeanScores};

use crate::report::{self, format_metric, markdown_table};
use seqavatar_compute::image::ImageF32;
use seqavatar_compute::lpips::{Lpips, LpipsNet};

/// Renders a frame of the sequence seen by a camera: the whole render path (network
/// evaluation included), RGB in [0, 1] of the camera's size.
pub trait ViewRenderer {
    fn render(&mut self, frame: usize, camera: &Camera) -> anyhow::Result<ImageF32>;

    /// Renders from now on with the motion-history inputs replaced as `probe` says (`None`:
    /// the frame's own); false when this renderer has no such inputs (nothing would change).
    fn set_context_probe(&mut self, _probe: Option<crate::context_probe::ContextProbe>) -> bool {
        false
    }

    /// Forgets any deformed frame kept for the next render, so that render runs the whole
    /// path (the speed measurement's renders all do).
    fn forget_deformed_frame(&mut self) {}
}

impl<F: FnMut(usize, &Camera) -> anyhow::Result<ImageF32>> ViewRenderer for F {
    fn render(&mut self, frame: usize, camera: &Camera) -> anyhow::Result<ImageF32> {
        self(frame, camera)
    }
}

/// LPIPS models the user configured (either may be absent).
#[derive(Default)]
pub struct LpipsModels {
    pub vgg: Option<Lpips>,
    pub alex: Option<Lpips>,
}

impl LpipsModels {
    pub fn get(&self, net: LpipsNet) -> Option<&Lpips> {
        match net {
            LpipsNet::Vgg => self.vgg.as_ref(),
            LpipsNet::Alex => self.alex.as_ref(),
        }
    }
}

/// One scored test image: the prepared pair (protocol applied) and its metrics.
#[derive(Clone, Debug)]
pub struct ScoredImage {
    pub pair: PreparedPair,
    pub score: ImageScore,
}

/// Applies the protocol to `render` against `truth` and `mask` and computes every metric, on
/// the whole image and, given a `garment` mask, on the garment region (crate::region).
pub fn score_image(
    protocol: &Protocol,
    lpips: &LpipsModels,
    render: &ImageF32,
    truth: &ImageF32,
    mask: &Mask,
    garment: Option<&Mask>,
) -> anyhow::Result<ScoredImage> {
    let pair = protocol.prepare(render, truth, mask)?;
    let (psnr, ssim) = psnr_ssim(&pair)?;
    let lpips_of = |net: LpipsNet| -> anyhow::Result<Option<f64>> {
        let Some(model) = lpips.get(net) else {
            return Ok(None);
        };
        let (render, truth) = (pair.render.crop(pair.region), pair.truth.crop(pair.region));
        let distances = model.distances(&[(&render, &truth)])?;
        Ok(Some(distances[0].total))
    };
    let garment = garment
        .map(|region| score_region(lpips, &pair, region))
        .transpose()?;
    let score = ImageScore {
        psnr,
        ssim,
        lpips_vgg: lpips_of(LpipsNet::Vgg)?,
        lpips_alex: lpips_of(LpipsNet::Alex)?,
        garment,
    };
    Ok(ScoredImage { pair, score })
}

/// The region metrics of a prepared pair (crate::region).
fn score_region(
    lpips: &LpipsModels,
    pair: &PreparedPair,
    region: &Mask,
) -> anyhow::Result<RegionScore> {
    let (Some(psnr), Some(ssim)) = (
        region_psnr(&pair.render, &pair.truth, region)?,
        region_ssim(&pair.render, &pair.truth, region)?,
    ) else {
        return Ok(RegionScore::Empty);
    };
    let lpips_of = |net: LpipsNet| -> anyhow::Result<Option<f64>> {
        let (Some(model), Some(crop)) = (lpips.get(net), region_lpips_crop(region, net)) else {
            return Ok(None);
        };
        let (render, truth) = (pair.render.crop(crop), pair.truth.crop(crop));
        let distances = model.distances(&[(&render, &truth)])?;
        Ok(Some(distances[0].total))
    };
    Ok(RegionScore::Scored {
        pixels: region.data.iter().filter(|&&v| v >= 128).count(),
        psnr,
        ssim,
        lpips_vgg: lpips_of(LpipsNet::Vgg)?,
        lpips_alex: lpips_of(LpipsNet::Alex)?,
    })
}

/// An LPIPS value for a table, x 1000 as the paper reports it; "unavailable" without weights.
pub fn format_lpips_x1000(value: Option<f64>) -> String {
    match value {
        None => "unavailable".to_owned(),
        Some(value) => format_metric(Some(value * 1000.0), 2),
    }
}

/// Header of the per-sequence mean table.
pub const MEAN_TABLE_HEADERS: [&str; 6] = [
    "sequence",
    "test images",
    "PSNR",
    "SSIM",
    "LPIPS-VGG x1000",
    "LPIPS-Alex x1000",
];

/// One row of the per-sequence mean table.
pub fn mean_table_row(sequence: &str, means: &MeanScores) -> Vec<String> {
    vec![
        sequence.to_owned(),
        means.images.to_string(),
        format_metric(Some(means.psnr), 2),
        format_metric(Some(means.ssim), 4),
        format_lpips_x1000(means.lpips_vgg),
        format_lpips_x1000(means.lpips_alex),
    ]
}

/// Header of the garment-region table: per subset, the whole-image figures beside the
/// garment region's.
pub const GARMENT_TABLE_HEADERS: [&str; 11] = [
    "subset",
    "images",
    "PSNR",
    "SSIM",
    "LPIPS-VGG x1000",
    "garment images",
    "empty regions",
    "garment PSNR",
    "garment SSIM",
    "garment LPIPS-VGG x1000",
    "garment LPIPS-Alex x1000",
];

/// The garment-region table (Markdown) of an eval summary: all test images, then each
/// non-empty subset; `None` when the means have no garment region.
pub fn garment_table(means: &MeanScores, subsets: &crate::subsets::SubsetScores) -> Option<String> {
    means.garment?;
    let row = |name: &str, m: &MeanScores| -> Vec<String> {
        let g = m.garment.unwrap_or(RegionMeans {
            images: 0,
            empty_images: 0,
            psnr: None,
            ssim: None,
            lpips_vgg: None,
            lpips_alex: None,
        });
        vec![
            name.to_owned(),
            m.images.to_string(),
            format_metric(Some(m.psnr), 2),
            format_metric(Some(m.ssim), 4),
            format_lpips_x1000(m.lpips_vgg),
            g.images.to_string(),
            g.empty_images.to_string(),
            format_metric(g.psnr, 2),
            format_metric(g.ssim, 4),
            format_lpips_x1000(g.lpips_vgg),
            format_lpips_x1000(g.lpips_alex),
        ]
    };
    let mut rows = vec![row("all test images", means)];
    for (name, subset) in subsets.named() {
        if let Some(m) = subset {
            rows.push(row(name, m));
        }
    }
    markdown_table(&GARMENT_TABLE_HEADERS, &rows).ok()
}

/// `image` placed in the top-left corner of a `width x height` black canvas (the ingest
/// layout for views smaller than the largest one).
pub fn pad_to(image: &RgbImage, width: u32, height: u32) -> RgbImage {
    if image.dimensions() == (width, height) {
        return image.clone();
    }
    let mut canvas = RgbImage::new(width, height);
    image::imageops::replace(&mut canvas, image, 0, 0);
    canvas
}

/// Up to `rows` indices spread evenly over `0..count`.
pub fn spread(count: usize, rows: usize) -> Vec<usize> {
    let picked = rows.min(count);
    (0..picked).map(|k| k * count / picked).collect()
}

/// Rendering speed at one resolution: the whole render path, frames per second.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SpeedRow {
    pub width: u32,
    pub height: u32,
    pub frames: usize,
    pub seconds: f64,
    pub fps: f64,
}

/// Times `frames.len()` renders of `camera` (one untimed warm-up render first: gpu pipelines
/// compile on first use), each deforming its frame anew.
pub fn measure_speed(
    renderer: &mut dyn ViewRenderer,
    camera: &Camera,
    frames: &[usize],
) -> anyhow::Result<SpeedRow> {
    anyhow::ensure!(
        !frames.is_empty(),
        "speed measurement needs at least one frame"
    );
    renderer.render(frames[0], camera)?;
    let started = Instant::now();
    for &frame in frames {
        renderer.forget_deformed_frame();
        let image = renderer.render(frame, camera)?;
        anyhow::ensure!(
            image.width == camera.width as usize && image.height == camera.height as usize,
            "the renderer returned {} x {} for a {} x {} camera",
            image.width,
            image.height,
            camera.width,
            camera.height
        );
    }
    let seconds = started.elapsed().as_secs_f64();
    Ok(SpeedRow {
        width: camera.width,
        height: camera.height,
        frames: frames.len(),
        seconds,
        fps: frames.len() as f64 / seconds.max(1e-12),
    })
}

/// Ground truth | render | error map rows, each padded to `width x height`.
pub fn contact_sheet_rows(
    images: &[(RgbImage, RgbImage, RgbImage)],
    width: u32,
    height: u32,
) -> anyhow::Result<RgbImage> {
    let padded: Vec<[RgbImage; 3]> = images
        .iter()
        .map(|(truth, render, error)| {
            [
                pad_to(truth, width, height),
                pad_to(render, width, height),
                pad_to(error, width, height),
            ]
        })
        .collect();
    let rows: Vec<Vec<&RgbImage>> = padded.iter().map(|row| row.iter().collect()).collect();
    report::contact_sheet(&rows, 4).map_err(anyhow::Error::msg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scores::mean_scores;

    /// A renderer that counts its renders and the deformed frames it was told to forget.
    #[derive(Default)]
    struct Counting {
        renders: usize,
        forgotten: usize,
    }

    impl ViewRenderer for Counting {
        fn render(&mut self, _frame: usize, camera: &Camera) -> anyhow::Result<ImageF32> {
            self.renders += 1;
            let (w, h) = (camera.width as usize, camera.height as usize);
            Ok(ImageF32::from_f32("counting", w, h, vec![0.5; w * h * 3])?)
        }

        fn forget_deformed_frame(&mut self) {
            self.forgotten += 1;
        }
    }

    /// Every timed render of the speed measurement runs the whole path: a renderer that
    /// keeps its last deformed frame is told to forget it before each.
    #[test]
    fn every_timed_render_deforms_anew() {
        let camera = Camera::look_at(
            8,
            6,
            seqavatar_core::camera::Intrinsics {
                fx: 8.0,
                fy: 8.0,
                cx: 4.0,
                cy: 3.0,
            },
            seqavatar_core::glam::DVec3::new(0.0, 0.0, 3.0),
            seqavatar_core::glam::DVec3::ZERO,
            seqavatar_core::glam::DVec3::Y,
        );
        let mut renderer = Counting::default();
        let row = measure_speed(&mut renderer, &camera, &[2, 2, 5]).unwrap();
        assert_eq!(
            (row.frames, renderer.renders, renderer.forgotten),
            (3, 4, 3)
        );
    }

    fn score(psnr: f64, lpips: Option<f64>) -> ImageScore {
        ImageScore {
            psnr,
            ssim: 0.5,
            lpips_vgg: lpips,
            lpips_alex: None,
            garment: None,
        }
    }

    #[test]
    fn means_average_per_image_values_and_keep_lpips_unavailable() {
        let means = mean_scores(&[score(20.0, Some(0.1)), score(30.0, Some(0.3))]);
        assert_eq!(means.images, 2);
        assert_eq!(means.psnr, 25.0);
        assert!((means.lpips_vgg.unwrap() - 0.2).abs() < 1e-15);
        assert_eq!(means.lpips_alex, None);
        // One image without LPIPS: the mean is unavailable, never a partial number.
        let partial = mean_scores(&[score(20.0, Some(0.1)), score(30.0, None)]);
        assert_eq!(partial.lpips_vgg, None);
        let row = mean_table_row("seq", &means);
        assert_eq!(
            row,
            ["seq", "2", "25.00", "0.5000", "200.00", "unavailable"]
        );
    }

    /// The garment table: the whole-image figures beside the region's, one row for all
    /// images and one per non-empty subset; no table without a garment region.
    #[test]
    fn garment_table_rows_per_subset_or_none_without_a_region() {
        let region = |psnr: f64| RegionScore::Scored {
            pixels: 5,
            psnr,
            ssim: 0.8,
            lpips_vgg: None,
            lpips_alex: None,
        };
        let with = |psnr: f64, garment: RegionScore| ImageScore {
            garment: Some(garment),
            ..score(psnr, None)
        };
        let scores = [with(20.0, region(18.0)), with(30.0, RegionScore::Empty)];
        let means = mean_scores(&scores);
        let subsets = crate::subsets::SubsetScores {
            held_out_cameras: Some(mean_scores(&scores[..1])),
            ..Default::default()
        };
        let table = garment_table(&means, &subsets).unwrap();
        assert!(
            table.contains("| all test images | 2 | 25.00 | 0.5000 | unavailable | 1 | 1 | 18.00 | 0.8000 | unavailable | unavailable |"),
            "{table}"
        );
        assert!(
            table.contains("| held-out cameras | 1 | 20.00 |"),
            "{table}"
        );
        assert!(!table.contains("history frames"), "{table}");
        let without = mean_scores(&[score(20.0, None)]);
        assert_eq!(without.garment, None);
        assert_eq!(garment_table(&without, &subsets), None);
    }

    #[test]
    fn spread_picks_evenly_and_handles_small_counts() {
        assert_eq!(spread(10, 4), [0, 2, 5, 7]);
        assert_eq!(spread(2, 4), [0, 1]);
        assert!(spread(0, 4).is_empty());
    }

    #[test]
    fn pad_keeps_the_top_left_corner() {
        let image = RgbImage::from_pixel(2, 1, image::Rgb([9, 9, 9]));
        let padded = pad_to(&image, 3, 2);
        assert_eq!(padded.dimensions(), (3, 2));
        assert_eq!(*padded.get_pixel(1, 0), image::Rgb([9, 9, 9]));
        assert_eq!(*padded.get_pixel(2, 0), image::Rgb([0, 0, 0]));
        assert_eq!(*padded.get_pixel(0, 1), image::Rgb([0, 0, 0]));
    }

    #[test]
    fn perfect_render_scores_infinite_psnr_and_unit_ssim() {
        let width = 30;
        let height = 24;
        let mut mask = vec![0_u8; width * height];
        let mut truth = ImageF32::black(width, height);
        for y in 3..9 {
            for x in 4..12 {
                mask[y * width + x] = 255;
                let at = (y * width + x) * 3;
                truth.data[at..at + 3].copy_from_slice(&[0.8, 0.4, 0.2]);
            }
        }
        let mask = Mask::new("mask", width, height, mask).unwrap();
        let scored = score_image(
            &Protocol::default(),
            &LpipsModels::default(),
            &truth,
            &truth,
            &mask,
            None,
        )
        .unwrap();
        assert_eq!(scored.score.psnr, f64::INFINITY);
        assert!((scored.score.ssim - 1.0).abs() < 1e-12);
        assert_eq!(scored.score.lpips_vgg, None);
        // A render with stray colour outside the bound box is cleaned by the protocol; one
        // inside it is not.
        // The bound box is x 0..17, y 0..14 (5 px padding); (29, 23) is outside it.
        let mut stray = truth.clone();
        let corner = (23 * width + 29) * 3;
        stray.data[corner..corner + 3].copy_from_slice(&[1.0, 1.0, 1.0]);
        let cleaned = score_image(
            &Protocol::default(),
            &LpipsModels::default(),
            &stray,
            &truth,
            &mask,
            None,
        )
        .unwrap();
        assert_eq!(cleaned.score.psnr, f64::INFINITY);
        let mut inside = truth.clone();
        let at = (2 * width + 4) * 3;
        inside.data[at..at + 3].copy_from_slice(&[1.0, 1.0, 1.0]);
        let hurt = score_image(
            &Protocol::default(),
            &LpipsModels::default(),
            &inside,
            &truth,
            &mask,
            None,
        )
        .unwrap();
        // One pixel off by 1 in every channel: mse = 3 / (3 * 720).
        let expected = -10.0 * (1.0_f64 / 720.0).log10();
        assert!((hurt.score.psnr - expected).abs() < 1e-9);
    }
}
