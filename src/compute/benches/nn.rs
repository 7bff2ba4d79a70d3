//! Dense-layer throughput: `cpu` (`gemm`) and `gpu` (WGSL) GFLOP/s on training-sized layers,
//! next to the machine's OpenBLAS figure through numpy for the same products.
//!
//! Run with `cargo bench -p seqavatar-compute --bench nn`. `SEQAVATAR_BENCH_ROWS` changes
//! the row count (default 50 000, the Gaussian count of a mid-training SeqAvatar model) and
//! `SEQAVATAR_BENCH_REPS` the repetitions (default 7). numpy missing, or no hardware GPU,
//! skips that column with a note.
//!
//! The cpu and numpy timings are interleaved (cpu, then numpy, for each product in each
//! repetition, numpy kept running in one process) and the medians reported, so a busy
//! machine slows both sides alike; the load average is printed before and after. Before
//! each run the bench waits until neither side uses CPU any more: OpenBLAS's worker threads
//! spin for about 100 ms of CPU after every product, so a fixed pause (200 ms here before)
//! let them compete with the next cpu run whenever the machine was busy enough to stretch
//! that spin past the pause. `cpu/numpy` is the ratio of the medians; `paired` the range of
//! the per-repetition ratios (each cpu run against the numpy run right after it). numpy
//! writes into preallocated outputs (`out=`) as the cpu layer does. Per shape, three rows:
//! `forward` (`X W + b`, ReLU; numpy `X W`), `backward` (ReLU mask, `db`, `dX = dY' W^T`,
//! `dW += X^T dY'`; numpy the two products) and `dW only` (the backward of a layer whose
//! input needs no gradient, the first layer's case; numpy `X^T dY`).
//!
//! Then, on the gpu, every dense-layer shape of the `paper` preset's networks (trunk 512 x 3,
//! tau 8, L 8, 3 scales, SMPL; listed from docs/method.md, "Networks": the avatar crate that
//! describes them depends on this one) at `SEQAVATAR_BENCH_GPU_ROWS` rows (default 94 000,
//! about a paper-sized model's Gaussians; every layer at the same rows, though the per-frame
//! layers run one row and the per-step ones `L` rows per Gaussian): forward and backward
//! GFLOP/s on the f32 path and, where the adapter has tensor cores, on the tensor-core path
//! (`precision: mixed`) side by side, each layer's throughput as a fraction of the 512 x 512
//! layer's, and the `networks:` line a `mixed` run prints. A hardware adapter only, unless
//! `SEQAVATAR_BENCH_GPU=software` allows Mesa lavapipe (then 2048 rows by default).

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use seqavatar_compute::backend::{AdapterChoice, GpuContext};
use seqavatar_compute::nn::gpu::{
    GpuInput, GpuInputGrad, GpuInputPart, GpuLinear, GpuLinearGrads, MatmulPath, NnGpu,
};
use seqavatar_compute::nn::init::{Rng, uniform_fill};
use seqavatar_compute::nn::linear::{InputGrad, LinearGrads};
use seqavatar_compute::nn::{
    Activation, InputPart, LinearShape, Precision, linear_backward, linear_forward,
};

/// Best of `repeats` timings of `work`, after one warm-up run, in seconds.
fn best_seconds(repeats: usize, mut work: impl FnMut()) -> f64 {
    work();
    (0..repeats)
        .map(|_| seconds(&mut work))
        .fold(f64::INFINITY, f64::min)
}

/// Wall time of one run of `work`, in seconds.
fn seconds(mut work: impl FnMut()) -> f64 {
    let start = Instant::now();
    work();
    start.elapsed().as_secs_f64()
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn random(rng: &mut Rng, len: usize) -> Vec<f32> {
    let mut values = vec![0.0f32; len];
    uniform_fill(rng, &mut values, 1.0);
    values
}

/// The 1, 5 and 15 minute load averages, or `unknown` where `/proc/loadavg` is missing.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|text| {
            text.split_whitespace()
                .take(3)
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|_| "unknown".into())
}

/// The products each row of the table times.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Product {
    Forward,
    Backward,
    WeightOnly,
}

impl Product {
    const ALL: [Product; 3] = [Product::Forward, Product::Backward, Product::WeightOnly];

