//! Report pieces: Markdown tables, error-map images, contact sheets (ground truth | render |
//! error), line plots and Pareto scatter plots drawn on `image::RgbImage` (no plotting
//! crate; pixels, text and tick labels come from `seqavatar_engine::picture`, the one pixel font).

use image::{Rgb, RgbImage};
use seqavatar_engine::picture::{label as tick_label, put, text_width};

use crate::metrics::MetricError;
use seqavatar_compute::image::ImageF32;

/// A Markdown table; every row must have one cell per header.
pub fn markdown_table(headers: &[&str], rows: &[Vec<String>]) -> Result<String, String> {
    let mut text = format!(
        "| {} |\n|{}|\n",
        headers.join(" | "),
        vec!["---"; headers.len()].join("|")
    );
    for (index, row) in rows.iter().enumerate() {
        if row.len() != headers.len() {
            return Err(format!(
                "table row {index} has {} cells, expected {}",
                row.len(),
                headers.len()
            ));
        }
        let cells: Vec<String> = row.iter().map(|cell| cell.replace('|', "\\|")).collect();
        text.push_str(&format!("| {} |\n", cells.join(" | ")));
    }
    Ok(text)
}

/// A metric for a table: `decimals` places, `inf` and `n/a` spelled out.
pub fn format_metric(value: Option<f64>, decimals: usize) -> String {
    match value {
        None => "n/a".to_owned(),
        Some(value) if value.is_infinite() => if value > 0.0 { "inf" } else { "-inf" }.to_owned(),
        Some(value) if value.is_nan() => "nan".to_owned(),
        Some(value) => format!("{value:.decimals$}"),
    }
}

/// What reports say where the ingest entry has no garment region.
pub const NO_GARMENT_REGION: &str = "garment region: not available for this dataset";

/// Colour of the garment region's outline on contact sheets.
pub const GARMENT_OUTLINE: Rgb<u8> = Rgb([0, 255, 255]);

/// Marks the region's border on `image` (same size as the mask): every region pixel with a
/// 4-neighbour outside the region (or on the image border) becomes [`GARMENT_OUTLINE`].
pub fn outline_region(image: &mut RgbImage, region: &crate::metrics::Mask) {
    let (width, height) = (region.width, region.height);
    if image.dimensions() != (width as u32, height as u32) {
        return;
    }
    for y in 0..height {
        for x in 0..width {
            if !region.is_foreground(x, y) {
                continue;
            }
            let border = x == 0
                || y == 0
                || x + 1 == width
                || y + 1 == height
                || !region.is_foreground(x - 1, y)
                || !region.is_foreground(x + 1, y)
                || !region.is_foreground(x, y - 1)
                || !region.is_foreground(x, y + 1);
            if border {
                image.put_pixel(x as u32, y as u32, GARMENT_OUTLINE);
            }
        }
    }
}

/// One line of the garment region's means, for logs.
pub fn describe_region_means(means: &crate::region::RegionMeans) -> String {
    format!(
        "{} images ({} with an empty region left out), PSNR {} dB, SSIM {}",
        means.images,
        means.empty_images,
        format_metric(means.psnr, 2),
        format_metric(means.ssim, 4)
    )
}

/// The "hot" colour map: black, red, yellow, white for t in [0, 1].
pub fn hot(t: f64) -> Rgb<u8> {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let channel = |start: f64| ((t - start) * 3.0).clamp(0.0, 1.0);
    Rgb([
        (channel(0.0) * 255.0).round() as u8,
        (channel(1.0 / 3.0) * 255.0).round() as u8,
        (channel(2.0 / 3.0) * 255.0).round() as u8,
    ])
}

