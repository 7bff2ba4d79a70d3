//! The one decoder of dataset images and masks (JPEG and PNG).
//!
//! The format is sniffed from the content, never from the file name (PNG bytes named `.jpg`
//! decode as PNG). Decoding is strict: a truncated or corrupt file is an error, never a
//! picture with wrong rows. JPEG goes through `zune-jpeg` in strict mode (the `image` crate
//! runs it leniently and fills a truncated scan with grey); PNG through the `image` crate,
//! which checks every chunk's CRC and fails on a truncated stream.
//!
//! Memory: the dimensions in the header are checked before any pixel is decoded, against
//! the size the caller expects (the camera's calibration) when it knows one, and always
//! against [`MAX_IMAGE_PIXELS`]. Decoding then allocates at most
//! [`MAX_BYTES_PER_PIXEL`] bytes per pixel of the checked size, so a small file that claims
//! a huge picture (a "PNG bomb") is refused before it allocates.

use std::io::Cursor;

use image::{DynamicImage, GrayImage, ImageDecoder, RgbImage};

/// The most pixels a dataset image may have: 8192 x 8192 (DNA-Rendering's 4K views are
/// 12.3 Mpx).
pub const MAX_IMAGE_PIXELS: u64 = 8192 * 8192;

/// Peak bytes a decode may allocate per pixel of the checked size: the decoder's own
/// buffer (up to four 16-bit channels, 8 bytes) plus the 8-bit RGB or grey result and
/// the conversion between them.
pub const MAX_BYTES_PER_PIXEL: u64 = 16;

/// The image formats the datasets use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    Jpeg,
    Png,
}

/// Why an image was refused.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("not a JPEG or PNG file (the content starts with {0:02x?})")]
    UnknownFormat(Vec<u8>),
    #[error("{format:?} header: {message}")]
    Header {
        format: ImageFormat,
        message: String,
    },
    #[error(
        "the header says {width}x{height} pixels, more than the limit of {} pixels",
        MAX_IMAGE_PIXELS
    )]
    TooLarge { width: u32, height: u32 },
    #[error(
        "the header says {width}x{height} pixels, but {expected_width}x{expected_height} are \
         expected"
    )]
    WrongSize {
        width: u32,
        height: u32,
        expected_width: u32,
        expected_height: u32,
    },
    #[error("truncated or corrupt {format:?} data: {message}")]
    Corrupt {
        format: ImageFormat,
        message: String,
    },
}

/// The format of `bytes`, from its signature.
pub fn sniff(bytes: &[u8]) -> Result<ImageFormat, ImageError> {
    if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
        Ok(ImageFormat::Jpeg)
    } else if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Ok(ImageFormat::Png)
    } else {
        Err(ImageError::UnknownFormat(
            bytes.iter().take(8).copied().collect(),
        ))
    }
}

/// Width and height from the header alone (nothing is decoded).
pub fn dimensions(bytes: &[u8]) -> Result<(u32, u32), ImageError> {
    let size = match sniff(bytes)? {
        ImageFormat::Jpeg => {
            let mut decoder = jpeg_decoder(bytes);
            jpeg_dimensions(&mut decoder)?
        }
        ImageFormat::Png => png_decoder(bytes)?.dimensions(),
    };
    check_size(size, None)?;
    Ok(size)
}

/// Decodes an image to 8-bit RGB. `expected` is `(width, height)` when the caller knows it:
/// a different header size is refused before decoding.
pub fn decode_rgb(bytes: &[u8], expected: Option<(u32, u32)>) -> Result<RgbImage, ImageError> {
    match sniff(bytes)? {
        ImageFormat::Jpeg => {
            let (width, height, pixels) = decode_jpeg_rgb(bytes, expected)?;
            Ok(RgbImage::from_raw(width, height, pixels).expect("the decoder's RGB buffer size"))
        }
        ImageFormat::Png => Ok(decode_png(bytes, expected)?.into_rgb8()),
    }
}