    fn label(self) -> &'static str {
        match self {
            Product::Forward => "forward",
            Product::Backward => "backward",
            Product::WeightOnly => "dW only",
        }
    }

    /// The worker's command for the same products.
    fn numpy_command(self) -> &'static str {
        match self {
            Product::Forward => "forward",
            Product::Backward => "backward",
            Product::WeightOnly => "weight",
        }
    }

    /// Multiples of one forward product's flops.
    fn flop_factor(self) -> f64 {
        match self {
            Product::Forward | Product::WeightOnly => 1.0,
            Product::Backward => 2.0,
        }
    }
}

/// numpy/OpenBLAS in one long-lived python process, timing one product per request.
struct Numpy {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
}

const NUMPY_WORKER: &str = "\
import sys, time
import numpy as np
rng = np.random.default_rng(0)
ops = {}
def shape(r, i, o):
    x = rng.standard_normal((r, i), dtype=np.float32)
    w = rng.standard_normal((i, o), dtype=np.float32)
    dy = rng.standard_normal((r, o), dtype=np.float32)
    y = np.empty((r, o), dtype=np.float32)
    dx = np.empty((r, i), dtype=np.float32)
    dw = np.empty((i, o), dtype=np.float32)
    def backward():
        np.matmul(dy, w.T, out=dx)
        np.matmul(x.T, dy, out=dw)
    return {
        'forward': lambda: np.matmul(x, w, out=y),
        'backward': backward,
        'weight': lambda: np.matmul(x.T, dy, out=dw),
    }
print('ready', flush=True)
for line in sys.stdin:
    words = line.split()
    if words[0] == 'shape':
        ops = shape(*map(int, words[1:]))
        print('ok', flush=True)
    else:
        start = time.perf_counter()
        ops[words[0]]()
        print(time.perf_counter() - start, flush=True)
";

impl Numpy {
    fn start() -> Result<Numpy, String> {
        let mut child = Command::new("python3")
            .args(["-c", NUMPY_WORKER])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|error| format!("python3 not runnable: {error}"))?;
        let stdin = child.stdin.take().ok_or("python3 stdin")?;
        let stdout = BufReader::new(child.stdout.take().ok_or("python3 stdout")?);
        let mut numpy = Numpy {
            child,
            stdin,
            stdout,
        };
        numpy.expect_line("ready")?;
        Ok(numpy)
    }

    fn reply(&mut self) -> Result<String, String> {
        let mut line = String::new();
        let read = self
            .stdout
            .read_line(&mut line)
            .map_err(|error| format!("numpy worker: {error}"))?;
        if read == 0 {
            let mut message = String::new();
            if let Some(stderr) = self.child.stderr.as_mut() {
                let _ = std::io::Read::read_to_string(stderr, &mut message);
            }
            return Err(format!("numpy worker exited: {}", message.trim()));
        }
        Ok(line.trim().to_string())
    }

    fn expect_line(&mut self, expected: &str) -> Result<(), String> {
        match self.reply()? {
            line if line == expected => Ok(()),
            line => Err(format!("numpy worker: expected {expected:?}, got {line:?}")),
        }
    }

    fn send(&mut self, command: &str) -> Result<(), String> {
        writeln!(self.stdin, "{command}").map_err(|error| format!("numpy worker: {error}"))
    }

    fn set_shape(&mut self, rows: usize, n_in: usize, n_out: usize) -> Result<(), String> {
        self.send(&format!("shape {rows} {n_in} {n_out}"))?;
        self.expect_line("ok")
    }

    /// Seconds of one run of `product`.
    fn time(&mut self, product: Product) -> Result<f64, String> {
        self.send(product.numpy_command())?;
        let line = self.reply()?;
        line.parse()
            .map_err(|_| format!("numpy worker: unexpected reply {line:?}"))
    }
}