/// Per-pixel mean absolute error over the channels, coloured with [`hot`] so that
/// `full_scale` (e.g. 0.25) and above is white.
pub fn error_map(
    render: &ImageF32,
    truth: &ImageF32,
    full_scale: f64,
) -> Result<RgbImage, MetricError> {
    if render.width != truth.width || render.height != truth.height {
        return Err(MetricError::SizeMismatch {
            what: "error map",
            left_width: render.width,
            left_height: render.height,
            right_width: truth.width,
            right_height: truth.height,
        });
    }
    if full_scale.is_nan() || full_scale <= 0.0 {
        return Err(MetricError::Invalid {
            what: "error map",
            message: format!("full scale {full_scale} must be positive"),
        });
    }
    let mut image = RgbImage::new(render.width as u32, render.height as u32);
    for (pixel, (a, b)) in image
        .pixels_mut()
        .zip(render.data.chunks_exact(3).zip(truth.data.chunks_exact(3)))
    {
        let error: f64 = a
            .iter()
            .zip(b)
            .map(|(x, y)| f64::from((x - y).abs()))
            .sum::<f64>()
            / 3.0;
        *pixel = hot(error / full_scale);
    }
    Ok(image)
}

/// Rows of equally sized images side by side (e.g. ground truth | render | error), separated
/// by `gap` pixels of dark grey.
pub fn contact_sheet(rows: &[Vec<&RgbImage>], gap: u32) -> Result<RgbImage, String> {
    let Some(first) = rows.first().and_then(|row| row.first()) else {
        return Err("contact sheet: no images".to_owned());
    };
    let (width, height) = first.dimensions();
    let columns = rows[0].len() as u32;
    for (index, row) in rows.iter().enumerate() {
        if row.len() as u32 != columns
            || row
                .iter()
                .any(|image| image.dimensions() != (width, height))
        {
            return Err(format!(
                "contact sheet row {index}: expected {columns} images of {width} x {height}"
            ));
        }
    }
    let sheet_width = columns * width + (columns + 1) * gap;
    let sheet_height = rows.len() as u32 * height + (rows.len() as u32 + 1) * gap;
    let mut sheet = RgbImage::from_pixel(sheet_width, sheet_height, Rgb([40, 40, 40]));
    for (row_index, row) in rows.iter().enumerate() {
        for (column, image) in row.iter().enumerate() {
            let x0 = gap + column as u32 * (width + gap);
            let y0 = gap + row_index as u32 * (height + gap);
            image::imageops::replace(&mut sheet, *image, i64::from(x0), i64::from(y0));
        }
    }
    Ok(sheet)
}

/// One named series of a plot.
#[derive(Clone, Debug)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    pub color: Rgb<u8>,
}

/// A distinct colour per series index.
pub fn palette(index: usize) -> Rgb<u8> {
    const COLORS: [[u8; 3]; 8] = [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
    ];
    Rgb(COLORS[index % COLORS.len()])
}

/// Axis options of a plot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlotOptions {
    pub width: u32,
    pub height: u32,
    /// Plot `log10(y)` (non-positive values are dropped).
    pub log_y: bool,
    /// Draw points as lines (else as markers only).
    pub lines: bool,
}

impl Default for PlotOptions {
    fn default() -> Self {
        Self {
            width: 640,
            height: 400,
            log_y: false,
            lines: true,
        }
    }
}

const MARGIN_LEFT: u32 = 60;
const MARGIN_RIGHT: u32 = 16;
const MARGIN_TOP: u32 = 16;
const MARGIN_BOTTOM: u32 = 30;

