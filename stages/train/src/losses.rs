//! Image and geometry losses of SeqAvatar training, each with its exact backward.
//!
//! - L1 on colour and `mask_weight x` MSE between rendered alpha and the foreground mask,
//!   both averaged over the bound mask (the 2D bounding box of the foreground, padded).
//! - `1 - SSIM` on the bounding-box crop, 11 px Gaussian window with sigma 1.5, zero padding
//!   ("same" output), constants `C1 = 0.01^2`, `C2 = 0.03^2`, as 3DGS computes it.
//! - As-isometric-as-possible: L1 between canonical and deformed distances of each Gaussian
//!   to its canonical nearest neighbours, for centres and for covariances (6 upper entries).
//! - LPIPS ([`LpipsLoss`]) on the bounding-box crop, grown where needed to the trunk's
//!   minimum input size; the network runs in f32 (`seqavatar_compute::lpips`).
//!
//! Images are row-major `H x W x 3` (colour) and `H x W` (alpha, mask), values in `[0, 1]`,
//! held in f64 so that the gradients can be checked against finite differences.

use seqavatar_compute::image::ImageF32;
use seqavatar_compute::lpips::{Lpips, LpipsError, LpipsInput, tap_sizes};
use seqavatar_compute::ssim::ssim_planes;
use seqavatar_knn::{MovingKnn, as_points};

use seqavatar_avatar::skinning::{canonical_covariances, canonical_covariances_backward};

/// A half-open pixel rectangle `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }
    pub fn area(&self) -> usize {
        self.width() * self.height()
    }
}

/// The bound mask: bounding box of the pixels whose mask value exceeds 0.5, grown by `pad`
/// pixels on each side and clipped to the image. `None` when the mask is empty.
pub fn bound_box(mask: &[f64], width: usize, height: usize, pad: usize) -> Option<Rect> {
    assert_eq!(mask.len(), width * height, "mask size");
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0usize, 0usize);
    for row in 0..height {
        for col in 0..width {
            if mask[row * width + col] > 0.5 {
                x0 = x0.min(col);
                y0 = y0.min(row);
                x1 = x1.max(col + 1);
                y1 = y1.max(row + 1);
            }
        }
    }
    if x0 == usize::MAX {
        return None;
    }
    Some(crate::run::pad_rect(
        Rect { x0, y0, x1, y1 },
        pad,
        width,
        height,
    ))
}

/// Weights of the photometric loss `l1 + mask_weight mask_mse + ssim_weight (1 - SSIM)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageLossWeights {
    pub mask: f64,
    pub ssim: f64,
}

/// The terms of the photometric loss (unweighted) and their weighted sum.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ImageLossTerms {
    pub l1: f64,
    pub mask_mse: f64,
    /// `1 - SSIM` on the crop.
    pub dssim: f64,
    pub total: f64,
}

/// Gradients of the photometric loss with respect to the rendered image and alpha.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageLossGrads {
    /// `H x W x 3`, zero outside the bound box.
    pub colour: Vec<f64>,
    /// `H x W`, zero outside the bound box.
    pub alpha: Vec<f64>,
}

/// A rendered and a target colour image of one camera, `H x W x 3` each (the LPIPS loss).
#[derive(Clone, Copy)]
pub struct ColourPair<'a> {
    pub width: usize,
    pub height: usize,
    /// Rendered colour.
    pub colour: &'a [f64],
    /// Ground-truth colour.
    pub target: &'a [f64],
}

/// One camera's images for the photometric loss.
pub struct ImagePair<'a> {
    pub width: usize,
    pub height: usize,
    /// Rendered colour, `H x W x 3`.
    pub colour: &'a [f64],
    /// Rendered accumulated alpha, `H x W`.
    pub alpha: &'a [f64],
    /// Ground-truth colour, `H x W x 3`.
    pub target_colour: &'a [f64],
    /// Ground-truth foreground mask in `[0, 1]`, `H x W`.
    pub target_mask: &'a [f64],
}

