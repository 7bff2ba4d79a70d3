//! A tiny drawing kit for the stages' `inspect --png` pictures and eval's reports: line
//! plots, a colour map with a colour bar, point splats with a depth buffer, and a 3x5 pixel
//! font for numbers.
//!
//! No plotting crate: pictures are diagnostics, drawn straight onto an `image::RgbImage`.

use image::{Rgb, RgbImage};

/// Background and axis colours.
pub const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
pub const BLACK: Rgb<u8> = Rgb([0, 0, 0]);
pub const GREY: Rgb<u8> = Rgb([200, 200, 200]);

/// Distinct line colours (Tableau 10), cycled for many series.
pub const PALETTE: [Rgb<u8>; 10] = [
    Rgb([31, 119, 180]),
    Rgb([255, 127, 14]),
    Rgb([44, 160, 44]),
    Rgb([214, 39, 40]),
    Rgb([148, 103, 189]),
    Rgb([140, 86, 75]),
    Rgb([227, 119, 194]),
    Rgb([127, 127, 127]),
    Rgb([188, 189, 34]),
    Rgb([23, 190, 207]),
];

/// The "turbo"-like colour map from blue (0) through green to red (1), piecewise linear
/// through six control colours. Inputs outside `[0, 1]` are clamped; NaN maps to black.
pub fn colour_map(x: f64) -> Rgb<u8> {
    if x.is_nan() {
        return BLACK;
    }
    const STOPS: [[f64; 3]; 6] = [
        [48.0, 18.0, 59.0],
        [70.0, 134.0, 251.0],
        [27.0, 229.0, 181.0],
        [164.0, 252.0, 60.0],
        [251.0, 128.0, 34.0],
        [122.0, 4.0, 3.0],
    ];
    let x = x.clamp(0.0, 1.0) * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    let c = [0, 1, 2].map(|k| (STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f).round() as u8);
    Rgb(c)
}

/// Sets a pixel if it lies inside the image.
pub fn put(img: &mut RgbImage, x: i64, y: i64, colour: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, colour);
    }
}

/// Draws a one-pixel line (Bresenham).
pub fn line(img: &mut RgbImage, from: (i64, i64), to: (i64, i64), colour: Rgb<u8>) {
    let (mut x0, mut y0) = from;
    let (x1, y1) = to;
    let dx = (x1 - x0).abs();
    let dy = -(y1 - y0).abs();
    let sx = if x0 < x1 { 1 } else { -1 };
    let sy = if y0 < y1 { 1 } else { -1 };
    let mut err = dx + dy;
    loop {
        put(img, x0, y0, colour);
        if x0 == x1 && y0 == y1 {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x0 += sx;
        }
        if e2 <= dx {
            err += dx;
            y0 += sy;
        }
    }
}

/// Fills an axis-aligned rectangle `[x0, x1) x [y0, y1)`.
pub fn fill_rect(img: &mut RgbImage, x0: i64, y0: i64, x1: i64, y1: i64, colour: Rgb<u8>) {
    for y in y0..y1 {
        for x in x0..x1 {
            put(img, x, y, colour);
        }
    }
}

/// 3x5 glyphs for the characters numbers need (`inf`, `nan` included); each row is 3 bits,
/// most significant left. The one pixel font of every picture the stages and reports draw.
fn glyph(c: char) -> Option<[u8; 5]> {
    Some(match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 1, 1],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        '+' => [0, 2, 7, 2, 0],
        'e' => [0, 7, 7, 4, 7],
        'i' => [2, 0, 2, 2, 2],
        'n' => [0, 6, 5, 5, 5],
        'f' => [3, 4, 6, 4, 4],
        'a' => [0, 7, 1, 7, 7],
        _ => return None,
    })
}

/// Writes `text` (digits, `.`, `-`, `+`, `e`, `inf`, `nan`; other characters as blanks) with
/// its top-left corner at `(x, y)`, each font pixel drawn as a `scale x scale` block.
pub fn text(img: &mut RgbImage, x: i64, y: i64, text: &str, scale: i64, colour: Rgb<u8>) {
    for (index, c) in text.chars().enumerate() {
        let Some(rows) = glyph(c) else {
            continue;
        };
        let left = x + index as i64 * 4 * scale;
        for (r, bits) in rows.iter().enumerate() {
            for col in 0..3 {
                if bits & (4 >> col) != 0 {
                    let px = left + col * scale;
                    let py = y + r as i64 * scale;
                    fill_rect(img, px, py, px + scale, py + scale, colour);
                }
            }
        }
    }
}

