//! The resident image losses against the cpu oracle (`losses::image_loss`, `gaussians::psnr`,
//! `ImageRecord::colour_on`) on lavapipe; `CI=1` makes a missing adapter a failure.

use super::*;
use crate::gaussians::psnr;
use crate::losses::{ImagePair, image_loss};
use crate::rng::Rng;
use seqavatar_compute::backend::test_support::{
    gpu_test_context, gpu_test_context_alone, gpu_test_context_with_dispatch_limit,
};

/// One camera of a test iteration: a random image, render and mask.
struct Case {
    width: usize,
    height: usize,
    rect: Rect,
    background: [f64; 3],
    record: ImageRecord,
    /// Rendered colour and alpha, f32 values (the device's) held as f64 for the oracle.
    colour: Vec<f64>,
    alpha: Vec<f64>,
}

enum Mask {
    /// Bytes drawn from 0, 255 and in between.
    Mixed,
    /// Every pixel background.
    Empty,
}

fn case(rng: &mut Rng, width: usize, height: usize, rect: Rect, mask: Mask) -> Case {
    let pixels = width * height;
    let byte = |rng: &mut Rng| rng.below(256) as u8;
    let rgb: Vec<u8> = (0..3 * pixels).map(|_| byte(rng)).collect();
    let mask: Vec<u8> = match mask {
        Mask::Mixed => (0..pixels)
            .map(|_| match rng.below(3) {
                0 => 0,
                1 => 255,
                _ => byte(rng),
            })
            .collect(),
        Mask::Empty => vec![0; pixels],
    };
    let f32_values = |rng: &mut Rng, n: usize| -> Vec<f64> {
        (0..n)
            .map(|_| f64::from(rng.uniform(0.0, 1.0) as f32))
            .collect()
    };
    let colour = f32_values(rng, 3 * pixels);
    let alpha = f32_values(rng, pixels);
    let background = [0, 1, 2].map(|_| f64::from(rng.uniform(0.0, 1.0) as f32));
    Case {
        width,
        height,
        rect,
        background,
        record: ImageRecord {
            view: 0,
            frame: 0,
            split: 0,
            rgb,
            mask,
            bound: None,
        },
        colour,
        alpha,
    }
}

fn rect(x0: usize, y0: usize, x1: usize, y1: usize) -> Rect {
    Rect { x0, y0, x1, y1 }
}

/// One camera's (colour, alpha) gradients as the cpu path computes them.
type CameraGradients = (Vec<f64>, Vec<f64>);

/// What the cpu path computes for one iteration of `cases`: per camera the gradients times
/// `1 / cameras`, and the iteration's averaged values.
fn oracle(cases: &[Case], weights: ImageLossWeights) -> (Vec<CameraGradients>, LossValues) {
    let scale = 1.0 / cases.len() as f64;
    let mut values = LossValues::default();
    let mut gradients = Vec::new();
    for case in cases {
        let target = case.record.colour_on(case.background);
        let mask = case.record.mask_f64();
        let (terms, grads) = image_loss(
            &ImagePair {
                width: case.width,
                height: case.height,
                colour: &case.colour,
                alpha: &case.alpha,
                target_colour: &target,
                target_mask: &mask,
            },
            case.rect,
            weights,
        );
        values.l1 += scale * terms.l1;
        values.mask_mse += scale * terms.mask_mse;
        values.dssim += scale * terms.dssim;
        values.total += scale * terms.total;
        values.psnr += scale * psnr(&case.colour, &target, case.width, case.rect);
        gradients.push((
            grads.colour.iter().map(|g| g * scale).collect(),
            grads.alpha.iter().map(|g| g * scale).collect(),
        ));
    }
    (gradients, values)
}

/// The device's results for one iteration: per camera (colour, alpha) gradients and the log.
struct DeviceRun {
    gradients: Vec<(Vec<f32>, Vec<f32>)>,
    log: LossLog,
}

/// Case `case`'s ground truth image.
fn truth_image(case: &Case) -> TruthImage<'_> {
    TruthImage {
        width: case.width,
        height: case.height,
        rgb: &case.record.rgb,
        mask: &case.record.mask,
    }
}

/// A colour and an alpha buffer on the device: rendered images or their gradients.
struct ImageBuffers {
    colour: GpuBuffer,
    alpha: GpuBuffer,
}