/// A plot of the series on white with axes and labelled ticks; `highlight` points (e.g. a
/// Pareto front) are joined in black. Series colours are the caller's; the legend belongs in
/// the accompanying Markdown.
pub fn plot(series: &[Series], options: PlotOptions, highlight: &[(f64, f64)]) -> RgbImage {
    let mut image = RgbImage::from_pixel(
        options.width.max(160),
        options.height.max(120),
        Rgb([255, 255, 255]),
    );
    let (width, height) = image.dimensions();
    let transform_y = |y: f64| {
        if options.log_y {
            (y > 0.0).then(|| y.log10())
        } else {
            Some(y)
        }
    };
    let points: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|series| series.points.iter())
        .chain(highlight)
        .filter_map(|&(x, y)| Some((x, transform_y(y)?)))
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect();
    let (plot_left, plot_right) = (MARGIN_LEFT as f64, (width - MARGIN_RIGHT) as f64);
    let (plot_top, plot_bottom) = (MARGIN_TOP as f64, (height - MARGIN_BOTTOM) as f64);
    let axis = Rgb([0, 0, 0]);
    draw_line(
        &mut image,
        (plot_left, plot_bottom),
        (plot_right, plot_bottom),
        axis,
    );
    draw_line(
        &mut image,
        (plot_left, plot_top),
        (plot_left, plot_bottom),
        axis,
    );
    if points.is_empty() {
        return image;
    }
    let range = |values: &mut dyn Iterator<Item = f64>| {
        let (low, high) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
        if high - low > 1e-12 * (1.0 + low.abs()) {
            (low, high)
        } else {
            (low - 0.5, high + 0.5)
        }
    };
    let (x_low, x_high) = range(&mut points.iter().map(|p| p.0));
    let (y_low, y_high) = range(&mut points.iter().map(|p| p.1));
    let to_pixel = |(x, y): (f64, f64)| {
        (
            plot_left + (x - x_low) / (x_high - x_low) * (plot_right - plot_left),
            plot_bottom - (y - y_low) / (y_high - y_low) * (plot_bottom - plot_top),
        )
    };
    let grey = Rgb([225, 225, 225]);
    for tick in 0..=4 {
        let fraction = f64::from(tick) / 4.0;
        let x_value = x_low + fraction * (x_high - x_low);
        let y_value = y_low + fraction * (y_high - y_low);
        let (px, _) = to_pixel((x_value, y_low));
        let (_, py) = to_pixel((x_low, y_value));
        draw_line(&mut image, (px, plot_top), (px, plot_bottom - 1.0), grey);
        draw_line(&mut image, (plot_left + 1.0, py), (plot_right, py), grey);
        let x_label = tick_label(x_value);
        seqavatar_engine::picture::text(
            &mut image,
            px as i64 - text_width(&x_label) as i64 / 2,
            plot_bottom as i64 + 6,
            &x_label,
            1,
            axis,
        );
        let y_label = if options.log_y {
            tick_label(10f64.powf(y_value))
        } else {
            tick_label(y_value)
        };
        seqavatar_engine::picture::text(
            &mut image,
            plot_left as i64 - 4 - text_width(&y_label) as i64,
            py as i64 - 4,
            &y_label,
            1,
            axis,
        );
    }
    for series in series {
        let pixels: Vec<(f64, f64)> = series
            .points
            .iter()
            .filter_map(|&(x, y)| Some((x, transform_y(y)?)))
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(to_pixel)
            .collect();
        if options.lines {
            for pair in pixels.windows(2) {
                draw_line(&mut image, pair[0], pair[1], series.color);
            }
        }
        if !options.lines || pixels.len() == 1 {
            for &point in &pixels {
                draw_marker(&mut image, point, series.color);
            }
        }
    }
    let front: Vec<(f64, f64)> = highlight
        .iter()
        .filter_map(|&(x, y)| Some((x, transform_y(y)?)))
        .map(to_pixel)
        .collect();
    for pair in front.windows(2) {
        draw_line(&mut image, pair[0], pair[1], axis);
    }
    image
}

/// Indices of the Pareto-optimal points when `cost` is minimised and `quality` maximised,
/// sorted by cost. Points with a non-finite coordinate are never on the front.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..points.len())
        .filter(|&index| points[index].0.is_finite() && points[index].1.is_finite())
        .collect();
    order.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[b].1.total_cmp(&points[a].1))
    });
    let mut front = Vec::new();
    let mut best_quality = f64::NEG_INFINITY;
    for index in order {
        if points[index].1 > best_quality {
            best_quality = points[index].1;
            front.push(index);
        }
    }
    front
}

