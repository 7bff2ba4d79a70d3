//! Benchmark: training iterations per second, with the time of every phase of an iteration
//! ([`Phase`]), for the `paper` preset at 512 x 512 (trunk 512 x 3, L = 8, tau = 8, all
//! scales, pose refiner, LBS offsets) and the `fast` preset at the demo's 128 x 128, on each
//! backend, and a roofline figure for the networks.
//!
//! The roofline: the gemm peak is the compute crate's f32 [`linear_forward`] at the trunk's
//! shape (one row per Gaussian, 512 -> 512, ReLU), timed in the same run; the network phases
//! are `deform` and `backward` (the phases that run the networks, together with the skinning
//! around them, so the figure is a lower bound), their FLOPs counted from the networks'
//! descriptions (`NetworkConfig::forward_flops`: forward `2 rows in out` per layer,
//! backward twice that, as `--bench nn` counts them). The last line is
//! `cpu paper preset: <X> it/s, network phases at <P>% of the gemm peak measured in this run`.
//!
//! LPIPS: a row with the loss as docs/method.md has it (VGG, weight 0.1, on the bound-box crop)
//! with seeded VGG weights (the trained ones cannot be committed; the cost depends only on
//! the architecture); `SEQAVATAR_BENCH_LPIPS=0` skips it.
//!
//! On a gpu whose adapter has timestamps inside encoders, each row also prints the device
//! time of every phase (`device ms per phase`), measured by timestamps between the phases of
//! the recorded iteration; the host's own clock (`host ms per phase`) sees there only the
//! recording and submission, charged to `deform`.
//!
//! Each row also prints the host-device traffic of its timed iterations
//! (`transfers per iteration: <R> readbacks, <U> KiB up, <D> KiB down`, counted by the gpu
//! context; zero on `cpu`), and gpu rows the path of the networks' dense layers (`networks:
//! f32` or `networks: f16 tensor cores (16x16x16)`, the presets' default `precision: mixed`).
//!
//! The scene is the built-in synthetic one (procedural body, two cameras, 512 x 512), run
//! through the real ingest and motion stages into a temporary cache. Each row runs
//! `SEQAVATAR_BENCH_WARMUP` (default 2) untimed and `SEQAVATAR_BENCH_ITERATIONS` (default 10)
//! timed iterations from the same initial state. The gpu backend needs a hardware adapter
//! (set `SEQAVATAR_BENCH_SOFTWARE_GPU=1` to time lavapipe instead).
//!
//! `SEQAVATAR_BENCH_PAPER_COPIES=K` (K >= 2) adds a `paper` row at the paper's scale: the
//! trainer's Gaussians repeated K times through a checkpoint (every copy after the first
//! with its centre moved by up to 5 mm), so the phases are timed at `K x 5860` Gaussians
//! (16: 93 760, near the 10^5 of a densified paper run) without training that long first.
//!
//! `SEQAVATAR_BENCH_BACKENDS=gpu` (or `cpu`) times one backend only;
//! `SEQAVATAR_BENCH_PRECISION=f32` (or `mixed`, the default) sets every row's `precision`.
//!
//! Run: `cargo bench -p seqavatar-train --bench train`.

use std::path::Path;
use std::time::Instant;

use seqavatar_compute::backend::{AdapterChoice, Backend, DeviceChoice};
use seqavatar_compute::lpips::{LpipsNet, seeded::seeded_weights};
use seqavatar_compute::nn::Precision;
use seqavatar_compute::nn::gpu::MatmulPath;
use seqavatar_compute::nn::{Activation, InputPart, LinearShape, Rng, linear_forward};
use seqavatar_engine::{EntryId, EntryReader, LocalStore, Pipeline, RunOptions, Store, run};
use seqavatar_train::config::{Preset, TrainConfig};
use seqavatar_train::data::TrainingData;
use seqavatar_train::densify::names;
use seqavatar_train::trainer::{Phase, PhaseTimes, Trainer};

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

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// GFLOP/s of the f32 `linear_forward` at `rows x in_features -> out_features` + ReLU, the
/// median of several timed products after one untimed.
fn gemm_peak(rows: usize, in_features: usize, out_features: usize) -> f64 {
    let shape = LinearShape {
        in_features,
        out_features,
        activation: Activation::Relu,
    };
    let mut rng = Rng::new(3);
    let mut random =
        |len: usize| -> Vec<f32> { (0..len).map(|_| rng.uniform(-1.0, 1.0) as f32).collect() };
    let x = random(rows * in_features);
    let weight = random(shape.weight_len());
    let bias = random(out_features);
    let mut y = vec![0.0f32; rows * out_features];
    let parts = [InputPart {
        data: &x,
        cols: in_features,
    }];
    let mut seconds = Vec::new();
    for repeat in 0..8 {
        let started = Instant::now();
        linear_forward(shape, &weight, &bias, &parts, rows, &mut y).expect("valid shapes");
        if repeat > 0 {
            seconds.push(started.elapsed().as_secs_f64());
        }
    }
    shape.forward_flops(rows) / median(seconds) / 1e9
}

