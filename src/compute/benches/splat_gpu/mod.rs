//! The gpu rows of the splat benchmark: kernels timed apart from transfers. Forward ms is
//! the forward kernels (projection, depth sort, binning with the pair count kept on the
//! device, tile sort over the pair capacity, compositing) with the Gaussians already resident
//! in a reused workspace; fwd+bwd ms adds the backward kernels with the upstream gradient
//! already resident. The traffic per call and the upload and download times are printed on
//! their own lines. Uses a hardware adapter, or lavapipe when `SEQAVATAR_BENCH_SOFTWARE=1`.

use std::sync::OnceLock;
use std::time::Instant;

use seqavatar_compute::backend::{AdapterChoice, GpuContext};
use seqavatar_compute::splat::RasterOptions;
use seqavatar_compute::splat::gpu::{
    DeviceImageGradient, GpuOptions, ResidentGaussians, SplatWorkspace,
};

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

/// Milliseconds of the forward kernels and of forward+backward kernels (medians), on one
/// [`SplatWorkspace`] reused over the repetitions like a training step: each forward and
/// backward is recorded into an encoder and submitted, with no read-back (the pair capacity
/// is sized by one checked call first). Prints the host-device traffic per call.
pub fn time_gpu(scene: &Prepared, reps: usize) -> Option<(f64, f64)> {
    let context = context()?;
    let cameras = std::slice::from_ref(&scene.camera);
    let options = RasterOptions::default();
    let view = scene.gaussians.view();
    let start = Instant::now();
    let gaussians = ResidentGaussians::upload(context, &view).ok()?;
    let upstream = context.upload("d colour", &scene.upstream).ok()?;
    context
        .device()
        .poll(wgpu::PollType::wait_indefinitely())
        .ok()?;
    let upload = start.elapsed();
    let mut workspace = SplatWorkspace::new(context, GpuOptions::default(), None).ok()?;
    // Sizes the workspace and its pair capacity, and compiles the pipelines.
    workspace
        .forward_checked(context, gaussians.view(), cameras, &options)
        .ok()?;
    let gradient = [DeviceImageGradient {
        colour: &upstream,
        alpha: None,
        depth: None,
    }];
    let mut run = || -> Option<(f64, f64)> {
        let start = Instant::now();
        let mut encoder = context.encoder();
        workspace
            .forward(context, &mut encoder, gaussians.view(), cameras, &options)
            .ok()?;
        context.submit_and_wait(encoder).ok()?;
        let forward_time = start.elapsed();
        let start = Instant::now();
        let mut encoder = context.encoder();
        workspace
            .backward(context, &mut encoder, gaussians.view(), &gradient)
            .ok()?;
        context.submit_and_wait(encoder).ok()?;
        let backward_time = start.elapsed();
        let ms = |d: std::time::Duration| d.as_secs_f64() * 1e3;
        Some((ms(forward_time), ms(forward_time + backward_time)))
    };
    run()?; // warm-up
    let before = context.transfers();
    let mut forward_ms = Vec::with_capacity(reps);
    let mut total_ms = Vec::with_capacity(reps);
    for _ in 0..reps {
        let (forward, total) = run()?;
        forward_ms.push(forward);
        total_ms.push(total);
    }
    let traffic = context.transfers().since(&before);
    let status = workspace.check_status(context).ok()?;
    let calls = reps.max(1) as u64;
    println!(
        "gpu      {:>9} per forward+backward: {} read-backs, {} bytes up, {} bytes down (pairs per band {}, bands {}, overflowed bands {})",
        scene.gaussians.opacities.len(),
        traffic.readbacks / calls,
        traffic.bytes_up / calls,
        traffic.bytes_down / calls,
        workspace.pairs_per_band(),
        workspace.bands(),
        status.overflowed_bands,
    );
    let start = Instant::now();
    let images = workspace.download_images(context).ok()?;
    let downloaded = workspace.gradients().ok()?.download(context).ok()?;
    std::hint::black_box((&images, &downloaded));
    println!(
        "gpu      {:>9} transfers (upload Gaussians and upstream once, download images and gradients): {:.2} ms",
        scene.gaussians.opacities.len(),
        (upload + start.elapsed()).as_secs_f64() * 1e3
    );
    Some((median(forward_ms), median(total_ms)))
}
