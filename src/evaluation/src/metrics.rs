//! PSNR and SSIM, and the paper's evaluation protocol (docs/method.md "Evaluation protocol"):
//! render pixels outside the bound mask become background, ground-truth pixels outside the
//! foreground mask become background, PSNR is taken over the whole image.
//!
//! SSIM is the 3DGS / GauHuman `ssim()`: an 11 x 11 Gaussian window with sigma 1.5
//! (normalised), convolved per channel with zero padding ("same" size), constants
//! `C1 = 0.01^2`, `C2 = 0.03^2` for data range 1, and the mean of the SSIM map over every
//! pixel and channel. It is computed by the training crate's `ssim_planes` (one
//! implementation for the loss and the metric); the tests here check it independently against
//! a direct 2D window and against torch.

use seqavatar_compute::ssim::ssim_planes;

use seqavatar_compute::image::{ImageF32, Rect};

/// Why a metric could not be computed.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum MetricError {
    #[error(
        "{what}: images differ in size ({left_width} x {left_height} vs {right_width} x {right_height})"
    )]
    SizeMismatch {
        what: &'static str,
        left_width: usize,
        left_height: usize,
        right_width: usize,
        right_height: usize,
    },
    #[error("{what}: {message}")]
    Invalid { what: &'static str, message: String },
}

fn check_same_size(
    what: &'static str,
    left: &ImageF32,
    right: &ImageF32,
) -> Result<(), MetricError> {
    if left.width != right.width || left.height != right.height {
        return Err(MetricError::SizeMismatch {
            what,
            left_width: left.width,
            left_height: left.height,
            right_width: right.width,
            right_height: right.height,
        });
    }
    if left.data.is_empty() {
        return Err(MetricError::Invalid {
            what,
            message: "empty image".to_owned(),
        });
    }
    Ok(())
}

/// Mean squared error over every pixel and channel.
pub fn mse(render: &ImageF32, truth: &ImageF32) -> Result<f64, MetricError> {
    check_same_size("mse", render, truth)?;
    let sum: f64 = render
        .data
        .iter()
        .zip(&truth.data)
        .map(|(&a, &b)| {
            let difference = f64::from(a) - f64::from(b);
            difference * difference
        })
        .sum();
    Ok(sum / render.data.len() as f64)
}

/// PSNR in dB for data range 1: `-10 log10(mse)`; identical images give `+inf`.
pub fn psnr(render: &ImageF32, truth: &ImageF32) -> Result<f64, MetricError> {
    let error = mse(render, truth)?;
    Ok(if error == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * error.log10()
    })
}

/// The per-channel planes of an image, in f64.
fn planes(image: &ImageF32) -> [Vec<f64>; 3] {
    std::array::from_fn(|channel| {
        image
            .data
            .iter()
            .skip(channel)
            .step_by(3)
            .map(|&value| f64::from(value))
            .collect()
    })
}

/// Mean SSIM over pixels and channels: the one SSIM of the workspace,
/// `seqavatar_compute::ssim::ssim_planes` (the training loss uses it with its gradient).
pub fn ssim(render: &ImageF32, truth: &ImageF32) -> Result<f64, MetricError> {
    check_same_size("ssim", render, truth)?;
    let (value, _) = ssim_planes(&planes(render), &planes(truth), render.width, render.height);
    Ok(value)
}

/// A foreground mask, `uint8` 0..255 row-major `(height, width)`; a pixel is foreground
/// when its value is at least 128.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Mask {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

