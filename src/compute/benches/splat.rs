//! Splatting benchmark on the standard scene of `rasterizer.md` (see `splat::scene`):
//! forward and forward+backward milliseconds per 512x512 image for 10k / 50k / 200k
//! Gaussians, and the speed-up over the published OpenSplat CPU figures. Prints a table and
//! never fails on speed.
//!
//! Run: `cargo bench -p seqavatar-compute --bench splat` (optional arguments: repetitions,
//! `--device cpu|gpu` to run one backend only).
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

/// Milliseconds of one forward and of one forward+backward (medians over `reps`), or
/// `None` when the backend is unavailable here.
type TimeFn = fn(&Prepared, usize) -> Option<(f64, f64)>;

const BACKENDS: &[(&str, TimeFn)] = &[("cpu", time_cpu), ("gpu", splat_gpu::time_gpu)];

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

fn time_cpu(scene: &Prepared, reps: usize) -> Option<(f64, f64)> {
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
    for _ in 0..reps {
        let start = Instant::now();
        let fwd = cpu::forward(&view, cameras, &options).ok()?;
        let forward_done = start.elapsed();
        let grads = cpu::backward(&fwd, &view, &upstream).ok()?;
        let total = start.elapsed();
        std::hint::black_box(&grads);
        forward_ms.push(forward_done.as_secs_f64() * 1e3);
        total_ms.push(total.as_secs_f64() * 1e3);
    }
    Some((median(forward_ms), median(total_ms)))
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let device = args
        .windows(2)
        .find(|pair| pair[0] == "--device")
        .map(|pair| pair[1].clone());
    let reps = std::env::args()
        .skip(1)
        .find_map(|a| a.parse::<usize>().ok())
        .unwrap_or(5)
        .max(1);
    println!(
        "splat benchmark: standard scene (rasterizer.md), 512x512, seed {STANDARD_SEED}, {} rayon threads, median of {reps}",
        rayon::current_num_threads()
    );
    println!(
        "{:<8} {:>9} {:>9} {:>9} {:>11} {:>11} {:>12} {:>10} {:>14}",
        "backend",
        "gaussians",
        "visible",
        "list/tile",
        "forward ms",
        "fwd+bwd ms",
        "host cpu ms",
        "fwd vs OS",
        "fwd+bwd vs OS"
    );
    for (i, &count) in COUNTS.iter().enumerate() {
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
            let Some((forward_ms, total_ms)) = time(&scene, reps) else {
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
                "{:<8} {:>9} {:>9} {:>9.1} {:>11.1} {:>11.1} {:>12.1} {:>9.1}x {:>13.1}x",
                name,
                count,
                visible,
                per_pixel,
                forward_ms,
                total_ms,
                cpu_ms,
                OPENSPLAT_FORWARD_MS[i] / forward_ms,
                OPENSPLAT_FORWARD_BACKWARD_MS[i] / total_ms
            );
        }
    }
    println!(
        "host cpu ms = CPU time of all threads per forward+backward, warm-up included \
         (about twice the wall time of an idle 2-core machine when both cores are busy)"
    );
    println!(
        "OS = OpenSplat CPU rasteriser, published in rasterizer.md: fwd {OPENSPLAT_FORWARD_MS:?} ms, fwd+bwd {OPENSPLAT_FORWARD_BACKWARD_MS:?} ms"
    );
}
