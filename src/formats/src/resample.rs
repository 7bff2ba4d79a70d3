//! Undistortion and rescaling of dataset images onto the ingested cameras (ingest stages
//! them; training and the fit's evidence resample them to their own resolution).

use rayon::prelude::*;
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::DVec2;

/// An image that does not match its camera or mask.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ResampleError {
    #[error("image is {}x{} but the camera calibration says {}x{}", image.0, image.1, camera.0, camera.1)]
    ImageSize {
        image: (u32, u32),
        camera: (u32, u32),
    },
    #[error("mask is {}x{} but the image is {}x{}", mask.0, mask.1, image.0, image.1)]
    MaskSize { mask: (u32, u32), image: (u32, u32) },
    #[error("region mask is {}x{} but the image is {}x{}", region.0, region.1, image.0, image.1)]
    RegionSize {
        region: (u32, u32),
        image: (u32, u32),
    },
}

/// One captured image and its foreground mask, both at the camera's full resolution.
#[derive(Clone, Debug, PartialEq)]
pub struct SourceImage {
    pub rgb: image::RgbImage,
    /// 0 = background, 255 = foreground; soft values allowed.
    pub mask: image::GrayImage,
}

/// Undistorts and rescales one image and mask onto `target` (a distortion-free camera with
/// the same pose as `source`, its intrinsics scaled). Each output pixel averages `n x n`
/// bilinear samples (`n = ceil(1 / scale)`), so downscaling does not alias.
pub fn resample(
    image: &SourceImage,
    source: &Camera,
    target: &Camera,
) -> Result<(Vec<u8>, Vec<u8>), ResampleError> {
    let (rgb, [mask]) = resample_planes(image, [], source, target)?;
    Ok((rgb, mask))
}

/// What [`resample_with_region`] returns: `rgb` and `mask` as [`resample`] gives them, and
/// the region mask, all at the target camera's size.
#[derive(Clone, Debug, PartialEq)]
pub struct ResampledWithRegion {
    pub rgb: Vec<u8>,
    pub mask: Vec<u8>,
    pub region: Vec<u8>,
}

/// [`resample`] plus one more mask of the same image (e.g. a garment region), resampled by the
/// same samples and weights as the foreground mask, so both stay aligned with the image; the
/// image and foreground mask come out bit for bit as [`resample`] gives them.
pub fn resample_with_region(
    image: &SourceImage,
    region: &image::GrayImage,
    source: &Camera,
    target: &Camera,
) -> Result<ResampledWithRegion, ResampleError> {
    let (sw, sh) = (image.rgb.width(), image.rgb.height());
    if region.dimensions() != (sw, sh) {
        return Err(ResampleError::RegionSize {
            region: region.dimensions(),
            image: (sw, sh),
        });
    }
    let (rgb, [mask, region]) =
        resample_planes(image, [region.as_raw().as_slice()], source, target)?;
    Ok(ResampledWithRegion { rgb, mask, region })
}

