//! Parity of the gpu splatting backend with the cpu backend (the reference): images within
//! 1e-4, identical diagnostics, gradients within 1e-3 of each array's largest magnitude (f32
//! atomics sum in a nondeterministic order), both atomic-add paths, band splitting, and the
//! numeric extremes. Scenes are small because lavapipe runs on the CPU.

use glam::DVec3;
use seqavatar_core::camera::{Camera, Intrinsics};

use super::*;
use crate::backend::test_support::gpu_test_context;
use crate::splat::covariance::covariance_from_scale_rotation;
use crate::splat::scene::SplitMix64;
use crate::splat::sh::SH_C0;
use crate::splat::{GaussianBuffers, cpu, sh_coefficient_count};

/// Tolerance of forward images (colour and alpha; depth relative to its magnitude).
const IMAGE_TOLERANCE: f32 = 1e-4;
/// Tolerance of gradients, relative to the largest magnitude in the array.
const GRADIENT_TOLERANCE: f32 = 1e-3;

fn camera(width: u32, height: u32, eye: DVec3) -> Camera {
    let focal = f64::from(width.max(height)) * 0.9;
    Camera::look_at(
        width,
        height,
        Intrinsics {
            fx: focal,
            fy: focal * 1.05,
            cx: f64::from(width) / 2.0 + 0.3,
            cy: f64::from(height) / 2.0 - 0.2,
        },
        eye,
        DVec3::ZERO,
        DVec3::Y,
    )
}

/// `n` Gaussians around the origin with degree-`degree` SH, seeded.
fn scene(n: usize, degree: u32, seed: u64) -> GaussianBuffers<f32> {
    let mut rng = SplitMix64::new(seed);
    let k = sh_coefficient_count(degree);
    let mut means = Vec::new();
    let mut scales = Vec::new();
    let mut rotations = Vec::new();
    let mut opacities = Vec::new();
    let mut sh = Vec::new();
    for _ in 0..n {
        means.extend([
            rng.uniform(-0.6, 0.6),
            rng.uniform(-0.4, 0.4),
            rng.uniform(-0.5, 0.5),
        ]);
        scales.extend([
            rng.uniform(0.01, 0.12),
            rng.uniform(0.01, 0.12),
            rng.uniform(0.01, 0.12),
        ]);
        let q: [f64; 4] = std::array::from_fn(|_| rng.normal());
        rotations.extend(q);
        opacities.push(rng.uniform(0.05, 0.95));
        for coefficient in 0..k {
            for _ in 0..3 {
                sh.push(if coefficient == 0 {
                    (rng.uniform(0.1, 0.9) - 0.5) / SH_C0
                } else {
                    rng.uniform(-0.2, 0.2)
                });
            }
        }
    }
    GaussianBuffers {
        covariances: covariance_from_scale_rotation(&scales, &rotations)
            .unwrap()
            .covariances,
        means,
        opacities,
        sh,
        sh_degree: degree,
    }
    .convert()
}

fn two_cameras() -> Vec<Camera> {
    vec![
        camera(70, 45, DVec3::new(0.3, -0.2, -2.5)),
        camera(33, 50, DVec3::new(-1.8, 0.4, -1.2)),
    ]
}

fn options() -> RasterOptions {
    RasterOptions {
        background: [0.1, 0.2, 0.3],
        smooth_cutoff: false,
    }
}

fn max_abs(values: &[f32]) -> f32 {
    values.iter().fold(0.0, |m, v| m.max(v.abs()))
}

fn assert_close(what: &str, gpu: &[f32], cpu: &[f32], tolerance: impl Fn(f32) -> f32) {
    assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
    let mut worst = (0.0_f32, 0_usize);
    for (index, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(g.is_finite(), "{what}[{index}] = {g} is not finite");
        let excess = (g - c).abs() - tolerance(*c);
        if excess > worst.0 {
            worst = (excess, index);
        }
    }
    let index = worst.1;
    assert!(
        worst.0 <= 0.0,
        "{what}[{index}]: gpu {} vs cpu {} (tolerance {})",
        gpu[index],
        cpu[index],
        tolerance(cpu[index])
    );
}

