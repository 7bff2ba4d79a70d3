//! SSIM as 3DGS computes it (11 px Gaussian window with sigma 1.5, zero padding, "same"
//! output, constants `C1 = 0.01^2`, `C2 = 0.03^2`), in f64 with its exact gradient: the
//! training loss (`1 - SSIM` on the bound-box crop) and eval's metric use this one function.

use rayon::prelude::*;

/// Side of the SSIM window in pixels.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM's luminance stabiliser `(0.01 L)^2` for the dynamic range `L = 1`.
pub const SSIM_C1: f64 = 0.01 * 0.01;
/// SSIM's contrast stabiliser `(0.03 L)^2` for the dynamic range `L = 1`.
pub const SSIM_C2: f64 = 0.03 * 0.03;

/// The normalised 1D Gaussian window.
pub fn gaussian_window(size: usize, sigma: f64) -> Vec<f64> {
    let centre = (size / 2) as f64;
    let raw: Vec<f64> = (0..size)
        .map(|i| (-((i as f64 - centre).powi(2)) / (2.0 * sigma * sigma)).exp())
        .collect();
    let sum: f64 = raw.iter().sum();
    raw.into_iter().map(|v| v / sum).collect()
}

/// Separable "same" correlation with zero padding. The kernel is symmetric, so this operator
/// is its own adjoint, which the SSIM backward relies on.
///
/// Rows run in parallel; every output value is the sum over the in-range taps in kernel
/// order, whatever the thread count, so the result does not depend on it.
fn blur_same(plane: &[f64], width: usize, height: usize, kernel: &[f64]) -> Vec<f64> {
    assert_eq!(plane.len(), width * height, "blur plane size");
    let mut out = vec![0.0; plane.len()];
    if plane.is_empty() {
        return out;
    }
    let half = kernel.len() / 2;
    // Taps `k` whose source `i + k - half` lies in `0..len`.
    let taps = |i: usize, len: usize| half.saturating_sub(i)..kernel.len().min(len + half - i);
    let mut rows = vec![0.0; plane.len()];
    rows.par_chunks_mut(width)
        .zip(plane.par_chunks(width))
        .with_min_len(8)
        .for_each(|(out_row, src)| {
            for (col, value) in out_row.iter_mut().enumerate() {
                let mut acc = 0.0;
                for k in taps(col, width) {
                    acc += kernel[k] * src[col + k - half];
                }
                *value = acc;
            }
        });
    out.par_chunks_mut(width)
        .enumerate()
        .with_min_len(8)
        .for_each(|(row, out_row)| {
            for k in taps(row, height) {
                let src = &rows[(row + k - half) * width..][..width];
                let weight = kernel[k];
                for (value, s) in out_row.iter_mut().zip(src) {
                    *value += weight * s;
                }
            }
        });
    out
}

/// The blurred local statistics of one plane pair: means `mu_x`, `mu_y` and second moments
/// `E[x^2]`, `E[y^2]`, `E[xy]` under the SSIM window.
struct LocalMoments {
    mu_x: Vec<f64>,
    mu_y: Vec<f64>,
    e_xx: Vec<f64>,
    e_yy: Vec<f64>,
    e_xy: Vec<f64>,
}

impl LocalMoments {
    fn of(xs: &[f64], ys: &[f64], width: usize, height: usize, kernel: &[f64]) -> Self {
        let sq = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).collect::<Vec<_>>();
        Self {
            mu_x: blur_same(xs, width, height, kernel),
            mu_y: blur_same(ys, width, height, kernel),
            e_xx: blur_same(&sq(xs, xs), width, height, kernel),
            e_yy: blur_same(&sq(ys, ys), width, height, kernel),
            e_xy: blur_same(&sq(xs, ys), width, height, kernel),
        }
    }

    /// The four factors of pixel `i`'s SSIM `a1 a2 / (b1 b2)`: `(a1, a2, b1, b2)`.
    fn factors(&self, i: usize) -> (f64, f64, f64, f64) {
        let (m, k) = (self.mu_x[i], self.mu_y[i]);
        let sxx = self.e_xx[i] - m * m;
        let syy = self.e_yy[i] - k * k;
        let sxy = self.e_xy[i] - m * k;
        (
            2.0 * m * k + SSIM_C1,
            2.0 * sxy + SSIM_C2,
            m * m + k * k + SSIM_C1,
            sxx + syy + SSIM_C2,
        )
    }
}

