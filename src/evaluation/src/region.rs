//! Metrics on a region of an image: the garment region of the ingest entry
//! (`garment_masks`, stages/ingest/src/lib.rs), scored beside the whole image by the eval
//! stage and shown by `pipeline view`'s compare mode. The one home of the region math.
//!
//! A pixel is in the region when its mask value is at least 128 ([`Mask::is_foreground`]).
//! On a prepared pair (the protocol applied, as the whole-image figures):
//! - PSNR: `-10 log10` of the squared error averaged over the region's pixels x 3 channels.
//! - SSIM: the mean of the whole image's SSIM map (`seqavatar_compute::ssim::ssim_map`, the
//!   same window and constants as the whole-image SSIM) over the region's pixels x channels,
//!   so windows near the region's border see its surroundings as they are.
//! - LPIPS: the LPIPS module returns one distance per image pair (its per-layer maps are at
//!   the trunk's reduced resolutions and stay inside it), so the region's LPIPS is that of the
//!   crop of the region's bounding box, grown about its centre to the trunk's smallest input
//!   where it is smaller (and clipped to the image).
//!
//! An image whose region is empty has no region figures: it is left out of the region means
//! and counted ([`RegionMeans::empty_images`]).

use seqavatar_compute::ssim::ssim_map;

use crate::metrics::{Mask, MetricError};
use seqavatar_compute::image::{ImageF32, Rect};
use seqavatar_compute::lpips::{LpipsNet, tap_sizes};

/// The region metrics of one image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RegionScore {
    /// The region has no pixel in this image.
    Empty,
    Scored {
        /// Pixels in the region.
        pixels: usize,
        psnr: f64,
        ssim: f64,
        /// `None` when no weights are configured (as the whole-image figures).
        lpips_vgg: Option<f64>,
        lpips_alex: Option<f64>,
    },
}

impl RegionScore {
    pub fn psnr(&self) -> Option<f64> {
        match self {
            Self::Scored { psnr, .. } => Some(*psnr),
            Self::Empty => None,
        }
    }

    pub fn ssim(&self) -> Option<f64> {
        match self {
            Self::Scored { ssim, .. } => Some(*ssim),
            Self::Empty => None,
        }
    }

    pub fn lpips_vgg(&self) -> Option<f64> {
        match self {
            Self::Scored { lpips_vgg, .. } => *lpips_vgg,
            Self::Empty => None,
        }
    }

    pub fn lpips_alex(&self) -> Option<f64> {
        match self {
            Self::Scored { lpips_alex, .. } => *lpips_alex,
            Self::Empty => None,
        }
    }
}

/// Means of the region metrics over the images whose region is not empty.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RegionMeans {
    /// Images with a non-empty region (those averaged).
    pub images: usize,
    /// Images whose region is empty (left out of the means).
    pub empty_images: usize,
    /// `None` when no image has a non-empty region.
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    /// `None` also when an averaged image has no LPIPS (no weights).
    pub lpips_vgg: Option<f64>,
    pub lpips_alex: Option<f64>,
}

/// How region LPIPS is taken; written into the summary and the reports.
pub const REGION_LPIPS_METHOD: &str =
    "crop of the region's bounding box (grown to the LPIPS trunk's smallest input)";

fn check_region(
    what: &'static str,
    render: &ImageF32,
    truth: &ImageF32,
    region: &Mask,
) -> Result<(), MetricError> {
    if render.width != truth.width || render.height != truth.height {
        return Err(MetricError::SizeMismatch {
            what,
            left_width: render.width,
            left_height: render.height,
            right_width: truth.width,
            right_height: truth.height,
        });
    }
    if region.width != render.width || region.height != render.height {
        return Err(MetricError::Invalid {
            what,
            message: format!(
                "region mask is {} x {}, images are {} x {}",
                region.width, region.height, render.width, render.height
            ),
        });
    }
    Ok(())
}

/// The indices of the region's pixels (row-major).
fn region_pixels(region: &Mask) -> Vec<usize> {
    (0..region.data.len())
        .filter(|&i| region.is_foreground(i % region.width, i / region.width))
        .collect()
}

/// PSNR over the region's pixels (data range 1); `None` when the region is empty, `+inf` when
/// the region's pixels are identical.
pub fn region_psnr(
    render: &ImageF32,
    truth: &ImageF32,
    region: &Mask,
) -> Result<Option<f64>, MetricError> {
    check_region("region psnr", render, truth, region)?;
    let pixels = region_pixels(region);
    if pixels.is_empty() {
        return Ok(None);
    }
    let mut sum = 0.0;
    for &p in &pixels {
        for c in 0..3 {
            let difference = f64::from(render.data[3 * p + c]) - f64::from(truth.data[3 * p + c]);
            sum += difference * difference;
        }
    }
    let mse = sum / (3 * pixels.len()) as f64;
    Ok(Some(if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }))
}