fn assert_images_match(gpu: &GpuForward, cpu: &cpu::CpuForward<f32>) {
    assert_eq!(gpu.diagnostics, cpu.diagnostics, "diagnostics");
    for (camera, (g, c)) in gpu.images.iter().zip(&cpu.images).enumerate() {
        assert_eq!((g.width, g.height), (c.width, c.height));
        assert_close(
            &format!("camera {camera} colour"),
            &g.colour,
            &c.colour,
            |_| IMAGE_TOLERANCE,
        );
        assert_close(
            &format!("camera {camera} alpha"),
            &g.alpha,
            &c.alpha,
            |_| IMAGE_TOLERANCE,
        );
        assert_close(&format!("camera {camera} depth"), &g.depth, &c.depth, |v| {
            IMAGE_TOLERANCE * v.abs().max(1.0)
        });
    }
}

fn assert_gradients_match(gpu: &SplatGradients<f32>, cpu: &SplatGradients<f32>) {
    for (what, g, c) in [
        ("means", &gpu.means, &cpu.means),
        ("covariances", &gpu.covariances, &cpu.covariances),
        ("opacities", &gpu.opacities, &cpu.opacities),
        ("sh", &gpu.sh, &cpu.sh),
        ("mean_2d_norm", &gpu.mean_2d_norm, &cpu.mean_2d_norm),
    ] {
        let scale = max_abs(c).max(1e-6);
        assert_close(what, g, c, |_| GRADIENT_TOLERANCE * scale);
    }
    assert_eq!(gpu.non_finite_gradients, cpu.non_finite_gradients);
}

/// Deterministic upstream gradients for every camera: colour, alpha and depth.
fn upstream(cameras: &[Camera], seed: u64) -> Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> {
    let mut rng = SplitMix64::new(seed);
    cameras
        .iter()
        .map(|camera| {
            let pixels = (camera.width * camera.height) as usize;
            let mut draw =
                |count: usize| -> Vec<f32> { (0..count).map(|_| rng.normal() as f32).collect() };
            (draw(pixels * 3), draw(pixels), draw(pixels))
        })
        .collect()
}

fn image_gradients(
    values: &[(Vec<f32>, Vec<f32>, Vec<f32>)],
    with_alpha_depth: bool,
) -> Vec<ImageGradient<'_, f32>> {
    values
        .iter()
        .map(|(colour, alpha, depth)| ImageGradient {
            colour,
            alpha: with_alpha_depth.then_some(alpha.as_slice()),
            depth: with_alpha_depth.then_some(depth.as_slice()),
        })
        .collect()
}

/// Forward and backward on both backends, compared.
fn check_parity(
    gaussians: &GaussianBuffers<f32>,
    cameras: &[Camera],
    options: &RasterOptions,
    gpu_options: GpuOptions,
) {
    let Some(context) = gpu_test_context() else {
        return;
    };
    check_parity_on(&context, gaussians, cameras, options, gpu_options);
}

fn check_parity_on(
    context: &GpuContext,
    gaussians: &GaussianBuffers<f32>,
    cameras: &[Camera],
    options: &RasterOptions,
    gpu_options: GpuOptions,
) {
    let view = gaussians.view();
    let cpu_forward = cpu::forward(&view, cameras, options).unwrap();
    let gpu_forward = forward_with(context, &view, cameras, options, gpu_options).unwrap();
    assert_images_match(&gpu_forward, &cpu_forward);
    let values = upstream(cameras, 99);
    for with_alpha_depth in [false, true] {
        let grads = image_gradients(&values, with_alpha_depth);
        let cpu_gradients = cpu::backward(&cpu_forward, &view, &grads).unwrap();
        let gpu_gradients = backward(context, &gpu_forward, &view, &grads).unwrap();
        // A scene with visible Gaussians must produce gradients, or the comparison is empty.
        let visible: usize = cpu_forward.diagnostics.iter().map(|d| d.visible).sum();
        if visible > 0 {
            assert!(max_abs(&cpu_gradients.means) > 0.0 && max_abs(&cpu_gradients.sh) > 0.0);
        }
        assert_gradients_match(&gpu_gradients, &cpu_gradients);
    }
}