/// Decodes a mask to 8-bit grey: the maximum over the colour channels of a colour file,
/// the grey channel of a grey one (alpha is ignored). With `binary`, any non-zero value is
/// foreground (255), for files that store labels 0/1.
pub fn decode_mask(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
    binary: bool,
) -> Result<GrayImage, ImageError> {
    let mut mask = match sniff(bytes)? {
        ImageFormat::Jpeg => {
            // A grey JPEG decodes to three equal channels: their maximum is the grey value.
            let (width, height, pixels) = decode_jpeg_rgb(bytes, expected)?;
            max_over_channels(width, height, &pixels)
        }
        ImageFormat::Png => {
            let image = decode_png(bytes, expected)?;
            if image.color().has_color() {
                let rgb = image.into_rgb8();
                max_over_channels(rgb.width(), rgb.height(), rgb.as_raw())
            } else {
                image.into_luma8()
            }
        }
    };
    if binary {
        for value in mask.iter_mut() {
            if *value != 0 {
                *value = 255;
            }
        }
    }
    Ok(mask)
}

/// The grey image of the largest channel of every RGB pixel.
fn max_over_channels(width: u32, height: u32, rgb: &[u8]) -> GrayImage {
    let grey = rgb
        .chunks_exact(3)
        .map(|p| p[0].max(p[1]).max(p[2]))
        .collect();
    GrayImage::from_raw(width, height, grey).expect("one grey byte per pixel")
}

/// JPEG sides are 16-bit: the header-only read admits every side, and the pixel count is
/// checked against [`MAX_IMAGE_PIXELS`] afterwards.
const MAX_SIDE: usize = 65535;

fn check_size((width, height): (u32, u32), expected: Option<(u32, u32)>) -> Result<(), ImageError> {
    if let Some((expected_width, expected_height)) = expected
        && (width, height) != (expected_width, expected_height)
    {
        return Err(ImageError::WrongSize {
            width,
            height,
            expected_width,
            expected_height,
        });
    }
    if u64::from(width) * u64::from(height) > MAX_IMAGE_PIXELS {
        return Err(ImageError::TooLarge { width, height });
    }
    Ok(())
}

fn jpeg_decoder(bytes: &[u8]) -> zune_jpeg::JpegDecoder<zune_core::bytestream::ZCursor<&[u8]>> {
    let options = zune_core::options::DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(MAX_SIDE)
        .set_max_height(MAX_SIDE)
        .jpeg_set_out_colorspace(zune_core::colorspace::ColorSpace::RGB);
    zune_jpeg::JpegDecoder::new_with_options(zune_core::bytestream::ZCursor::new(bytes), options)
}

fn jpeg_dimensions(
    decoder: &mut zune_jpeg::JpegDecoder<zune_core::bytestream::ZCursor<&[u8]>>,
) -> Result<(u32, u32), ImageError> {
    let header = |message: String| ImageError::Header {
        format: ImageFormat::Jpeg,
        message,
    };
    decoder
        .decode_headers()
        .map_err(|e| header(e.to_string()))?;
    let (width, height) = decoder
        .dimensions()
        .ok_or_else(|| header("no frame header".to_owned()))?;
    // JPEG sides are 16-bit, so these conversions cannot fail.
    Ok((width as u32, height as u32))
}

fn decode_jpeg_rgb(
    bytes: &[u8],
    expected: Option<(u32, u32)>,
) -> Result<(u32, u32, Vec<u8>), ImageError> {
    // The size is checked here, from the header, before anything is decoded (the
    // decoder's own side limits would refuse a wrong size with a vaguer message).
    let mut decoder = jpeg_decoder(bytes);
    let size = jpeg_dimensions(&mut decoder)?;
    check_size(size, expected)?;
    check_jpeg_scan_length(bytes, size)?;
    let pixels = decoder.decode().map_err(|e| ImageError::Corrupt {
        format: ImageFormat::Jpeg,
        message: e.to_string(),
    })?;
    let (width, height) = size;
    if pixels.len() as u64 != u64::from(width) * u64::from(height) * 3 {
        return Err(ImageError::Corrupt {
            format: ImageFormat::Jpeg,
            message: format!(
                "decoded {} bytes for {width}x{height} RGB pixels",
                pixels.len()
            ),
        });
    }
    Ok((width, height, pixels))
}