/// A line by sampling at one-pixel steps (clipped to the image).
pub fn draw_line(image: &mut RgbImage, from: (f64, f64), to: (f64, f64), color: Rgb<u8>) {
    let steps = (to.0 - from.0)
        .abs()
        .max((to.1 - from.1).abs())
        .ceil()
        .clamp(1.0, 1e5) as usize;
    for step in 0..=steps {
        let t = step as f64 / steps as f64;
        let x = from.0 + t * (to.0 - from.0);
        let y = from.1 + t * (to.1 - from.1);
        put(image, x.round() as i64, y.round() as i64, color);
    }
}

fn draw_marker(image: &mut RgbImage, (x, y): (f64, f64), color: Rgb<u8>) {
    for dy in -2..=2_i64 {
        for dx in -2..=2_i64 {
            if dx * dx + dy * dy <= 5 {
                put(image, x.round() as i64 + dx, y.round() as i64 + dy, color);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outline_marks_the_region_border_only() {
        // A 4 x 3 block at (2, 1) in a 8 x 6 image: its 10 border pixels are outlined, its 2
        // inner ones and everything outside are left alone.
        let data = (0..48)
            .map(|i| u8::from((2..6).contains(&(i % 8)) && (1..4).contains(&(i / 8))) * 255)
            .collect();
        let region = crate::metrics::Mask::new("region", 8, 6, data).unwrap();
        let mut image = RgbImage::from_pixel(8, 6, Rgb([10, 20, 30]));
        outline_region(&mut image, &region);
        let outlined: Vec<(u32, u32)> = image
            .enumerate_pixels()
            .filter(|(_, _, p)| **p == GARMENT_OUTLINE)
            .map(|(x, y, _)| (x, y))
            .collect();
        assert_eq!(outlined.len(), 10, "{outlined:?}");
        assert_eq!(*image.get_pixel(3, 2), Rgb([10, 20, 30]));
        assert_eq!(*image.get_pixel(4, 2), Rgb([10, 20, 30]));
        assert_eq!(*image.get_pixel(1, 2), Rgb([10, 20, 30]));
        assert_eq!(*image.get_pixel(2, 1), GARMENT_OUTLINE);
    }

    #[test]
    fn markdown_table_checks_rows_and_escapes_pipes() {
        let table = markdown_table(&["a", "b"], &[vec!["1".into(), "x|y".into()]]).unwrap();
        assert_eq!(table, "| a | b |\n|---|---|\n| 1 | x\\|y |\n");
        let error = markdown_table(&["a", "b"], &[vec!["1".into()]]).unwrap_err();
        assert!(error.contains("row 0 has 1 cells, expected 2"), "{error}");
    }

    #[test]
    fn formats_metrics_with_special_values() {
        assert_eq!(format_metric(Some(31.0249), 2), "31.02");
        assert_eq!(format_metric(Some(f64::INFINITY), 2), "inf");
        assert_eq!(format_metric(None, 2), "n/a");
        assert_eq!(format_metric(Some(f64::NAN), 2), "nan");
    }

    #[test]
    fn hot_colour_map_endpoints() {
        assert_eq!(hot(0.0), Rgb([0, 0, 0]));
        assert_eq!(hot(1.0 / 3.0), Rgb([255, 0, 0]));
        assert_eq!(hot(2.0 / 3.0), Rgb([255, 255, 0]));
        assert_eq!(hot(1.0), Rgb([255, 255, 255]));
        assert_eq!(hot(7.0), Rgb([255, 255, 255]));
        assert_eq!(hot(f64::NAN), Rgb([0, 0, 0]));
    }

    #[test]
    fn error_map_colours_the_mean_absolute_error() {
        let truth = ImageF32::black(2, 1);
        let render = ImageF32::from_f32("r", 2, 1, vec![0.0, 0.0, 0.0, 0.25, 0.25, 0.25]).unwrap();
        let map = error_map(&render, &truth, 0.25).unwrap();
        assert_eq!(*map.get_pixel(0, 0), Rgb([0, 0, 0]));
        assert_eq!(*map.get_pixel(1, 0), Rgb([255, 255, 255]));
        assert!(error_map(&render, &ImageF32::black(1, 1), 0.25).is_err());
        assert!(error_map(&render, &truth, 0.0).is_err());
    }

    #[test]
    fn contact_sheet_places_images_with_gaps() {
        let red = RgbImage::from_pixel(3, 2, Rgb([255, 0, 0]));
        let blue = RgbImage::from_pixel(3, 2, Rgb([0, 0, 255]));
        let sheet = contact_sheet(&[vec![&red, &blue], vec![&blue, &red]], 1).unwrap();
        assert_eq!(sheet.dimensions(), (2 * 3 + 3, 2 * 2 + 3));
        assert_eq!(*sheet.get_pixel(1, 1), Rgb([255, 0, 0]));
        assert_eq!(*sheet.get_pixel(5, 1), Rgb([0, 0, 255]));
        assert_eq!(*sheet.get_pixel(1, 4), Rgb([0, 0, 255]));
        assert_eq!(*sheet.get_pixel(0, 0), Rgb([40, 40, 40]));
        let small = RgbImage::new(2, 2);
        assert!(
            contact_sheet(&[vec![&red], vec![&small]], 1)
                .unwrap_err()
                .contains("row 1")
        );
        assert!(contact_sheet(&[], 1).is_err());
    }

    #[test]
    fn pareto_front_keeps_the_undominated_points() {
        // (cost, quality): 1 and 3 are dominated; 4 is not finite.
        let points = [
            (1.0, 20.0),
            (2.0, 19.0),
            (3.0, 25.0),
            (4.0, 24.0),
            (f64::NAN, 30.0),
            (5.0, 26.0),
        ];
        assert_eq!(pareto_front(&points), [0, 2, 5]);
        // Equal cost: only the better quality.
        assert_eq!(pareto_front(&[(1.0, 1.0), (1.0, 2.0)]), [1]);
        assert!(pareto_front(&[]).is_empty());
    }

    #[test]
    fn plot_draws_series_inside_the_axes() {
        let series = [Series {
            name: "loss".to_owned(),
            points: vec![(0.0, 1.0), (10.0, 0.1), (20.0, 0.01)],
            color: palette(0),
        }];
        let image = plot(
            &series,
            PlotOptions {
                log_y: true,
                ..PlotOptions::default()
            },
            &[],
        );
        assert_eq!(image.dimensions(), (640, 400));
        // On a log axis the three points are collinear: the line passes through the middle
        // of the plot area.
        let centre_x = (MARGIN_LEFT + (640 - MARGIN_RIGHT)) / 2;
        let centre_y = (MARGIN_TOP + (400 - MARGIN_BOTTOM)) / 2;
        let near =
            (centre_y - 2..=centre_y + 2).any(|y| *image.get_pixel(centre_x, y) == palette(0));
        assert!(near, "the series should cross the plot centre");
        // The first point is at the top left of the plot area, the last at the bottom right.
        assert_eq!(*image.get_pixel(MARGIN_LEFT, MARGIN_TOP), palette(0));
        assert_eq!(
            *image.get_pixel(640 - MARGIN_RIGHT, 400 - MARGIN_BOTTOM),
            palette(0)
        );
        // Empty input still draws axes.
        let empty = plot(&[], PlotOptions::default(), &[]);
        assert_eq!(*empty.get_pixel(MARGIN_LEFT, 200), Rgb([0, 0, 0]));
    }
}
