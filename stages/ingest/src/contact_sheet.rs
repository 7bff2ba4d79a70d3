//! The ingest entry's contact sheet picture.

use seqavatar_engine::{EntryReader, PictureOptions};

/// A grid of ingested images with the mask overlaid in green at the foreground boundary
/// and tinted outside.
pub fn contact_sheet(
    entry: &EntryReader,
    options: &PictureOptions,
) -> anyhow::Result<image::RgbImage> {
    let which = options.get_str("split", "all")?;
    let wanted: Option<u8> = match which.as_str() {
        "train" => Some(0),
        "test" => Some(1),
        "all" => None,
        other => anyhow::bail!("picture option split={other}: expected train, test or all"),
    };
    let max = options.get_u64("max", 16)?.max(1) as usize;
    let split = entry.read::<u8>("image_split")?;
    let chosen: Vec<usize> = (0..split.data.len())
        .filter(|&i| wanted.is_none_or(|w| split.data[i] == w))
        .collect();
    anyhow::ensure!(!chosen.is_empty(), "the entry has no {which} images");
    // Spread the picks over the whole list.
    let picks: Vec<usize> = (0..max.min(chosen.len()))
        .map(|k| chosen[k * chosen.len() / max.min(chosen.len())])
        .collect();
    let shape = entry.shape("images")?;
    anyhow::ensure!(
        shape.len() == 4,
        "array images has shape {shape:?}, expected (image, height, width, 3)"
    );
    let (h, w) = (shape[1] as usize, shape[2] as usize);
    let columns = (options.get_u64("columns", 4)?.max(1) as usize).min(picks.len());
    let rows = picks.len().div_ceil(columns);
    let mut sheet = image::RgbImage::new((columns * w) as u32, (rows * h) as u32);
    for (k, &index) in picks.iter().enumerate() {
        let rgb = entry.read_region::<u8>(
            "images",
            &[index as u64, 0, 0, 0],
            &[1, h as u64, w as u64, 3],
        )?;
        let mask =
            entry.read_region::<u8>("masks", &[index as u64, 0, 0], &[1, h as u64, w as u64])?;
        let (ox, oy) = ((k % columns) * w, (k / columns) * h);
        for y in 0..h {
            for x in 0..w {
                let m = mask.data[y * w + x];
                let p = (y * w + x) * 3;
                let mut c = [rgb.data[p], rgb.data[p + 1], rgb.data[p + 2]];
                let boundary = m >= 128
                    && [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)]
                        .iter()
                        .any(|(dx, dy)| {
                            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                            nx < 0
                                || ny < 0
                                || nx >= w as i64
                                || ny >= h as i64
                                || mask.data[ny as usize * w + nx as usize] < 128
                        });
                if boundary {
                    c = [0, 255, 0];
                } else if m < 128 {
                    // Background: dark blue tint so the mask's extent is visible.
                    c = [c[0] / 2, c[1] / 2, c[2] / 2 + 60];
                }
                sheet.put_pixel((ox + x) as u32, (oy + y) as u32, image::Rgb(c));
            }
        }
    }
    Ok(sheet)
}