#[test]
fn forward_and_backward_match_cpu_with_native_float_atomics() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    if !context.has_float_atomics() {
        eprintln!(
            "skipped native f32 atomics: adapter {} lacks SHADER_FLOAT32_ATOMIC",
            context.describe()
        );
        return;
    }
    let gpu_options = GpuOptions {
        atomic_add: Some(AtomicAdd::NativeFloat),
        ..GpuOptions::default()
    };
    check_parity(&scene(150, 3, 1), &two_cameras(), &options(), gpu_options);
}

#[test]
fn forward_and_backward_match_cpu_with_the_compare_exchange_fallback() {
    let gpu_options = GpuOptions {
        atomic_add: Some(AtomicAdd::CompareExchange),
        ..GpuOptions::default()
    };
    check_parity(&scene(150, 2, 2), &two_cameras(), &options(), gpu_options);
}

#[test]
fn two_dimensional_dispatches_match_cpu() {
    // Three workgroups per dimension at most: every one-thread-per-item kernel (projection,
    // binning, scan, sort) runs on a 2D grid with excess workgroups.
    let Some(context) = crate::backend::test_support::gpu_test_context_with_dispatch_limit(3)
    else {
        return;
    };
    check_parity_on(
        &context,
        &scene(1100, 1, 12),
        &two_cameras(),
        &options(),
        GpuOptions::default(),
    );
}

#[test]
fn smooth_cutoff_and_low_degrees_match_cpu() {
    let smooth = RasterOptions {
        smooth_cutoff: true,
        ..options()
    };
    for degree in [0, 1] {
        check_parity(
            &scene(60, degree, 3 + u64::from(degree)),
            &two_cameras(),
            &smooth,
            GpuOptions::default(),
        );
    }
}

#[test]
fn splitting_into_bands_of_tile_rows_changes_nothing() {
    let gaussians = scene(120, 1, 5);
    let cameras = vec![camera(64, 70, DVec3::new(0.1, 0.1, -2.0))];
    // Small enough that the five tile rows are binned in several bands.
    let gpu_options = GpuOptions {
        max_pairs_per_band: Some(400),
        ..GpuOptions::default()
    };
    check_parity(&gaussians, &cameras, &options(), gpu_options);
    let Some(context) = gpu_test_context() else {
        return;
    };
    let result = forward_with(
        &context,
        &gaussians.view(),
        &cameras,
        &options(),
        gpu_options,
    )
    .unwrap();
    let bands = result.band_counts();
    assert!(
        bands[0] > 1,
        "bands {bands:?}, pairs {}",
        result.diagnostics[0].intersections
    );
}

#[test]
fn a_band_that_cannot_be_split_further_is_a_clear_error() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let gaussians = scene(50, 0, 6);
    let gpu_options = GpuOptions {
        max_pairs_per_band: Some(1),
        ..GpuOptions::default()
    };
    let result = forward_with(
        &context,
        &gaussians.view(),
        &two_cameras(),
        &options(),
        gpu_options,
    );
    let error = result
        .err()
        .expect("one pair per band cannot hold the scene");
    assert!(error.to_string().contains("tile row"), "{error}");
}

#[test]
fn zero_gaussians_render_the_background() {
    let gaussians = scene(0, 0, 7);
    check_parity(
        &gaussians,
        &two_cameras(),
        &options(),
        GpuOptions::default(),
    );
    let Some(context) = gpu_test_context() else {
        return;
    };
    let result = forward(&context, &gaussians.view(), &two_cameras(), &options()).unwrap();
    assert!(
        result.images[0]
            .colour
            .chunks(3)
            .all(|c| c == [0.1, 0.2, 0.3])
    );
}