/// The ingest and motion entries of [`UPSTREAM`], computed by the real stages into a cache
/// under `cache`.
fn upstream_entries(cache: &Path) -> anyhow::Result<(EntryReader, EntryReader)> {
    let registry = seqavatar_registry::registry();
    let store = LocalStore::open(cache)?;
    let pipeline = Pipeline::parse(UPSTREAM, Path::new("bench.yaml"), &registry, &[])?;
    let reports = run(&pipeline, &registry, &store, &RunOptions::default())?;
    let open = |name: &str| {
        let r = reports.iter().find(|r| r.name == name).expect("stage ran");
        store.open_entry(&EntryId::new(&r.kind, &r.key))
    };
    Ok((open("ingest")?, open("motion")?))
}

/// The backends timed: `cpu`, and `gpu` when an adapter is found (hardware unless
/// `SEQAVATAR_BENCH_SOFTWARE_GPU` is set), or only those `SEQAVATAR_BENCH_BACKENDS` names
/// (`cpu`, `gpu`, comma-separated): the paper-scale row takes minutes on a cpu.
fn bench_backends() -> anyhow::Result<Vec<(&'static str, Backend)>> {
    let wanted = std::env::var("SEQAVATAR_BENCH_BACKENDS").unwrap_or_else(|_| "cpu,gpu".into());
    let wants = |name: &str| wanted.split(',').any(|w| w.trim() == name);
    let mut backends = Vec::new();
    if wants("cpu") {
        backends.push(("cpu", Backend::select(DeviceChoice::Cpu)?));
    }
    if !wants("gpu") {
        return Ok(backends);
    }
    let choice = if std::env::var_os("SEQAVATAR_BENCH_SOFTWARE_GPU").is_some() {
        AdapterChoice::AllowSoftware
    } else {
        AdapterChoice::Hardware
    };
    match Backend::select_adapter(DeviceChoice::Gpu, choice) {
        Ok(gpu) => backends.push(("gpu", gpu)),
        Err(e) => println!("gpu: not measured ({e})"),
    }
    Ok(backends)
}

/// How many iterations each row runs untimed and timed, and the gemm peak the network
/// phases are compared with.
#[derive(Clone, Copy)]
struct Timing {
    warmup: usize,
    timed: usize,
    /// GFLOP/s.
    peak: f64,
}

