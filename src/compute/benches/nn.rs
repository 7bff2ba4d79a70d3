//! Dense-layer throughput: `cpu` (`gemm`) and `gpu` (WGSL) GFLOP/s on training-sized layers,
//! next to the machine's OpenBLAS figure through numpy for the same products.
//!
//! Run with `cargo bench -p seqavatar-compute --bench nn`. `SEQAVATAR_BENCH_ROWS` changes
//! the row count (default 50 000, the Gaussian count of a mid-training SeqAvatar model).
//! numpy missing, or no hardware GPU, skips that column with a note.

use std::process::Command;
use std::time::Instant;

use seqavatar_compute::backend::{AdapterChoice, GpuContext};
use seqavatar_compute::nn::gpu::{GpuInputGrad, GpuInputPart, GpuLinearGrads, NnGpu};
use seqavatar_compute::nn::init::{Rng, uniform_fill};
use seqavatar_compute::nn::linear::{InputGrad, LinearGrads};
use seqavatar_compute::nn::{Activation, InputPart, LinearShape, linear_backward, linear_forward};

/// Best of `repeats` timings of `work`, after one warm-up run, in seconds.
fn best_seconds(repeats: usize, mut work: impl FnMut()) -> f64 {
    work();
    (0..repeats)
        .map(|_| {
            let start = Instant::now();
            work();
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn random(rng: &mut Rng, len: usize) -> Vec<f32> {
    let mut values = vec![0.0f32; len];
    uniform_fill(rng, &mut values, 1.0);
    values
}

/// numpy's forward and backward GFLOP/s for `rows x n_in x n_out` (f32, best of 3), or why not.
fn numpy_gflops(rows: usize, n_in: usize, n_out: usize) -> Result<(f64, f64), String> {
    let script = format!(
        "import time, numpy as np\n\
         r, i, o = {rows}, {n_in}, {n_out}\n\
         rng = np.random.default_rng(0)\n\
         x = rng.standard_normal((r, i), dtype=np.float32)\n\
         w = rng.standard_normal((i, o), dtype=np.float32)\n\
         dy = rng.standard_normal((r, o), dtype=np.float32)\n\
         def best(f):\n\
         \x20   f()\n\
         \x20   t = []\n\
         \x20   for _ in range(3):\n\
         \x20       s = time.perf_counter(); f(); t.append(time.perf_counter() - s)\n\
         \x20   return min(t)\n\
         fwd = best(lambda: x @ w)\n\
         bwd = best(lambda: (dy @ w.T, x.T @ dy))\n\
         flops = 2.0 * r * i * o\n\
         print(flops / fwd / 1e9, 2 * flops / bwd / 1e9)\n"
    );
    let output = Command::new("python3")
        .args(["-c", &script])
        .output()
        .map_err(|error| format!("python3 not runnable: {error}"))?;
    if !output.status.success() {
        return Err(format!(
            "numpy failed: {}",
            String::from_utf8_lossy(&output.stderr).trim()
        ));
    }
    let text = String::from_utf8_lossy(&output.stdout);
    let values: Vec<f64> = text
        .split_whitespace()
        .filter_map(|word| word.parse().ok())
        .collect();
    match values[..] {
        [forward, backward] => Ok((forward, backward)),
        _ => Err(format!("unexpected numpy output {text:?}")),
    }
}

/// cpu forward and backward GFLOP/s of one `Linear(n_in, n_out) + ReLU` over `rows` rows.
fn cpu_gflops(rows: usize, shape: LinearShape) -> (f64, f64) {
    let mut rng = Rng::new(1);
    let x = random(&mut rng, rows * shape.in_features);
    let weight = random(&mut rng, shape.weight_len());
    let bias = random(&mut rng, shape.out_features);
    let d_y = random(&mut rng, rows * shape.out_features);
    let mut y = vec![0.0f32; rows * shape.out_features];
    let parts = [InputPart {
        data: &x[..],
        cols: shape.in_features,
    }];
    let forward = best_seconds(3, || {
        linear_forward(shape, &weight, &bias, &parts, rows, &mut y).expect("forward");
    });
    let mut d_weight = vec![0.0f32; shape.weight_len()];
    let mut d_bias = vec![0.0f32; shape.out_features];
    let mut d_x = vec![0.0f32; x.len()];
    let mut d_pre = d_y.clone();
    let backward = best_seconds(3, || {
        d_pre.copy_from_slice(&d_y);
        linear_backward(
            shape,
            &weight,
            &parts,
            rows,
            &y,
            &mut d_pre,
            LinearGrads {
                weight: &mut d_weight,
                bias: &mut d_bias,
            },
            &mut [InputGrad::Write(&mut d_x)],
        )
        .expect("backward");
    });
    let flops = shape.forward_flops(rows);
    (flops / forward / 1e9, 2.0 * flops / backward / 1e9)
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
                        shape,
                        &weight,
                        &parts,
                        rows,
                        &y,
                        &d_y,
                        GpuLinearGrads {
                            weight: &d_weight,
                            bias: &d_bias,
                        },
                        &[GpuInputGrad::Write(&d_x)],
                    )
                } else {
                    nn.linear_forward(&mut encoder, shape, &weight, &bias, &parts, rows, &y)
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

fn main() {
    let rows: usize = std::env::var("SEQAVATAR_BENCH_ROWS")
        .ok()
        .and_then(|text| text.parse().ok())
        .unwrap_or(50_000);
    let shapes = [(223, 512), (512, 512), (512, 10), (63, 128)];
    println!(
        "nn: Linear + ReLU over {rows} rows, f32, GFLOP/s (backward = dX + dW + db, 2x forward flops); cpu: {} rayon threads",
        rayon::current_num_threads()
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
    println!(
        "{:>14} | {:>9} {:>9} | {:>9} {:>9} | {:>13} {:>13} | {:>9} {:>9}",
        "in x out",
        "cpu fwd",
        "cpu bwd",
        "numpy fwd",
        "numpy bwd",
        "cpu/numpy fwd",
        "cpu/numpy bwd",
        "gpu fwd",
        "gpu bwd"
    );
    for (n_in, n_out) in shapes {
        let shape = LinearShape {
            in_features: n_in,
            out_features: n_out,
            activation: Activation::Relu,
        };
        let (cpu_forward, cpu_backward) = cpu_gflops(rows, shape);
        let numpy = match numpy_gflops(rows, n_in, n_out) {
            Ok((forward, backward)) => format!(
                "{forward:>9.1} {backward:>9.1} | {:>13.2} {:>13.2}",
                cpu_forward / forward,
                cpu_backward / backward
            ),
            Err(reason) => {
                eprintln!("numpy skipped: {reason}");
                format!("{:>9} {:>9} | {:>13} {:>13}", "-", "-", "-", "-")
            }
        };
        let gpu_column = match &gpu {
            Some((context, nn)) => match gpu_gflops(context, nn, rows, shape) {
                Ok((forward, backward)) => format!("{forward:>9.1} {backward:>9.1}"),
                Err(error) => format!("failed: {error}"),
            },
            None => format!("{:>9} {:>9}", "-", "-"),
        };
        println!(
            "{:>14} | {cpu_forward:>9.1} {cpu_backward:>9.1} | {numpy} | {gpu_column}",
            format!("{n_in} x {n_out}")
        );
    }
}