impl Drop for Numpy {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The buffers of one cpu `Linear(n_in, n_out) + ReLU` over `rows` rows.
struct CpuLayer {
    shape: LinearShape,
    rows: usize,
    x: Vec<f32>,
    weight: Vec<f32>,
    bias: Vec<f32>,
    d_y: Vec<f32>,
    y: Vec<f32>,
    d_pre: Vec<f32>,
    d_x: Vec<f32>,
    d_weight: Vec<f32>,
    d_bias: Vec<f32>,
}

impl CpuLayer {
    fn new(rows: usize, shape: LinearShape) -> Self {
        let mut rng = Rng::new(1);
        CpuLayer {
            shape,
            rows,
            x: random(&mut rng, rows * shape.in_features),
            weight: random(&mut rng, shape.weight_len()),
            bias: random(&mut rng, shape.out_features),
            d_y: random(&mut rng, rows * shape.out_features),
            y: vec![0.0; rows * shape.out_features],
            d_pre: vec![0.0; rows * shape.out_features],
            d_x: vec![0.0; rows * shape.in_features],
            d_weight: vec![0.0; shape.weight_len()],
            d_bias: vec![0.0; shape.out_features],
        }
    }

    /// Seconds of one run of `product` (the backward's `dL/dY` copy is not timed).
    fn time(&mut self, product: Product) -> f64 {
        let parts = [InputPart {
            data: &self.x[..],
            cols: self.shape.in_features,
        }];
        if product == Product::Forward {
            return seconds(|| {
                linear_forward(
                    self.shape,
                    &self.weight,
                    &self.bias,
                    &parts,
                    self.rows,
                    &mut self.y,
                )
                .expect("forward");
            });
        }
        self.d_pre.copy_from_slice(&self.d_y);
        let d_input = if product == Product::Backward {
            InputGrad::Write(&mut self.d_x[..])
        } else {
            InputGrad::Skip
        };
        let mut d_inputs = [d_input];
        seconds(|| {
            linear_backward(
                self.shape,
                &self.weight,
                &parts,
                self.rows,
                &self.y,
                &mut self.d_pre,
                LinearGrads {
                    weight: &mut self.d_weight,
                    bias: &mut self.d_bias,
                    inputs: &mut d_inputs,
                },
            )
            .expect("backward");
        })
    }
}

/// The shortest pause before each timed run.
const SETTLE: Duration = Duration::from_millis(50);

/// The window in which a process counts as idle when it used less than `IDLE_CPU` of CPU.
const IDLE_WINDOW: Duration = Duration::from_millis(25);

/// See [`IDLE_WINDOW`]: 4% of one core.
const IDLE_CPU: Duration = Duration::from_millis(1);

/// The longest wait for a process to go idle before a run is timed anyway.
const IDLE_TIMEOUT: Duration = Duration::from_secs(3);

/// CPU time used so far by all threads of process `pid` (from `/proc/<pid>/task/*/schedstat`,
/// nanoseconds), or `None` where that is unreadable (not Linux).
fn process_cpu(pid: u32) -> Option<Duration> {
    let mut total = 0u64;
    for entry in std::fs::read_dir(format!("/proc/{pid}/task")).ok()? {
        // A thread may exit between the listing and the read; it no longer runs.
        if let Ok(text) = std::fs::read_to_string(entry.ok()?.path().join("schedstat")) {
            total += text.split_whitespace().next()?.parse::<u64>().ok()?;
        }
    }
    Some(Duration::from_nanos(total))
}

/// Sleeps [`SETTLE`], then until each process in `pids` used less than [`IDLE_CPU`] in an
/// [`IDLE_WINDOW`] (at most [`IDLE_TIMEOUT`]), so that no thread of the previous run still
/// spins on a core. Returns how long it waited beyond `SETTLE`.
fn settle(pids: &[u32]) -> Duration {
    std::thread::sleep(SETTLE);
    let start = Instant::now();
    loop {
        let before: Vec<Option<Duration>> = pids.iter().map(|&pid| process_cpu(pid)).collect();
        std::thread::sleep(IDLE_WINDOW);
        let busy =
            pids.iter()
                .zip(&before)
                .any(|(&pid, before)| match (before, process_cpu(pid)) {
                    (Some(before), Some(after)) => after.saturating_sub(*before) >= IDLE_CPU,
                    _ => false,
                });
        if !busy || start.elapsed() >= IDLE_TIMEOUT {
            return start.elapsed();
        }
    }
}

/// One shape's cpu and numpy figures, per product in [`Product::ALL`] order.
struct Figures {
    /// cpu GFLOP/s (median time).
    cpu: Vec<f64>,
    /// numpy GFLOP/s (median time), or why numpy was skipped.
    numpy: Result<Vec<f64>, String>,
    /// Smallest and largest per-repetition cpu/numpy ratio.
    paired: Vec<(f64, f64)>,
    /// The longest wait, beyond the fixed pause, for the other side to go idle.
    longest_wait: Duration,
}

/// Median cpu and numpy timings per product, interleaved over `reps` repetitions after
/// one untimed warm-up repetition.
fn interleaved(rows: usize, shape: LinearShape, reps: usize, numpy: &mut Option<Numpy>) -> Figures {
    let mut layer = CpuLayer::new(rows, shape);
    let mut numpy_error = None;
    if let Some(worker) = numpy.as_mut()
        && let Err(error) = worker.set_shape(rows, shape.in_features, shape.out_features)
    {
        numpy_error = Some(error);
        *numpy = None;
    }
    let own = std::process::id();
    let mut cpu_times = vec![Vec::new(); Product::ALL.len()];
    let mut numpy_times = vec![Vec::new(); Product::ALL.len()];
    let mut longest_wait = Duration::ZERO;
    for rep in 0..=reps {
        for (index, &product) in Product::ALL.iter().enumerate() {
            let mut pids = vec![own];
            pids.extend(numpy.as_ref().map(|worker| worker.child.id()));
            let waited = settle(&pids);
            let cpu = layer.time(product);
            let waited = waited.max(settle(&pids));
            let other = match numpy.as_mut() {
                Some(worker) => match worker.time(product) {
                    Ok(seconds) => Some(seconds),
                    Err(error) => {
                        numpy_error = Some(error);
                        *numpy = None;
                        None
                    }
                },
                None => None,
            };
            if rep > 0 {
                longest_wait = longest_wait.max(waited);
                cpu_times[index].push(cpu);
                numpy_times[index].extend(other);
            }
        }
    }
    let flops = shape.forward_flops(rows);
    let paired = cpu_times
        .iter()
        .zip(&numpy_times)
        .map(|(cpu, other)| {
            // Throughput ratio cpu/numpy = numpy seconds / cpu seconds, per repetition.
            cpu.iter()
                .zip(other)
                .map(|(c, n)| n / c)
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| {
                    (lo.min(r), hi.max(r))
                })
        })
        .collect();
    let gflops = |times: &mut Vec<f64>, product: Product| {
        product.flop_factor() * flops / median(times) / 1e9
    };
    let cpu = Product::ALL
        .iter()
        .zip(&mut cpu_times)
        .map(|(&product, times)| gflops(times, product))
        .collect();
    let numpy_result = match numpy_error {
        Some(error) => Err(error),
        None if numpy.is_none() => Err("numpy worker not running".into()),
        None => Ok(Product::ALL
            .iter()
            .zip(&mut numpy_times)
            .map(|(&product, times)| gflops(times, product))
            .collect()),
    };
    Figures {
        cpu,
        numpy: numpy_result,
        paired,
        longest_wait,
    }
}