#[test]
fn a_one_pixel_image_matches_cpu() {
    check_parity(
        &scene(40, 1, 8),
        &[camera(1, 1, DVec3::new(0.0, 0.0, -2.0))],
        &options(),
        GpuOptions::default(),
    );
}

#[test]
fn non_finite_behind_camera_and_offscreen_gaussians_are_culled_like_cpu() {
    let mut gaussians = scene(40, 1, 9);
    let k3 = sh_coefficient_count(1) * 3;
    gaussians.means[0] = f32::NAN;
    gaussians.covariances[6 + 3] = f32::INFINITY;
    gaussians.opacities[2] = f32::NAN;
    gaussians.sh[3 * k3 + 1] = f32::NEG_INFINITY;
    // Behind the camera at z = -2.5 looking towards +z, and far off to the side.
    gaussians.means[12..15].copy_from_slice(&[0.0, 0.0, -4.0]);
    gaussians.means[15..18].copy_from_slice(&[40.0, 0.0, 0.0]);
    // A huge Gaussian straddling the camera plane and one with a tiny opacity.
    gaussians.means[18..21].copy_from_slice(&[0.0, 0.0, -2.495]);
    gaussians.opacities[7] = 1e-4;
    // A covariance whose projection overflows f32, and a denormal one (the blur keeps it
    // visible), and an opacity of exactly 1/255.
    gaussians.covariances[8 * 6..9 * 6].copy_from_slice(&[1e30, 0.0, 0.0, 1e30, 0.0, 1e30]);
    gaussians.covariances[9 * 6..10 * 6].copy_from_slice(&[1e-40, 0.0, 0.0, 1e-40, 0.0, 1e-40]);
    gaussians.opacities[10] = 1.0 / 255.0;
    let cameras = vec![camera(48, 40, DVec3::new(0.0, 0.0, -2.5))];
    check_parity(&gaussians, &cameras, &options(), GpuOptions::default());
    let Some(context) = gpu_test_context() else {
        return;
    };
    let result = forward(&context, &gaussians.view(), &cameras, &options()).unwrap();
    let diagnostics = result.diagnostics[0];
    assert_eq!(diagnostics.non_finite_inputs, 4, "{diagnostics:?}");
    assert!(diagnostics.culled_depth >= 1, "{diagnostics:?}");
    assert!(diagnostics.culled_offscreen >= 1, "{diagnostics:?}");
    assert!(diagnostics.culled_opacity >= 1, "{diagnostics:?}");
    assert!(diagnostics.non_finite_projections >= 1, "{diagnostics:?}");
}

#[test]
fn bad_upstream_gradients_are_rejected_with_the_field_named() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let gaussians = scene(10, 0, 10);
    let cameras = vec![camera(20, 20, DVec3::new(0.0, 0.0, -2.0))];
    let result = forward(&context, &gaussians.view(), &cameras, &options()).unwrap();
    let mut colour = vec![0.0_f32; 20 * 20 * 3];
    colour[5] = f32::NAN;
    let upstream = [ImageGradient {
        colour: &colour,
        alpha: None,
        depth: None,
    }];
    let error = backward(&context, &result, &gaussians.view(), &upstream).unwrap_err();
    assert!(error.to_string().contains("colour"), "{error}");
    let short = [ImageGradient {
        colour: &colour[..10],
        alpha: None,
        depth: None,
    }];
    let error = backward(&context, &result, &gaussians.view(), &short).unwrap_err();
    assert!(error.to_string().contains("colour"), "{error}");
    let other = scene(11, 0, 10);
    let error = backward(&context, &result, &other.view(), &upstream).unwrap_err();
    assert!(
        matches!(
            error,
            GpuSplatError::Splat(SplatError::GaussiansChanged { .. })
        ),
        "{error}"
    );
}