impl ImageBuffers {
    fn images(&self) -> DeviceImages<'_> {
        DeviceImages {
            colour: &self.colour,
            alpha: &self.alpha,
        }
    }
}

/// What a test that records the losses itself starts from: see [`upload_cases`].
struct Uploaded {
    truth: GroundTruth,
    rendered: ImageBuffers,
    gradients: ImageBuffers,
    cameras: Vec<LossCamera>,
}

/// The cases on the device: ground truth image `i` is case `i`'s, the renders lie back to
/// back from pixel 0, the gradient buffers are zeros, and camera `i` reads image `i` at its
/// render's offset.
fn upload_cases(context: &GpuContext, cases: &[Case]) -> Uploaded {
    let images: Vec<Option<TruthImage<'_>>> =
        cases.iter().map(|case| Some(truth_image(case))).collect();
    let truth = GroundTruth::upload(context, &images).unwrap();
    let colour: Vec<f32> = cases
        .iter()
        .flat_map(|c| c.colour.iter().map(|&v| v as f32))
        .collect();
    let alpha: Vec<f32> = cases
        .iter()
        .flat_map(|c| c.alpha.iter().map(|&v| v as f32))
        .collect();
    let rendered = ImageBuffers {
        colour: context.upload("colour", &colour).unwrap(),
        alpha: context.upload("alpha", &alpha).unwrap(),
    };
    let gradients = ImageBuffers {
        colour: context.zeros("colour gradient", colour.len(), 4).unwrap(),
        alpha: context.zeros("alpha gradient", alpha.len(), 4).unwrap(),
    };
    let mut pixel_offset = 0;
    let cameras = cases
        .iter()
        .enumerate()
        .map(|(index, case)| {
            let camera = LossCamera {
                image: index,
                pixel_offset,
                rect: case.rect,
                background: case.background,
            };
            pixel_offset += case.width * case.height;
            camera
        })
        .collect();
    Uploaded {
        truth,
        rendered,
        gradients,
        cameras,
    }
}

/// Uploads the cases' ground truth (with `chunk_bytes` chunks), renders them into shared
/// buffers at consecutive offsets (after `lead` unused pixels) and runs `iterations`
/// identical iterations.
fn run_device(
    context: &Arc<GpuContext>,
    cases: &[Case],
    weights: ImageLossWeights,
    chunk_bytes: u64,
    iterations: u64,
) -> DeviceRun {
    let lead = 7;
    let images: Vec<Option<TruthImage<'_>>> = std::iter::once(None)
        .chain(cases.iter().map(|case| Some(truth_image(case))))
        .collect();
    let truth = GroundTruth::upload_with_chunk_limit(context, &images, chunk_bytes).unwrap();
    assert!(truth.slot(0).is_none());
    let mut offsets = Vec::new();
    let mut colour = vec![0.25_f32; 3 * lead];
    let mut alpha = vec![0.25_f32; lead];
    for case in cases {
        offsets.push(alpha.len());
        colour.extend(case.colour.iter().map(|&v| v as f32));
        alpha.extend(case.alpha.iter().map(|&v| v as f32));
    }
    let rendered_colour = context.upload("rendered colour", &colour).unwrap();
    let rendered_alpha = context.upload("rendered alpha", &alpha).unwrap();
    // Gradients start as garbage: the losses must overwrite every pixel of their images.
    let gradient_colour = context
        .upload("colour gradient", &vec![9.0_f32; colour.len()])
        .unwrap();
    let gradient_alpha = context
        .upload("alpha gradient", &vec![9.0_f32; alpha.len()])
        .unwrap();
    let max_pixels = cases.iter().map(|c| c.width * c.height).max().unwrap();
    let mut loss = ImageLoss::new(context.clone(), weights, 0.0, 3, max_pixels).unwrap();
    let cameras: Vec<LossCamera> = cases
        .iter()
        .enumerate()
        .map(|(index, case)| LossCamera {
            image: index + 1,
            pixel_offset: offsets[index],
            rect: case.rect,
            background: case.background,
        })
        .collect();
    for iteration in 1..=iterations {
        let mut encoder = context.encoder();
        loss.begin_iteration(&mut encoder, iteration, &cameras, &truth)
            .unwrap();
        for camera in 0..cases.len() {
            loss.record_camera(
                &mut encoder,
                camera,
                &truth,
                DeviceImages {
                    colour: &rendered_colour,
                    alpha: &rendered_alpha,
                },
                DeviceImages {
                    colour: &gradient_colour,
                    alpha: &gradient_alpha,
                },
            )
            .unwrap();
        }
        loss.finish_iteration(&mut encoder);
        context.submit_and_wait(encoder).unwrap();
    }
    let log = loss.download_log(context.encoder()).unwrap();
    let colour_gradient: Vec<f32> = context
        .download(context.encoder(), &gradient_colour.buffer, colour.len())
        .unwrap();
    let alpha_gradient: Vec<f32> = context
        .download(context.encoder(), &gradient_alpha.buffer, alpha.len())
        .unwrap();
    // The unused lead pixels keep their values.
    assert!(colour_gradient[..3 * lead].iter().all(|&g| g == 9.0));
    assert!(alpha_gradient[..lead].iter().all(|&g| g == 9.0));
    let gradients = cases
        .iter()
        .zip(&offsets)
        .map(|(case, &offset)| {
            let pixels = case.width * case.height;
            (
                colour_gradient[3 * offset..3 * (offset + pixels)].to_vec(),
                alpha_gradient[offset..offset + pixels].to_vec(),
            )
        })
        .collect();
    DeviceRun { gradients, log }
}