/// Photometric loss and its gradients over the bound box `rect`.
pub fn image_loss(
    pair: &ImagePair<'_>,
    rect: Rect,
    weights: ImageLossWeights,
) -> (ImageLossTerms, ImageLossGrads) {
    let (w, h) = (pair.width, pair.height);
    assert_eq!(pair.colour.len(), w * h * 3, "colour size");
    assert_eq!(pair.target_colour.len(), w * h * 3, "target colour size");
    assert_eq!(pair.alpha.len(), w * h, "alpha size");
    assert_eq!(pair.target_mask.len(), w * h, "mask size");
    assert!(
        rect.x1 <= w && rect.y1 <= h && rect.area() > 0,
        "bad rect {rect:?}"
    );
    let mut grads = ImageLossGrads {
        colour: vec![0.0; w * h * 3],
        alpha: vec![0.0; w * h],
    };
    let pixel_count = rect.area() as f64;
    let mut l1 = 0.0;
    let mut mse = 0.0;
    let l1_scale = 1.0 / (3.0 * pixel_count);
    let mse_scale = 1.0 / pixel_count;
    for row in rect.y0..rect.y1 {
        for col in rect.x0..rect.x1 {
            let p = row * w + col;
            for c in 0..3 {
                let diff = pair.colour[3 * p + c] - pair.target_colour[3 * p + c];
                l1 += diff.abs();
                grads.colour[3 * p + c] = l1_scale * sign(diff);
            }
            let diff = pair.alpha[p] - pair.target_mask[p];
            mse += diff * diff;
            grads.alpha[p] = weights.mask * mse_scale * 2.0 * diff;
        }
    }
    let l1 = l1 * l1_scale;
    let mask_mse = mse * mse_scale;
    let mut dssim = 0.0;
    if weights.ssim != 0.0 {
        let crop = crop_planes(pair.colour, w, rect);
        let crop_target = crop_planes(pair.target_colour, w, rect);
        let (ssim, d_crop) = ssim_planes(&crop, &crop_target, rect.width(), rect.height());
        dssim = 1.0 - ssim;
        for c in 0..3 {
            for row in 0..rect.height() {
                for col in 0..rect.width() {
                    let p = (rect.y0 + row) * w + rect.x0 + col;
                    grads.colour[3 * p + c] -= weights.ssim * d_crop[c][row * rect.width() + col];
                }
            }
        }
    }
    let total = l1 + weights.mask * mask_mse + weights.ssim * dssim;
    (
        ImageLossTerms {
            l1,
            mask_mse,
            dssim,
            total,
        },
        grads,
    )
}