/// Width in pixels of `text` drawn by [`text`] at scale 1.
pub fn text_width(text: &str) -> u32 {
    text.chars().count() as u32 * 4
}

/// A short axis label: up to 4 significant digits, exponent form when very large or small.
pub fn label(value: f64) -> String {
    if value == 0.0 || !value.is_finite() {
        return if value.is_finite() {
            "0".to_owned()
        } else {
            format!("{value}")
        };
    }
    let magnitude = value.abs().log10().floor() as i32;
    if !(-3..5).contains(&magnitude) {
        return format!("{value:.1e}");
    }
    let decimals = (3 - magnitude).clamp(0, 6) as usize;
    let text = format!("{value:.decimals$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        text
    }
}

/// Draws a line plot of `series` (each a list of y values at x = 0, 1, 2, ...) filling the
/// image, with axes, the y range labelled, and one palette colour per series. Non-finite
/// values break the line.
pub fn line_plot(width: u32, height: u32, series: &[Vec<f64>]) -> RgbImage {
    let mut img = RgbImage::from_pixel(width.max(64), height.max(48), WHITE);
    let (w, h) = (i64::from(img.width()), i64::from(img.height()));
    let (left, right, top, bottom) = (50, w - 10, 10, h - 20);
    let finite = series.iter().flatten().copied().filter(|v| v.is_finite());
    let (mut lo, mut hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    if !lo.is_finite() {
        (lo, hi) = (0.0, 1.0);
    }
    if hi - lo < 1e-12 {
        hi = lo + 1.0;
    }
    let n = series.iter().map(Vec::len).max().unwrap_or(0).max(2);
    let to_px = |i: usize, v: f64| {
        let x = left + ((right - left) as f64 * i as f64 / (n - 1) as f64).round() as i64;
        let y = bottom - ((bottom - top) as f64 * (v - lo) / (hi - lo)).round() as i64;
        (x, y)
    };
    // Horizontal grid lines at quarters.
    for q in 0..=4 {
        let y = bottom - (bottom - top) * q / 4;
        line(&mut img, (left, y), (right, y), GREY);
    }
    line(&mut img, (left, top), (left, bottom), BLACK);
    line(&mut img, (left, bottom), (right, bottom), BLACK);
    text(&mut img, 2, top, &label(hi), 1, BLACK);
    text(&mut img, 2, bottom - 5, &label(lo), 1, BLACK);
    text(&mut img, left, bottom + 6, "0", 1, BLACK);
    text(
        &mut img,
        right - 16,
        bottom + 6,
        &format!("{}", n - 1),
        1,
        BLACK,
    );
    for (k, values) in series.iter().enumerate() {
        let colour = PALETTE[k % PALETTE.len()];
        for i in 1..values.len() {
            let (a, b) = (values[i - 1], values[i]);
            if a.is_finite() && b.is_finite() {
                line(&mut img, to_px(i - 1, a), to_px(i, b), colour);
            }
        }
        if values.len() == 1 && values[0].is_finite() {
            let (x, y) = to_px(0, values[0]);
            fill_rect(&mut img, x - 1, y - 1, x + 2, y + 2, colour);
        }
    }
    img
}

/// Draws a vertical colour bar for values `lo..hi` in the rectangle at `(x, y)` of size
/// `w x h`, labelled with both ends.
pub fn colour_bar(img: &mut RgbImage, x: i64, y: i64, w: i64, h: i64, lo: f64, hi: f64) {
    for row in 0..h {
        let f = 1.0 - row as f64 / (h - 1).max(1) as f64;
        fill_rect(img, x, y + row, x + w, y + row + 1, colour_map(f));
    }
    text(img, x, y - 8, &label(hi), 1, BLACK);
    text(img, x, y + h + 3, &label(lo), 1, BLACK);
}

/// Splats points as small discs with a depth test. `points` are `(col, row, depth, colour)`
/// in pixels; nearer (smaller depth) points win.
pub fn splat_points(img: &mut RgbImage, points: &[(f64, f64, f64, Rgb<u8>)], radius: i64) {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let mut depth = vec![f64::INFINITY; w * h];
    for &(px, py, z, colour) in points {
        if !(px.is_finite() && py.is_finite() && z.is_finite()) {
            continue;
        }
        let (cx, cy) = (px.floor() as i64, py.floor() as i64);
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                if dx * dx + dy * dy > radius * radius {
                    continue;
                }
                let (x, y) = (cx + dx, cy + dy);
                if x < 0 || y < 0 || x as usize >= w || y as usize >= h {
                    continue;
                }
                let at = y as usize * w + x as usize;
                if z < depth[at] {
                    depth[at] = z;
                    img.put_pixel(x as u32, y as u32, colour);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_map_ends_and_clamping() {
        assert_eq!(colour_map(0.0), Rgb([48, 18, 59]));
        assert_eq!(colour_map(1.0), Rgb([122, 4, 3]));
        assert_eq!(colour_map(-5.0), colour_map(0.0));
        assert_eq!(colour_map(7.0), colour_map(1.0));
        assert_eq!(colour_map(f64::NAN), BLACK);
        // Halfway between stops 2 and 3 (x = 0.5).
        assert_eq!(colour_map(0.5), Rgb([96, 241, 121]));
    }

    #[test]
    fn line_plot_draws_each_series_where_expected() {
        let img = line_plot(200, 100, &[vec![0.0, 1.0], vec![1.0, 1.0, f64::NAN]]);
        // Series 1 is constant at the top value: a horizontal line at y = top (10).
        let orange = PALETTE[1];
        let hits = (50..190)
            .filter(|&x| *img.get_pixel(x, 10) == orange)
            .count();
        assert!(hits > 60, "{hits}");
        // Series 0 rises from bottom-left to top-right: its end pixel is at the top right.
        assert!(img.pixels().any(|p| *p == PALETTE[0]));
        // A plot of nothing still draws axes.
        let empty = line_plot(100, 60, &[]);
        assert_eq!(*empty.get_pixel(50, 20), BLACK);
    }

    #[test]
    fn splats_respect_depth() {
        let mut img = RgbImage::from_pixel(10, 10, WHITE);
        let red = Rgb([255, 0, 0]);
        let blue = Rgb([0, 0, 255]);
        splat_points(
            &mut img,
            &[
                (5.5, 5.5, 2.0, red),
                (5.5, 5.5, 1.0, blue),
                (5.5, 5.5, 3.0, red),
            ],
            1,
        );
        assert_eq!(*img.get_pixel(5, 5), blue);
        assert_eq!(*img.get_pixel(0, 0), WHITE);
        splat_points(
            &mut img,
            &[(f64::NAN, 1.0, 1.0, red), (-40.0, 2.0, 0.5, red)],
            2,
        );
        assert!(img.pixels().all(|p| *p != red));
    }

    #[test]
    fn text_and_labels() {
        assert_eq!(label(0.0), "0");
        assert_eq!(label(1.5), "1.5");
        assert_eq!(label(1500.0), "1500");
        assert_eq!(label(0.0125), "0.0125");
        assert_eq!(label(31.25), "31.25");
        assert_eq!(label(123456.0), "1.2e5");
        assert_eq!(label(1.5e-5), "1.5e-5");
        assert_eq!(label(-2.5), "-2.5");
        let mut img = RgbImage::from_pixel(20, 10, WHITE);
        text(&mut img, 0, 0, "1", 1, BLACK);
        // '1' = rows [2, 6, 2, 2, 7]: the middle column is set on every row.
        for r in 0..5 {
            assert_eq!(*img.get_pixel(1, r), BLACK);
        }
        assert_eq!(*img.get_pixel(0, 0), WHITE);
        // Unknown characters are blanks: '-' after '?' starts at x = 4 and fills row 2.
        text(&mut img, 0, 5, "?-", 1, BLACK);
        assert!((4..7).all(|x| *img.get_pixel(x, 7) == BLACK));
        assert!((0..4).all(|x| *img.get_pixel(x, 7) == WHITE));
        assert_eq!(text_width("?-"), 8);
    }
}