/// Refuses JPEG data too short for the picture its header declares. The decoder pads a
/// scan that ends early (at its end-of-image marker) instead of failing, so the length is
/// checked first: every 8 x 8 luma block codes at least its DC coefficient, one bit at
/// the least (baseline or progressive), so the entropy-coded data from the first scan
/// header on must hold at least one bit per block.
fn check_jpeg_scan_length(bytes: &[u8], (width, height): (u32, u32)) -> Result<(), ImageError> {
    let scan_start = bytes
        .windows(2)
        .position(|marker| marker == [0xff, 0xda])
        .unwrap_or(bytes.len());
    let scan_bytes = (bytes.len() - scan_start) as u64;
    let blocks = u64::from(width.div_ceil(8)) * u64::from(height.div_ceil(8));
    let needed = blocks.div_ceil(8);
    if scan_bytes < needed {
        return Err(ImageError::Corrupt {
            format: ImageFormat::Jpeg,
            message: format!(
                "{scan_bytes} bytes of scan data cannot code the {blocks} blocks of a \
                 {width}x{height} picture (at least {needed} bytes): the data runs short"
            ),
        });
    }
    Ok(())
}

fn png_decoder(bytes: &[u8]) -> Result<image::codecs::png::PngDecoder<Cursor<&[u8]>>, ImageError> {
    image::codecs::png::PngDecoder::new(Cursor::new(bytes)).map_err(|e| ImageError::Header {
        format: ImageFormat::Png,
        message: e.to_string(),
    })
}

