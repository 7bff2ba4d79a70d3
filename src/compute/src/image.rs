//! The float image the metrics work on: RGB, row-major `(height, width, 3)`, values in [0, 1].

use image::RgbImage;

/// An RGB image with f32 values in [0, 1], row-major `(height, width, 3)`.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageF32 {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// Why an image could not be built.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("{what}: {message}")]
pub struct ImageError {
    pub what: String,
    pub message: String,
}

impl ImageF32 {
    pub fn black(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; width * height * 3],
        }
    }

    /// From `uint8` RGB bytes `(height, width, 3)`; `what` names the source in errors.
    pub fn from_rgb8(
        what: &str,
        width: usize,
        height: usize,
        bytes: &[u8],
    ) -> Result<Self, ImageError> {
        let expected = width
            .checked_mul(height)
            .and_then(|pixels| pixels.checked_mul(3))
            .ok_or_else(|| ImageError {
                what: what.to_owned(),
                message: format!("{width} x {height} overflows"),
            })?;
        if bytes.len() != expected {
            return Err(ImageError {
                what: what.to_owned(),
                message: format!(
                    "{} bytes, expected {expected} for {width} x {height} RGB",
                    bytes.len()
                ),
            });
        }
        Ok(Self {
            width,
            height,
            data: bytes.iter().map(|&byte| f32::from(byte) / 255.0).collect(),
        })
    }

    /// From f32 values `(height, width, 3)`; every value must be finite.
    pub fn from_f32(
        what: &str,
        width: usize,
        height: usize,
        data: Vec<f32>,
    ) -> Result<Self, ImageError> {
        if data.len() != width * height * 3 {
            return Err(ImageError {
                what: what.to_owned(),
                message: format!(
                    "{} values, expected {} for {width} x {height} RGB",
                    data.len(),
                    width * height * 3
                ),
            });
        }
        if let Some(position) = data.iter().position(|value| !value.is_finite()) {
            return Err(ImageError {
                what: what.to_owned(),
                message: format!("value {position} is not finite"),
            });
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Rounds to 8 bits, clamping to [0, 1].
    pub fn to_rgb_image(&self) -> RgbImage {
        let bytes = self
            .data
            .iter()
            .map(|value| (value.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        RgbImage::from_raw(self.width as u32, self.height as u32, bytes)
            .expect("an ImageF32 holds width * height * 3 values")
    }

    /// The `(x, y, width, height)` sub-image.
    pub fn crop(&self, rect: Rect) -> Self {
        let mut data = Vec::with_capacity(rect.width * rect.height * 3);
        for row in rect.y..rect.y + rect.height {
            let start = (row * self.width + rect.x) * 3;
            data.extend_from_slice(&self.data[start..start + rect.width * 3]);
        }
        Self {
            width: rect.width,
            height: rect.height,
            data,
        }
    }

    pub fn pixel(&self, x: usize, y: usize) -> [f32; 3] {
        let start = (y * self.width + x) * 3;
        [self.data[start], self.data[start + 1], self.data[start + 2]]
    }
}

/// An axis-aligned pixel rectangle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rect {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn converts_bytes_both_ways_and_validates_lengths() {
        let image = ImageF32::from_rgb8("test", 2, 1, &[0, 128, 255, 10, 20, 30]).unwrap();
        assert_eq!(image.pixel(0, 0), [0.0, 128.0 / 255.0, 1.0]);
        assert_eq!(image.to_rgb_image().as_raw(), &[0, 128, 255, 10, 20, 30]);
        let error = ImageF32::from_rgb8("gt frame 3", 2, 2, &[0; 6]).unwrap_err();
        assert_eq!(
            error.to_string(),
            "gt frame 3: 6 bytes, expected 12 for 2 x 2 RGB"
        );
        let error = ImageF32::from_f32("render", 1, 1, vec![0.0, f32::NAN, 0.0]).unwrap_err();
        assert!(error.to_string().contains("value 1 is not finite"));
    }

    #[test]
    fn crop_takes_the_rectangle() {
        let data: Vec<f32> = (0..4 * 3 * 3).map(|value| value as f32).collect();
        let image = ImageF32::from_f32("t", 4, 3, data).unwrap();
        let crop = image.crop(Rect {
            x: 1,
            y: 1,
            width: 2,
            height: 2,
        });
        assert_eq!(crop.pixel(0, 0), image.pixel(1, 1));
        assert_eq!(crop.pixel(1, 1), image.pixel(2, 2));
        assert_eq!(crop.data.len(), 12);
    }
}
