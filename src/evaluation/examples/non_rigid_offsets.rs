//! How far a trained avatar's non-rigid network moves its Gaussians, frame by frame, beside
//! how far the garment moves off its static drape (the ingest entry's
//! `history_displacement_mm`, on the synthetic history scene): whether the deformation
//! reaches the displacements the garment needs.
//!
//! `cargo run --release -p seqavatar-evaluation --example non_rigid_offsets -- CACHE TRAIN`
//! (`TRAIN`: a train entry's key or key prefix). Prints, over the frames with and without
//! history (more than 1 px of history-only displacement), the mean per-frame RMS, 99th
//! percentile and largest canonical offset `|d_xyz|`, and the correlation over frames
//! between the 99th percentile and the garment's displacement.

use anyhow::Context;
use seqavatar_compute::backend::{Backend, DeviceChoice};
use seqavatar_evaluation::animate::{resolve_entry, upstream_input};
use seqavatar_evaluation::avatar_render::AvatarRenderer;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [cache, train] = args.as_slice() else {
        anyhow::bail!("usage: non_rigid_offsets CACHE TRAIN_KEY");
    };
    let store = seqavatar_engine::LocalStore::open(std::path::Path::new(cache))?;
    let train = resolve_entry(&store, "train", train)?;
    let ingest = upstream_input(&store, &train, "ingest")?.context("no ingest input")?;
    let params = upstream_input(&store, &train, "fit")?.unwrap_or_else(|| ingest.clone());
    let motion = upstream_input(&store, &train, "motion")?;
    let backend = Backend::select(DeviceChoice::Cpu)?;
    let renderer = AvatarRenderer::open(&train, &ingest, &params, motion.as_ref(), &backend)?;
    let avatar = &renderer.avatar;
    anyhow::ensure!(
        avatar.networks.is_some(),
        "the avatar of {} has no non-rigid network",
        train.location()
    );
    let history = seqavatar_schema::ingest::read_garment_history(&ingest)?
        .context("the ingest entry has no garment history (not the history scene)")?;
    let device = avatar.backend(backend)?;
    let xyz = &avatar.gaussians.xyz;
    let n = xyz.len() / 3;
    // Per frame: RMS, 99th percentile and largest |d_xyz| (mm).
    let mut rows = Vec::new();
    for frame in renderer.first_frame()..history.millimetres.len() {
        let inputs = renderer.frame_inputs(frame)?;
        let deformed = avatar.deform(&inputs, &device)?;
        let mut lengths: Vec<f64> = (0..n)
            .map(|g| {
                let d = |a: usize| deformed.positions[3 * g + a] - xyz[3 * g + a];
                (d(0).powi(2) + d(1).powi(2) + d(2).powi(2)).sqrt() * 1e3
            })
            .collect();
        lengths.sort_by(f64::total_cmp);
        let rms = (lengths.iter().map(|l| l * l).sum::<f64>() / n as f64).sqrt();
        rows.push(FrameOffsets {
            frame,
            rms,
            p99: lengths[n * 99 / 100],
            largest: lengths[n - 1],
        });
    }
    println!(
        "train entry {}: {n} Gaussians, {} frames",
        train.location(),
        rows.len()
    );
    println!(
        "| frames | count | garment off its drape, RMS (mm) | offset RMS (mm) | offset p99 (mm) | largest offset (mm) |"
    );
    println!("|---|---|---|---|---|---|");
    for (label, want) in [("history frames", true), ("other frames", false)] {
        let picked: Vec<_> = rows
            .iter()
            .filter(|row| history.frames[row.frame] == want)
            .collect();
        let count = picked.len().max(1) as f64;
        let mean =
            |f: fn(&FrameOffsets) -> f64| picked.iter().map(|row| f(row)).sum::<f64>() / count;
        let garment = picked
            .iter()
            .map(|row| history.millimetres[row.frame])
            .sum::<f64>()
            / count;
        println!(
            "| {label} | {} | {garment:.1} | {:.1} | {:.1} | {:.1} |",
            picked.len(),
            mean(|row| row.rms),
            mean(|row| row.p99),
            mean(|row| row.largest),
        );
    }
    let xs: Vec<f64> = rows
        .iter()
        .map(|row| history.millimetres[row.frame])
        .collect();
    let ys: Vec<f64> = rows.iter().map(|row| row.p99).collect();
    println!(
        "correlation over frames of the offsets' p99 with the garment's displacement: {:.3}",
        correlation(&xs, &ys)
    );
    Ok(())
}

/// One frame's canonical offsets `|d_xyz|` over the Gaussians, millimetres.
struct FrameOffsets {
    frame: usize,
    rms: f64,
    p99: f64,
    largest: f64,
}

/// Pearson correlation; 0 when either side is constant.
fn correlation(xs: &[f64], ys: &[f64]) -> f64 {
    let n = xs.len() as f64;
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (x, y) in xs.iter().zip(ys) {
        sxy += (x - mx) * (y - my);
        sxx += (x - mx).powi(2);
        syy += (y - my).powi(2);
    }
    if sxx > 0.0 && syy > 0.0 {
        sxy / (sxx * syy).sqrt()
    } else {
        0.0
    }
}