/// Times one row (a backend and a variant) and prints it; returns its iterations per second
/// and, when it trains networks, the percentage of the gemm peak its network phases reach.
/// Milliseconds per iteration of every phase.
fn per_phase(times: &PhaseTimes) -> String {
    let iterations = times.iterations().max(1) as f64;
    Phase::ALL
        .iter()
        .map(|&phase| {
            format!(
                "{} {:.2}",
                phase.name(),
                1e3 * times.seconds(phase) / iterations
            )
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// A trainer whose Gaussians are `trainer`'s repeated `copies` times, through a checkpoint:
/// every per-Gaussian column (parameters, Adam moments, densification statistics) repeated,
/// the centres of every copy after the first moved by up to 5 mm on each axis.
fn with_copies<'d>(
    mut trainer: Trainer<'d>,
    config: &TrainConfig,
    data: &'d TrainingData,
    backend: &Backend,
    copies: usize,
) -> anyhow::Result<Trainer<'d>> {
    let mut checkpoint = trainer.checkpoint()?;
    let n = trainer.state.len();
    let position = format!("gaussians/{}", names::POSITION);
    let mut rng = Rng::new(29);
    for tensor in &mut checkpoint.tensors {
        if !tensor.name.starts_with("gaussians/") {
            continue;
        }
        let original = tensor.values.len();
        tensor.values = tensor.values.repeat(copies);
        if tensor.name == position {
            for value in &mut tensor.values[original..] {
                *value += rng.uniform(-5e-3, 5e-3);
            }
        }
        tensor.shape[0] = copies * n;
    }
    checkpoint.metadata["gaussians"] = serde_json::json!(copies * n);
    Trainer::resume(config.clone(), data, backend.clone(), &checkpoint)
}

fn time_row(
    row: &str,
    variant: &Variant<'_>,
    backend: &Backend,
    timing: Timing,
) -> anyhow::Result<(f64, Option<f64>)> {
    let Timing {
        warmup,
        timed,
        peak,
    } = timing;
    let (config, data) = (&variant.config, variant.data);
    let description = backend.describe();
    let mut trainer = Trainer::new(config.clone(), data, backend.clone())?;
    if variant.copies > 1 {
        trainer = with_copies(trainer, config, data, backend, variant.copies)?;
    }
    for _ in 0..warmup {
        trainer.step()?;
    }
    trainer.reset_phase_times();
    // On the device, each phase is timed by timestamps between its commands (the host sees
    // only the recording and the submission).
    trainer.time_device_phases()?;
    let searches_before = trainer.aiap_neighbour_searches()?;
    let traffic_before = backend.transfers();
    let started = Instant::now();
    for _ in 0..timed {
        trainer.step()?;
    }
    // A device-resident step returns once submitted: the time includes the device
    // finishing the last one.
    trainer.wait_for_device()?;
    let seconds = started.elapsed().as_secs_f64();
    let traffic = backend.transfers().since(&traffic_before);
    let it_s = timed as f64 / seconds;
    println!(
        "{row}: {it_s:.3} iterations/s ({:.1} ms per iteration over {timed}, {} Gaussians; {description})",
        1e3 * seconds / timed as f64,
        trainer.state.len()
    );
    if trainer.resident() {
        // The path the trainer's networks took (`precision` of the row's config).
        println!(
            "  {}",
            MatmulPath::of_backend(backend, config.networks_precision()).describe()
        );
    }
    let device_times = trainer.device_phase_times()?;
    let host_times = *trainer.phase_times();
    println!("  host ms per phase: {}", per_phase(&host_times));
    if let Some(device) = &device_times {
        println!(
            "  device ms per phase (timestamps over {} iterations): {}",
            device.iterations(),
            per_phase(device)
        );
    }
    println!(
        "  transfers per iteration: {} readbacks, {:.1} KiB up, {:.1} KiB down",
        traffic.readbacks as f64 / timed as f64,
        traffic.bytes_up as f64 / 1024.0 / timed as f64,
        traffic.bytes_down as f64 / 1024.0 / timed as f64
    );
    // A full search is quadratic in the Gaussians on the device: how often the timed
    // iterations needed one says whether the losses phase is the search.
    let (searches, calls) = trainer.aiap_neighbour_searches()?;
    println!(
        "  AIAP neighbour lists: {} full searches in {} timed iterations that asked for neighbours",
        searches - searches_before.0,
        calls - searches_before.1
    );
    let Some(networks) = &trainer.networks else {
        return Ok((it_s, None));
    };
    // Forward + backward (dX and dW, twice the forward) of every layer, counted from the
    // networks' descriptions at the Gaussian count of the timed iterations' end; timed by
    // the device where it times its phases.
    let times = device_times.unwrap_or(host_times);
    let flops = 3.0 * networks.config().forward_flops(trainer.state.len());
    let network_seconds = (times.seconds(Phase::Deform) + times.seconds(Phase::Backward))
        / times.iterations().max(1) as f64;
    let achieved = flops / network_seconds / 1e9;
    let percent = 100.0 * achieved / peak;
    println!(
        "  network phases (deform + backward): {:.2} GFLOP per iteration at {achieved:.1} GFLOP/s, {percent:.0}% of the gemm peak",
        flops / 1e9
    );
    Ok((it_s, Some(percent)))
}

/// One row's configuration: a preset on a scene, its Gaussians repeated `copies` times
/// (1: as initialised).
struct Variant<'d> {
    name: &'static str,
    config: TrainConfig,
    data: &'d TrainingData,
    copies: usize,
}