/// gpu forward and backward GFLOP/s (10 layers per submission, best of 3 submissions).
fn gpu_gflops(
    context: &GpuContext,
    nn: &NnGpu,
    rows: usize,
    shape: LinearShape,
) -> Result<(f64, f64), String> {
    let mut rng = Rng::new(1);
    let upload = |what: &str, values: &[f32]| {
        context
            .upload(what, values)
            .map(|b| b.buffer)
            .map_err(|e| e.to_string())
    };
    let x = upload("x", &random(&mut rng, rows * shape.in_features))?;
    let weight = upload("w", &random(&mut rng, shape.weight_len()))?;
    let bias = upload("b", &random(&mut rng, shape.out_features))?;
    let d_y = upload("dy", &random(&mut rng, rows * shape.out_features))?;
    let y = upload("y", &vec![0.0; rows * shape.out_features])?;
    let d_weight = upload("dw", &vec![0.0; shape.weight_len()])?;
    let d_bias = upload("db", &vec![0.0; shape.out_features])?;
    let d_x = upload("dx", &vec![0.0; rows * shape.in_features])?;
    let parts = [GpuInputPart {
        buffer: &x,
        cols: shape.in_features,
    }];
    let per_submit = 10;
    let time = |backward: bool| -> Result<f64, String> {
        let mut failure = None;
        let seconds = best_seconds(3, || {
            let mut encoder = context.encoder();
            for _ in 0..per_submit {
                let result = if backward {
                    nn.linear_backward(
                        &mut encoder,
                        GpuLinear::new(shape, &weight),
                        GpuInput::new(&parts, rows),
                        &y,
                        &d_y,
                        GpuLinearGrads {
                            weight: &d_weight,
                            bias: &d_bias,
                            inputs: &[GpuInputGrad::Write(&d_x)],
                        },
                    )
                } else {
                    nn.linear_forward(
                        &mut encoder,
                        GpuLinear::new(shape, &weight),
                        &bias,
                        GpuInput::new(&parts, rows),
                        &y,
                    )
                };
                if let Err(error) = result {
                    failure = Some(error.to_string());
                }
            }
            if let Err(error) = context.submit_and_wait(encoder) {
                failure = Some(error.to_string());
            }
        });
        match failure {
            Some(error) => Err(error),
            None => Ok(seconds / per_submit as f64),
        }
    };
    let forward = time(false)?;
    let backward = time(true)?;
    let flops = shape.forward_flops(rows);
    Ok((flops / forward / 1e9, 2.0 * flops / backward / 1e9))
}