fn assert_close_values(what: &str, got: LossValues, want: LossValues) {
    let pairs = [
        ("l1", got.l1, want.l1, 1e-5),
        ("mask_mse", got.mask_mse, want.mask_mse, 1e-5),
        ("dssim", got.dssim, want.dssim, 1e-5),
        ("lpips", got.lpips, want.lpips, 1e-5),
        ("total", got.total, want.total, 1e-5),
        ("psnr", got.psnr, want.psnr, 1e-3),
    ];
    for (name, g, w, tolerance) in pairs {
        assert!(
            (g - w).abs() <= tolerance * w.abs().max(1.0),
            "{what}: {name} device {g} cpu {w}"
        );
    }
}

/// `got` against `want` (`channels` values a pixel of a `width`-wide image): close inside
/// `rect` (relative to the largest value), exactly zero outside.
fn assert_close_gradient(
    what: &str,
    got: &[f32],
    want: &[f64],
    channels: usize,
    rect: Rect,
    width: usize,
) {
    assert_eq!(got.len(), want.len(), "{what}");
    let scale = want.iter().fold(0.0_f64, |m, g| m.max(g.abs()));
    for (index, (&g, &w)) in got.iter().zip(want).enumerate() {
        let pixel = index / channels;
        let (row, col) = (pixel / width, pixel % width);
        let inside = col >= rect.x0 && col < rect.x1 && row >= rect.y0 && row < rect.y1;
        if !inside {
            assert_eq!(g, 0.0, "{what}: value {index} outside the rect");
        }
        assert!(
            (f64::from(g) - w).abs() <= 2e-5 * scale + 1e-12,
            "{what}: value {index}: device {g} cpu {w} (largest {scale})"
        );
    }
}

fn check(
    context: &Arc<GpuContext>,
    what: &str,
    cases: &[Case],
    weights: ImageLossWeights,
    chunk_bytes: u64,
) {
    let (want_gradients, want) = oracle(cases, weights);
    let run = run_device(context, cases, weights, chunk_bytes, 1);
    assert_close_values(what, run.log.last, want);
    assert_close_values(what, run.log.mean, want);
    assert_eq!(run.log.iterations, 1, "{what}");
    assert_eq!(run.log.last_iteration, 1, "{what}");
    assert_eq!(run.log.first_nonfinite_iteration, None, "{what}");
    for (camera, (case, ((got_colour, got_alpha), (want_colour, want_alpha)))) in cases
        .iter()
        .zip(run.gradients.iter().zip(&want_gradients))
        .enumerate()
    {
        assert_close_gradient(
            &format!("{what} camera {camera} colour"),
            got_colour,
            want_colour,
            3,
            case.rect,
            case.width,
        );
        assert_close_gradient(
            &format!("{what} camera {camera} alpha"),
            got_alpha,
            want_alpha,
            1,
            case.rect,
            case.width,
        );
    }
}