fn sign(v: f64) -> f64 {
    if v > 0.0 {
        1.0
    } else if v < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// Copies the crop of an interleaved `H x W x 3` image into three row-major planes.
fn crop_planes(image: &[f64], width: usize, rect: Rect) -> [Vec<f64>; 3] {
    std::array::from_fn(|c| {
        let mut plane = Vec::with_capacity(rect.area());
        for row in rect.y0..rect.y1 {
            for col in rect.x0..rect.x1 {
                plane.push(image[3 * (row * width + col) + c]);
            }
        }
        plane
    })
}

/// The LPIPS loss on the bound-box crop (docs/method.md "Losses": `w x LPIPS(render crop, target
/// crop)`), with its gradient with respect to the rendered colour.
pub struct LpipsLoss {
    lpips: Lpips,
    input: LpipsInput,
    min_extent: usize,
}

impl LpipsLoss {
    pub fn new(lpips: Lpips, input: LpipsInput) -> Self {
        let net = lpips.weights().net;
        // The smallest square input the trunk accepts (VGG: 16, AlexNet: 31); the trunk's
        // size rules are per axis, so it is also the smallest extent along either axis.
        let min_extent = (1..=4096)
            .find(|&extent| tap_sizes(net, extent, extent).is_ok())
            .expect("both trunks accept 4096 px");
        Self {
            lpips,
            input,
            min_extent,
        }
    }

    /// The smallest crop side the trunk accepts.
    pub fn min_extent(&self) -> usize {
        self.min_extent
    }

    pub fn lpips(&self) -> &Lpips {
        &self.lpips
    }

    /// Whether a `width x height` image can hold the trunk's smallest input; the error names
    /// both sizes.
    pub fn check_image(&self, width: usize, height: usize) -> Result<(), LpipsError> {
        if width >= self.min_extent && height >= self.min_extent {
            return Ok(());
        }
        Err(LpipsError::Input {
            message: format!(
                "the {} trunk needs images of at least {m} x {m} px; this one is {width} x {height}",
                self.lpips.weights().net.name(),
                m = self.min_extent
            ),
        })
    }

    /// The crop LPIPS sees: `rect`, grown symmetrically to at least [`Self::min_extent`] per
    /// axis (shifted to stay inside the image). A bound box smaller than the trunk's input is
    /// grown rather than skipped, so the loss never silently drops out; an image smaller
    /// than that is an error naming both sizes ([`Self::check_image`]).
    pub fn crop(&self, rect: Rect, width: usize, height: usize) -> Result<Rect, LpipsError> {
        self.check_image(width, height)?;
        let grow = |start: usize, end: usize, size: usize| -> (usize, usize) {
            let extent = end - start;
            if extent >= self.min_extent {
                return (start, end);
            }
            let missing = self.min_extent - extent;
            let start = start
                .saturating_sub(missing / 2)
                .min(size - self.min_extent);
            (start, start + self.min_extent)
        };
        let (x0, x1) = grow(rect.x0, rect.x1, width);
        let (y0, y1) = grow(rect.y0, rect.y1, height);
        Ok(Rect { x0, y0, x1, y1 })
    }

    /// LPIPS between the crops of the rendered and the target colour, and `weight x` its
    /// gradient with respect to `images.colour` added into `gradient` (`H x W x 3`).
    pub fn add_loss(
        &self,
        images: ColourPair<'_>,
        rect: Rect,
        weight: f64,
        gradient: &mut [f64],
    ) -> Result<f64, LpipsError> {
        let ColourPair {
            width,
            height,
            colour,
            target,
        } = images;
        assert!(
            colour.len() == width * height * 3
                && target.len() == colour.len()
                && gradient.len() == colour.len(),
            "LPIPS loss: image sizes"
        );
        let crop = self.crop(rect, width, height)?;
        let cut = |image: &[f64]| {
            let mut values = Vec::with_capacity(crop.area() * 3);
            for row in crop.y0..crop.y1 {
                values.extend(
                    image[3 * (row * width + crop.x0)..3 * (row * width + crop.x1)]
                        .iter()
                        .map(|&v| v as f32),
                );
            }
            ImageF32::from_f32("LPIPS crop", crop.width(), crop.height(), values).map_err(|error| {
                LpipsError::Input {
                    message: error.to_string(),
                }
            })
        };
        let (render, truth) = (cut(colour)?, cut(target)?);
        let (distances, gradients) = self
            .lpips
            .distances_with_gradient(&[(&render, &truth)], self.input)?;
        let crop_gradient = &gradients[0];
        for row in 0..crop.height() {
            let line = &mut gradient[3 * ((crop.y0 + row) * width + crop.x0)..][..3 * crop.width()];
            for (g, &d) in line
                .iter_mut()
                .zip(&crop_gradient[3 * row * crop.width()..][..3 * crop.width()])
            {
                *g += weight * f64::from(d);
            }
        }
        Ok(distances[0].total)
    }
}

/// Unweighted as-isometric-as-possible terms (means over all neighbour pairs).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AiapTerms {
    pub centres: f64,
    pub covariances: f64,
}

/// Gradients of `centre_weight x centres + covariance_weight x covariances`.
#[derive(Clone, Debug, PartialEq)]
pub struct AiapGrads {
    pub canonical_centres: Vec<f64>,
    pub deformed_centres: Vec<f64>,
    pub canonical_covariances: Vec<f64>,
    pub deformed_covariances: Vec<f64>,
}

/// Inputs of the as-isometric-as-possible loss: `N x 3` centres and `N x 6` covariance upper
/// triangles before and after deformation, and `N x k` canonical neighbour indices whose first
/// column is the Gaussian itself (it is skipped, as in 3DGS-Avatar).
pub struct AiapInputs<'a> {
    pub canonical_centres: &'a [f64],
    pub deformed_centres: &'a [f64],
    pub canonical_covariances: &'a [f64],
    pub deformed_covariances: &'a [f64],
    pub neighbours: &'a [u32],
    pub k: usize,
}

/// As-isometric-as-possible loss on centres and covariances, with gradients for all four
/// tensors scaled by the given weights.
pub fn aiap_loss(
    inputs: &AiapInputs<'_>,
    centre_weight: f64,
    covariance_weight: f64,
) -> (AiapTerms, AiapGrads) {
    let n = inputs.canonical_centres.len() / 3;
    assert_eq!(inputs.deformed_centres.len(), 3 * n);
    assert_eq!(inputs.canonical_covariances.len(), 6 * n);
    assert_eq!(inputs.deformed_covariances.len(), 6 * n);
    assert_eq!(inputs.neighbours.len(), inputs.k * n);
    let mut grads = AiapGrads {
        canonical_centres: vec![0.0; 3 * n],
        deformed_centres: vec![0.0; 3 * n],
        canonical_covariances: vec![0.0; 6 * n],
        deformed_covariances: vec![0.0; 6 * n],
    };
    let pairs = (n * inputs.k.saturating_sub(1)) as f64;
    if pairs == 0.0 {
        return (AiapTerms::default(), grads);
    }
    let centres = aiap_term::<3>(
        inputs.canonical_centres,
        inputs.deformed_centres,
        inputs,
        centre_weight / pairs,
        &mut grads.canonical_centres,
        &mut grads.deformed_centres,
    );
    let covariances = aiap_term::<6>(
        inputs.canonical_covariances,
        inputs.deformed_covariances,
        inputs,
        covariance_weight / pairs,
        &mut grads.canonical_covariances,
        &mut grads.deformed_covariances,
    );
    (
        AiapTerms {
            centres: centres / pairs,
            covariances: covariances / pairs,
        },
        grads,
    )
}