/// The upstream gradients of `values` uploaded, one per camera.
fn upload_gradients(
    context: &GpuContext,
    values: &[(Vec<f32>, Vec<f32>, Vec<f32>)],
) -> Vec<(GpuBuffer, GpuBuffer, GpuBuffer)> {
    values
        .iter()
        .map(|(colour, alpha, depth)| {
            (
                context.upload("d colour", colour).unwrap(),
                context.upload("d alpha", alpha).unwrap(),
                context.upload("d depth", depth).unwrap(),
            )
        })
        .collect()
}

fn device_gradients(
    buffers: &[(GpuBuffer, GpuBuffer, GpuBuffer)],
    with_alpha_depth: bool,
) -> Vec<DeviceImageGradient<'_>> {
    buffers
        .iter()
        .map(|(colour, alpha, depth)| DeviceImageGradient {
            colour,
            alpha: with_alpha_depth.then_some(alpha),
            depth: with_alpha_depth.then_some(depth),
        })
        .collect()
}

/// Bitwise equality of two renders (the same kernels on the same pairs).
fn assert_images_identical(
    what: &str,
    resident: &[RenderedImage<f32>],
    reference: &[RenderedImage<f32>],
) {
    assert_eq!(resident.len(), reference.len(), "{what}: cameras");
    for (camera, (r, h)) in resident.iter().zip(reference).enumerate() {
        let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!((r.width, r.height), (h.width, h.height), "{what}: size");
        assert!(
            bits(&r.colour) == bits(&h.colour),
            "{what}: camera {camera} colour"
        );
        assert!(
            bits(&r.alpha) == bits(&h.alpha),
            "{what}: camera {camera} alpha"
        );
        assert!(
            bits(&r.depth) == bits(&h.depth),
            "{what}: camera {camera} depth"
        );
    }
}

/// One workspace reused over calls whose Gaussian count goes up and down: every forward
/// recorded into the caller's encoder equals the host path bitwise (images and
/// diagnostics), and every backward matches the cpu backend.
/// Records one unchecked forward of `gaussians` (as a training step does) and runs it.
fn forward_unchecked(
    context: &GpuContext,
    workspace: &mut SplatWorkspace,
    gaussians: DeviceGaussians<'_>,
    cameras: &[Camera],
) {
    let mut encoder = context.encoder();
    workspace
        .forward(context, &mut encoder, gaussians, cameras, &options())
        .unwrap();
    context.submit_and_wait(encoder).unwrap();
}

/// The workspace's last render has the reference's diagnostics and bit-identical images.
fn assert_renders_reference(
    what: &str,
    context: &GpuContext,
    workspace: &SplatWorkspace,
    reference: &GpuForward,
) {
    let (images, diagnostics) = workspace.download_images(context).unwrap();
    assert_eq!(diagnostics, reference.diagnostics, "{what}");
    assert_images_identical(what, &images, &reference.images);
}

fn check_reused_workspace(context: &GpuContext, scenes: &[GaussianBuffers<f32>]) {
    let cameras = two_cameras();
    let mut workspace = SplatWorkspace::new(context, GpuOptions::default(), None).unwrap();
    let values = upstream(&cameras, 41);
    let device_upstream = upload_gradients(context, &values);
    for (call, gaussians) in scenes.iter().enumerate() {
        let view = gaussians.view();
        let reference = forward(context, &view, &cameras, &options()).unwrap();
        let resident = ResidentGaussians::upload(context, &view).unwrap();
        // Checked once (the capacity may grow), then recorded unchecked like a training step.
        workspace
            .forward_checked(context, resident.view(), &cameras, &options())
            .unwrap();
        let mut encoder = context.encoder();
        workspace
            .forward(context, &mut encoder, resident.view(), &cameras, &options())
            .unwrap();
        let with_alpha_depth = call % 2 == 1;
        workspace
            .backward(
                context,
                &mut encoder,
                resident.view(),
                &device_gradients(&device_upstream, with_alpha_depth),
            )
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
        assert_eq!(workspace.check_status(context).unwrap().overflowed_bands, 0);
        assert_renders_reference(&format!("call {call}"), context, &workspace, &reference);
        let cpu_forward = cpu::forward(&view, &cameras, &options()).unwrap();
        let cpu_gradients = cpu::backward(
            &cpu_forward,
            &view,
            &image_gradients(&values, with_alpha_depth),
        )
        .unwrap();
        let gradients = workspace.gradients().unwrap().download(context).unwrap();
        assert_gradients_match(&gradients, &cpu_gradients);
    }
}