const WEIGHTS: ImageLossWeights = ImageLossWeights {
    mask: 0.1,
    ssim: 0.2,
};

#[test]
fn resident_losses_match_image_loss_on_random_images_and_rects() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut rng = Rng::new(31);
    let all = u64::MAX;
    for (what, width, height, rect, mask) in [
        ("inner rect", 23, 17, rect(3, 2, 20, 15), Mask::Mixed),
        // Touching the left, top and right borders, and the bottom row.
        ("border rect", 19, 13, rect(0, 0, 19, 9), Mask::Mixed),
        ("bottom-right rect", 14, 16, rect(4, 5, 14, 16), Mask::Mixed),
        // One pixel wide, and one pixel high.
        ("1-px-wide rect", 16, 12, rect(5, 1, 6, 11), Mask::Mixed),
        ("1-px-high rect", 16, 12, rect(2, 7, 15, 8), Mask::Mixed),
        ("one-pixel rect", 5, 4, rect(2, 1, 3, 2), Mask::Mixed),
        // An all-zero mask: the target is the background.
        ("all-zero mask", 18, 15, rect(2, 3, 16, 12), Mask::Empty),
    ] {
        let one = case(&mut rng, width, height, rect, mask);
        check(&context, what, &[one], WEIGHTS, all);
    }
    // SSIM off: no SSIM term, no SSIM gradient.
    let plain = case(&mut rng, 21, 11, rect(1, 1, 20, 10), Mask::Mixed);
    check(
        &context,
        "SSIM off",
        &[plain],
        ImageLossWeights {
            mask: 0.3,
            ssim: 0.0,
        },
        all,
    );
}

#[test]
fn two_cameras_average_and_use_separate_chunks_and_offsets() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut rng = Rng::new(32);
    let cases = [
        case(&mut rng, 26, 19, rect(2, 3, 24, 17), Mask::Mixed),
        case(&mut rng, 17, 22, rect(0, 4, 12, 22), Mask::Mixed),
    ];
    // Chunks of 26 x 19 x 4 bytes: each image in its own chunk.
    check(&context, "two cameras", &cases, WEIGHTS, 26 * 19 * 4);
    // Both images in one chunk.
    check(
        &context,
        "two cameras, one chunk",
        &cases,
        WEIGHTS,
        u64::MAX,
    );
}

#[test]
fn two_dimensional_dispatch_agrees() {
    // Two workgroups per dimension: every pixel kernel of a 40 x 30 image goes 2D.
    let Some(narrow) = gpu_test_context_with_dispatch_limit(2) else {
        return;
    };
    let mut rng = Rng::new(33);
    let cases = [
        case(&mut rng, 40, 30, rect(1, 2, 39, 29), Mask::Mixed),
        case(&mut rng, 33, 31, rect(0, 0, 33, 31), Mask::Mixed),
    ];
    check(&narrow, "2D dispatch", &cases, WEIGHTS, u64::MAX);
}

#[test]
fn the_log_averages_iterations_and_flags_non_finite_values() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut rng = Rng::new(34);
    let cases = [case(&mut rng, 20, 16, rect(2, 2, 18, 14), Mask::Mixed)];
    let (_, want) = oracle(&cases, WEIGHTS);
    let run = run_device(&context, &cases, WEIGHTS, u64::MAX, 3);
    assert_eq!(run.log.iterations, 3);
    assert_eq!(run.log.last_iteration, 3);
    assert_close_values("three iterations, last", run.log.last, want);
    assert_close_values("three iterations, mean", run.log.mean, want);
    let mut broken = case(&mut rng, 20, 16, rect(2, 2, 18, 14), Mask::Mixed);
    broken.colour[3 * (5 * 20 + 6) + 1] = f64::NAN;
    let run = run_device(&context, &[broken], WEIGHTS, u64::MAX, 2);
    assert_eq!(run.log.first_nonfinite_iteration, Some(1));
}

