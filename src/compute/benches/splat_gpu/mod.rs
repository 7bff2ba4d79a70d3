//! The gpu rows of the splat benchmark: kernels timed apart from transfers. Forward ms is
//! the forward kernels (projection, depth sort, binning with its 4-byte pair-count read,
//! tile sort, compositing) with the Gaussians already resident; fwd+bwd ms adds the backward
//! kernels with the upstream gradient already resident. Upload and download times are printed
//! on their own line. Uses a hardware adapter, or lavapipe when `SEQAVATAR_BENCH_SOFTWARE=1`.

use std::sync::OnceLock;
use std::time::Instant;

use seqavatar_compute::backend::{AdapterChoice, GpuContext};
use seqavatar_compute::splat::gpu::{
    GpuOptions, ResidentGaussians, ResidentImageGradient, backward_resident, forward_resident,
};
use seqavatar_compute::splat::{ImageGradient, RasterOptions};

use super::{Prepared, median};

fn context() -> Option<&'static GpuContext> {
    static CONTEXT: OnceLock<Option<GpuContext>> = OnceLock::new();
    CONTEXT
        .get_or_init(|| {
            let choice = if std::env::var("SEQAVATAR_BENCH_SOFTWARE").is_ok_and(|v| v == "1") {
                AdapterChoice::AllowSoftware
            } else {
                AdapterChoice::Hardware
            };
            match GpuContext::new(choice) {
                Ok(context) => {
                    println!("gpu adapter: {}", context.describe());
                    Some(context)
                }
                Err(error) => {
                    println!("gpu unavailable: {error}");
                    None
                }
            }
        })
        .as_ref()
}

/// Milliseconds of the forward kernels and of forward+backward kernels (medians).
pub fn time_gpu(scene: &Prepared, reps: usize) -> Option<(f64, f64)> {
    let context = context()?;
    let cameras = std::slice::from_ref(&scene.camera);
    let options = RasterOptions::default();
    let view = scene.gaussians.view();
    let gradient = [ImageGradient {
        colour: &scene.upstream,
        alpha: None,
        depth: None,
    }];
    let run = || -> Option<(f64, f64, f64)> {
        let start = Instant::now();
        let gaussians = ResidentGaussians::upload(context, &view).ok()?;
        let upload = start.elapsed();
        let start = Instant::now();
        let forward =
            forward_resident(context, gaussians, cameras, &options, GpuOptions::default()).ok()?;
        let forward_time = start.elapsed();
        let start = Instant::now();
        let upstream = ResidentImageGradient::upload_all(context, &forward, &gradient).ok()?;
        context
            .device()
            .poll(wgpu::PollType::wait_indefinitely())
            .ok()?;
        let transfers = upload + start.elapsed();
        let start = Instant::now();
        let gradients = backward_resident(context, &forward, &upstream).ok()?;
        let backward_time = start.elapsed();
        let start = Instant::now();
        let images = forward.download(context).ok()?;
        let downloaded = gradients.download(context).ok()?;
        std::hint::black_box((&images, &downloaded));
        let transfers = transfers + start.elapsed();
        let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
        Some((
            ms(forward_time),
            ms(forward_time + backward_time),
            ms(transfers),
        ))
    };
    run()?; // warm-up: pipeline compilation
    let mut forward_ms = Vec::with_capacity(reps);
    let mut total_ms = Vec::with_capacity(reps);
    let mut transfer_ms = Vec::with_capacity(reps);
    for _ in 0..reps {
        let (forward, total, transfers) = run()?;
        forward_ms.push(forward);
        total_ms.push(total);
        transfer_ms.push(transfers);
    }
    println!(
        "gpu      {:>9} transfers (upload Gaussians and upstream, download images and gradients): {:.2} ms",
        scene.gaussians.opacities.len(),
        median(transfer_ms)
    );
    Some((median(forward_ms), median(total_ms)))
}