/// Weights and neighbourhood of the as-isometric-as-possible loss (the train config's
/// `aiap_centre_weight`, `aiap_covariance_weight`, `aiap_neighbours`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AiapWeights {
    pub centre: f64,
    pub covariance: f64,
    /// Neighbours per Gaussian, the Gaussian itself included.
    pub neighbours: usize,
}

/// The canonical Gaussians and their deformation, as the AIAP loss of one iteration reads
/// them: `N x 3` centres, log-scales and deformed centres, `N x 4` rotations `[w, x, y, z]`,
/// `N x 6` deformed covariance upper triangles.
pub struct AiapGaussians<'a> {
    pub xyz: &'a [f64],
    pub log_scale: &'a [f64],
    pub rotation: &'a [f64],
    pub deformed_centres: &'a [f64],
    pub deformed_covariances: &'a [f64],
}

/// The weighted AIAP loss of one iteration and its gradients: into the deformed centres and
/// covariances (added to the splatting's before the skinning backward) and into the
/// canonical Gaussians' own parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct AiapGaussianGrads {
    /// `centre x centres + covariance x covariances`.
    pub value: f64,
    pub deformed_centres: Vec<f64>,
    pub deformed_covariances: Vec<f64>,
    pub xyz: Vec<f64>,
    pub log_scale: Vec<f64>,
    pub rotation: Vec<f64>,
}

/// As-isometric-as-possible loss between the canonical Gaussians and their deformation, over
/// each Gaussian's canonical nearest neighbours (exact for this call's centres, as the
/// reference code's per-iteration search: the centres move and densification renumbers them;
/// `knn` keeps candidate lists between calls so that small moves cost no full search), with
/// the canonical covariances built from the log-scales and rotations and their gradients
/// carried back to those. `None` when both weights are 0 or there is at most one Gaussian (no
/// pair to compare).
pub fn aiap_gaussians(
    gaussians: &AiapGaussians<'_>,
    weights: AiapWeights,
    knn: &mut MovingKnn,
) -> Option<AiapGaussianGrads> {
    let n = gaussians.xyz.len() / 3;
    if !(weights.centre > 0.0 || weights.covariance > 0.0) || n <= 1 {
        return None;
    }
    let k = weights.neighbours.min(n);
    let points = as_points(gaussians.xyz);
    let neighbours = knn.neighbours(&points, k);
    let canonical_covariances = canonical_covariances(gaussians.log_scale, gaussians.rotation);
    let (terms, grads) = aiap_loss(
        &AiapInputs {
            canonical_centres: gaussians.xyz,
            deformed_centres: gaussians.deformed_centres,
            canonical_covariances: &canonical_covariances,
            deformed_covariances: gaussians.deformed_covariances,
            neighbours: &neighbours,
            k,
        },
        weights.centre,
        weights.covariance,
    );
    let mut log_scale = vec![0.0; 3 * n];
    let mut rotation = vec![0.0; 4 * n];
    canonical_covariances_backward(
        gaussians.log_scale,
        gaussians.rotation,
        &grads.canonical_covariances,
        &mut log_scale,
        &mut rotation,
    );
    Some(AiapGaussianGrads {
        value: weights.centre * terms.centres + weights.covariance * terms.covariances,
        deformed_centres: grads.deformed_centres,
        deformed_covariances: grads.deformed_covariances,
        xyz: grads.canonical_centres,
        log_scale,
        rotation,
    })
}

