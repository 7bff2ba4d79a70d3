//! The scores of test images and their means: what every subset, probe and report of the
//! protocol is made of.

use crate::region::{RegionMeans, RegionScore, region_means};

/// The metrics of one test image. LPIPS is `None` when no weights were configured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageScore {
    pub psnr: f64,
    pub ssim: f64,
    pub lpips_vgg: Option<f64>,
    pub lpips_alex: Option<f64>,
    /// The garment region's metrics (crate::region); `None` where the image has no garment
    /// mask (its dataset has no garment region).
    pub garment: Option<RegionScore>,
}

/// Means of the per-image metrics (LPIPS means only when every image has LPIPS).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeanScores {
    pub images: usize,
    pub psnr: f64,
    pub ssim: f64,
    pub lpips_vgg: Option<f64>,
    pub lpips_alex: Option<f64>,
    /// The garment region's means; absent where the images have no garment mask (and in
    /// summaries written before eval version 10).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub garment: Option<RegionMeans>,
}

/// Averages scores (PSNR per image, then averaged, as the paper).
pub fn mean_scores(scores: &[ImageScore]) -> MeanScores {
    let count = scores.len();
    let mean = |values: &mut dyn Iterator<Item = f64>| values.sum::<f64>() / count as f64;
    let optional_mean = |pick: fn(&ImageScore) -> Option<f64>| -> Option<f64> {
        let values: Option<Vec<f64>> = scores.iter().map(pick).collect();
        values
            .filter(|values| !values.is_empty())
            .map(|values| values.iter().sum::<f64>() / values.len() as f64)
    };
    MeanScores {
        images: count,
        psnr: mean(&mut scores.iter().map(|score| score.psnr)),
        ssim: mean(&mut scores.iter().map(|score| score.ssim)),
        lpips_vgg: optional_mean(|score| score.lpips_vgg),
        lpips_alex: optional_mean(|score| score.lpips_alex),
        garment: region_means(scores.iter().filter_map(|score| score.garment.as_ref())),
    }
}
