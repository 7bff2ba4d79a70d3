//! Benchmark: training iterations per second at 512 x 512 with the `paper` preset (trunk
//! 512 x 3, L = 8, tau = 8, all scales, pose refiner, LBS offsets) on each backend.
//!
//! Two rows per backend: without the LPIPS loss, and with it as method.md has it (VGG, weight
//! 0.1, on the bound-box crop). The LPIPS row uses seeded VGG weights: the trained ones cannot
//! be committed, and the cost depends only on the architecture (`SEQAVATAR_BENCH_LPIPS=0`
//! skips the row).
//!
//! The scene is the built-in synthetic one (procedural body, two cameras, 512 x 512), run
//! through the real ingest and motion stages into a temporary cache. Each backend runs
//! `SEQAVATAR_BENCH_WARMUP` (default 2) untimed and `SEQAVATAR_BENCH_ITERATIONS` (default 10)
//! timed iterations from the same initial state. The gpu backend needs a hardware adapter
//! (set `SEQAVATAR_BENCH_SOFTWARE_GPU=1` to time lavapipe instead).
//!
//! Run: `cargo bench -p seqavatar-train --bench train`.

use std::path::Path;
use std::time::Instant;

use seqavatar_compute::backend::{AdapterChoice, Backend, GpuContext};
use seqavatar_compute::lpips::{LpipsNet, seeded::seeded_weights};
use seqavatar_engine::{EntryId, LocalStore, Pipeline, Registry, RunOptions, Store, run};
use seqavatar_train::config::{Preset, TrainConfig};
use seqavatar_train::data::TrainingData;
use seqavatar_train::trainer::Trainer;

const UPSTREAM: &str = r#"
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 2, frames: 10, width: 512, height: 512, supersample: 1, garment: true}
      past_frames: 0
  - name: motion
    kind: motion
    inputs: [ingest]
    config: {scales: [1, 2, 3], knn: 6}
"#;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let mut registry = Registry::new();
    seqavatar_ingest::register(&mut registry);
    seqavatar_motion::register(&mut registry);
    let store = LocalStore::open(dir.path())?;
    let pipeline = Pipeline::parse(UPSTREAM, Path::new("bench.yaml"), &registry, &[])?;
    let reports = run(&pipeline, &registry, &store, &RunOptions::default())?;
    let open = |name: &str| {
        let r = reports.iter().find(|r| r.name == name).expect("stage ran");
        store.open_entry(&EntryId::new(&r.kind, &r.key))
    };
    let (ingest, motion) = (open("ingest")?, open("motion")?);
    let mut config = TrainConfig::preset(Preset::Paper);
    config.sequence_length = 8;
    let data = TrainingData::read(&ingest, &ingest, &motion, 1.0)?;
    let warmup = env_usize("SEQAVATAR_BENCH_WARMUP", 2);
    let timed = env_usize("SEQAVATAR_BENCH_ITERATIONS", 10);
    let mut backends = vec![("cpu", Backend::Cpu)];
    let choice = if std::env::var_os("SEQAVATAR_BENCH_SOFTWARE_GPU").is_some() {
        AdapterChoice::AllowSoftware
    } else {
        AdapterChoice::Hardware
    };
    match GpuContext::new(choice) {
        Ok(context) => backends.push(("gpu", Backend::Gpu(std::sync::Arc::new(context)))),
        Err(e) => println!("gpu: not measured ({e})"),
    }
    println!(
        "paper preset at 512x512: {} Gaussians, trunk {}x{}, L = {}, tau = {}, scales {:?}",
        data.rig.vertex_count(),
        config.trunk_width,
        config.trunk_depth,
        config.sequence_length,
        config.tau,
        data.motion.scales
    );
    let mut variants = vec![("no LPIPS loss", config.clone())];
    if std::env::var("SEQAVATAR_BENCH_LPIPS").map_or(true, |v| v != "0") {
        let weights = dir.path().join("lpips_vgg_seeded.safetensors");
        seeded_weights(LpipsNet::Vgg, 1).write_safetensors(&weights)?;
        let mut with_lpips = config.clone();
        with_lpips.lpips_weight = 0.1;
        with_lpips.lpips_weights = Some(weights);
        variants.push(("LPIPS loss (VGG, weight 0.1)", with_lpips));
    }
    for (name, backend) in backends {
        let description = backend.describe();
        for (variant, config) in &variants {
            let mut trainer = Trainer::new(config.clone(), &data, backend.clone())?;
            for _ in 0..warmup {
                trainer.step()?;
            }
            let started = Instant::now();
            for _ in 0..timed {
                trainer.step()?;
            }
            let seconds = started.elapsed().as_secs_f64();
            println!(
                "{name}, {variant}: {:.3} iterations/s ({:.1} ms per iteration over {timed}; {description})",
                timed as f64 / seconds,
                1e3 * seconds / timed as f64
            );
        }
    }
    Ok(())
}
