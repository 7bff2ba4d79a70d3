//! Prints what the LPIPS training loss costs at the demo resolution on the cpu: the demo's
//! bound-box crop sizes, LPIPS forward and forward+gradient per crop (VGG, AlexNet), and
//! milliseconds per `fast`-preset training iteration with the loss off and on.
//!
//! The scene is the demo's (`pipelines/synthetic.yaml`: synthetic body in a skirt, 256 x 256,
//! trained at the `fast` preset's `resolution_scale` 0.5) with fewer cameras and frames (the
//! per-iteration cost does not depend on them). The weights are seeded (`lpips::seeded`):
//! real weights cost the same.
//!
//! Run: `cargo run --release -p seqavatar-train --example lpips_cost`
//! (`SEQAVATAR_BENCH_ITERATIONS`, default 10, timed iterations per setting).

use std::path::Path;
use std::time::Instant;

use seqavatar_compute::backend::{Backend, DeviceChoice};
use seqavatar_compute::image::ImageF32;
use seqavatar_compute::lpips::{Lpips, LpipsInput, LpipsNet, seeded};
use seqavatar_engine::{EntryId, LocalStore, Pipeline, RunOptions, Store, run};
use seqavatar_train::config::{Preset, TrainConfig};
use seqavatar_train::data::TrainingData;
use seqavatar_train::trainer::Trainer;

const UPSTREAM: &str = r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 4, frames: 8, width: 256, height: 256}
      past_frames: 0
  - name: motion
    kind: motion
    inputs: [ingest]
    config: {scales: [6, 3], velocity: {kind: per_scale}, knn: 6}
"#;

fn milliseconds_per_call(runs: usize, mut call: impl FnMut()) -> f64 {
    call();
    let start = Instant::now();
    for _ in 0..runs {
        call();
    }
    start.elapsed().as_secs_f64() * 1e3 / runs as f64
}

fn main() -> anyhow::Result<()> {
    let iterations: usize = std::env::var("SEQAVATAR_BENCH_ITERATIONS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10);
    let dir = tempfile::tempdir()?;
    let registry = seqavatar_registry::registry();
    let store = LocalStore::open(dir.path())?;
    let pipeline = Pipeline::parse(UPSTREAM, Path::new("lpips_cost.yaml"), &registry, &[])?;
    let reports = run(&pipeline, &registry, &store, &RunOptions::default())?;
    let open = |name: &str| {
        let report = reports.iter().find(|r| r.name == name).expect("stage ran");
        store.open_entry(&EntryId::new(&report.kind, &report.key))
    };
    let (ingest, motion) = (open("ingest")?, open("motion")?);
    let mut base = TrainConfig::preset(Preset::Fast);
    base.device = DeviceChoice::Cpu;
    let data = TrainingData::read(&ingest, &ingest, &motion, base.resolution_scale)?;

    // The crops the loss sees: the padded bound boxes of the training images.
    let mut crops: Vec<(usize, usize)> = data
        .split(0)
        .into_iter()
        .filter_map(|index| {
            let rect = data.padded_bound(index, base.bound_padding)?;
            Some((rect.width(), rect.height()))
        })
        .collect();
    crops.sort_by_key(|&(w, h)| w * h);
    let (crop_width, crop_height) = crops[crops.len() / 2];
    let camera = &data.cameras[0];
    println!(
        "demo training images {} x {}; crops (w x h) from {:?} to {:?}, median {crop_width} x {crop_height}",
        camera.width,
        camera.height,
        crops[0],
        crops[crops.len() - 1]
    );

    let image = |salt: u64| {
        let values = seeded::uniforms(salt, "lpips cost", crop_width * crop_height * 3)
            .into_iter()
            .map(|u| u as f32)
            .collect();
        ImageF32::from_f32("crop", crop_width, crop_height, values).expect("valid size")
    };
    let (render, target) = (image(1), image(2));
    for net in [LpipsNet::Vgg, LpipsNet::Alex] {
        let lpips = Lpips::new(
            seeded::seeded_weights(net, 1),
            &Backend::select(base.device)?,
        )?;
        let pairs = [(&render, &target)];
        let forward = milliseconds_per_call(5, || {
            lpips.distances(&pairs).expect("lpips");
        });
        let gradient = milliseconds_per_call(5, || {
            lpips
                .distances_with_gradient(&pairs, LpipsInput::Unit)
                .expect("lpips gradient");
        });
        println!(
            "lpips {} {crop_width}x{crop_height} cpu: forward {forward:.1} ms, forward+gradient {gradient:.1} ms ({} threads)",
            net.name(),
            rayon::current_num_threads()
        );
    }

    let weights_dir = tempfile::tempdir()?;
    let mut settings: Vec<(String, TrainConfig)> = vec![("LPIPS off".to_owned(), base.clone())];
    for net in [LpipsNet::Vgg, LpipsNet::Alex] {
        let path = weights_dir
            .path()
            .join(format!("lpips_{}.safetensors", net.name()));
        seeded::seeded_weights(net, 1).write_safetensors(&path)?;
        let mut config = base.clone();
        config.lpips_weight = 0.1;
        config.lpips_weights = Some(path);
        config.lpips_net = net;
        settings.push((format!("LPIPS {} on", net.name()), config));
    }
    let mut off = None;
    for (name, config) in settings {
        let backend = Backend::select(config.device)?;
        let mut trainer = Trainer::new(config, &data, backend)?;
        for _ in 0..2 {
            trainer.step()?;
        }
        let start = Instant::now();
        for _ in 0..iterations {
            trainer.step()?;
        }
        let per_iteration = start.elapsed().as_secs_f64() * 1e3 / iterations as f64;
        let extra = match off {
            None => {
                off = Some(per_iteration);
                String::new()
            }
            Some(base) => format!(" (+{:.1} ms)", per_iteration - base),
        };
        println!("fast preset iteration, {name}: {per_iteration:.1} ms{extra}");
    }
    Ok(())
}
