//! Splatting benchmark on the standard scene of `rasterizer.md` (see `splat::scene`):
//! forward and forward+backward wall milliseconds per 512x512 image for 10k / 50k / 200k
//! Gaussians (medians), the speed-up over the published OpenSplat CPU figures computed from
//! those wall times, and for the cpu backend the median wall time of each phase. Prints
//! tables and never fails on speed.
//!
//! Run: `cargo bench -p seqavatar-compute --bench splat` (optional arguments: repetitions,
//! `--device cpu|gpu` to run one backend only, `--count N` to run one Gaussian count only).
//! A backend adds one function with the signature of [`time_cpu`] to [`BACKENDS`].

use std::time::Instant;

use seqavatar_compute::splat::scene::{BenchmarkScene, STANDARD_SEED, standard_scene};
use seqavatar_compute::splat::{GaussianBuffers, ImageGradient, RasterOptions, cpu};
use seqavatar_core::camera::Camera;

mod splat_gpu;

/// Gaussian counts of the standard benchmark.
const COUNTS: [usize; 3] = [10_000, 50_000, 200_000];
/// OpenSplat CPU (single-threaded, 2-core EPYC) from `rasterizer.md`: forward ms.
const OPENSPLAT_FORWARD_MS: [f64; 3] = [153.0, 633.0, 1114.0];
/// OpenSplat CPU forward+backward ms.
const OPENSPLAT_FORWARD_BACKWARD_MS: [f64; 3] = [254.0, 1015.0, 1770.0];

/// The scene in the precision the backends run in.
struct Prepared {
    camera: Camera,
    gaussians: GaussianBuffers<f32>,
    upstream: Vec<f32>,
}

impl Prepared {
    fn new(scene: &BenchmarkScene) -> Self {
        Self {
            camera: scene.camera.clone(),
            gaussians: scene.gaussians.convert(),
            upstream: scene.upstream_colour.iter().map(|&v| v as f32).collect(),
        }
    }
}