fn decode_png(bytes: &[u8], expected: Option<(u32, u32)>) -> Result<DynamicImage, ImageError> {
    let mut decoder = png_decoder(bytes)?;
    let (width, height) = decoder.dimensions();
    check_size((width, height), expected)?;
    // The checked size bounds the decoder's allocations: at most four 16-bit channels per
    // pixel, plus its row buffers.
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(width);
    limits.max_image_height = Some(height);
    limits.max_alloc = Some(u64::from(width) * u64::from(height) * 8 + (1 << 20));
    let corrupt = |e: image::ImageError| ImageError::Corrupt {
        format: ImageFormat::Png,
        message: e.to_string(),
    };
    decoder.set_limits(limits).map_err(corrupt)?;
    DynamicImage::from_decoder(decoder).map_err(corrupt)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 40x30 picture with a different colour in every pixel, so wrong rows show.
    fn pattern() -> RgbImage {
        RgbImage::from_fn(40, 30, |x, y| {
            image::Rgb([(x * 6) as u8, (y * 8) as u8, ((x + y) * 3) as u8])
        })
    }

    fn png_bytes(image: &DynamicImage) -> Vec<u8> {
        let mut out = Vec::new();
        image
            .write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
            .unwrap();
        out
    }

    fn jpeg_bytes(image: &RgbImage) -> Vec<u8> {
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
            .encode_image(image)
            .unwrap();
        out
    }

    /// A PNG whose header claims `width` x `height` (the CRC fixed, the pixels not).
    fn png_claiming(width: u32, height: u32) -> Vec<u8> {
        let mut bytes = png_bytes(&DynamicImage::ImageLuma8(GrayImage::new(8, 8)));
        // IHDR: length (8..12), type (12..16), width (16..20), height (20..24), ..., CRC
        // over type and data (12..29) at 29..33.
        bytes[16..20].copy_from_slice(&width.to_be_bytes());
        bytes[20..24].copy_from_slice(&height.to_be_bytes());
        let crc = crc32fast::hash(&bytes[12..29]);
        bytes[29..33].copy_from_slice(&crc.to_be_bytes());
        bytes
    }

    #[test]
    fn formats_are_sniffed_from_the_content() {
        let rgb = pattern();
        let png = png_bytes(&DynamicImage::ImageRgb8(rgb.clone()));
        let jpeg = jpeg_bytes(&rgb);
        assert_eq!(sniff(&png).unwrap(), ImageFormat::Png);
        assert_eq!(sniff(&jpeg).unwrap(), ImageFormat::Jpeg);
        assert!(matches!(
            sniff(b"GIF89a..."),
            Err(ImageError::UnknownFormat(_))
        ));
        assert_eq!(dimensions(&png).unwrap(), (40, 30));
        assert_eq!(dimensions(&jpeg).unwrap(), (40, 30));
        // PNG is lossless: exact pixels back.
        assert_eq!(decode_rgb(&png, Some((40, 30))).unwrap(), rgb);
        // JPEG at quality 95: close to the pattern everywhere, bottom rows included.
        let decoded = decode_rgb(&jpeg, Some((40, 30))).unwrap();
        let worst = decoded
            .as_raw()
            .iter()
            .zip(rgb.as_raw())
            .map(|(&a, &b)| a.abs_diff(b))
            .max()
            .unwrap();
        assert!(worst < 40, "largest JPEG error {worst}");
    }

    #[test]
    fn truncated_or_corrupt_images_are_errors() {
        let rgb = pattern();
        let jpeg = jpeg_bytes(&rgb);
        let png = png_bytes(&DynamicImage::ImageRgb8(rgb));
        for (name, bytes) in [("jpeg", &jpeg), ("png", &png)] {
            for fraction in [0.5, 0.9, 0.98] {
                let cut = &bytes[..(bytes.len() as f64 * fraction) as usize];
                assert!(
                    decode_rgb(cut, Some((40, 30))).is_err(),
                    "{name} truncated to {fraction} decoded"
                );
                assert!(decode_mask(cut, Some((40, 30)), true).is_err());
            }
        }
        // A flipped byte inside the PNG's pixel data fails its chunk CRC.
        let mut flipped = png.clone();
        let at = flipped.len() - 20;
        flipped[at] ^= 0x55;
        assert!(matches!(
            decode_rgb(&flipped, Some((40, 30))),
            Err(ImageError::Corrupt { .. })
        ));
    }

    /// Scan data that runs short but ends with its end-of-image marker (the decoder would
    /// pad it): a 16 x 16 picture's scan under a header claiming 2000 x 2000.
    #[test]
    fn jpeg_data_too_short_for_its_header_is_an_error() {
        let mut jpeg = jpeg_bytes(&RgbImage::new(16, 16));
        assert!(jpeg.ends_with(&[0xff, 0xd9]), "ends with its EOI marker");
        let sof = jpeg
            .windows(2)
            .position(|w| w == [0xff, 0xc0])
            .expect("a baseline frame header");
        jpeg[sof + 5..sof + 9].copy_from_slice(&[0x07, 0xd0, 0x07, 0xd0]);
        let error = decode_rgb(&jpeg, None).unwrap_err();
        assert!(
            matches!(&error, ImageError::Corrupt { message, .. } if message.contains("runs short")),
            "{error}"
        );
        assert!(decode_mask(&jpeg, None, true).is_err());
        // The same picture at its own size decodes.
        jpeg[sof + 5..sof + 9].copy_from_slice(&[0x00, 0x10, 0x00, 0x10]);
        assert_eq!(decode_rgb(&jpeg, None).unwrap().dimensions(), (16, 16));
    }

    #[test]
    fn sizes_are_checked_from_the_header_before_decoding() {
        let bomb = png_claiming(8000, 8000);
        assert_eq!(dimensions(&bomb).unwrap(), (8000, 8000));
        assert!(matches!(
            decode_mask(&bomb, Some((8, 8)), true),
            Err(ImageError::WrongSize {
                width: 8000,
                height: 8000,
                ..
            })
        ));
        let huge = png_claiming(100_000, 100_000);
        assert!(matches!(
            dimensions(&huge),
            Err(ImageError::TooLarge { .. }) | Err(ImageError::Header { .. })
        ));
        assert!(decode_rgb(&huge, None).is_err());
    }

    #[test]
    fn masks_take_the_largest_channel_and_binarise() {
        let mut rgb = RgbImage::new(4, 2);
        rgb.put_pixel(1, 0, image::Rgb([0, 7, 3]));
        rgb.put_pixel(2, 1, image::Rgb([200, 0, 0]));
        let colour = png_bytes(&DynamicImage::ImageRgb8(rgb));
        let mask = decode_mask(&colour, Some((4, 2)), false).unwrap();
        assert_eq!(mask.as_raw(), &[0, 7, 0, 0, 0, 0, 200, 0]);
        let labels = GrayImage::from_raw(4, 2, vec![0, 1, 0, 1, 1, 0, 0, 0]).unwrap();
        let grey = png_bytes(&DynamicImage::ImageLuma8(labels));
        let mask = decode_mask(&grey, Some((4, 2)), true).unwrap();
        assert_eq!(mask.as_raw(), &[0, 255, 0, 255, 255, 0, 0, 0]);
        // Grey with alpha: the grey channel, not the alpha.
        let la = image::GrayAlphaImage::from_raw(2, 1, vec![9, 255, 0, 128]).unwrap();
        let la = png_bytes(&DynamicImage::ImageLumaA8(la));
        assert_eq!(
            decode_mask(&la, Some((2, 1)), false).unwrap().as_raw(),
            &[9, 0]
        );
    }
}