/// The mean of the whole image's SSIM map over the region's pixels and channels; `None` when
/// the region is empty.
pub fn region_ssim(
    render: &ImageF32,
    truth: &ImageF32,
    region: &Mask,
) -> Result<Option<f64>, MetricError> {
    check_region("region ssim", render, truth, region)?;
    let pixels = region_pixels(region);
    if pixels.is_empty() {
        return Ok(None);
    }
    let planes = |image: &ImageF32| -> [Vec<f64>; 3] {
        std::array::from_fn(|c| {
            image
                .data
                .iter()
                .skip(c)
                .step_by(3)
                .map(|&v| f64::from(v))
                .collect()
        })
    };
    let map = ssim_map(&planes(render), &planes(truth), render.width, render.height);
    let total: f64 = map
        .iter()
        .map(|plane| pixels.iter().map(|&p| plane[p]).sum::<f64>())
        .sum();
    Ok(Some(total / (3 * pixels.len()) as f64))
}

/// The smallest square side the LPIPS trunk of `net` accepts.
fn smallest_lpips_side(net: LpipsNet) -> usize {
    (1..=4096)
        .find(|&side| tap_sizes(net, side, side).is_ok())
        .unwrap_or(4096)
}

/// The crop region LPIPS is taken on: the region's bounding box, grown about its centre to
/// the trunk's smallest input where it is smaller, clipped to the image; `None` when the
/// region is empty.
pub fn region_lpips_crop(region: &Mask, net: LpipsNet) -> Option<Rect> {
    let bound = region.bound_box(0)?;
    let side = smallest_lpips_side(net);
    let grow = |start: usize, extent: usize, limit: usize| -> (usize, usize) {
        let wanted = extent.max(side).min(limit);
        let centre = start + extent / 2;
        let begin = centre.saturating_sub(wanted / 2).min(limit - wanted);
        (begin, wanted)
    };
    let (x, width) = grow(bound.x, bound.width, region.width);
    let (y, height) = grow(bound.y, bound.height, region.height);
    Some(Rect {
        x,
        y,
        width,
        height,
    })
}