#[test]
fn a_steady_state_iteration_reads_nothing_back_and_writes_only_its_record() {
    // A context of its own: the traffic counters of the shared one see the other tests.
    let Some(context) = gpu_test_context_alone() else {
        return;
    };
    let mut rng = Rng::new(35);
    let cases = [
        case(&mut rng, 24, 20, rect(2, 2, 22, 18), Mask::Mixed),
        case(&mut rng, 24, 20, rect(0, 3, 20, 20), Mask::Mixed),
    ];
    let Uploaded {
        truth,
        rendered,
        gradients,
        cameras,
    } = upload_cases(&context, &cases);
    assert_eq!(truth.bytes(), 2 * 24 * 20 * 4);
    let mut loss = ImageLoss::new(context.clone(), WEIGHTS, 0.0, 2, 24 * 20).unwrap();
    let mut iterate = |iteration: u64| {
        let mut encoder = context.encoder();
        loss.begin_iteration(&mut encoder, iteration, &cameras, &truth)
            .unwrap();
        for camera in 0..2 {
            loss.record_camera(
                &mut encoder,
                camera,
                &truth,
                rendered.images(),
                gradients.images(),
            )
            .unwrap();
        }
        loss.finish_iteration(&mut encoder);
        context.submit_and_wait(encoder).unwrap();
    };
    iterate(1);
    let before = context.transfers();
    iterate(2);
    iterate(3);
    let traffic = context.transfers().since(&before);
    assert_eq!(traffic.readbacks, 0, "{traffic:?}");
    assert_eq!(traffic.bytes_down, 0, "{traffic:?}");
    // Two iterations of one record each: 8 header words and 16 words per camera.
    assert_eq!(traffic.bytes_up, 2 * 4 * (8 + 16 * 2), "{traffic:?}");
    assert!(traffic.bytes_up / 2 < 256);
}

#[test]
fn bad_inputs_are_errors_naming_the_sizes() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let rgb = vec![0_u8; 3 * 8 * 6];
    let mask = vec![0_u8; 8 * 6];
    let image = TruthImage {
        width: 8,
        height: 6,
        rgb: &rgb,
        mask: &mask,
    };
    // An image larger than one chunk.
    let error = GroundTruth::upload_with_chunk_limit(&context, &[Some(image)], 100)
        .err()
        .unwrap()
        .to_string();
    assert!(
        error.contains("8 x 6") && error.contains("192 bytes"),
        "{error}"
    );
    // Mismatched byte counts.
    let error = GroundTruth::upload(&context, &[Some(TruthImage { width: 9, ..image })])
        .err()
        .unwrap()
        .to_string();
    assert!(error.contains("9 x 6"), "{error}");
    let truth = GroundTruth::upload(&context, &[Some(image)]).unwrap();
    let mut loss = ImageLoss::new(context.clone(), WEIGHTS, 0.0, 1, 48).unwrap();
    let mut encoder = context.encoder();
    let camera = LossCamera {
        image: 0,
        pixel_offset: 0,
        rect: rect(2, 2, 9, 5),
        background: [0.0; 3],
    };
    let error = loss
        .begin_iteration(&mut encoder, 1, &[camera], &truth)
        .unwrap_err()
        .to_string();
    assert!(error.contains("8 x 6"), "{error}");
    let error = loss
        .begin_iteration(&mut encoder, 1, &[camera, camera], &truth)
        .unwrap_err()
        .to_string();
    assert!(error.contains("2 cameras"), "{error}");
    let error = loss
        .begin_iteration(
            &mut encoder,
            1,
            &[LossCamera { image: 1, ..camera }],
            &truth,
        )
        .unwrap_err()
        .to_string();
    assert!(error.contains("image 1"), "{error}");
}