/// The dense layers of the `paper` preset's networks (SMPL: J = 24; tau 8, L 8, |S| 3):
/// where each runs, and its `in x out`, as docs/method.md ("Networks") lists them.
const PAPER_LAYERS: [(&str, usize, usize); 18] = [
    ("trunk.0 (63 + 32 + 32 + 96)", 223, 512),
    ("trunk.1, trunk.2", 512, 512),
    ("heads (3 + 4 + 3)", 512, 10),
    ("pose encoder 0 (3 (J-1))", 69, 32),
    ("pose encoder 1", 32, 32),
    ("seq pose frame (3 (J+1) |S|)", 225, 16),
    ("seq pose sequence (16 L)", 128, 32),
    ("seq xyz velocity (3 tau |S|)", 72, 64),
    ("seq xyz position", 63, 32),
    ("seq xyz frame", 96, 96),
    ("seq xyz sequence 0 (96 L)", 768, 256),
    ("seq xyz sequence 1", 256, 96),
    ("pose refiner 0", 69, 128),
    ("refiner 1, lbs 1-2", 128, 128),
    ("pose refiner 2", 128, 69),
    ("lbs 0", 63, 128),
    ("lbs 3 (128 + 63)", 191, 128),
    ("lbs 4 (J)", 128, 24),
];

/// The gpu context of the paper-layer table, per `SEQAVATAR_BENCH_GPU` (`software` allows
/// lavapipe; anything else, or nothing, asks for a hardware adapter).
fn paper_context() -> Result<GpuContext, String> {
    let choice = match std::env::var("SEQAVATAR_BENCH_GPU").as_deref() {
        Ok("software") => AdapterChoice::AllowSoftware,
        _ => AdapterChoice::Hardware,
    };
    GpuContext::new(choice).map_err(|error| error.to_string())
}

/// Forward and backward GFLOP/s of one layer on one path, or why it failed.
type PathFigures = Result<(f64, f64), String>;

/// Formats `figures` as two columns, with the two ratios to `reference` after them.
fn path_columns(figures: &PathFigures, reference: &PathFigures) -> String {
    match (figures, reference) {
        (Ok((forward, backward)), Ok((reference_forward, reference_backward))) => format!(
            "{forward:>8.1} {backward:>8.1} {:>6.2} {:>6.2}",
            forward / reference_forward,
            backward / reference_backward
        ),
        (Ok((forward, backward)), Err(_)) => {
            format!("{forward:>8.1} {backward:>8.1} {:>6} {:>6}", "-", "-")
        }
        (Err(_), _) => format!("{:>8} {:>8} {:>6} {:>6}", "-", "-", "-", "-"),
    }
}