/// Means over the images' region scores (`None` entries: no region for that image, not
/// counted); `None` when no image has a region score at all.
pub fn region_means<'a>(scores: impl IntoIterator<Item = &'a RegionScore>) -> Option<RegionMeans> {
    let (mut any, mut empty_images) = (false, 0);
    let mut scored = Vec::new();
    for score in scores {
        any = true;
        match *score {
            RegionScore::Empty => empty_images += 1,
            RegionScore::Scored {
                psnr,
                ssim,
                lpips_vgg,
                lpips_alex,
                ..
            } => scored.push((psnr, ssim, lpips_vgg, lpips_alex)),
        }
    }
    if !any {
        return None;
    }
    let count = scored.len();
    let mean = |values: Vec<f64>| (count > 0).then(|| values.iter().sum::<f64>() / count as f64);
    let optional_mean = |values: Option<Vec<f64>>| values.and_then(mean);
    Some(RegionMeans {
        images: count,
        empty_images,
        psnr: mean(scored.iter().map(|s| s.0).collect()),
        ssim: mean(scored.iter().map(|s| s.1).collect()),
        lpips_vgg: optional_mean(scored.iter().map(|s| s.2).collect()),
        lpips_alex: optional_mean(scored.iter().map(|s| s.3).collect()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::tests::image;
    use crate::metrics::{psnr, ssim};

    fn mask(width: usize, height: usize, inside: impl Fn(usize, usize) -> u8) -> Mask {
        let data = (0..width * height)
            .map(|i| inside(i % width, i / width))
            .collect();
        Mask::new("region", width, height, data).unwrap()
    }

    /// A pair with a known error inside the region (0.1 in every channel: MSE 0.01, 20 dB) and
    /// another outside (0.5: MSE 0.25): the region PSNR sees only the inside; soft mask values
    /// below 128 are outside.
    #[test]
    fn region_psnr_averages_over_the_region_only() {
        let (width, height) = (16, 12);
        let inside = |x: usize, y: usize| (4..10).contains(&x) && (3..8).contains(&y);
        let truth = image(width, height, |x, y, c| 0.2 + 0.01 * (x + y + c) as f32);
        let render = image(width, height, |x, y, c| {
            truth.pixel(x, y)[c] + if inside(x, y) { 0.1 } else { 0.5 }
        });
        let region = mask(width, height, |x, y| {
            if inside(x, y) {
                200
            } else if x == 0 {
                127
            } else {
                0
            }
        });
        let value = region_psnr(&render, &truth, &region).unwrap().unwrap();
        assert!((value - 20.0).abs() < 1e-5, "{value}");
        // The whole image sees both errors: 30 pixels at 0.01, 162 at 0.25.
        let whole = psnr(&render, &truth).unwrap();
        let expected = -10.0 * ((30.0 * 0.01 + 162.0 * 0.25) / 192.0_f64).log10();
        assert!((whole - expected).abs() < 1e-5, "{whole} vs {expected}");
        // Identical inside: +inf whatever the outside.
        let same_inside = image(width, height, |x, y, c| {
            truth.pixel(x, y)[c] + if inside(x, y) { 0.0 } else { 0.5 }
        });
        assert_eq!(
            region_psnr(&same_inside, &truth, &region).unwrap(),
            Some(f64::INFINITY)
        );
        // Empty region: no value; a mask of another size: an error.
        let empty = mask(width, height, |_, _| 0);
        assert_eq!(region_psnr(&render, &truth, &empty).unwrap(), None);
        assert_eq!(region_ssim(&render, &truth, &empty).unwrap(), None);
        let wrong = mask(width - 1, height, |_, _| 255);
        assert!(
            region_psnr(&render, &truth, &wrong)
                .unwrap_err()
                .to_string()
                .contains("region mask is 15 x 12")
        );
    }

    /// Region = whole image gives the whole-image PSNR and SSIM; a region of identical pixels
    /// far from any difference scores SSIM 1; one over the difference scores below the mean.
    #[test]
    fn region_equal_to_the_image_gives_the_whole_image_figures() {
        let (width, height) = (23, 17);
        let noise = |x: usize, y: usize, c: usize, salt: usize| {
            (((x * 7919 + y * 104_729 + c * 31 + salt * 613) % 1000) as f32) / 1000.0
        };
        let truth = image(width, height, |x, y, c| noise(x, y, c, 1));
        let render = image(width, height, |x, y, c| {
            0.7 * noise(x, y, c, 1) + 0.3 * noise(x, y, c, 2)
        });
        let all = mask(width, height, |_, _| 255);
        let region = region_psnr(&render, &truth, &all).unwrap().unwrap();
        let whole = psnr(&render, &truth).unwrap();
        assert!((region - whole).abs() < 1e-12, "{region} vs {whole}");
        let region = region_ssim(&render, &truth, &all).unwrap().unwrap();
        let whole = ssim(&render, &truth).unwrap();
        assert!((region - whole).abs() < 1e-12, "{region} vs {whole}");
        // The render differs only in columns 15.. : the SSIM window (radius 5) of a region in
        // columns 0..4 sees no difference, one in columns 15.. sees it.
        let partly = image(width, height, |x, y, c| {
            if x >= 15 {
                render.pixel(x, y)[c]
            } else {
                truth.pixel(x, y)[c]
            }
        });
        let left = mask(width, height, |x, _| if x < 4 { 255 } else { 0 });
        let right = mask(width, height, |x, _| if x >= 15 { 255 } else { 0 });
        let left_ssim = region_ssim(&partly, &truth, &left).unwrap().unwrap();
        assert!((left_ssim - 1.0).abs() < 1e-12, "{left_ssim}");
        let right_ssim = region_ssim(&partly, &truth, &right).unwrap().unwrap();
        assert!(right_ssim < ssim(&partly, &truth).unwrap(), "{right_ssim}");
    }

    #[test]
    fn lpips_crop_is_the_bounding_box_grown_to_the_trunk_minimum() {
        let side = smallest_lpips_side(LpipsNet::Vgg);
        assert!(tap_sizes(LpipsNet::Vgg, side, side).is_ok());
        assert!(tap_sizes(LpipsNet::Vgg, side - 1, side - 1).is_err());
        let (width, height) = (200, 120);
        // A large region: its bounding box.
        let large = mask(width, height, |x, y| {
            u8::from((20..120).contains(&x) && (10..90).contains(&y)) * 255
        });
        assert_eq!(
            region_lpips_crop(&large, LpipsNet::Vgg),
            Some(Rect {
                x: 20,
                y: 10,
                width: 100,
                height: 80
            })
        );
        // A 2 x 2 region at the corner: grown to the minimum, kept inside the image.
        let small = mask(width, height, |x, y| u8::from(x < 2 && y < 2) * 255);
        let crop = region_lpips_crop(&small, LpipsNet::Vgg).unwrap();
        assert_eq!(
            crop,
            Rect {
                x: 0,
                y: 0,
                width: side,
                height: side
            }
        );
        assert_eq!(
            region_lpips_crop(&mask(width, height, |_, _| 0), LpipsNet::Vgg),
            None
        );
    }

    #[test]
    fn means_leave_empty_regions_out_and_count_them() {
        let scored = |psnr: f64, lpips: Option<f64>| RegionScore::Scored {
            pixels: 10,
            psnr,
            ssim: psnr / 100.0,
            lpips_vgg: lpips,
            lpips_alex: None,
        };
        let scores = [
            scored(20.0, Some(0.1)),
            RegionScore::Empty,
            scored(30.0, Some(0.3)),
        ];
        let means = region_means(&scores).unwrap();
        assert_eq!((means.images, means.empty_images), (2, 1));
        assert_eq!(means.psnr, Some(25.0));
        assert!((means.ssim.unwrap() - 0.25).abs() < 1e-15);
        assert!((means.lpips_vgg.unwrap() - 0.2).abs() < 1e-15);
        assert_eq!(means.lpips_alex, None);
        let only_empty = region_means(&[RegionScore::Empty]).unwrap();
        assert_eq!((only_empty.images, only_empty.empty_images), (0, 1));
        assert_eq!(only_empty.psnr, None);
        assert_eq!(region_means(std::iter::empty()), None);
    }
}
