//! Generic pictures of image-like arrays for `inspect --png/--exr`: `uint8 (..., H, W, 3)`
//! colour images, `(..., H, W)` masks or scalar maps, `(..., H, W, C)` float images.

use std::path::Path;

use anyhow::Context as _;

use crate::PictureOptions;
use crate::entry::EntryReader;

/// Where one picture lies inside an array.
#[derive(Debug, Clone, PartialEq, Eq)]
struct ImageLayout {
    /// Leading (batch) extents.
    leading: Vec<u64>,
    height: u64,
    width: u64,
    channels: u64,
}

/// Interprets `shape` as `(..., H, W)` or `(..., H, W, C)` with C in `color_channels`.
fn image_layout(shape: &[u64], color_channels: &[u64]) -> Option<ImageLayout> {
    let rank = shape.len();
    if rank >= 3 && color_channels.contains(&shape[rank - 1]) {
        return Some(ImageLayout {
            leading: shape[..rank - 3].to_vec(),
            height: shape[rank - 3],
            width: shape[rank - 2],
            channels: shape[rank - 1],
        });
    }
    if rank >= 2 {
        return Some(ImageLayout {
            leading: shape[..rank - 2].to_vec(),
            height: shape[rank - 2],
            width: shape[rank - 1],
            channels: 1,
        });
    }
    None
}

/// The layout, size and values (as `f64`) of the picture `--opt index` (row-major over the
/// leading dimensions) of the image-like array `name`, whose last axis may hold
/// `color_channels` channels.
fn read_picture(
    entry: &EntryReader,
    name: &str,
    options: &PictureOptions,
    color_channels: &[u64],
) -> anyhow::Result<(ImageLayout, (u32, u32), Vec<f64>)> {
    let full_shape = entry.shape(name)?;
    let layout = image_layout(&full_shape, color_channels).ok_or_else(|| {
        let channels: Vec<String> = color_channels.iter().map(u64::to_string).collect();
        anyhow::anyhow!(
            "array \"{name}\" of shape {full_shape:?} is not image-like; expected (..., H, W) or (..., H, W, {})",
            channels.join("|")
        )
    })?;
    let size = checked_dimensions(name, &layout)?;
    let index = options.get_u64("index", 0)?;
    let count: u64 = layout.leading.iter().product();
    anyhow::ensure!(
        index < count,
        "array \"{name}\" holds {count} picture(s) (leading shape {:?}); --opt index={index} is out of range",
        layout.leading
    );
    let mut start = vec![0u64; layout.leading.len()];
    let mut rest = index;
    for (position, &extent) in layout.leading.iter().enumerate().rev() {
        start[position] = rest % extent;
        rest /= extent;
    }
    let mut shape = vec![1u64; layout.leading.len()];
    start.extend([0, 0]);
    shape.extend([layout.height, layout.width]);
    if full_shape.len() == shape.len() + 1 {
        start.push(0);
        shape.push(layout.channels);
    }
    let values = entry.read_region_f64(name, &start, &shape)?;
    Ok((layout, size, values))
}

fn checked_dimensions(name: &str, layout: &ImageLayout) -> anyhow::Result<(u32, u32)> {
    let width = u32::try_from(layout.width)
        .ok()
        .filter(|&w| w > 0 && w <= 65_536);
    let height = u32::try_from(layout.height)
        .ok()
        .filter(|&h| h > 0 && h <= 65_536);
    match (width, height) {
        (Some(width), Some(height)) => Ok((width, height)),
        _ => anyhow::bail!(
            "array \"{name}\": picture size {}x{} is not drawable",
            layout.width,
            layout.height
        ),
    }
}

/// A PNG-ready picture of an image-like array: `uint8` values as they are, other types
/// scaled from `min..max` (options; default the picture's finite range) to `0..255`.
pub(crate) fn array_png(
    entry: &EntryReader,
    name: &str,
    options: &PictureOptions,
) -> anyhow::Result<image::RgbImage> {
    let (layout, (width, height), values) = read_picture(entry, name, options, &[3])?;
    let is_bytes = entry.dtype(name)? == "uint8";
    let finite = values.iter().copied().filter(|value| value.is_finite());
    let data_min = finite.clone().fold(f64::INFINITY, f64::min);
    let data_max = finite.fold(f64::NEG_INFINITY, f64::max);
    let (low, high) = if is_bytes {
        (0.0, 255.0)
    } else {
        (
            options.get_f64("min", if data_min.is_finite() { data_min } else { 0.0 })?,
            options.get_f64("max", if data_max.is_finite() { data_max } else { 1.0 })?,
        )
    };
    let span = if high > low { high - low } else { 1.0 };
    let to_byte = |value: f64| -> u8 {
        if value.is_nan() {
            0
        } else {
            (((value - low) / span).clamp(0.0, 1.0) * 255.0).round() as u8
        }
    };
    let channels = layout.channels as usize;
    let mut picture = image::RgbImage::new(width, height);
    for (pixel_index, pixel) in picture.pixels_mut().enumerate() {
        let base = pixel_index * channels;
        *pixel = if channels == 3 {
            image::Rgb([
                to_byte(values[base]),
                to_byte(values[base + 1]),
                to_byte(values[base + 2]),
            ])
        } else {
            let gray = to_byte(values[base]);
            image::Rgb([gray, gray, gray])
        };
    }
    Ok(picture)
}

/// Writes the raw values of an image-like array as 32-bit float OpenEXR channels (`Y`, or
/// `R,G,B`, or `R,G,B,A`); returns width, height and channel count.
pub(crate) fn array_exr(
    entry: &EntryReader,
    name: &str,
    options: &PictureOptions,
    out: &Path,
) -> anyhow::Result<(u32, u32, u64)> {
    use exr::prelude::*;
    let (layout, (width, height), values) = read_picture(entry, name, options, &[1, 3, 4])?;
    let channel_names: &[&str] = match layout.channels {
        1 => &["Y"],
        3 => &["R", "G", "B"],
        _ => &["R", "G", "B", "A"],
    };
    let channels_count = channel_names.len();
    let channels: Vec<AnyChannel<FlatSamples>> = channel_names
        .iter()
        .enumerate()
        .map(|(channel, channel_name)| {
            let samples: Vec<f32> = values
                .iter()
                .skip(channel)
                .step_by(channels_count)
                .map(|&value| value as f32)
                .collect();
            AnyChannel::new(*channel_name, FlatSamples::F32(samples))
        })
        .collect();
    let layer = Layer::new(
        (width as usize, height as usize),
        LayerAttributes::named(name),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    Image::from_layer(layer)
        .write()
        .to_file(out)
        .with_context(|| format!("cannot write {}", out.display()))?;
    Ok((width, height, layout.channels))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_of_common_shapes() {
        let color = image_layout(&[5, 4, 6, 3], &[3]).unwrap();
        assert_eq!(
            (
                color.leading.clone(),
                color.height,
                color.width,
                color.channels
            ),
            (vec![5], 4, 6, 3)
        );
        let mask = image_layout(&[2, 7, 9], &[3]).unwrap();
        assert_eq!(
            (mask.leading.clone(), mask.height, mask.width, mask.channels),
            (vec![2], 7, 9, 1)
        );
        assert!(image_layout(&[10], &[3]).is_none());
        let plain = image_layout(&[4, 3], &[3]).unwrap();
        assert_eq!((plain.height, plain.width), (4, 3));
    }
}