/// The gpu table of every dense layer of the `paper` networks, f32 and tensor cores.
fn paper_layers_table() {
    let context = match paper_context() {
        Ok(context) => context,
        Err(error) => {
            println!("paper layers on the gpu: {error}, skipped (networks: f32 on cpu)");
            println!("tensor-core path: not available (no gpu adapter)");
            return;
        }
    };
    let software = context.info().device_type == wgpu::DeviceType::Cpu;
    let rows: usize = std::env::var("SEQAVATAR_BENCH_GPU_ROWS")
        .ok()
        .and_then(|text| text.parse().ok())
        .unwrap_or(if software { 2048 } else { 94_000 });
    let kernels = |precision| {
        NnGpu::for_context(&context, precision)
            .map(|nn| nn.with_max_workgroups_per_dimension(context.max_workgroups_per_dimension()))
    };
    let (f32_nn, mixed_nn) = match (kernels(Precision::F32), kernels(Precision::Mixed)) {
        (Ok(f32_nn), Ok(mixed_nn)) => (f32_nn, mixed_nn),
        (Err(error), _) | (_, Err(error)) => {
            println!("paper layers on the gpu: kernels failed to compile ({error}), skipped");
            return;
        }
    };
    println!();
    println!("gpu adapter: {}", context.describe());
    println!("{}", mixed_nn.describe());
    let tensor_cores = match mixed_nn.matmul_path() {
        MatmulPath::TensorCores(_) => Some(&mixed_nn),
        MatmulPath::F32 => {
            println!(
                "tensor-core path: not available on this adapter (no 16x16x16 f16 -> f32 \
                 cooperative matrices with a fixed subgroup size); f32 only"
            );
            None
        }
    };
    println!(
        "paper networks' dense layers + ReLU over {rows} rows, GFLOP/s (backward = dX + dW + db, \
         2x forward flops), x512: throughput over the 512 x 512 layer's on the same path"
    );
    let mut measured: Vec<((usize, usize), PathFigures, Option<PathFigures>)> = Vec::new();
    for &(_, n_in, n_out) in &PAPER_LAYERS {
        if measured.iter().any(|(shape, ..)| *shape == (n_in, n_out)) {
            continue;
        }
        let shape = LinearShape {
            in_features: n_in,
            out_features: n_out,
            activation: Activation::Relu,
        };
        let f32_figures = gpu_gflops(&context, &f32_nn, rows, shape);
        let tc_figures = tensor_cores.map(|nn| gpu_gflops(&context, nn, rows, shape));
        for (path, figures) in [
            ("f32", Some(&f32_figures)),
            ("tensor cores", tc_figures.as_ref()),
        ] {
            if let Some(Err(error)) = figures {
                eprintln!("gpu {path} failed for {n_in} x {n_out}: {error}");
            }
        }
        measured.push(((n_in, n_out), f32_figures, tc_figures));
    }
    let find = |shape: (usize, usize)| {
        measured
            .iter()
            .find(|(measured_shape, ..)| *measured_shape == shape)
            .expect("every shape measured")
    };
    let (_, f32_reference, tc_reference) = find((512, 512));
    println!(
        "{:>28} | {:>9} | {:>8} {:>8} {:>6} {:>6} | {:>8} {:>8} {:>6} {:>6} | {:>6} {:>6}",
        "layer",
        "in x out",
        "f32 fwd",
        "f32 bwd",
        "x512",
        "x512",
        "tc fwd",
        "tc bwd",
        "x512",
        "x512",
        "tc/f32",
        "tc/f32"
    );
    for &(name, n_in, n_out) in &PAPER_LAYERS {
        let (_, f32_figures, tc_figures) = find((n_in, n_out));
        let tc_columns = match (tc_figures, tc_reference) {
            (Some(figures), Some(reference)) => path_columns(figures, reference),
            _ => format!("{:>8} {:>8} {:>6} {:>6}", "-", "-", "-", "-"),
        };
        let speedup = match (tc_figures, f32_figures) {
            (Some(Ok((tc_forward, tc_backward))), Ok((forward, backward))) => {
                format!(
                    "{:>6.2} {:>6.2}",
                    tc_forward / forward,
                    tc_backward / backward
                )
            }
            _ => format!("{:>6} {:>6}", "-", "-"),
        };
        println!(
            "{name:>28} | {:>9} | {} | {tc_columns} | {speedup}",
            format!("{n_in} x {n_out}"),
            path_columns(f32_figures, f32_reference),
        );
    }
}