#[test]
fn a_reused_workspace_equals_the_host_path_as_the_gaussian_count_changes() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    check_reused_workspace(
        &context,
        &[scene(100, 2, 21), scene(170, 2, 22), scene(60, 1, 23)],
    );
}

#[test]
fn a_reused_workspace_on_two_dimensional_dispatches_equals_the_host_path() {
    let Some(context) = crate::backend::test_support::gpu_test_context_with_dispatch_limit(3)
    else {
        return;
    };
    check_reused_workspace(&context, &[scene(1100, 1, 24), scene(900, 1, 25)]);
}

#[test]
fn an_overflowed_pair_capacity_is_flagged_grown_and_exact_after_the_rerun() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let gaussians = scene(150, 1, 26);
    let view = gaussians.view();
    let cameras = two_cameras();
    let reference = forward(&context, &view, &cameras, &options()).unwrap();
    let needed = reference
        .diagnostics
        .iter()
        .map(|d| d.intersections)
        .max()
        .unwrap();
    let resident = ResidentGaussians::upload(&context, &view).unwrap();
    let mut workspace = SplatWorkspace::new(&context, GpuOptions::default(), Some(16)).unwrap();
    forward_unchecked(&context, &mut workspace, resident.view(), &cameras);
    // The truncated render still counts every pair it needed.
    let (truncated, diagnostics) = workspace.download_images(&context).unwrap();
    assert_eq!(diagnostics, reference.diagnostics);
    assert_ne!(truncated[0].colour, reference.images[0].colour);
    let status = workspace.check_status(&context).unwrap();
    assert_eq!(
        status,
        SplatStatus {
            overflowed_bands: 2,
            largest_band_pairs: needed as u32,
            grown: true,
        }
    );
    assert!(workspace.pairs_per_band() as usize >= needed);
    // The status was reset by the check.
    assert_eq!(
        workspace.check_status(&context).unwrap(),
        SplatStatus {
            overflowed_bands: 0,
            largest_band_pairs: 0,
            grown: false,
        }
    );
    forward_unchecked(&context, &mut workspace, resident.view(), &cameras);
    let status = workspace.check_status(&context).unwrap();
    assert_eq!(status.overflowed_bands, 0);
    assert_eq!(status.largest_band_pairs as usize, needed);
    assert_renders_reference("after growing", &context, &workspace, &reference);

    // The checked call does the same at once.
    let mut workspace = SplatWorkspace::new(&context, GpuOptions::default(), Some(16)).unwrap();
    let status = workspace
        .forward_checked(&context, resident.view(), &cameras, &options())
        .unwrap();
    assert_eq!(status.overflowed_bands, 0);
    assert_renders_reference("checked", &context, &workspace, &reference);
}

#[test]
fn an_overflow_beyond_the_band_limit_adds_bands_and_stays_exact() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let gaussians = scene(120, 1, 5);
    let view = gaussians.view();
    let cameras = vec![camera(64, 70, DVec3::new(0.1, 0.1, -2.0))];
    let reference = forward(&context, &view, &cameras, &options()).unwrap();
    let gpu_options = GpuOptions {
        max_pairs_per_band: Some(400),
        ..GpuOptions::default()
    };
    assert!(reference.diagnostics[0].intersections > 400);
    let resident = ResidentGaussians::upload(&context, &view).unwrap();
    let mut workspace = SplatWorkspace::new(&context, gpu_options, Some(300)).unwrap();
    assert_eq!(workspace.bands(), 1);
    workspace
        .forward_checked(&context, resident.view(), &cameras, &options())
        .unwrap();
    assert!(workspace.bands() > 1, "bands {}", workspace.bands());
    assert!(workspace.pairs_per_band() <= 400);
    assert!(workspace.band_counts()[0] > 1);
    assert_renders_reference("banded", &context, &workspace, &reference);
}