impl Mask {
    pub fn new(
        what: &'static str,
        width: usize,
        height: usize,
        data: Vec<u8>,
    ) -> Result<Self, MetricError> {
        if data.len() != width * height {
            return Err(MetricError::Invalid {
                what,
                message: format!(
                    "{} mask values, expected {} for {width} x {height}",
                    data.len(),
                    width * height
                ),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    pub fn is_foreground(&self, x: usize, y: usize) -> bool {
        self.data[y * self.width + x] >= 128
    }

    /// The bound mask: the bounding box of the foreground padded by `padding` pixels and
    /// clipped to the image; `None` when there is no foreground.
    pub fn bound_box(&self, padding: usize) -> Option<Rect> {
        let (mut min_x, mut min_y, mut max_x, mut max_y) = (usize::MAX, usize::MAX, 0, 0);
        for y in 0..self.height {
            for x in 0..self.width {
                if self.is_foreground(x, y) {
                    min_x = min_x.min(x);
                    min_y = min_y.min(y);
                    max_x = max_x.max(x);
                    max_y = max_y.max(y);
                }
            }
        }
        if min_x == usize::MAX {
            return None;
        }
        let x = min_x.saturating_sub(padding);
        let y = min_y.saturating_sub(padding);
        let end_x = (max_x + padding + 1).min(self.width);
        let end_y = (max_y + padding + 1).min(self.height);
        Some(Rect {
            x,
            y,
            width: end_x - x,
            height: end_y - y,
        })
    }
}

/// How a test view is scored.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Protocol {
    /// Background colour in [0, 1] (all three datasets train on black).
    pub background: [f32; 3],
    /// Padding of the bound box around the foreground mask, in pixels (docs/method.md: 5).
    pub bound_padding: usize,
    /// Score SSIM and LPIPS on the bound-box crop instead of the whole image (GauHuman's
    /// evaluation script crops; the paper's text does not say). PSNR is always whole-image.
    pub crop_ssim_lpips_to_bound_box: bool,
}

impl Default for Protocol {
    fn default() -> Self {
        Self {
            background: seqavatar_avatar::config::PROTOCOL_BACKGROUND.map(|c| c as f32),
            bound_padding: 5,
            crop_ssim_lpips_to_bound_box: false,
        }
    }
}

/// A render and its ground truth prepared for scoring.
#[derive(Clone, Debug, PartialEq)]
pub struct PreparedPair {
    pub render: ImageF32,
    pub truth: ImageF32,
    /// The region SSIM and LPIPS are computed on.
    pub region: Rect,
}

impl Protocol {
    /// Applies the background rules: render outside the bound box and ground truth outside
    /// the foreground mask become background. An empty mask leaves an all-background truth and
    /// scores the whole image.
    pub fn prepare(
        &self,
        render: &ImageF32,
        truth: &ImageF32,
        mask: &Mask,
    ) -> Result<PreparedPair, MetricError> {
        check_same_size("evaluation", render, truth)?;
        if mask.width != truth.width || mask.height != truth.height {
            return Err(MetricError::Invalid {
                what: "evaluation",
                message: format!(
                    "mask is {} x {}, images are {} x {}",
                    mask.width, mask.height, truth.width, truth.height
                ),
            });
        }
        let whole = Rect {
            x: 0,
            y: 0,
            width: truth.width,
            height: truth.height,
        };
        let bound = mask.bound_box(self.bound_padding);
        let mut render = render.clone();
        let mut truth = truth.clone();
        for y in 0..truth.height {
            for x in 0..truth.width {
                let start = (y * truth.width + x) * 3;
                let inside_bound = bound.is_some_and(|rect| {
                    x >= rect.x
                        && x < rect.x + rect.width
                        && y >= rect.y
                        && y < rect.y + rect.height
                });
                if !inside_bound {
                    render.data[start..start + 3].copy_from_slice(&self.background);
                }
                if !mask.is_foreground(x, y) {
                    truth.data[start..start + 3].copy_from_slice(&self.background);
                }
            }
        }
        let region = match (self.crop_ssim_lpips_to_bound_box, bound) {
            (true, Some(rect)) => rect,
            _ => whole,
        };
        Ok(PreparedPair {
            render,
            truth,
            region,
        })
    }
}

/// PSNR and SSIM of one prepared pair (LPIPS is separate: it runs batched on a backend).
pub fn psnr_ssim(pair: &PreparedPair) -> Result<(f64, f64), MetricError> {
    let psnr = psnr(&pair.render, &pair.truth)?;
    let ssim = ssim(
        &pair.render.crop(pair.region),
        &pair.truth.crop(pair.region),
    )?;
    Ok((psnr, ssim))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A test image whose channel `c` at `(x, y)` is `value(x, y, c)`.
    pub(crate) fn image(
        width: usize,
        height: usize,
        value: impl Fn(usize, usize, usize) -> f32,
    ) -> ImageF32 {
        let mut data = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            for x in 0..width {
                for channel in 0..3 {
                    data.push(value(x, y, channel));
                }
            }
        }
        ImageF32::from_f32("test", width, height, data).unwrap()
    }

    /// Deterministic pseudo-random values in [0, 1).
    fn noise(x: usize, y: usize, channel: usize, salt: u64) -> f32 {
        let mut z =
            ((x as u64) * 0x9E37_79B9) ^ ((y as u64) << 20) ^ ((channel as u64) << 40) ^ salt;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / 16_777_216.0
    }

    #[test]
    fn psnr_matches_closed_forms() {
        let black = image(8, 4, |_, _, _| 0.0);
        let grey = image(8, 4, |_, _, _| 0.1);
        // mse = 0.01 -> 20 dB.
        assert!((psnr(&grey, &black).unwrap() - 20.0).abs() < 1e-6);
        assert_eq!(psnr(&grey, &grey).unwrap(), f64::INFINITY);
        // Half the values off by 1: mse = 0.5 -> 3.0103 dB.
        let half = image(8, 4, |x, _, _| if x < 4 { 1.0 } else { 0.0 });
        assert!((psnr(&half, &black).unwrap() - 10.0 * 2f64.log10()).abs() < 1e-12);
        let error = psnr(&black, &image(4, 8, |_, _, _| 0.0)).unwrap_err();
        assert!(error.to_string().contains("8 x 4 vs 4 x 8"), "{error}");
    }

    /// The normalised 1D Gaussian, written out for the reference below.
    fn reference_window() -> Vec<f64> {
        let raw: Vec<f64> = (0..11)
            .map(|i| (-((i as f64 - 5.0).powi(2)) / 4.5).exp())
            .collect();
        let total: f64 = raw.iter().sum();
        raw.into_iter().map(|v| v / total).collect()
    }

    /// Direct 2D SSIM with an explicit 11 x 11 window: the independent reference.
    fn ssim_direct(a: &ImageF32, b: &ImageF32) -> f64 {
        let g = reference_window();
        let (width, height) = (a.width as isize, a.height as isize);
        let mut total = 0.0;
        for channel in 0..3 {
            for y in 0..height {
                for x in 0..width {
                    let (mut ma, mut mb, mut maa, mut mbb, mut mab) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for dy in -5..=5_isize {
                        for dx in -5..=5_isize {
                            let (sx, sy) = (x + dx, y + dy);
                            if sx < 0 || sy < 0 || sx >= width || sy >= height {
                                continue;
                            }
                            let w = g[(dy + 5) as usize] * g[(dx + 5) as usize];
                            let va = f64::from(a.pixel(sx as usize, sy as usize)[channel]);
                            let vb = f64::from(b.pixel(sx as usize, sy as usize)[channel]);
                            ma += w * va;
                            mb += w * vb;
                            maa += w * va * va;
                            mbb += w * vb * vb;
                            mab += w * va * vb;
                        }
                    }
                    let (c1, c2) = (1e-4, 9e-4);
                    total += ((2.0 * ma * mb + c1) * (2.0 * (mab - ma * mb) + c2))
                        / ((ma * ma + mb * mb + c1) * (maa - ma * ma + mbb - mb * mb + c2));
                }
            }
        }
        total / (3 * width * height) as f64
    }

    #[test]
    fn ssim_matches_a_direct_two_dimensional_window() {
        let a = image(23, 17, |x, y, c| noise(x, y, c, 1));
        let b = image(23, 17, |x, y, c| {
            (noise(x, y, c, 1) * 0.7 + noise(x, y, c, 2) * 0.3).min(1.0)
        });
        let fast = ssim(&a, &b).unwrap();
        let direct = ssim_direct(&a, &b);
        assert!((fast - direct).abs() < 1e-12, "{fast} vs {direct}");
        assert!(fast > 0.0 && fast < 1.0);
        // Tiny images (smaller than the window) work the same way.
        let (a, b) = (
            image(3, 2, |x, y, c| noise(x, y, c, 3)),
            image(3, 2, |x, y, c| noise(x, y, c, 4)),
        );
        assert!((ssim(&a, &b).unwrap() - ssim_direct(&a, &b)).abs() < 1e-12);
    }

    #[test]
    fn ssim_closed_forms() {
        let a = image(30, 30, |x, y, c| noise(x, y, c, 5));
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
        // Constant images far larger than the window: the mean SSIM tends to the interior
        // closed form (2 a b + C1) / (a^2 + b^2 + C1) (variances are zero); the direct window
        // gives the exact value including the zero-padded border.
        let (va, vb) = (0.2_f32, 0.6_f32);
        let (ca, cb) = (image(40, 40, |_, _, _| va), image(40, 40, |_, _, _| vb));
        let direct = ssim_direct(&ca, &cb);
        let ours = ssim(&ca, &cb).unwrap();
        assert!((ours - direct).abs() < 1e-12, "{ours} vs {direct}");
        let (a, b) = (f64::from(va), f64::from(vb));
        let interior = (2.0 * a * b + 1e-4) / (a * a + b * b + 1e-4);
        assert!((ours - interior).abs() < 0.1, "{ours} vs {interior}");
        // Black against black is 1 everywhere (C1 and C2 keep it defined).
        let black = image(5, 5, |_, _, _| 0.0);
        assert_eq!(ssim(&black, &black).unwrap(), 1.0);
    }

    /// PSNR and SSIM of the LPIPS fixture's image pairs, computed by torch in f64
    /// (tests/lpips/make_fixture.py, the 3DGS `ssim()` formula with `F.conv2d`).
    #[test]
    fn psnr_and_ssim_match_torch_on_the_fixture_pairs() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/lpips/fixture.safetensors");
        let file = seqavatar_compute::safetensors::SafetensorsFile::read(&path).unwrap();
        let (first, shape) = file.u8_tensor("in0").unwrap();
        let (second, _) = file.u8_tensor("in1").unwrap();
        let (expected_psnr, _) = file.f64_tensor("psnr").unwrap();
        let (expected_ssim, _) = file.f64_tensor("ssim").unwrap();
        let [count, height, width, 3] = shape[..] else {
            panic!("shape {shape:?}");
        };
        let size = height * width * 3;
        for index in 0..count {
            let a = ImageF32::from_rgb8(
                "in0",
                width,
                height,
                &first[index * size..(index + 1) * size],
            )
            .unwrap();
            let b = ImageF32::from_rgb8(
                "in1",
                width,
                height,
                &second[index * size..(index + 1) * size],
            )
            .unwrap();
            let (ours_psnr, ours_ssim) = (psnr(&a, &b).unwrap(), ssim(&a, &b).unwrap());
            // Our f32 pixel values (byte / 255 in f32) differ from torch's f64 ones by 3e-8.
            assert!(
                (ours_psnr - expected_psnr[index]).abs() < 1e-5,
                "pair {index}: {ours_psnr} vs {}",
                expected_psnr[index]
            );
            assert!(
                (ours_ssim - expected_ssim[index]).abs() < 1e-6,
                "pair {index}: {ours_ssim} vs {}",
                expected_ssim[index]
            );
        }
    }

    #[test]
    fn bound_box_pads_and_clips() {
        let mut data = vec![0_u8; 20 * 10];
        data[3 * 20 + 4] = 255;
        data[6 * 20 + 17] = 200;
        data[9 * 20 + 19] = 127; // Below the threshold: background.
        let mask = Mask::new("mask", 20, 10, data).unwrap();
        assert_eq!(
            mask.bound_box(0),
            Some(Rect {
                x: 4,
                y: 3,
                width: 14,
                height: 4
            })
        );
        assert_eq!(
            mask.bound_box(5),
            Some(Rect {
                x: 0,
                y: 0,
                width: 20,
                height: 10
            })
        );
        assert_eq!(
            mask.bound_box(2),
            Some(Rect {
                x: 2,
                y: 1,
                width: 18,
                height: 8
            })
        );
        assert_eq!(
            Mask::new("mask", 3, 3, vec![0; 9]).unwrap().bound_box(5),
            None
        );
        assert!(
            Mask::new("mask", 3, 3, vec![0; 8])
                .unwrap_err()
                .to_string()
                .contains("8 mask values")
        );
    }

    #[test]
    fn protocol_applies_background_rules() {
        let mut data = vec![0_u8; 12 * 12];
        data[6 * 12 + 6] = 255;
        let mask = Mask::new("mask", 12, 12, data).unwrap();
        let render = image(12, 12, |_, _, _| 0.5);
        let truth = image(12, 12, |_, _, _| 0.25);
        let protocol = Protocol {
            background: [1.0, 0.0, 0.0],
            bound_padding: 1,
            crop_ssim_lpips_to_bound_box: true,
        };
        let pair = protocol.prepare(&render, &truth, &mask).unwrap();
        assert_eq!(
            pair.region,
            Rect {
                x: 5,
                y: 5,
                width: 3,
                height: 3
            }
        );
        // Render: kept inside the 3 x 3 bound box, background outside.
        assert_eq!(pair.render.pixel(5, 5), [0.5; 3]);
        assert_eq!(pair.render.pixel(4, 5), [1.0, 0.0, 0.0]);
        // Truth: kept only on the foreground pixel.
        assert_eq!(pair.truth.pixel(6, 6), [0.25; 3]);
        assert_eq!(pair.truth.pixel(5, 5), [1.0, 0.0, 0.0]);
        let (psnr_value, ssim_value) = psnr_ssim(&pair).unwrap();
        // Whole-image PSNR: 8 pixels of the box differ (render grey 0.5 against the red
        // background: 0.25 + 0.25 + 0.25 per pixel) plus the foreground pixel (3 x 0.25^2),
        // over 144 pixels x 3 channels.
        let squared = 8.0 * 0.75 + 3.0 * 0.0625;
        let expected = -10.0 * (squared / 432.0_f64).log10();
        assert!(
            (psnr_value - expected).abs() < 1e-9,
            "{psnr_value} vs {expected}"
        );
        let crop_ssim = ssim(
            &pair.render.crop(pair.region),
            &pair.truth.crop(pair.region),
        )
        .unwrap();
        assert_eq!(ssim_value, crop_ssim);
        let whole = Protocol::default().prepare(&render, &truth, &mask).unwrap();
        assert_eq!(
            whole.region,
            Rect {
                x: 0,
                y: 0,
                width: 12,
                height: 12
            }
        );
        let wrong = Mask::new("mask", 11, 12, vec![0; 132]).unwrap();
        assert!(
            Protocol::default()
                .prepare(&render, &truth, &wrong)
                .is_err()
        );
    }
}