/// LPIPS on: the image losses with the resident LPIPS added per camera, against
/// `image_loss` + `LpipsLoss::add_loss` (seeded VGG weights, the cpu trunk as the oracle) on
/// two cameras whose rects are smaller than the trunk's input (the crop grows), one at the
/// image border.
#[test]
fn resident_losses_with_lpips_match_image_loss_and_lpips_add_loss() {
    use crate::losses::{ColourPair, LpipsLoss};
    use seqavatar_compute::backend::{Backend, DeviceChoice};
    use seqavatar_compute::lpips::gpu::{Crop, CropPair, DeviceImage, GpuLpips};
    use seqavatar_compute::lpips::seeded::seeded_weights;
    use seqavatar_compute::lpips::{Lpips, LpipsInput, LpipsNet};
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut rng = Rng::new(36);
    let (w, h) = (30, 28);
    let cases = [
        case(&mut rng, w, h, rect(6, 5, 17, 20), Mask::Mixed),
        case(&mut rng, w, h, rect(20, 0, 30, 9), Mask::Mixed),
    ];
    let lpips_weight = 0.4;
    let input = LpipsInput::Unit;
    let cpu = Backend::select(DeviceChoice::Cpu).unwrap();
    let oracle_lpips = LpipsLoss::new(
        Lpips::new(seeded_weights(LpipsNet::Vgg, 7), &cpu).unwrap(),
        input,
    );
    // The cpu path: image_loss, then LPIPS added into its colour gradient, all times 1/2.
    let (mut want_gradients, mut want) = oracle(&cases, WEIGHTS);
    for (camera, case) in cases.iter().enumerate() {
        let target = case.record.colour_on(case.background);
        let mut lpips_gradient = vec![0.0; 3 * w * h];
        let value = oracle_lpips
            .add_loss(
                ColourPair {
                    width: w,
                    height: h,
                    colour: &case.colour,
                    target: &target,
                },
                case.rect,
                lpips_weight,
                &mut lpips_gradient,
            )
            .unwrap();
        want.lpips += 0.5 * value;
        want.total += 0.5 * lpips_weight * value;
        for (g, l) in want_gradients[camera].0.iter_mut().zip(&lpips_gradient) {
            *g += 0.5 * l;
        }
    }
    // The device path.
    let weights = seeded_weights(LpipsNet::Vgg, 7);
    let gpu = GpuLpips::new(context.clone(), &weights).unwrap();
    let resident = gpu.resident(input, h, w, 2).unwrap();
    let Uploaded {
        truth,
        rendered,
        gradients,
        cameras,
    } = upload_cases(&context, &cases);
    let mut loss = ImageLoss::new(context.clone(), WEIGHTS, lpips_weight, 2, w * h).unwrap();
    let mut encoder = context.encoder();
    loss.begin_iteration(&mut encoder, 4, &cameras, &truth)
        .unwrap();
    for (camera, info) in cameras.iter().enumerate() {
        loss.record_camera(
            &mut encoder,
            camera,
            &truth,
            rendered.images(),
            gradients.images(),
        )
        .unwrap();
        let target = loss.record_target(&mut encoder, camera, &truth).unwrap();
        let crop = oracle_lpips.crop(info.rect, w, h).unwrap();
        resident
            .record(
                &mut encoder,
                camera,
                CropPair {
                    render: DeviceImage {
                        buffer: &rendered.colour,
                        offset: info.pixel_offset,
                        width: w,
                        height: h,
                    },
                    target: DeviceImage {
                        buffer: target,
                        offset: 0,
                        width: w,
                        height: h,
                    },
                    crop: Crop {
                        x0: crop.x0,
                        y0: crop.y0,
                        width: crop.width(),
                        height: crop.height(),
                    },
                },
                (lpips_weight / cameras.len() as f64) as f32,
                &gradients.colour,
            )
            .unwrap();
        loss.record_lpips(&mut encoder, camera, resident.value(camera))
            .unwrap();
    }
    loss.finish_iteration(&mut encoder);
    context.submit_and_wait(encoder).unwrap();
    let log = loss.download_log(context.encoder()).unwrap();
    assert!(want.lpips > 0.0);
    assert_close_values("with LPIPS", log.last, want);
    let colour_gradient: Vec<f32> = context
        .download(
            context.encoder(),
            &gradients.colour.buffer,
            gradients.colour.len,
        )
        .unwrap();
    let largest = want_gradients
        .iter()
        .flat_map(|(c, _)| c.iter())
        .fold(0.0_f64, |m, g| m.max(g.abs()));
    for (camera, (want_colour, _)) in want_gradients.iter().enumerate() {
        let got = &colour_gradient[camera * 3 * w * h..(camera + 1) * 3 * w * h];
        for (index, (&g, &want)) in got.iter().zip(want_colour).enumerate() {
            assert!(
                (f64::from(g) - want).abs() <= 1e-4 * largest,
                "camera {camera} value {index}: device {g} cpu {want}"
            );
        }
    }
}
