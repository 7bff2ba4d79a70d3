//! Benchmark of the SeqAvatar networks on `cpu`: milliseconds per non-rigid forward +
//! backward at the paper widths (trunk 512 x 3, L = 8, tau = 8, three scales, SMPL), for
//! 10k and 50k Gaussians, and the GFLOP/s of the dominant layer (the 512 x 512 trunk layer);
//! the LBS-offset network forward + backward at the demo's 5860 Gaussians (and the sizes
//! given) and the per-frame pose refiner, in f64 (the test oracle, and the trainer's
//! networks before they became f32) and in f32 on `cpu`, as the trainer runs them now.
//!
//! Run: `cargo bench -p seqavatar-avatar --bench networks` (f32). `SEQAVATAR_BENCH_SIZES`
//! (comma-separated Gaussian counts) and `SEQAVATAR_BENCH_REPEATS` change the defaults.
//! `SEQAVATAR_BENCH_GPU=1` also times `GpuNetworks` on a hardware adapter (`=software` allows
//! lavapipe) as the device-resident step runs them: the recorded programs on device buffers
//! (no upload or read-back), forward and backward each one submission waited for, with the
//! networks at `precision: mixed` (the `networks:` line says which path that is).

use std::sync::Arc;
use std::time::Instant;

use seqavatar_avatar::model::gpu::{GpuNetworks, NonRigidDeviceInputs};
use seqavatar_compute::backend::{AdapterChoice, GpuContext};
use seqavatar_compute::nn::gpu::MatmulPath;

use seqavatar_avatar::config::MotionContext;
use seqavatar_avatar::model::{
    FrameInputs, GaussianInputs, NetworkConfig, NetworkGroup, Networks, Widths,
};
use seqavatar_compute::nn::{Activation, InputPart, LinearShape, Precision, Rng, linear_forward};

fn random(rng: &mut Rng, len: usize) -> Vec<f32> {
    (0..len).map(|_| rng.uniform(-1.0, 1.0) as f32).collect()
}