/// Sum over pairs of `|d(a_i, a_j) - d(b_i, b_j)|` for `D`-vectors; accumulates gradients
/// times `scale`. A zero distance has a zero (sub)gradient instead of NaN.
fn aiap_term<const D: usize>(
    canonical: &[f64],
    deformed: &[f64],
    inputs: &AiapInputs<'_>,
    scale: f64,
    grad_canonical: &mut [f64],
    grad_deformed: &mut [f64],
) -> f64 {
    let n = canonical.len() / D;
    let mut sum = 0.0;
    for i in 0..n {
        for slot in 1..inputs.k {
            let j = inputs.neighbours[i * inputs.k + slot] as usize;
            let mut du = [0.0; D];
            let mut dv = [0.0; D];
            for d in 0..D {
                du[d] = canonical[i * D + d] - canonical[j * D + d];
                dv[d] = deformed[i * D + d] - deformed[j * D + d];
            }
            let lu = du.iter().map(|v| v * v).sum::<f64>().sqrt();
            let lv = dv.iter().map(|v| v * v).sum::<f64>().sqrt();
            let diff = lu - lv;
            sum += diff.abs();
            let g = scale * sign(diff);
            if g == 0.0 {
                continue;
            }
            for d in 0..D {
                if lu > 0.0 {
                    let t = g * du[d] / lu;
                    grad_canonical[i * D + d] += t;
                    grad_canonical[j * D + d] -= t;
                }
                if lv > 0.0 {
                    let t = g * dv[d] / lv;
                    grad_deformed[i * D + d] -= t;
                    grad_deformed[j * D + d] += t;
                }
            }
        }
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn random_vec(rng: &mut Rng, n: usize, lo: f64, hi: f64) -> Vec<f64> {
        (0..n).map(|_| rng.uniform(lo, hi)).collect()
    }

    #[test]
    fn bound_box_pads_and_clips() {
        let (w, h) = (20, 10);
        let mut mask = vec![0.0; w * h];
        mask[3 * w + 2] = 1.0;
        mask[6 * w + 17] = 0.9;
        mask[9 * w + 10] = 0.4; // below threshold
        let rect = bound_box(&mask, w, h, 5).unwrap();
        assert_eq!(
            rect,
            Rect {
                x0: 0,
                y0: 0,
                x1: 20,
                y1: 10
            }
        );
        let rect = bound_box(&mask, w, h, 1).unwrap();
        assert_eq!(
            rect,
            Rect {
                x0: 1,
                y0: 2,
                x1: 19,
                y1: 8
            }
        );
        assert_eq!(bound_box(&vec![0.0; w * h], w, h, 5), None);
    }

    fn image_loss_value(pair: &ImagePair<'_>, rect: Rect, weights: ImageLossWeights) -> f64 {
        image_loss(pair, rect, weights).0.total
    }

    #[test]
    fn image_loss_gradient_matches_finite_differences() {
        let mut rng = Rng::new(11);
        let (w, h) = (16, 12);
        let colour = random_vec(&mut rng, w * h * 3, 0.0, 1.0);
        let target = random_vec(&mut rng, w * h * 3, 0.0, 1.0);
        let alpha = random_vec(&mut rng, w * h, 0.0, 1.0);
        let mask: Vec<f64> = (0..w * h).map(|_| rng.uniform(0.0, 1.0).round()).collect();
        let rect = Rect {
            x0: 2,
            y0: 1,
            x1: 14,
            y1: 11,
        };
        let weights = ImageLossWeights {
            mask: 0.1,
            ssim: 0.3,
        };
        let pair = ImagePair {
            width: w,
            height: h,
            colour: &colour,
            alpha: &alpha,
            target_colour: &target,
            target_mask: &mask,
        };
        let (terms, grads) = image_loss(&pair, rect, weights);
        assert!(terms.l1 > 0.0 && terms.mask_mse > 0.0 && terms.dssim > 0.0);
        let eps = 1e-6;
        for index in [
            0usize,
            3 * (2 * w + 3) + 1,
            3 * (5 * w + 7),
            3 * (10 * w + 13) + 2,
            3 * (11 * w + 15),
        ] {
            let mut plus = colour.clone();
            plus[index] += eps;
            let mut minus = colour.clone();
            minus[index] -= eps;
            let fp = image_loss_value(
                &ImagePair {
                    colour: &plus,
                    ..pair
                },
                rect,
                weights,
            );
            let fm = image_loss_value(
                &ImagePair {
                    colour: &minus,
                    ..pair
                },
                rect,
                weights,
            );
            let numeric = (fp - fm) / (2.0 * eps);
            assert!(
                (numeric - grads.colour[index]).abs() < 1e-7,
                "colour {index}: numeric {numeric} analytic {}",
                grads.colour[index]
            );
        }
        for index in [0usize, 2 * w + 3, 7 * w + 9, 11 * w + 15] {
            let mut plus = alpha.clone();
            plus[index] += eps;
            let mut minus = alpha.clone();
            minus[index] -= eps;
            let fp = image_loss_value(
                &ImagePair {
                    alpha: &plus,
                    ..pair
                },
                rect,
                weights,
            );
            let fm = image_loss_value(
                &ImagePair {
                    alpha: &minus,
                    ..pair
                },
                rect,
                weights,
            );
            let numeric = (fp - fm) / (2.0 * eps);
            assert!((numeric - grads.alpha[index]).abs() < 1e-7, "alpha {index}");
        }
    }

    #[test]
    fn image_loss_of_perfect_render_is_zero() {
        let mut rng = Rng::new(5);
        let (w, h) = (12, 12);
        let colour = random_vec(&mut rng, w * h * 3, 0.0, 1.0);
        let mask: Vec<f64> = (0..w * h).map(|_| rng.uniform(0.0, 1.0).round()).collect();
        let pair = ImagePair {
            width: w,
            height: h,
            colour: &colour,
            alpha: &mask,
            target_colour: &colour,
            target_mask: &mask,
        };
        let rect = Rect {
            x0: 0,
            y0: 0,
            x1: 12,
            y1: 12,
        };
        let (terms, _) = image_loss(
            &pair,
            rect,
            ImageLossWeights {
                mask: 0.1,
                ssim: 0.1,
            },
        );
        assert!(terms.total.abs() < 1e-12, "{terms:?}");
    }

    fn lpips_loss(net: seqavatar_compute::lpips::LpipsNet, input: LpipsInput) -> LpipsLoss {
        use seqavatar_compute::backend::{Backend, DeviceChoice};
        use seqavatar_compute::lpips::seeded::seeded_weights;
        let cpu = Backend::select(DeviceChoice::Cpu).unwrap();
        LpipsLoss::new(Lpips::new(seeded_weights(net, 7), &cpu).unwrap(), input)
    }

    #[test]
    fn lpips_crop_grows_to_the_trunk_minimum_inside_the_image() {
        use seqavatar_compute::lpips::LpipsNet;
        let vgg = lpips_loss(LpipsNet::Vgg, LpipsInput::Unit);
        let alex = lpips_loss(LpipsNet::Alex, LpipsInput::Unit);
        assert_eq!((vgg.min_extent(), alex.min_extent()), (16, 31));
        let rect = |x0, y0, x1, y1| Rect { x0, y0, x1, y1 };
        // Large enough: unchanged.
        assert_eq!(
            vgg.crop(rect(3, 4, 30, 25), 40, 30).unwrap(),
            rect(3, 4, 30, 25)
        );
        // 6 x 10 in the middle grows symmetrically to 16 x 16.
        assert_eq!(
            vgg.crop(rect(10, 10, 16, 20), 40, 30).unwrap(),
            rect(5, 7, 21, 23)
        );
        // At the borders it shifts inwards.
        assert_eq!(
            vgg.crop(rect(0, 25, 4, 30), 40, 30).unwrap(),
            rect(0, 14, 16, 30)
        );
        assert_eq!(
            alex.crop(rect(0, 0, 5, 5), 31, 40).unwrap(),
            rect(0, 0, 31, 31)
        );
        let error = alex.crop(rect(0, 0, 5, 5), 30, 40).unwrap_err().to_string();
        assert!(
            error.contains("31 x 31") && error.contains("30 x 40"),
            "{error}"
        );
    }

    #[test]
    fn lpips_loss_gradient_through_the_crop_matches_finite_differences() {
        use seqavatar_compute::lpips::{LpipsNet, cpu::totals_in, image_to_trunk};
        let mut rng = Rng::new(21);
        let (w, h) = (26, 21);
        let colour = random_vec(&mut rng, w * h * 3, 0.0, 1.0);
        let target = random_vec(&mut rng, w * h * 3, 0.0, 1.0);
        let rect = Rect {
            x0: 3,
            y0: 2,
            x1: 22,
            y1: 20,
        };
        for input in [LpipsInput::Unit, LpipsInput::UnitAsSigned] {
            let loss = lpips_loss(LpipsNet::Vgg, input);
            let weights = loss.lpips().weights();
            let mut gradient = vec![0.5; w * h * 3];
            let value = loss
                .add_loss(
                    ColourPair {
                        width: w,
                        height: h,
                        colour: &colour,
                        target: &target,
                    },
                    rect,
                    0.1,
                    &mut gradient,
                )
                .unwrap();
            // The reference: the f64 trunk on the f64 crop.
            let total = |image: &[f64]| {
                let pixels = rect.area();
                let mut data = vec![0.0; 6 * pixels];
                let (first, second) = data.split_at_mut(3 * pixels);
                let crop = |image: &[f64]| -> Vec<f64> {
                    (rect.y0..rect.y1)
                        .flat_map(|row| {
                            image[3 * (row * w + rect.x0)..3 * (row * w + rect.x1)].to_vec()
                        })
                        .collect()
                };
                image_to_trunk(weights, &crop(image), input, first);
                image_to_trunk(weights, &crop(&target), input, second);
                totals_in::<f64>(weights, &data, [2, rect.height(), rect.width()]).unwrap()[0]
            };
            assert!((value - total(&colour)).abs() < 1e-5, "{input:?}");
            // Outside the crop the gradient buffer is untouched.
            for index in [0, 3 * (w * h) - 1, 3 * (h - 1) * w, 3 * (2 * w + 22)] {
                assert_eq!(gradient[index], 0.5);
            }
            let scale = gradient.iter().fold(0.0_f64, |m, g| m.max((g - 0.5).abs()));
            let eps = 1e-6;
            for index in [
                3 * (2 * w + 3),
                3 * (10 * w + 11) + 1,
                3 * (19 * w + 21) + 2,
                3 * (7 * w + 4) + 2,
            ] {
                let mut plus = colour.clone();
                plus[index] += eps;
                let mut minus = colour.clone();
                minus[index] -= eps;
                let numeric = 0.1 * (total(&plus) - total(&minus)) / (2.0 * eps);
                let analytic = gradient[index] - 0.5;
                // The LPIPS gradient is computed in f32.
                assert!(
                    (analytic - numeric).abs() <= 1e-3 * scale,
                    "{input:?} value {index}: analytic {analytic} numeric {numeric}"
                );
            }
        }
    }

    #[test]
    fn aiap_gradient_matches_finite_differences() {
        let mut rng = Rng::new(9);
        let n = 12;
        let k = 4;
        let cx = random_vec(&mut rng, 3 * n, -1.0, 1.0);
        let dx = random_vec(&mut rng, 3 * n, -1.0, 1.0);
        let cc = random_vec(&mut rng, 6 * n, -1.0, 1.0);
        let dc = random_vec(&mut rng, 6 * n, -1.0, 1.0);
        let neighbours: Vec<u32> = (0..n)
            .flat_map(|i| {
                let mut row = vec![i as u32];
                row.extend((1..k).map(|s| ((i + 3 * s) % n) as u32));
                row
            })
            .collect();
        let eval = |cx: &[f64], dx: &[f64], cc: &[f64], dc: &[f64]| {
            let inputs = AiapInputs {
                canonical_centres: cx,
                deformed_centres: dx,
                canonical_covariances: cc,
                deformed_covariances: dc,
                neighbours: &neighbours,
                k,
            };
            aiap_loss(&inputs, 1.0, 100.0)
        };
        let (terms, grads) = eval(&cx, &dx, &cc, &dc);
        assert!(terms.centres > 0.0 && terms.covariances > 0.0);
        let value = |t: AiapTerms| t.centres + 100.0 * t.covariances;
        let eps = 1e-7;
        let tensors = [&cx, &dx, &cc, &dc];
        let analytic = [
            &grads.canonical_centres,
            &grads.deformed_centres,
            &grads.canonical_covariances,
            &grads.deformed_covariances,
        ];
        for which in 0..4 {
            for index in 0..tensors[which].len() {
                let mut plus: Vec<Vec<f64>> = tensors.iter().map(|t| t.to_vec()).collect();
                let mut minus = plus.clone();
                plus[which][index] += eps;
                minus[which][index] -= eps;
                let fp = value(eval(&plus[0], &plus[1], &plus[2], &plus[3]).0);
                let fm = value(eval(&minus[0], &minus[1], &minus[2], &minus[3]).0);
                let numeric = (fp - fm) / (2.0 * eps);
                assert!(
                    (numeric - analytic[which][index]).abs() < 1e-6,
                    "tensor {which} index {index}: {numeric} vs {}",
                    analytic[which][index]
                );
            }
        }
    }

    #[test]
    fn aiap_on_gaussians_matches_finite_differences_of_its_parameters() {
        let mut rng = Rng::new(21);
        let n = 10;
        let xyz = random_vec(&mut rng, 3 * n, -0.5, 0.5);
        let log_scale = random_vec(&mut rng, 3 * n, -3.0, -1.0);
        let rotation = random_vec(&mut rng, 4 * n, -1.0, 1.0);
        let deformed_centres: Vec<f64> = xyz.iter().map(|x| 1.3 * x + 0.05).collect();
        let deformed_covariances = random_vec(&mut rng, 6 * n, -0.01, 0.01);
        let weights = AiapWeights {
            centre: 1.0,
            covariance: 100.0,
            neighbours: 4,
        };
        let eval = |t: &[Vec<f64>]| {
            aiap_gaussians(
                &AiapGaussians {
                    xyz: &t[0],
                    log_scale: &t[1],
                    rotation: &t[2],
                    deformed_centres: &t[3],
                    deformed_covariances: &t[4],
                },
                weights,
                &mut MovingKnn::default(),
            )
            .expect("active with ten Gaussians")
        };
        let tensors = vec![
            xyz,
            log_scale,
            rotation,
            deformed_centres,
            deformed_covariances,
        ];
        let grads = eval(&tensors);
        assert!(grads.value > 0.0);
        // An independent composition of the pieces: brute-force neighbours, covariances
        // from `canonical_covariances`, the weighted sum of `aiap_loss`'s terms.
        let neighbours = seqavatar_knn::knn_brute_force(
            &as_points(&tensors[0]),
            &as_points(&tensors[0]),
            weights.neighbours,
        );
        let (terms, _) = aiap_loss(
            &AiapInputs {
                canonical_centres: &tensors[0],
                deformed_centres: &tensors[3],
                canonical_covariances: &canonical_covariances(&tensors[1], &tensors[2]),
                deformed_covariances: &tensors[4],
                neighbours: &neighbours,
                k: weights.neighbours,
            },
            1.0,
            1.0,
        );
        let expected = terms.centres + 100.0 * terms.covariances;
        assert!(
            (grads.value - expected).abs() <= 1e-12 * expected,
            "{grads:?}"
        );
        let analytic = [
            &grads.xyz,
            &grads.log_scale,
            &grads.rotation,
            &grads.deformed_centres,
            &grads.deformed_covariances,
        ];
        let eps = 1e-6;
        for which in 0..tensors.len() {
            for index in 0..tensors[which].len() {
                let mut plus = tensors.clone();
                let mut minus = tensors.clone();
                plus[which][index] += eps;
                minus[which][index] -= eps;
                let numeric = (eval(&plus).value - eval(&minus).value) / (2.0 * eps);
                let a = analytic[which][index];
                assert!(
                    (numeric - a).abs() <= 1e-5 * (1.0 + a.abs()),
                    "tensor {which} index {index}: numeric {numeric} analytic {a}"
                );
            }
        }
        // Off: both weights 0, or a single Gaussian.
        let off = AiapWeights {
            centre: 0.0,
            covariance: 0.0,
            neighbours: 4,
        };
        let t = &tensors;
        let inputs = AiapGaussians {
            xyz: &t[0],
            log_scale: &t[1],
            rotation: &t[2],
            deformed_centres: &t[3],
            deformed_covariances: &t[4],
        };
        assert!(aiap_gaussians(&inputs, off, &mut MovingKnn::default()).is_none());
        let single = AiapGaussians {
            xyz: &t[0][..3],
            log_scale: &t[1][..3],
            rotation: &t[2][..4],
            deformed_centres: &t[3][..3],
            deformed_covariances: &t[4][..6],
        };
        assert!(aiap_gaussians(&single, weights, &mut MovingKnn::default()).is_none());
    }

    #[test]
    fn aiap_is_zero_for_rigid_motion_and_finite_for_duplicates() {
        let n = 6;
        let centres: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.37).sin()).collect();
        // A rotation about z by 90 degrees plus a translation preserves distances.
        let moved: Vec<f64> = centres
            .chunks(3)
            .flat_map(|p| [-p[1] + 1.0, p[0] - 2.0, p[2] + 0.5])
            .collect();
        let mut covs = vec![0.1; 6 * n];
        covs[0] = 0.3;
        let neighbours: Vec<u32> = (0..n)
            .flat_map(|i| [i as u32, ((i + 1) % n) as u32, 0])
            .collect();
        let inputs = AiapInputs {
            canonical_centres: &centres,
            deformed_centres: &moved,
            canonical_covariances: &covs,
            deformed_covariances: &covs,
            neighbours: &neighbours,
            k: 3,
        };
        let (terms, grads) = aiap_loss(&inputs, 1.0, 100.0);
        assert!(terms.centres.abs() < 1e-12 && terms.covariances == 0.0);
        // Neighbour 0 of Gaussian 0 is itself (distance 0): gradients stay finite.
        assert!(grads.canonical_centres.iter().all(|g| g.is_finite()));
    }
}