/// What a backend measured.
struct Timing {
    /// Median wall milliseconds of one forward.
    forward_ms: f64,
    /// Median wall milliseconds of one forward+backward.
    total_ms: f64,
    /// Mean CPU milliseconds (all threads) of the timed forwards alone, where the backend
    /// runs on the host.
    forward_cpu_ms: Option<f64>,
    /// Median wall milliseconds of each phase, where the backend reports them.
    phases: Vec<(&'static str, f64)>,
}

/// A backend's timing of `reps` forward+backward runs, or `None` when it is unavailable
/// here.
type TimeFn = fn(&Prepared, usize) -> Option<Timing>;

const BACKENDS: &[(&str, TimeFn)] = &[("cpu", time_cpu), ("gpu", time_gpu)];

fn time_gpu(scene: &Prepared, reps: usize) -> Option<Timing> {
    let (forward_ms, total_ms) = splat_gpu::time_gpu(scene, reps)?;
    Some(Timing {
        forward_ms,
        total_ms,
        forward_cpu_ms: None,
        phases: Vec::new(),
    })
}

/// CPU time of the whole process (all threads) in milliseconds, from Linux
/// `/proc/self/task/*/schedstat`; `None` elsewhere. On a shared machine this, divided by the
/// thread count, is closer to what an idle machine would give than the wall time.
fn process_cpu_ms() -> Option<f64> {
    let mut total_ns: u64 = 0;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let stat = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        total_ns += stat.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(total_ns as f64 / 1e6)
}

fn median(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn time_cpu(scene: &Prepared, reps: usize) -> Option<Timing> {
    let cameras = std::slice::from_ref(&scene.camera);
    let options = RasterOptions::default();
    let view = scene.gaussians.view();
    let upstream = [ImageGradient {
        colour: &scene.upstream,
        alpha: None,
        depth: None,
    }];
    // Warm-up (page faults, thread pool start).
    let warm = cpu::forward(&view, cameras, &options).ok()?;
    cpu::backward(&warm, &view, &upstream).ok()?;
    drop(warm);
    let mut forward_ms = Vec::with_capacity(reps);
    let mut total_ms = Vec::with_capacity(reps);
    let mut forward_cpu_ms = Some(0.0);
    let mut phases: Vec<(&'static str, Vec<f64>)> = [
        "project",
        "sort+bin",
        "composite",
        "check",
        "walk",
        "reduce+proj.bwd",
    ]
    .into_iter()
    .map(|name| (name, Vec::with_capacity(reps)))
    .collect();
    for _ in 0..reps {
        let cpu_before = process_cpu_ms();
        let start = Instant::now();
        let fwd = cpu::forward(&view, cameras, &options).ok()?;
        let forward_done = start.elapsed();
        forward_cpu_ms = match (forward_cpu_ms, cpu_before, process_cpu_ms()) {
            (Some(sum), Some(before), Some(after)) => Some(sum + after - before),
            _ => None,
        };
        let (grads, backward_phases) = cpu::backward_with_phases(&fwd, &view, &upstream).ok()?;
        let total = start.elapsed();
        std::hint::black_box(&grads);
        let f = fwd.phases;
        let b = backward_phases;
        for ((_, samples), ms) in phases.iter_mut().zip([
            f.project_ms,
            f.bin_ms,
            f.composite_ms,
            b.check_ms,
            b.walk_ms,
            b.reduce_ms,
        ]) {
            samples.push(ms);
        }
        forward_ms.push(forward_done.as_secs_f64() * 1e3);
        total_ms.push(total.as_secs_f64() * 1e3);
    }
    Some(Timing {
        forward_ms: median(forward_ms),
        total_ms: median(total_ms),
        forward_cpu_ms: forward_cpu_ms.map(|sum| sum / reps as f64),
        phases: phases
            .into_iter()
            .map(|(name, samples)| (name, median(samples)))
            .collect(),
    })
}

fn main() {
    // As the `pipeline` binary does, so the figures are the ones users get.
    seqavatar_compute::memory::retain_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let device = args
        .windows(2)
        .find(|pair| pair[0] == "--device")
        .map(|pair| pair[1].clone());
    // The first bare number (not the value of an option).
    let reps = args
        .iter()
        .enumerate()
        .skip(1)
        .filter(|(i, _)| !args[i - 1].starts_with("--"))
        .find_map(|(_, a)| a.parse::<usize>().ok())
        .unwrap_or(5)
        .max(1);
    let only_count = args
        .windows(2)
        .find(|pair| pair[0] == "--count")
        .and_then(|pair| pair[1].parse::<usize>().ok());
    println!(
        "splat benchmark: standard scene (rasterizer.md), 512x512, seed {STANDARD_SEED}, {} rayon threads, median of {reps}",
        rayon::current_num_threads()
    );
    println!(
        "{:<8} {:>9} {:>9} {:>9} {:>11} {:>11} {:>10} {:>14} {:>12} {:>12}",
        "backend",
        "gaussians",
        "visible",
        "list/tile",
        "fwd wall ms",
        "f+b wall ms",
        "fwd vs OS",
        "fwd+bwd vs OS",
        "host cpu ms",
        "fwd cpu ms"
    );
    let mut phase_rows = Vec::new();
    for (i, &count) in COUNTS.iter().enumerate() {
        if only_count.is_some_and(|only| only != count) {
            continue;
        }
        let scene = Prepared::new(&standard_scene(count, STANDARD_SEED));
        let stats = cpu::forward(
            &scene.gaussians.view(),
            std::slice::from_ref(&scene.camera),
            &RasterOptions::default(),
        )
        .map(|f| f.diagnostics[0])
        .ok();
        for (name, time) in BACKENDS
            .iter()
            .filter(|(name, _)| device.as_deref().is_none_or(|d| d == *name))
        {
            let cpu_before = process_cpu_ms();
            let Some(timing) = time(&scene, reps) else {
                println!("{name:<8} {count:>9} unavailable");
                continue;
            };
            let (visible, per_pixel) =
                stats.map_or((0, 0.0), |d| (d.visible, d.intersections as f64 / 1024.0));
            // Every backend runs one warm-up forward+backward before its `reps` timed ones.
            let cpu_ms = match (cpu_before, process_cpu_ms()) {
                (Some(before), Some(after)) => (after - before) / (reps + 1) as f64,
                _ => f64::NAN,
            };
            println!(
                "{:<8} {:>9} {:>9} {:>9.1} {:>11.1} {:>11.1} {:>9.1}x {:>13.1}x {:>12.1} {:>12.1}",
                name,
                count,
                visible,
                per_pixel,
                timing.forward_ms,
                timing.total_ms,
                OPENSPLAT_FORWARD_MS[i] / timing.forward_ms,
                OPENSPLAT_FORWARD_BACKWARD_MS[i] / timing.total_ms,
                cpu_ms,
                timing.forward_cpu_ms.unwrap_or(f64::NAN)
            );
            if !timing.phases.is_empty() {
                phase_rows.push((*name, count, timing.phases));
            }
        }
    }
    println!(
        "wall ms = median wall time (the headline; vs OS = OpenSplat's time / this wall time); \
         host cpu ms = CPU time of all threads per forward+backward, warm-up included; \
         fwd cpu ms = the same for the timed forwards alone"
    );
    if let Some((_, _, first)) = phase_rows.first() {
        print!(
            "\nphases (median wall ms)\n{:<8} {:>9}",
            "backend", "gaussians"
        );
        for (phase, _) in first {
            print!(" {phase:>15}");
        }
        println!();
        for (name, count, phases) in &phase_rows {
            print!("{name:<8} {count:>9}");
            for (_, ms) in phases {
                print!(" {ms:>15.1}");
            }
            println!();
        }
    }
    println!(
        "OS = OpenSplat CPU rasteriser, published in rasterizer.md: fwd {OPENSPLAT_FORWARD_MS:?} ms, fwd+bwd {OPENSPLAT_FORWARD_BACKWARD_MS:?} ms"
    );
}