/// The one resampling loop: the image, its foreground mask and `E` extra one-channel planes of
/// the image's size (checked by the caller). `M = E + 1` planes come out: the mask, then the
/// extras in order. Each channel is accumulated on its own in the same order, so adding
/// planes does not change the others' values.
fn resample_planes<const E: usize, const M: usize>(
    image: &SourceImage,
    extra: [&[u8]; E],
    source: &Camera,
    target: &Camera,
) -> Result<(Vec<u8>, [Vec<u8>; M]), ResampleError> {
    assert_eq!(M, E + 1, "one output plane per mask");
    let (sw, sh) = (image.rgb.width(), image.rgb.height());
    if (sw, sh) != (source.width, source.height) {
        return Err(ResampleError::ImageSize {
            image: (sw, sh),
            camera: (source.width, source.height),
        });
    }
    if image.mask.dimensions() != (sw, sh) {
        return Err(ResampleError::MaskSize {
            mask: image.mask.dimensions(),
            image: (sw, sh),
        });
    }
    let masks: [&[u8]; M] = std::array::from_fn(|m| {
        if m == 0 {
            image.mask.as_raw().as_slice()
        } else {
            extra[m - 1]
        }
    });
    let (tw, th) = (target.width as usize, target.height as usize);
    let identity =
        (tw, th) == (sw as usize, sh as usize) && source.distortion.iter().all(|d| *d == 0.0);
    if identity {
        return Ok((image.rgb.as_raw().clone(), masks.map(<[u8]>::to_vec)));
    }
    let ratio = DVec2::new(sw as f64 / tw as f64, sh as f64 / th as f64);
    let n = ratio.max_element().ceil().max(1.0) as usize;
    let rgb = image.rgb.as_raw();
    let (sw, sh) = (sw as usize, sh as usize);
    // Bilinear sample of the colour channels and every mask at a continuous pixel position;
    // outside the image counts as black background.
    let sample = |q: DVec2| -> ([f64; 3], [f64; M]) {
        let x = q.x - 0.5;
        let y = q.y - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (tx, ty) = (x - x0, y - y0);
        let mut colour = [0.0; 3];
        let mut coverage = [0.0; M];
        for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
            for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                let (xi, yi) = (x0 as i64 + dx, y0 as i64 + dy);
                if xi < 0 || yi < 0 || xi >= sw as i64 || yi >= sh as i64 {
                    continue;
                }
                let p = yi as usize * sw + xi as usize;
                let w = wx * wy;
                colour[0] += w * rgb[3 * p] as f64;
                colour[1] += w * rgb[3 * p + 1] as f64;
                colour[2] += w * rgb[3 * p + 2] as f64;
                for (value, mask) in coverage.iter_mut().zip(&masks) {
                    *value += w * mask[p] as f64;
                }
            }
        }
        (colour, coverage)
    };
    let mut out_rgb = vec![0u8; tw * th * 3];
    // Row-interleaved while resampling (one row of every mask per parallel task), split below.
    let mut out_masks = vec![0u8; tw * th * M];
    out_rgb
        .par_chunks_mut(tw * 3)
        .zip(out_masks.par_chunks_mut(tw * M))
        .enumerate()
        .for_each(|(row, (rgb_row, mask_rows))| {
            for col in 0..tw {
                let mut colour = [0.0; 3];
                let mut coverage = [0.0; M];
                for sy in 0..n {
                    for sx in 0..n {
                        let target_pixel = DVec2::new(
                            col as f64 + (sx as f64 + 0.5) / n as f64,
                            row as f64 + (sy as f64 + 0.5) / n as f64,
                        );
                        // Undistorted full-resolution pixel, then where the lens put it.
                        let undistorted = target_pixel * ratio;
                        let captured = source.undistort_source_pixel(undistorted);
                        let (c, m) = sample(captured);
                        for k in 0..3 {
                            colour[k] += c[k];
                        }
                        for k in 0..M {
                            coverage[k] += m[k];
                        }
                    }
                }
                let scale = 1.0 / (n * n) as f64;
                for k in 0..3 {
                    rgb_row[3 * col + k] = (colour[k] * scale).round().clamp(0.0, 255.0) as u8;
                }
                for k in 0..M {
                    mask_rows[k * tw + col] = (coverage[k] * scale).round().clamp(0.0, 255.0) as u8;
                }
            }
        });
    let planes = std::array::from_fn(|k| {
        out_masks
            .chunks_exact(tw * M)
            .flat_map(|rows| &rows[k * tw..(k + 1) * tw])
            .copied()
            .collect()
    });
    Ok((out_rgb, planes))
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::glam::DVec3;

    #[test]
    fn resampling_undistorts_and_rescales_a_known_point() {
        let source = Camera::from_opencv(
            200,
            160,
            [[180.0, 0.0, 101.3], [0.0, 182.0, 78.6], [0.0, 0.0, 1.0]],
            seqavatar_core::rotation::axis_angle_to_matrix(DVec3::new(0.05, -0.1, 0.02)),
            DVec3::new(0.1, 0.0, 2.0),
            [-0.25, 0.08, 0.002, -0.001, 0.0],
        )
        .unwrap();
        let point = DVec3::new(0.8, -0.5, 0.3);
        let captured = source.project_distorted(point).unwrap();
        // A bright 4x4 block centred on the captured (distorted) position.
        let mut rgb = image::RgbImage::new(200, 160);
        let mut mask = image::GrayImage::new(200, 160);
        for y in 0..160u32 {
            for x in 0..200u32 {
                let d = DVec2::new(x as f64 + 0.5, y as f64 + 0.5) - captured;
                if d.x.abs() < 2.0 && d.y.abs() < 2.0 {
                    rgb.put_pixel(x, y, image::Rgb([255, 200, 100]));
                    mask.put_pixel(x, y, image::Luma([255]));
                }
            }
        }
        let mut target = source.rescaled(0.5);
        target.distortion = [0.0; 5];
        let (out_rgb, out_mask) = resample(&SourceImage { rgb, mask }, &source, &target).unwrap();
        // Centroid of the mask in the output lands where the ideal camera projects the point.
        let (mut sum, mut total) = (DVec2::ZERO, 0.0);
        for y in 0..80 {
            for x in 0..100 {
                let m = out_mask[y * 100 + x] as f64;
                sum += DVec2::new(x as f64 + 0.5, y as f64 + 0.5) * m;
                total += m;
            }
        }
        let centroid = sum / total;
        let expected = target.project(point).unwrap();
        assert!(
            (centroid - expected).length() < 0.15,
            "{centroid:?} vs {expected:?}"
        );
        // Distortion moved the point by pixels: the test would notice a missing undistortion.
        assert!((captured * 0.5 - expected).length() > 1.0);
        assert!(out_rgb.iter().any(|&c| c > 0));
        // A region mask goes through the same samples: given the foreground mask as the
        // region, it comes out equal to the mask, and the image and mask are unchanged.
        let source_image = SourceImage {
            rgb: image::RgbImage::from_raw(
                200,
                160,
                (0..200 * 160 * 3).map(|i| (i * 7 % 251) as u8).collect(),
            )
            .unwrap(),
            mask: image::GrayImage::from_raw(
                200,
                160,
                (0..200 * 160).map(|i| (i * 13 % 256) as u8).collect(),
            )
            .unwrap(),
        };
        let (plain_rgb, plain_mask) = resample(&source_image, &source, &target).unwrap();
        let with =
            resample_with_region(&source_image, &source_image.mask, &source, &target).unwrap();
        assert_eq!(plain_rgb, with.rgb);
        assert_eq!(plain_mask, with.mask);
        assert_eq!(with.region, plain_mask);
        assert!(
            resample_with_region(
                &source_image,
                &image::GrayImage::new(3, 3),
                &source,
                &target
            )
            .unwrap_err()
            .to_string()
            .contains("region mask is 3x3")
        );
        // A mask of the wrong size is an error naming the mask.
        let bad = SourceImage {
            rgb: image::RgbImage::new(200, 160),
            mask: image::GrayImage::new(10, 10),
        };
        assert!(
            resample(&bad, &source, &target)
                .unwrap_err()
                .to_string()
                .contains("mask")
        );
    }
}