impl<'d> Variant<'d> {
    fn new(name: &'static str, config: TrainConfig, data: &'d TrainingData) -> Self {
        Variant {
            name,
            config,
            data,
            copies: 1,
        }
    }
}

fn main() -> anyhow::Result<()> {
    // As the `pipeline` binary does, so the figures are the ones users get.
    seqavatar_compute::memory::retain_freed_memory();
    let dir = tempfile::tempdir()?;
    let (ingest, motion) = upstream_entries(dir.path())?;
    let precision: Option<Precision> = match std::env::var("SEQAVATAR_BENCH_PRECISION") {
        Ok(name) => Some(serde_json::from_value(serde_json::Value::String(name))?),
        Err(_) => None,
    };
    let mut config = TrainConfig::preset(Preset::Paper);
    config.sequence_length = 8;
    config.precision = precision;
    let data = TrainingData::read(&ingest, &ingest, &motion, 1.0)?;
    // The `fast` preset at the demo's training resolution (128 x 128).
    let mut fast = TrainConfig::preset(Preset::Fast);
    fast.resolution_scale = 0.25;
    fast.precision = precision;
    let fast_data = TrainingData::read(&ingest, &ingest, &motion, fast.resolution_scale)?;
    let warmup = env_usize("SEQAVATAR_BENCH_WARMUP", 2);
    let timed = env_usize("SEQAVATAR_BENCH_ITERATIONS", 10);
    let backends = bench_backends()?;
    let gaussians = data.rig.vertex_count();
    println!(
        "paper preset at 512x512: {gaussians} Gaussians, trunk {}x{}, L = {}, tau = {}, scales {:?}",
        config.trunk_width,
        config.trunk_depth,
        config.sequence_length,
        config.tau,
        data.motion.scales
    );
    let peak = gemm_peak(gaussians, config.trunk_width, config.trunk_width);
    println!(
        "gemm peak: {peak:.1} GFLOP/s (f32 linear_forward, {gaussians} x {w} -> {w} + ReLU, the trunk's shape; {} rayon threads)",
        rayon::current_num_threads(),
        w = config.trunk_width
    );
    let mut variants = vec![Variant::new(
        "paper preset, no LPIPS loss",
        config.clone(),
        &data,
    )];
    if std::env::var("SEQAVATAR_BENCH_LPIPS").map_or(true, |v| v != "0") {
        let weights = dir.path().join("lpips_vgg_seeded.safetensors");
        seeded_weights(LpipsNet::Vgg, 1).write_safetensors(&weights)?;
        let mut with_lpips = config.clone();
        with_lpips.lpips_weight = 0.1;
        with_lpips.lpips_weights = Some(weights);
        variants.push(Variant::new(
            "paper preset, LPIPS loss (VGG, weight 0.1)",
            with_lpips,
            &data,
        ));
    }
    variants.push(Variant::new("fast preset at 128x128", fast, &fast_data));
    let copies = env_usize("SEQAVATAR_BENCH_PAPER_COPIES", 0);
    if copies > 1 {
        variants.push(Variant {
            copies,
            ..Variant::new(
                "paper preset at paper scale, no LPIPS loss",
                config.clone(),
                &data,
            )
        });
    }
    let timing = Timing {
        warmup,
        timed,
        peak,
    };
    let mut headline = None;
    for (name, backend) in backends {
        for variant in &variants {
            let row = format!("{name}, {}", variant.name);
            let (it_s, percent) = time_row(&row, variant, &backend, timing)?;
            if let Some(percent) = percent
                && name == "cpu"
                && variant.name == "paper preset, no LPIPS loss"
            {
                headline = Some((it_s, percent));
            }
        }
    }
    if let Some((it_s, percent)) = headline {
        println!(
            "cpu paper preset: {it_s:.2} it/s, network phases at {percent:.0}% of the gemm peak measured in this run"
        );
    }
    Ok(())
}