/// The SSIM map of three planes: per plane, the local SSIM of every pixel (the values whose
/// mean over pixels and planes [`ssim_planes`] returns), for means over part of an image
/// (eval's garment region).
pub fn ssim_map(
    x: &[Vec<f64>; 3],
    y: &[Vec<f64>; 3],
    width: usize,
    height: usize,
) -> [Vec<f64>; 3] {
    let kernel = gaussian_window(SSIM_WINDOW, SSIM_SIGMA);
    std::array::from_fn(|c| {
        let moments = LocalMoments::of(&x[c], &y[c], width, height, &kernel);
        (0..x[c].len())
            .map(|i| {
                let (a1, a2, b1, b2) = moments.factors(i);
                a1 * a2 / (b1 * b2)
            })
            .collect()
    })
}

/// Mean SSIM over three planes and its gradient with respect to the first image's planes.
pub fn ssim_planes(
    x: &[Vec<f64>; 3],
    y: &[Vec<f64>; 3],
    width: usize,
    height: usize,
) -> (f64, [Vec<f64>; 3]) {
    let kernel = gaussian_window(SSIM_WINDOW, SSIM_SIGMA);
    let n = (width * height) as f64;
    let mut total = 0.0;
    let grads = std::array::from_fn(|c| {
        let (xs, ys) = (&x[c], &y[c]);
        let moments = LocalMoments::of(xs, ys, width, height, &kernel);
        // Per-pixel partial derivatives of S (times dMean/dS = 1/(3n)) with respect to
        // mu_x, E[x^2] and E[xy], the three blurred quantities that depend on x.
        let mut d_mu = vec![0.0; xs.len()];
        let mut d_exx = vec![0.0; xs.len()];
        let mut d_exy = vec![0.0; xs.len()];
        for i in 0..xs.len() {
            let (m, k) = (moments.mu_x[i], moments.mu_y[i]);
            let (a1, a2, b1, b2) = moments.factors(i);
            let s = a1 * a2 / (b1 * b2);
            total += s;
            let inv = 1.0 / (b1 * b2);
            let mean_factor = 1.0 / (3.0 * n);
            d_mu[i] = ((2.0 * k * a2 - 2.0 * k * a1) * inv - s * (2.0 * m / b1 - 2.0 * m / b2))
                * mean_factor;
            d_exx[i] = -s / b2 * mean_factor;
            d_exy[i] = 2.0 * a1 * inv * mean_factor;
        }
        let g_mu = blur_same(&d_mu, width, height, &kernel);
        let g_exx = blur_same(&d_exx, width, height, &kernel);
        let g_exy = blur_same(&d_exy, width, height, &kernel);
        (0..xs.len())
            .map(|i| g_mu[i] + 2.0 * xs[i] * g_exx[i] + ys[i] * g_exy[i])
            .collect()
    });
    (total / (3.0 * n), grads)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rng::SplitMix64 as Rng;

    fn random_vec(rng: &mut Rng, n: usize, lo: f64, hi: f64) -> Vec<f64> {
        (0..n).map(|_| rng.uniform(lo, hi)).collect()
    }

    /// The mean of the SSIM map over every pixel and plane, summed in `ssim_planes`' order
    /// (plane by plane, pixel by pixel), is its value bit for bit.
    #[test]
    fn ssim_map_mean_is_the_ssim_value() {
        let mut rng = Rng::new(11);
        for (width, height) in [(23, 17), (3, 2), (12, 12)] {
            let n = width * height;
            let x: [Vec<f64>; 3] = std::array::from_fn(|_| random_vec(&mut rng, n, 0.0, 1.0));
            let y: [Vec<f64>; 3] = std::array::from_fn(|_| random_vec(&mut rng, n, 0.0, 1.0));
            let (value, _) = ssim_planes(&x, &y, width, height);
            let map = ssim_map(&x, &y, width, height);
            let mut total = 0.0;
            for plane in &map {
                assert_eq!(plane.len(), n);
                for v in plane {
                    total += v;
                }
            }
            assert_eq!(total / (3 * n) as f64, value, "{width}x{height}");
            // Identical planes: 1 at every pixel.
            assert!(
                ssim_map(&x, &x, width, height)
                    .iter()
                    .flatten()
                    .all(|v| (v - 1.0).abs() < 1e-12)
            );
        }
    }

    /// The separable row-parallel blur against a direct 2D zero-padded correlation, on
    /// planes narrower and shorter than the window as well as larger ones.
    #[test]
    fn blur_matches_a_direct_two_dimensional_correlation() {
        let kernel = gaussian_window(SSIM_WINDOW, SSIM_SIGMA);
        let half = (SSIM_WINDOW / 2) as isize;
        let mut rng = Rng::new(4);
        for (width, height) in [(37, 23), (3, 40), (29, 4), (1, 1), (11, 11)] {
            let plane = random_vec(&mut rng, width * height, -1.0, 1.0);
            let blurred = blur_same(&plane, width, height, &kernel);
            for row in 0..height as isize {
                for col in 0..width as isize {
                    let mut expected = 0.0;
                    for dy in -half..=half {
                        for dx in -half..=half {
                            let (r, c) = (row + dy, col + dx);
                            if r >= 0 && r < height as isize && c >= 0 && c < width as isize {
                                expected += kernel[(dy + half) as usize]
                                    * kernel[(dx + half) as usize]
                                    * plane[r as usize * width + c as usize];
                            }
                        }
                    }
                    let got = blurred[row as usize * width + col as usize];
                    assert!(
                        (got - expected).abs() <= 1e-14,
                        "{width}x{height} at ({row}, {col}): {got} vs {expected}"
                    );
                }
            }
        }
    }

    #[test]
    fn window_is_normalised_and_symmetric() {
        let k = gaussian_window(11, 1.5);
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for i in 0..11 {
            assert_eq!(k[i], k[10 - i]);
        }
        // Closed form ratio of the centre to its neighbour.
        assert!((k[5] / k[4] - (1.0 / (2.0 * 2.25f64)).exp()).abs() < 1e-12);
    }

    /// SSIM recomputed with a direct 2D window sum (no separability), per pixel.
    fn ssim_direct(x: &[f64], y: &[f64], w: usize, h: usize) -> f64 {
        let k = gaussian_window(11, 1.5);
        let mut total = 0.0;
        for r in 0..h as isize {
            for c in 0..w as isize {
                let (mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for dr in -5isize..=5 {
                    for dc in -5isize..=5 {
                        let (rr, cc) = (r + dr, c + dc);
                        if rr < 0 || cc < 0 || rr >= h as isize || cc >= w as isize {
                            continue;
                        }
                        let g = k[(dr + 5) as usize] * k[(dc + 5) as usize];
                        let i = rr as usize * w + cc as usize;
                        mx += g * x[i];
                        my += g * y[i];
                        xx += g * x[i] * x[i];
                        yy += g * y[i] * y[i];
                        xy += g * x[i] * y[i];
                    }
                }
                let (sx, sy, sxy) = (xx - mx * mx, yy - my * my, xy - mx * my);
                total += (2.0 * mx * my + SSIM_C1) * (2.0 * sxy + SSIM_C2)
                    / ((mx * mx + my * my + SSIM_C1) * (sx + sy + SSIM_C2));
            }
        }
        total / (w * h) as f64
    }

    #[test]
    fn ssim_matches_direct_window_sum_and_is_one_on_identical_images() {
        let mut rng = Rng::new(3);
        let (w, h) = (13, 9);
        let x: [Vec<f64>; 3] = std::array::from_fn(|_| random_vec(&mut rng, w * h, 0.0, 1.0));
        let y: [Vec<f64>; 3] = std::array::from_fn(|_| random_vec(&mut rng, w * h, 0.0, 1.0));
        let (s, _) = ssim_planes(&x, &y, w, h);
        let direct = (0..3).map(|c| ssim_direct(&x[c], &y[c], w, h)).sum::<f64>() / 3.0;
        assert!((s - direct).abs() < 1e-12, "{s} vs {direct}");
        let (same, grad) = ssim_planes(&x, &x, w, h);
        assert!((same - 1.0).abs() < 1e-12);
        // SSIM is maximal at x = y: the gradient vanishes there.
        assert!(grad.iter().flatten().all(|g| g.abs() < 1e-12));
    }

    #[test]
    fn ssim_gradient_matches_finite_differences() {
        let mut rng = Rng::new(8);
        let (w, h) = (9, 7);
        let x: [Vec<f64>; 3] = std::array::from_fn(|_| random_vec(&mut rng, w * h, 0.0, 1.0));
        let y: [Vec<f64>; 3] = std::array::from_fn(|_| random_vec(&mut rng, w * h, 0.0, 1.0));
        let (_, grad) = ssim_planes(&x, &y, w, h);
        let eps = 1e-6;
        for c in 0..3 {
            for i in 0..w * h {
                let mut plus = x.clone();
                plus[c][i] += eps;
                let mut minus = x.clone();
                minus[c][i] -= eps;
                let numeric = (ssim_planes(&plus, &y, w, h).0 - ssim_planes(&minus, &y, w, h).0)
                    / (2.0 * eps);
                assert!(
                    (numeric - grad[c][i]).abs() < 1e-8,
                    "plane {c} pixel {i}: {numeric} vs {}",
                    grad[c][i]
                );
            }
        }
    }
}