fn paper_config(context: MotionContext) -> NetworkConfig {
    NetworkConfig {
        motion_context: context,
        trunk_width: 512,
        trunk_depth: 3,
        skinning_joints: 24,
        motion_joints: 24,
        tau: 8,
        sequence_length: 8,
        n_scales: if context == MotionContext::Multiscale {
            3
        } else {
            1
        },
        pose_refiner: true,
        lbs_offsets: true,
        widths: Widths::PAPER,
    }
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// The gpu context the benchmark may use, per `SEQAVATAR_BENCH_GPU`.
fn bench_gpu_context() -> Option<Arc<GpuContext>> {
    let choice = match std::env::var("SEQAVATAR_BENCH_GPU").ok()?.as_str() {
        "1" => AdapterChoice::Hardware,
        "software" => AdapterChoice::AllowSoftware,
        _ => return None,
    };
    match GpuContext::new(choice) {
        Ok(context) => {
            println!("gpu: {}", context.describe());
            // `GpuNetworks` are uploaded with `precision: mixed`, the configs' default.
            println!(
                "gpu {}",
                MatmulPath::choose(&context, Precision::Mixed).describe()
            );
            Some(Arc::new(context))
        }
        Err(error) => {
            println!("gpu: not benchmarked ({error})");
            None
        }
    }
}

/// Median milliseconds of the resident forward and backward over `repeats` after one warm-up:
/// `record(encoder, backward)` records one of them, each submitted and waited for alone.
fn time_resident(
    context: &GpuContext,
    repeats: usize,
    mut record: impl FnMut(&mut wgpu::CommandEncoder, bool),
) -> (f64, f64) {
    let (mut forward, mut backward) = (Vec::new(), Vec::new());
    for repeat in 0..=repeats {
        for (backward_pass, times) in [(false, &mut forward), (true, &mut backward)] {
            let start = Instant::now();
            let mut encoder = context.encoder();
            record(&mut encoder, backward_pass);
            context.submit_and_wait(encoder).expect("gpu submission");
            if repeat > 0 {
                times.push(start.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    (median(forward), median(backward))
}

/// A device buffer of `len` random values.
fn device_random(context: &GpuContext, rng: &mut Rng, len: usize) -> wgpu::Buffer {
    context
        .upload("bench input", &random(rng, len))
        .expect("upload")
        .buffer
}

fn bench_non_rigid(
    context: MotionContext,
    n: usize,
    repeats: usize,
    gpu_context: Option<&Arc<GpuContext>>,
) {
    let config = paper_config(context);
    let mut networks = Networks::<f32>::new(&config, 0).expect("paper config is valid");
    let mut rng = Rng::new(1);
    let pose = random(&mut rng, config.pose_dim());
    let skeleton = random(&mut rng, config.skeleton_motion_len());
    let xyz = random(&mut rng, 3 * n);
    let velocity = random(&mut rng, n * config.sequence_length * config.seq_xyz_row());
    let frame = FrameInputs {
        local_pose: &pose,
        skeleton_motion: context.has_skeleton_motion().then_some(&skeleton[..]),
    };
    let gaussians = GaussianInputs {
        xyz: &xyz,
        knn_velocity: context.has_velocity().then_some(&velocity[..]),
    };
    let d_xyz = random(&mut rng, 3 * n);
    let d_rot = random(&mut rng, 4 * n);
    let d_scale = random(&mut rng, 3 * n);
    let (mut forward, mut backward) = (Vec::new(), Vec::new());
    for repeat in 0..=repeats {
        let start = Instant::now();
        let (_, cache) = networks
            .non_rigid_forward(&frame, &gaussians)
            .expect("forward");
        let middle = Instant::now();
        networks
            .non_rigid_backward(&cache, &d_xyz, &d_rot, &d_scale)
            .expect("backward");
        let end = Instant::now();
        if repeat > 0 {
            forward.push((middle - start).as_secs_f64() * 1e3);
            backward.push((end - middle).as_secs_f64() * 1e3);
        }
    }
    let (f, b) = (median(forward), median(backward));
    println!(
        "non-rigid {context:?} n = {n}: forward {f:.1} ms, backward {b:.1} ms, total {:.1} ms ({} parameters)",
        f + b,
        networks.parameter_count()
    );
    let Some(gpu_context) = gpu_context else {
        return;
    };
    let mut gpu =
        GpuNetworks::upload(gpu_context.clone(), &networks, Precision::Mixed).expect("upload");
    let up = |rng: &mut Rng, len| device_random(gpu_context, rng, len);
    let (pose, xyz) = (up(&mut rng, pose.len()), up(&mut rng, xyz.len()));
    let skeleton = up(&mut rng, skeleton.len());
    let velocity: Vec<wgpu::Buffer> = (0..config.sequence_length)
        .map(|_| up(&mut rng, n * config.seq_xyz_row()))
        .collect();
    let velocity: Vec<&wgpu::Buffer> = velocity.iter().collect();
    let d_heads = up(&mut rng, 10 * n);
    let inputs = NonRigidDeviceInputs {
        local_pose: &pose,
        skeleton_motion: context.has_skeleton_motion().then_some(&skeleton),
        xyz: &xyz,
        knn_velocity: if context.has_velocity() {
            &velocity
        } else {
            &[]
        },
    };
    let (f, b) = time_resident(gpu_context, repeats, |encoder, backward| {
        if backward {
            gpu.record_non_rigid_backward(encoder, &d_heads)
                .expect("gpu backward");
        } else {
            gpu.record_non_rigid_forward(encoder, n, &inputs)
                .expect("gpu forward");
        }
    });
    println!(
        "  gpu: forward {f:.1} ms, backward {b:.1} ms, total {:.1} ms",
        f + b
    );
}

/// Median milliseconds of `run` over `repeats` after one warm-up.
fn time_ms(repeats: usize, mut run: impl FnMut()) -> f64 {
    let mut times = Vec::with_capacity(repeats);
    for repeat in 0..=repeats {
        let start = Instant::now();
        run();
        if repeat > 0 {
            times.push(start.elapsed().as_secs_f64() * 1e3);
        }
    }
    median(times)
}

/// The LBS-offset network (63 -> 128 x 3, skip, -> 24), forward + backward: `cpu` f64 (the
/// trainer's networks before they became f32), `cpu` f32 (as it trains), and the resident
/// `GpuNetworks` (as the device-resident step runs them).
fn bench_lbs_offsets(n: usize, repeats: usize, gpu_context: Option<&Arc<GpuContext>>) {
    let config = paper_config(MotionContext::None);
    let mut rng = Rng::new(3);
    let xyz = random(&mut rng, 3 * n);
    let d_offsets = random(&mut rng, n * config.skinning_joints);
    let mut f64_networks = Networks::<f64>::new(&config, 0).expect("paper config is valid");
    let xyz64: Vec<f64> = xyz.iter().map(|&x| f64::from(x)).collect();
    let d_offsets64: Vec<f64> = d_offsets.iter().map(|&x| f64::from(x)).collect();
    let cpu64 = time_ms(repeats, || {
        let (_, cache) = f64_networks.lbs_offsets_forward(&xyz64).expect("forward");
        f64_networks
            .lbs_offsets_backward(&cache, &d_offsets64)
            .expect("backward");
    });
    let mut networks = Networks::<f32>::new(&config, 0).expect("paper config is valid");
    let cpu32 = time_ms(repeats, || {
        let (_, cache) = networks.lbs_offsets_forward(&xyz).expect("forward");
        networks
            .lbs_offsets_backward(&cache, &d_offsets)
            .expect("backward");
    });
    print!("lbs offsets n = {n}: forward + backward cpu f64 {cpu64:.1} ms, cpu f32 {cpu32:.1} ms");
    if let Some(gpu_context) = gpu_context {
        let mut gpu =
            GpuNetworks::upload(gpu_context.clone(), &networks, Precision::Mixed).expect("upload");
        let xyz = device_random(gpu_context, &mut rng, xyz.len());
        let d_offsets = device_random(gpu_context, &mut rng, d_offsets.len());
        let (f, b) = time_resident(gpu_context, repeats, |encoder, backward| {
            if backward {
                gpu.record_backward(encoder, NetworkGroup::LbsOffsets, &d_offsets)
                    .expect("gpu backward");
            } else {
                gpu.record_forward(encoder, NetworkGroup::LbsOffsets, n, &[&[&xyz]])
                    .expect("gpu forward");
            }
        });
        print!(", gpu {:.1} ms", f + b);
    }
    println!();
}

/// The pose refiner (one row per frame), forward + backward: `cpu` f64 and the resident
/// `GpuNetworks`.
fn bench_pose_refiner(repeats: usize, gpu_context: Option<&Arc<GpuContext>>) {
    let config = paper_config(MotionContext::None);
    let mut rng = Rng::new(4);
    let pose = random(&mut rng, config.pose_dim());
    let d_rotations = random(&mut rng, 3 * config.pose_dim());
    let pose64: Vec<f64> = pose.iter().map(|&x| f64::from(x)).collect();
    let d_rotations64: Vec<f64> = d_rotations.iter().map(|&x| f64::from(x)).collect();
    let mut f64_networks = Networks::<f64>::new(&config, 0).expect("paper config is valid");
    let repeats = repeats.max(20);
    let cpu = time_ms(repeats, || {
        let (_, cache) = f64_networks.pose_refiner_forward(&pose64).expect("forward");
        f64_networks
            .pose_refiner_backward(&cache, &d_rotations64)
            .expect("backward");
    });
    print!("pose refiner (one frame): forward + backward cpu f64 {cpu:.3} ms");
    if let Some(gpu_context) = gpu_context {
        let networks = Networks::<f32>::new(&config, 0).expect("paper config is valid");
        let mut gpu =
            GpuNetworks::upload(gpu_context.clone(), &networks, Precision::Mixed).expect("upload");
        let pose = device_random(gpu_context, &mut rng, pose.len());
        let d_rotations = device_random(gpu_context, &mut rng, d_rotations.len());
        let (f, b) = time_resident(gpu_context, repeats, |encoder, backward| {
            if backward {
                gpu.record_backward(encoder, NetworkGroup::PoseRefiner, &d_rotations)
                    .expect("gpu backward");
            } else {
                gpu.record_forward(encoder, NetworkGroup::PoseRefiner, 0, &[&[&pose]])
                    .expect("gpu forward");
            }
        });
        print!(", gpu {:.3} ms", f + b);
    }
    println!();
}

fn bench_trunk_layer(n: usize, repeats: usize) {
    let mut rng = Rng::new(2);
    let shape = LinearShape {
        in_features: 512,
        out_features: 512,
        activation: Activation::Relu,
    };
    let weight = random(&mut rng, shape.weight_len());
    let bias = random(&mut rng, 512);
    let input = random(&mut rng, n * 512);
    let mut output = vec![0.0f32; n * 512];
    let mut times = Vec::new();
    for repeat in 0..=repeats {
        let start = Instant::now();
        linear_forward(
            shape,
            &weight,
            &bias,
            &[InputPart {
                data: &input,
                cols: 512,
            }],
            n,
            &mut output,
        )
        .expect("layer");
        if repeat > 0 {
            times.push(start.elapsed().as_secs_f64());
        }
    }
    let seconds = median(times);
    println!(
        "trunk layer 512 x 512, n = {n}: {:.1} ms, {:.1} GFLOP/s",
        seconds * 1e3,
        shape.forward_flops(n) / seconds / 1e9
    );
}

fn main() {
    // As the `pipeline` binary does, so the figures are the ones users get.
    seqavatar_compute::memory::retain_freed_memory();
    let sizes: Vec<usize> = std::env::var("SEQAVATAR_BENCH_SIZES")
        .ok()
        .map(|text| {
            text.split(',')
                .filter_map(|s| s.trim().parse().ok())
                .collect()
        })
        .unwrap_or_else(|| vec![10_000, 50_000]);
    let repeats: usize = std::env::var("SEQAVATAR_BENCH_REPEATS")
        .ok()
        .and_then(|text| text.parse().ok())
        .unwrap_or(3)
        .max(1);
    println!(
        "cpu threads: {} (f32, median of {repeats} after one warm-up)",
        rayon::current_num_threads()
    );
    let gpu_context = bench_gpu_context();
    bench_pose_refiner(repeats, gpu_context.as_ref());
    let mut lbs_sizes = vec![5860];
    lbs_sizes.extend(sizes.iter().copied().filter(|&n| n != 5860));
    for &n in &lbs_sizes {
        bench_lbs_offsets(n, repeats, gpu_context.as_ref());
    }
    for &n in &sizes {
        bench_trunk_layer(n, repeats);
        for context in [MotionContext::Pose, MotionContext::Multiscale] {
            bench_non_rigid(context, n, repeats, gpu_context.as_ref());
        }
    }
}