fn main() {
    // As the `pipeline` binary does, so the figures are the ones users get.
    seqavatar_compute::memory::retain_freed_memory();
    let rows: usize = std::env::var("SEQAVATAR_BENCH_ROWS")
        .ok()
        .and_then(|text| text.parse().ok())
        .unwrap_or(50_000);
    let reps: usize = std::env::var("SEQAVATAR_BENCH_REPS")
        .ok()
        .and_then(|text| text.parse().ok())
        .filter(|&reps| reps > 0)
        .unwrap_or(7);
    let shapes = [(223, 512), (512, 512), (512, 10), (63, 128)];
    println!(
        "nn: Linear + ReLU over {rows} rows, f32, GFLOP/s, median of {reps} interleaved \
         repetitions (backward = dX + dW + db, 2x forward flops); cpu: {} rayon threads; \
         load average before: {}",
        rayon::current_num_threads(),
        load_average()
    );
    let gpu = match GpuContext::new(AdapterChoice::Hardware) {
        Ok(context) => match NnGpu::new(context.device()) {
            Ok(nn) => {
                println!("gpu adapter: {}", context.describe());
                Some((context, nn))
            }
            Err(error) => {
                println!("gpu: kernels failed to compile ({error}), skipped");
                None
            }
        },
        Err(error) => {
            println!("gpu: {error}, skipped");
            None
        }
    };
    let mut numpy = match Numpy::start() {
        Ok(worker) => Some(worker),
        Err(error) => {
            println!("numpy: {error}, skipped");
            None
        }
    };
    println!(
        "{:>11} | {:>9} | {:>8} {:>8} {:>9} {:>11} | {:>8}",
        "in x out", "product", "cpu", "numpy", "cpu/numpy", "paired", "gpu"
    );
    let mut longest_wait = Duration::ZERO;
    for (n_in, n_out) in shapes {
        let shape = LinearShape {
            in_features: n_in,
            out_features: n_out,
            activation: Activation::Relu,
        };
        let figures = interleaved(rows, shape, reps, &mut numpy);
        if let Err(reason) = &figures.numpy {
            eprintln!("numpy skipped for {n_in} x {n_out}: {reason}");
        }
        longest_wait = longest_wait.max(figures.longest_wait);
        let gpu_figures = match &gpu {
            Some((context, nn)) => match gpu_gflops(context, nn, rows, shape) {
                Ok((forward, backward)) => [Some(forward), Some(backward), None],
                Err(error) => {
                    eprintln!("gpu failed for {n_in} x {n_out}: {error}");
                    [None; 3]
                }
            },
            None => [None; 3],
        };
        for (index, product) in Product::ALL.iter().enumerate() {
            let (numpy_column, ratio_column, paired_column) = match &figures.numpy {
                Ok(numpy_figures) => {
                    let (low, high) = figures.paired[index];
                    (
                        format!("{:>8.1}", numpy_figures[index]),
                        format!("{:>9.2}", figures.cpu[index] / numpy_figures[index]),
                        format!("{:>11}", format!("{low:.2}-{high:.2}")),
                    )
                }
                Err(_) => (
                    format!("{:>8}", "-"),
                    format!("{:>9}", "-"),
                    format!("{:>11}", "-"),
                ),
            };
            let gpu_column = gpu_figures[index]
                .map(|value| format!("{value:>8.1}"))
                .unwrap_or_else(|| format!("{:>8}", "-"));
            println!(
                "{:>11} | {:>9} | {:>8.1} {numpy_column} {ratio_column} {paired_column} | \
                 {gpu_column}",
                if index == 0 {
                    format!("{n_in} x {n_out}")
                } else {
                    String::new()
                },
                product.label(),
                figures.cpu[index]
            );
        }
    }
    println!(
        "longest wait for the other side's threads to stop spinning before a run: {} ms",
        longest_wait.as_millis()
    );
    println!("load average after: {}", load_average());
    paper_layers_table();
}