#[test]
fn a_steady_state_forward_and_backward_reads_nothing_back_and_writes_only_the_cameras() {
    // A context of its own: tests running in parallel on the shared one add their traffic.
    let Some(context) = crate::backend::test_support::gpu_test_context_alone() else {
        return;
    };
    let gaussians = scene(150, 3, 27);
    let view = gaussians.view();
    let cameras = two_cameras();
    let resident = ResidentGaussians::upload(&context, &view).unwrap();
    let device_upstream = upload_gradients(&context, &upstream(&cameras, 5));
    let mut workspace = SplatWorkspace::new(&context, GpuOptions::default(), None).unwrap();
    let step = |workspace: &mut SplatWorkspace, cameras: &[Camera]| {
        let mut encoder = context.encoder();
        workspace
            .forward(&context, &mut encoder, resident.view(), cameras, &options())
            .unwrap();
        workspace
            .backward(
                &context,
                &mut encoder,
                resident.view(),
                &device_gradients(&device_upstream, true),
            )
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
    };
    // The first call sizes the workspace.
    step(&mut workspace, &cameras);
    assert_eq!(
        workspace.check_status(&context).unwrap().overflowed_bands,
        0
    );
    // Cameras that move (same sizes) are the training steady state.
    let moved = vec![
        camera(70, 45, DVec3::new(0.35, -0.1, -2.4)),
        camera(33, 50, DVec3::new(-1.7, 0.5, -1.3)),
    ];
    for cameras in [&cameras, &moved] {
        let before = context.transfers();
        step(&mut workspace, cameras);
        let traffic = context.transfers().since(&before);
        // Per camera band: its camera uniform (forward) and gradient flags (backward).
        let bands: usize = workspace.band_counts().iter().sum();
        let expected = bands * (std::mem::size_of::<CameraUniform>() + 16);
        assert_eq!(traffic.readbacks, 0, "{traffic:?}");
        assert_eq!(traffic.bytes_down, 0, "{traffic:?}");
        assert_eq!(traffic.bytes_up as usize, expected, "{traffic:?}");
    }
    // And the steady-state render is the right one.
    let reference = forward(&context, &view, &moved, &options()).unwrap();
    let (images, _) = workspace.download_images(&context).unwrap();
    assert_images_identical("steady state", &images, &reference.images);
}

#[test]
fn device_inputs_of_the_wrong_size_are_rejected_with_the_field_named() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let gaussians = scene(10, 1, 28);
    let resident = ResidentGaussians::upload(&context, &gaussians.view()).unwrap();
    let mut workspace = SplatWorkspace::new(&context, GpuOptions::default(), None).unwrap();
    let cameras = vec![camera(20, 20, DVec3::new(0.0, 0.0, -2.0))];
    let mut too_many = resident.view();
    too_many.count = 11;
    let mut encoder = context.encoder();
    let error = workspace
        .forward(&context, &mut encoder, too_many, &cameras, &options())
        .unwrap_err();
    assert!(error.to_string().contains("means"), "{error}");
    let error = workspace
        .backward(&context, &mut encoder, resident.view(), &[])
        .unwrap_err();
    assert!(error.to_string().contains("before any forward"), "{error}");
    workspace
        .forward(
            &context,
            &mut encoder,
            resident.view(),
            &cameras,
            &options(),
        )
        .unwrap();
    let short = context.zeros("d colour", 20 * 20 * 3 - 1, 4).unwrap();
    let error = workspace
        .backward(
            &context,
            &mut encoder,
            resident.view(),
            &[DeviceImageGradient {
                colour: &short,
                alpha: None,
                depth: None,
            }],
        )
        .unwrap_err();
    assert!(error.to_string().contains("colour"), "{error}");
}
