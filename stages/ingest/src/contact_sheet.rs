//! The ingest entry's pictures: the contact sheet (history frames framed in red) and the
//! garment's history-only displacement per frame.

use seqavatar_engine::{EntryReader, PictureOptions};

/// A grid of ingested images with the mask overlaid in green at the foreground boundary
/// and tinted outside. Images of history frames (the entry's `history_frame`) get a red
/// frame.
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
    let table = seqavatar_schema::ingest::ImageArrays::read(entry)?;
    let chosen: Vec<usize> = (0..table.len())
        .filter(|&i| wanted.is_none_or(|w| table.split[i] == w))
        .collect();
    anyhow::ensure!(!chosen.is_empty(), "the entry has no {which} images");
    // Spread the picks over the whole list.
    let picks: Vec<usize> = (0..max.min(chosen.len()))
        .map(|k| chosen[k * chosen.len() / max.min(chosen.len())])
        .collect();
    let (h, w) = (table.height as usize, table.width as usize);
    let columns = (options.get_u64("columns", 4)?.max(1) as usize).min(picks.len());
    let rows = picks.len().div_ceil(columns);
    let mut sheet = image::RgbImage::new((columns * w) as u32, (rows * h) as u32);
    let history = seqavatar_schema::ingest::read_garment_history(entry)?;
    for (k, &index) in picks.iter().enumerate() {
        let (rgb, mask) = table.stored(entry, index)?;
        let (rgb, mask) = (rgb.as_raw(), mask.as_raw());
        let (ox, oy) = ((k % columns) * w, (k / columns) * h);
        for y in 0..h {
            for x in 0..w {
                let m = mask[y * w + x];
                let p = (y * w + x) * 3;
                let mut c = [rgb[p], rgb[p + 1], rgb[p + 2]];
                let boundary = m >= 128
                    && [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)]
                        .iter()
                        .any(|(dx, dy)| {
                            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                            nx < 0
                                || ny < 0
                                || nx >= w as i64
                                || ny >= h as i64
                                || mask[ny as usize * w + nx as usize] < 128
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
        let frame = table.frame[index] as usize;
        let flagged = history
            .as_ref()
            .is_some_and(|history| history.frames.get(frame) == Some(&true));
        if flagged {
            for y in 0..h {
                for x in 0..w {
                    if x < 2 || y < 2 || x + 2 >= w || y + 2 >= h {
                        sheet.put_pixel((ox + x) as u32, (oy + y) as u32, image::Rgb([255, 0, 0]));
                    }
                }
            }
        }
    }
    Ok(sheet)
}

/// The garment's history-only displacement per frame as bars (3 pixels wide per frame,
/// `height` pixels for the largest value): red for history frames, grey otherwise, with the
/// history-frame threshold as a blue line.
pub fn history_chart(
    entry: &EntryReader,
    options: &PictureOptions,
) -> anyhow::Result<image::RgbImage> {
    let history = seqavatar_schema::ingest::read_garment_history(entry)?.ok_or_else(|| {
        anyhow::anyhow!(
            "entry {}: no garment history (only the synthetic history scene records it)",
            entry.location()
        )
    })?;
    let height = options.get_u64("height", 120)?.clamp(16, 4096) as usize;
    let n = history.pixels.len();
    let largest = history
        .pixels
        .iter()
        .copied()
        .fold(seqavatar_schema::ingest::HISTORY_FRAME_PX, f64::max);
    let mut chart = image::RgbImage::from_pixel(
        (3 * n).max(1) as u32,
        height as u32,
        image::Rgb([255, 255, 255]),
    );
    let to_row = |value: f64| {
        let bar = (value / largest * (height - 1) as f64).round() as usize;
        height - 1 - bar.min(height - 1)
    };
    for (f, (&value, &flag)) in history.pixels.iter().zip(&history.frames).enumerate() {
        let colour = if flag { [200, 30, 30] } else { [150, 150, 150] };
        for y in to_row(value)..height {
            for x in 3 * f..3 * f + 2 {
                chart.put_pixel(x as u32, y as u32, image::Rgb(colour));
            }
        }
    }
    let threshold = to_row(seqavatar_schema::ingest::HISTORY_FRAME_PX);
    for x in 0..3 * n {
        chart.put_pixel(x as u32, threshold as u32, image::Rgb([40, 60, 220]));
    }
    Ok(chart)
}
