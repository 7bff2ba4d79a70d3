//! Prints the time of LPIPS (VGG16, AlexNet) per image pair (forward, and forward+gradient:
//! the training loss) and of SSIM per image at several resolutions, on the cpu and, when there
//! is a hardware adapter, the gpu.
//!
//! `cargo bench -p seqavatar-evaluation --bench lpips`; `SEQAVATAR_BENCH_SIZES=256,512` picks the
//! square sizes; `SEQAVATAR_BENCH_SOFTWARE_GPU=1` also times a software adapter (lavapipe).

use std::time::Instant;

use seqavatar_compute::backend::{AdapterChoice, Backend, DeviceChoice};
use seqavatar_compute::image::ImageF32;
use seqavatar_compute::lpips::{Lpips, LpipsInput, LpipsNet, seeded};
use seqavatar_evaluation::metrics::ssim;

fn test_image(size: usize, salt: u64) -> ImageF32 {
    let data = seeded::uniforms(salt, "bench image", size * size * 3)
        .into_iter()
        .map(|u| u as f32)
        .collect();
    ImageF32::from_f32("bench", size, size, data).expect("valid size")
}

fn main() {
    let sizes: Vec<usize> = std::env::var("SEQAVATAR_BENCH_SIZES")
        .unwrap_or_else(|_| "128,256,512".to_owned())
        .split(',')
        .filter_map(|text| text.trim().parse().ok())
        .collect();
    let cpu = Backend::select(DeviceChoice::Cpu).expect("the cpu backend");
    let mut backends = vec![("cpu".to_owned(), cpu)];
    let choice = if std::env::var("SEQAVATAR_BENCH_SOFTWARE_GPU").is_ok_and(|value| value == "1") {
        AdapterChoice::AllowSoftware
    } else {
        AdapterChoice::Hardware
    };
    match Backend::select_adapter(DeviceChoice::Gpu, choice) {
        Ok(gpu) => backends.push((gpu.describe(), gpu)),
        Err(error) => println!("gpu: not timed ({error})"),
    }
    for &size in &sizes {
        let (first, second) = (test_image(size, 1), test_image(size, 2));
        let start = Instant::now();
        let value = ssim(&first, &second).expect("same size");
        println!(
            "ssim {size}x{size}: {:.1} ms/image (value {value:.4})",
            start.elapsed().as_secs_f64() * 1e3
        );
    }
    for net in [LpipsNet::Alex, LpipsNet::Vgg] {
        let weights = seeded::seeded_weights(net, 1);
        for (name, backend) in &backends {
            let lpips = Lpips::new(weights.clone(), backend).expect("weights upload");
            for &size in &sizes {
                let (first, second) = (test_image(size, 1), test_image(size, 2));
                let pairs = [(&first, &second)];
                // One warm-up run (kernel compilation, allocations), then the timed runs.
                lpips.distances(&pairs).expect("lpips");
                let runs = 3;
                let start = Instant::now();
                for _ in 0..runs {
                    lpips.distances(&pairs).expect("lpips");
                }
                let per_pair = start.elapsed().as_secs_f64() / runs as f64;
                println!(
                    "lpips {} {size}x{size} {name}: {:.1} ms/pair",
                    net.name(),
                    per_pair * 1e3
                );
                // The training loss: forward plus the gradient with respect to the first image
                // (cpu: `lpips::cpu`; gpu: shaders/lpips_backward.wgsl).
                lpips
                    .distances_with_gradient(&pairs, LpipsInput::Unit)
                    .expect("lpips gradient");
                let start = Instant::now();
                for _ in 0..runs {
                    lpips
                        .distances_with_gradient(&pairs, LpipsInput::Unit)
                        .expect("lpips gradient");
                }
                let per_pair = start.elapsed().as_secs_f64() / runs as f64;
                println!(
                    "lpips {} {size}x{size} {name}: {:.1} ms/pair forward+gradient",
                    net.name(),
                    per_pair * 1e3
                );
            }
        }
    }
}
