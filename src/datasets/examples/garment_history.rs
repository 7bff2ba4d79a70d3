//! How much of the synthetic skirt only motion history explains, in millimetres, pixels and
//! PSNR: the ceiling on what motion context (ablation rows (c)-(e)) can gain over the current
//! pose alone (row (b)) on the demo scene.
//!
//! For every frame, the skirt's *static drape* is what the current pose alone determines:
//! the same skirt with its velocity removed, settled while the body holds the pose
//! ([`SyntheticScene::static_drape`]). The difference to the simulated skirt is its swing and
//! lag, which depend on the frames before. Any pose-only model can at best learn the average
//! of that difference per pose, so it bounds what the rows (c)-(e) can add. Rendering every
//! camera with the static drape in place of the simulated skirt measures the bound in the
//! units of the ablation table (PSNR of the true image against the drape image).
//!
//! `cargo run --release -p seqavatar-datasets --example garment_history [frames] [settle_s] [size] [walk|history]`
//!
//! With `history` (the history scene, `frames` at most its script's length at 30 fps; 0 =
//! the whole script) the drape is exact (the skirt's oscillator at rest) and `settle_s` is
//! not used.

use rayon::prelude::*;
use seqavatar_datasets::synthetic::{SceneKind, SyntheticConfig, SyntheticScene, history};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let frames: usize = args.next().map_or(Ok(48), |a| a.parse())?;
    let settle_seconds: f64 = args.next().map_or(Ok(6.0), |a| a.parse())?;
    // The demo's scene (pipelines/synthetic.yaml): 8 cameras at 256 x 256; the `fast`
    // preset trains and scores at half that (`... 48 6 128`).
    let size: u32 = args.next().map_or(Ok(256), |a| a.parse())?;
    let scene = match args.next().as_deref() {
        None | Some("walk") => SceneKind::Walk,
        Some("history") => SceneKind::History,
        Some(other) => anyhow::bail!("scene `{other}`: expected walk or history"),
    };
    let config = match scene {
        SceneKind::Walk => SyntheticConfig {
            frames,
            width: size,
            height: size,
            ..Default::default()
        },
        SceneKind::History => SyntheticConfig {
            scene,
            frames: if frames == 0 { history::LENGTH } else { frames },
            fps: history::FPS,
            width: size,
            height: size,
            ..Default::default()
        },
    };
    let frames = config.frames;
    let scene = SyntheticScene::generate(&config)?;
    let cameras: Vec<_> = (0..config.cameras).collect();
    println!(
        "synthetic scene: {frames} frames at {} fps, {} cameras at {}x{}; drape settles {settle_seconds} s",
        config.fps, config.cameras, config.width, config.height
    );
    println!(
        "frame | skirt swing RMS / max (mm) | on screen mean / max (px) | PSNR truth vs drape (dB)"
    );
    let rows: Vec<(f64, f64, f64, f64, f64)> = (0..frames)
        .into_par_iter()
        .map(|frame| -> anyhow::Result<(f64, f64, f64, f64, f64)> {
            let simulated = scene.skirt_positions(frame).to_vec();
            let drape = scene.static_drape(frame, settle_seconds)?;
            let offsets: Vec<f64> = simulated
                .iter()
                .zip(&drape)
                .map(|(a, b)| (*a - *b).length())
                .collect();
            let rms = (offsets.iter().map(|d| d * d).sum::<f64>() / offsets.len() as f64).sqrt();
            let max = offsets.iter().copied().fold(0.0, f64::max);
            let (mut pixel_sum, mut pixel_max, mut pixel_count) = (0.0, 0.0_f64, 0usize);
            let mut psnr_sum = 0.0;
            for &view in &cameras {
                let camera = &scene_camera(&scene, view);
                for (a, b) in simulated.iter().zip(&drape) {
                    if let (Some(pa), Some(pb)) = (camera.project(*a), camera.project(*b)) {
                        let d = (pa - pb).length();
                        pixel_sum += d;
                        pixel_max = pixel_max.max(d);
                        pixel_count += 1;
                    }
                }
                let truth = scene.render(view, frame)?;
                let draped = scene.render_with_skirt(view, frame, &drape)?;
                psnr_sum += psnr(truth.rgb.as_raw(), draped.rgb.as_raw());
            }
            Ok((
                rms * 1e3,
                max * 1e3,
                pixel_sum / pixel_count.max(1) as f64,
                pixel_max,
                psnr_sum / cameras.len() as f64,
            ))
        })
        .collect::<anyhow::Result<_>>()?;
    for (frame, (rms, max, pixel_mean, pixel_max, psnr)) in rows.iter().enumerate() {
        println!(
            "{frame:5} | {rms:7.1} / {max:6.1} | {pixel_mean:6.2} / {pixel_max:6.2} | {}",
            format_psnr(*psnr)
        );
    }
    let mean = |pick: fn(&(f64, f64, f64, f64, f64)) -> f64| {
        rows.iter().map(pick).sum::<f64>() / rows.len() as f64
    };
    let finite_psnr: Vec<f64> = rows.iter().map(|r| r.4).filter(|p| p.is_finite()).collect();
    println!(
        "mean  | {:7.1} / {:6.1} | {:6.2} / {:6.2} | {} over {} frames with a visible difference",
        mean(|r| r.0),
        mean(|r| r.1),
        mean(|r| r.2),
        mean(|r| r.3),
        format_psnr(finite_psnr.iter().sum::<f64>() / finite_psnr.len().max(1) as f64),
        finite_psnr.len()
    );
    Ok(())
}

fn scene_camera(scene: &SyntheticScene, view: usize) -> seqavatar_core::camera::Camera {
    use seqavatar_datasets::DatasetReader;
    scene.cameras()[view].camera.clone()
}

/// PSNR of two 8-bit images (values scaled to [0, 1]); infinite when identical.
fn psnr(a: &[u8], b: &[u8]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(x, y)| {
            let d = (f64::from(*x) - f64::from(*y)) / 255.0;
            d * d
        })
        .sum::<f64>()
        / a.len() as f64;
    -10.0 * mse.log10()
}

fn format_psnr(value: f64) -> String {
    if value.is_finite() {
        format!("{value:6.2}")
    } else {
        "  inf".to_owned()
    }
}
