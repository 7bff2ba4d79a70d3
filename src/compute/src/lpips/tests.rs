//! LPIPS tests: each cpu op against a direct f64 computation, the whole network against the
//! `lpips` Python package (the committed fixture), and the gpu against the cpu.

use std::path::PathBuf;

use crate::backend::{Backend, test_support::gpu_test_context};

use super::*;
use crate::safetensors::SafetensorsFile;

fn fixture_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/lpips/fixture.safetensors")
}

/// Deterministic values in [-1, 1).
fn values(count: usize, salt: u64) -> Vec<f32> {
    seeded::uniforms(salt, "test values", count)
        .into_iter()
        .map(|u| (2.0 * u - 1.0) as f32)
        .collect()
}

fn conv_weights(
    in_channels: usize,
    out_channels: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
) -> ConvWeights {
    let spec = ConvSpec {
        name: "test".to_owned(),
        in_channels,
        out_channels,
        kernel,
        stride,
        padding,
    };
    ConvWeights {
        weight: values(out_channels * in_channels * kernel * kernel, 1),
        bias: values(out_channels, 2),
        spec,
    }
}

/// Direct convolution in f64 straight from the definition.
fn conv_direct(
    input: &[f32],
    images: usize,
    [c, h, w]: [usize; 3],
    conv: &ConvWeights,
) -> Vec<f64> {
    let spec = &conv.spec;
    let (oh, ow) = (
        spec.output_extent(h).unwrap(),
        spec.output_extent(w).unwrap(),
    );
    let mut output = Vec::new();
    for image in 0..images {
        for oc in 0..spec.out_channels {
            for oy in 0..oh {
                for ox in 0..ow {
                    let mut sum = f64::from(conv.bias[oc]);
                    for ic in 0..c {
                        for ky in 0..spec.kernel {
                            for kx in 0..spec.kernel {
                                let y = (oy * spec.stride + ky) as isize - spec.padding as isize;
                                let x = (ox * spec.stride + kx) as isize - spec.padding as isize;
                                if y < 0 || x < 0 || y >= h as isize || x >= w as isize {
                                    continue;
                                }
                                let value =
                                    input[((image * c + ic) * h + y as usize) * w + x as usize];
                                let weight = conv.weight
                                    [((oc * c + ic) * spec.kernel + ky) * spec.kernel + kx];
                                sum += f64::from(value) * f64::from(weight);
                            }
                        }
                    }
                    output.push(sum.max(0.0));
                }
            }
        }
    }
    output
}

#[test]
fn cpu_convolution_matches_the_definition() {
    // Odd sizes, stride and padding like AlexNet's first layer, and a 3x3 like VGG's.
    for (in_channels, out_channels, kernel, stride, padding, height, width) in [
        (3, 5, 11, 4, 2, 23, 30),
        (4, 6, 3, 1, 1, 7, 9),
        (2, 3, 5, 1, 2, 5, 4),
    ] {
        let conv = conv_weights(in_channels, out_channels, kernel, stride, padding);
        let input = values(2 * in_channels * height * width, 3);
        let (oh, ow) = (
            conv.spec.output_extent(height).unwrap(),
            conv.spec.output_extent(width).unwrap(),
        );
        let fast = cpu::ops::conv2d_relu(&input, 2, [in_channels, height, width], &conv, [oh, ow]);
        let direct = conv_direct(&input, 2, [in_channels, height, width], &conv);
        assert_eq!(fast.len(), direct.len());
        for (index, (a, b)) in fast.iter().zip(&direct).enumerate() {
            assert!(
                (f64::from(*a) - b).abs() < 1e-4,
                "kernel {kernel} element {index}: {a} vs {b}"
            );
        }
    }
}

#[test]
fn cpu_max_pool_and_layer_distance_match_the_definitions() {
    // 1 plane of 5 x 7, 3x3 stride 2 -> 2 x 3 (floor mode drops the last row and column).
    let input: Vec<f32> = (0..35).map(|value| ((value * 17) % 35) as f32).collect();
    let pooled = cpu::ops::max_pool(&input, 1, [5, 7], 3, 2, [2, 3]);
    for oy in 0..2 {
        for ox in 0..3 {
            let mut best = f32::MIN;
            for y in 2 * oy..2 * oy + 3 {
                for x in 2 * ox..2 * ox + 3 {
                    best = best.max(input[y * 7 + x]);
                }
            }
            assert_eq!(pooled[oy * 3 + ox], best);
        }
    }
    // Two pairs, 3 channels, 2 pixels; an all-zero feature vector normalises to zero.
    let mut features = vec![0.0_f32; 4 * 3 * 2];
    let put = |features: &mut Vec<f32>, image: usize, pixel: usize, vector: [f32; 3]| {
        for channel in 0..3 {
            features[(image * 3 + channel) * 2 + pixel] = vector[channel];
        }
    };
    put(&mut features, 0, 0, [3.0, 4.0, 0.0]); // unit: (0.6, 0.8, 0)
    put(&mut features, 2, 0, [0.0, 0.0, 2.0]); // unit: (0, 0, 1)
    put(&mut features, 0, 1, [1.0, 1.0, 1.0]);
    put(&mut features, 2, 1, [2.0, 2.0, 2.0]); // same direction: distance 0
    put(&mut features, 1, 0, [5.0, 0.0, 0.0]); // pair 1 pixel 0 against zeros
    let lin = [1.0, 2.0, 3.0];
    let map = cpu::ops::layer_distance_map(&features, 2, 3, 2, &lin);
    let expected = [0.36 + 2.0 * 0.64 + 3.0, 0.0, 1.0, 0.0];
    for (value, expected) in map.iter().zip(expected) {
        assert!((value - expected).abs() < 1e-6, "{map:?}");
    }
}

#[test]
fn tap_sizes_follow_the_trunks_and_reject_tiny_images() {
    assert_eq!(
        tap_sizes(LpipsNet::Vgg, 40, 56).unwrap(),
        [(40, 56), (20, 28), (10, 14), (5, 7), (2, 3)]
    );
    // AlexNet: conv1 (k11 s4 p2) 40 -> 9, 56 -> 13; pools 3/2: 9 -> 4 -> 1, 13 -> 6 -> 2.
    assert_eq!(
        tap_sizes(LpipsNet::Alex, 40, 56).unwrap(),
        [(9, 13), (4, 6), (1, 2), (1, 2), (1, 2)]
    );
    let error = tap_sizes(LpipsNet::Vgg, 15, 64).unwrap_err().to_string();
    assert!(
        error.contains("15 x 64") && error.contains("vgg"),
        "{error}"
    );
    assert!(tap_sizes(LpipsNet::Alex, 10, 64).is_err());
}

#[test]
fn loading_reports_the_file_and_the_tensor() {
    let folder = tempfile::tempdir().unwrap();
    let path = folder.path().join("alex.safetensors");
    let weights = seeded::seeded_weights(LpipsNet::Alex, 9);
    // Without the scaling layer: loading falls back to the package's constants.
    let tensors: Vec<_> = weights
        .state_dict()
        .into_iter()
        .filter(|(name, _, _)| !name.starts_with("scaling_layer."))
        .collect();
    let write = |tensors: &[(String, Vec<usize>, &[f32])]| {
        super::write_f32_tensors(&path, tensors).unwrap();
    };
    write(&tensors);
    assert_eq!(LpipsWeights::load(&path, LpipsNet::Alex).unwrap(), weights);
    // The VGG trunk is not in an AlexNet file.
    let error = LpipsWeights::load(&path, LpipsNet::Vgg)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("alex.safetensors")
            && error.contains("net.slice1.0.weight")
            && error.contains("[64, 3, 3, 3]"),
        "{error}"
    );
    // A missing lin layer names it.
    write(&tensors[..tensors.len() - 1]);
    let error = LpipsWeights::load(&path, LpipsNet::Alex)
        .unwrap_err()
        .to_string();
    assert!(error.contains("lin4.model.0.weight"), "{error}");
    let error =
        LpipsWeights::load(&folder.path().join("absent.safetensors"), LpipsNet::Alex).unwrap_err();
    assert!(error.to_string().contains("absent.safetensors"), "{error}");
}

struct Fixture {
    pairs: Vec<(ImageF32, ImageF32)>,
    file: SafetensorsFile,
    seed: u64,
}

fn load_fixture() -> Fixture {
    let file = SafetensorsFile::read(&fixture_path()).unwrap();
    let seed: u64 = file.metadata()["seed"].parse().unwrap();
    let (first, shape) = file.u8_tensor("in0").unwrap();
    let (second, shape1) = file.u8_tensor("in1").unwrap();
    assert_eq!(shape, shape1);
    let [count, height, width, 3] = shape[..] else {
        panic!("fixture images have shape {shape:?}");
    };
    let size = height * width * 3;
    let pairs = (0..count)
        .map(|index| {
            (
                ImageF32::from_rgb8(
                    "in0",
                    width,
                    height,
                    &first[index * size..(index + 1) * size],
                )
                .unwrap(),
                ImageF32::from_rgb8(
                    "in1",
                    width,
                    height,
                    &second[index * size..(index + 1) * size],
                )
                .unwrap(),
            )
        })
        .collect();
    Fixture { pairs, file, seed }
}

/// The seeded weights must be the ones the fixture script used: compare per-tensor checksums
/// (sum and sum of squares in f64) and the exact first and last values.
fn check_weights_match_fixture(fixture: &Fixture, weights: &LpipsWeights) {
    let net = weights.net.name();
    let (checks, shape) = fixture.file.f64_tensor(&format!("checksum.{net}")).unwrap();
    let mut tensors: Vec<&[f32]> = Vec::new();
    for conv in &weights.convs {
        tensors.push(&conv.weight);
        tensors.push(&conv.bias);
    }
    for lin in &weights.lins {
        tensors.push(lin);
    }
    assert_eq!(shape, [tensors.len(), 4], "{net} checksum shape");
    for (index, tensor) in tensors.iter().enumerate() {
        let row = &checks[index * 4..index * 4 + 4];
        let sum: f64 = tensor.iter().map(|&v| f64::from(v)).sum();
        let squares: f64 = tensor.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
        assert!(
            (sum - row[0]).abs() <= 1e-9 * (1.0 + row[0].abs()),
            "{net} tensor {index} sum {sum} vs {}",
            row[0]
        );
        assert!(
            (squares - row[1]).abs() <= 1e-9 * row[1],
            "{net} tensor {index} squares"
        );
        assert_eq!(
            f64::from(tensor[0]),
            row[2],
            "{net} tensor {index} first value"
        );
        assert_eq!(
            f64::from(tensor[tensor.len() - 1]),
            row[3],
            "{net} tensor {index} last value"
        );
    }
}

fn check_against_fixture(backend: &Backend, pair_count: usize) {
    let fixture = load_fixture();
    for net in [LpipsNet::Alex, LpipsNet::Vgg] {
        let weights = seeded::seeded_weights(net, fixture.seed);
        check_weights_match_fixture(&fixture, &weights);
        let (expected, shape) = fixture
            .file
            .f64_tensor(&format!("lpips.{}", net.name()))
            .unwrap();
        let (expected_layers, _) = fixture
            .file
            .f64_tensor(&format!("lpips.{}.layers", net.name()))
            .unwrap();
        assert_eq!(shape, [fixture.pairs.len()]);
        let lpips = Lpips::new(weights, backend).unwrap();
        let pairs: Vec<(&ImageF32, &ImageF32)> = fixture
            .pairs
            .iter()
            .take(pair_count)
            .map(|(a, b)| (a, b))
            .collect();
        let distances = lpips.distances(&pairs).unwrap();
        for (index, distance) in distances.iter().enumerate() {
            eprintln!(
                "{} pair {index}: ours {:.7} package {:.7}",
                net.name(),
                distance.total,
                expected[index]
            );
            assert!(
                (distance.total - expected[index]).abs() < 1e-4,
                "{} pair {index}: {} vs {}",
                net.name(),
                distance.total,
                expected[index]
            );
            // Per layer, also relatively: the deep layers' terms are small.
            for layer in 0..5 {
                let (ours, theirs) = (distance.layers[layer], expected_layers[index * 5 + layer]);
                assert!(
                    (ours - theirs).abs() < 1e-4 && (ours - theirs).abs() <= 1e-4 * theirs.abs(),
                    "{} pair {index} layer {layer}: {ours} vs {theirs}",
                    net.name()
                );
            }
        }
    }
}

#[test]
fn cpu_lpips_matches_the_python_package() {
    check_against_fixture(&Backend::Cpu, usize::MAX);
}

#[test]
fn gpu_lpips_matches_the_python_package_and_the_cpu() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // One pair keeps the software adapter's run short.
    check_against_fixture(&Backend::Gpu(context), 1);
}

#[test]
fn gpu_ops_match_cpu_ops_on_odd_shapes() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // A whole AlexNet pass at an odd size, every layer map compared element by element.
    let weights = seeded::seeded_weights(LpipsNet::Alex, 11);
    let gpu = gpu::GpuLpips::new(context, &weights).unwrap();
    let images: Vec<ImageF32> = (0..4)
        .map(|salt| {
            let data = values(37 * 45 * 3, 20 + salt)
                .into_iter()
                .map(|v| v * 0.5 + 0.5)
                .collect();
            ImageF32::from_f32("test", 45, 37, data).unwrap()
        })
        .collect();
    let pairs = [(&images[0], &images[1]), (&images[2], &images[3])];
    let input = trunk_input(&weights, &pairs, LpipsInput::Unit).unwrap();
    let cpu_maps = cpu::distance_maps(&weights, &input).unwrap();
    let gpu_maps = gpu.distance_maps(&input).unwrap();
    assert_eq!(cpu_maps.len(), 5);
    for (layer, (cpu_map, gpu_map)) in cpu_maps.iter().zip(&gpu_maps).enumerate() {
        assert_eq!(cpu_map.len(), gpu_map.len(), "layer {layer}");
        for (index, (a, b)) in cpu_map.iter().zip(gpu_map).enumerate() {
            assert!(
                (a - b).abs() <= 1e-5 * (1.0 + a.abs()),
                "layer {layer} element {index}: {a} vs {b}"
            );
        }
    }
}

#[test]
fn identical_images_have_zero_distance_and_sizes_must_agree() {
    let weights = seeded::seeded_weights(LpipsNet::Alex, 2);
    let lpips = Lpips::new(weights, &Backend::Cpu).unwrap();
    let image = ImageF32::from_f32(
        "t",
        33,
        33,
        values(33 * 33 * 3, 5)
            .into_iter()
            .map(|v| v.abs())
            .collect(),
    )
    .unwrap();
    let distance = lpips.distances(&[(&image, &image)]).unwrap();
    assert_eq!(distance[0].total, 0.0);
    let other = ImageF32::black(34, 33);
    let error = lpips
        .distances(&[(&image, &image), (&image, &other)])
        .unwrap_err()
        .to_string();
    assert!(error.contains("pair 1"), "{error}");
    assert!(lpips.distances(&[]).unwrap().is_empty());
}

#[test]
fn written_weights_load_back_identically() {
    let folder = tempfile::tempdir().unwrap();
    for net in [LpipsNet::Alex, LpipsNet::Vgg] {
        let path = folder.path().join(format!("{}.safetensors", net.name()));
        let mut weights = seeded::seeded_weights(net, 4);
        weights.shift = [0.1, -0.2, 0.3];
        weights.write_safetensors(&path).unwrap();
        assert_eq!(LpipsWeights::load(&path, net).unwrap(), weights);
    }
}

// ---------------------------------------------------------------------------------------
// Gradient with respect to the first image.

/// `(pairs * 2, 3, h, w)` trunk input in f64 with values like scaled images (about +-2).
fn trunk_values_f64(images: usize, height: usize, width: usize, salt: u64) -> Vec<f64> {
    values(images * 3 * height * width, salt)
        .into_iter()
        .map(|v| 2.0 * f64::from(v))
        .collect()
}

/// Central differences of pair `pair`'s total along `direction` (first images only).
fn directional_difference(
    weights: &LpipsWeights,
    data: &[f64],
    shape: [usize; 3],
    pair: usize,
    direction: &[f64],
    step: f64,
) -> f64 {
    let shifted = |sign: f64| {
        let mut moved = data.to_vec();
        for (value, d) in moved.iter_mut().zip(direction) {
            *value += sign * step * d;
        }
        cpu::totals_in::<f64>(weights, &moved, shape).unwrap()[pair]
    };
    (shifted(1.0) - shifted(-1.0)) / (2.0 * step)
}

fn check_gradient_against_differences(net: LpipsNet, pairs: usize, height: usize, width: usize) {
    let weights = seeded::seeded_weights(net, 21);
    let shape = [2 * pairs, height, width];
    let data = trunk_values_f64(2 * pairs, height, width, 31);
    let (maps, gradient) = cpu::distance_gradient_in::<f64>(&weights, &data, shape).unwrap();
    let per_image = 3 * height * width;
    assert_eq!(gradient.len(), pairs * per_image);
    assert_eq!(maps.len(), 5);
    let totals = cpu::totals_in::<f64>(&weights, &data, shape).unwrap();
    assert!(totals.iter().all(|t| *t > 0.0), "{totals:?}");
    // A step of 1e-6 in f64: round-off ~1e-10, and crossing a ReLU kink is unlikely.
    let step = 1e-6;
    for pair in 0..pairs {
        let own = &gradient[pair * per_image..(pair + 1) * per_image];
        let scale = own.iter().fold(0.0_f64, |m, g| m.max(g.abs()));
        assert!(scale > 0.0, "{net:?} pair {pair}: zero gradient");
        // A random direction over the whole pair's first image (the other pairs' images and
        // every second image stay put).
        let mut direction = vec![0.0; data.len()];
        let random = trunk_values_f64(1, height, width, 40 + pair as u64);
        direction[pair * per_image..(pair + 1) * per_image].copy_from_slice(&random);
        let analytic: f64 = own.iter().zip(&random).map(|(g, d)| g * d).sum();
        let numeric = directional_difference(&weights, &data, shape, pair, &direction, step);
        assert!(
            (analytic - numeric).abs() <= 1e-6 * (1.0 + analytic.abs()),
            "{net:?} pair {pair} direction: analytic {analytic} numeric {numeric}"
        );
        // Single coordinates: corners, borders, interior, each channel.
        for (channel, y, x) in [
            (0, 0, 0),
            (1, height / 2, width / 3),
            (2, height - 1, width - 1),
            (0, height / 3, width - 1),
            (2, 1, width / 2),
        ] {
            let index = (channel * height + y) * width + x;
            let mut direction = vec![0.0; data.len()];
            direction[pair * per_image + index] = 1.0;
            let numeric = directional_difference(&weights, &data, shape, pair, &direction, step);
            assert!(
                (own[index] - numeric).abs() <= 1e-6 * scale + 1e-9,
                "{net:?} pair {pair} channel {channel} ({y}, {x}): analytic {} numeric {numeric}",
                own[index]
            );
        }
        // The other pair's first image does not affect this pair's total.
        if pairs > 1 {
            let other = (pair + 1) % pairs;
            let mut direction = vec![0.0; data.len()];
            direction[other * per_image..(other + 1) * per_image].copy_from_slice(&random);
            let numeric = directional_difference(&weights, &data, shape, pair, &direction, step);
            assert!(numeric.abs() < 1e-9, "{numeric}");
        }
    }
}

#[test]
fn vgg_gradient_matches_finite_differences_in_f64() {
    check_gradient_against_differences(LpipsNet::Vgg, 1, 20, 20);
}

#[test]
fn alex_gradient_matches_finite_differences_in_f64() {
    // 70 x 70: conv1 -> 17, pool -> 8, pool -> 3; two pairs through overlapping pools.
    check_gradient_against_differences(LpipsNet::Alex, 2, 70, 70);
}

#[test]
fn f32_gradient_matches_the_f64_gradient() {
    for (net, height, width) in [(LpipsNet::Vgg, 24, 18), (LpipsNet::Alex, 67, 75)] {
        let weights = seeded::seeded_weights(net, 5);
        let data64 = trunk_values_f64(4, height, width, 8);
        let input = TrunkInput {
            batch: 4,
            height,
            width,
            data: data64.iter().map(|&v| v as f32).collect(),
        };
        // The f32 values widened exactly, so both paths see the same input.
        let widened: Vec<f64> = input.data.iter().map(|&v| f64::from(v)).collect();
        let (maps32, gradient32) = cpu::distance_gradient(&weights, &input).unwrap();
        let (maps64, gradient64) =
            cpu::distance_gradient_in::<f64>(&weights, &widened, [4, height, width]).unwrap();
        assert_eq!(gradient32.len(), gradient64.len());
        let scale = gradient64.iter().fold(0.0_f64, |m, g| m.max(g.abs()));
        let worst = gradient32
            .iter()
            .zip(&gradient64)
            .fold(0.0_f64, |m, (a, b)| m.max((f64::from(*a) - b).abs()));
        assert!(worst <= 1e-4 * scale, "{net:?}: {worst} vs scale {scale}");
        for (map32, map64) in maps32.iter().zip(&maps64) {
            for (a, b) in map32.iter().zip(map64) {
                assert!((f64::from(*a) - b).abs() <= 1e-5 * (1.0 + b.abs()));
            }
        }
        // The forward-only entry point gives the same maps.
        assert_eq!(cpu::distance_maps(&weights, &input).unwrap(), maps32);
    }
}

/// A linear convolution (no bias, no ReLU) straight from the definition, in f64.
fn conv_linear_direct(input: &[f64], [c, h, w]: [usize; 3], conv: &ConvWeights) -> Vec<f64> {
    let spec = &conv.spec;
    let (oh, ow) = (
        spec.output_extent(h).unwrap(),
        spec.output_extent(w).unwrap(),
    );
    let mut output = vec![0.0; spec.out_channels * oh * ow];
    for oc in 0..spec.out_channels {
        for oy in 0..oh {
            for ox in 0..ow {
                let mut sum = 0.0;
                for ic in 0..c {
                    for ky in 0..spec.kernel {
                        for kx in 0..spec.kernel {
                            let y = (oy * spec.stride + ky) as isize - spec.padding as isize;
                            let x = (ox * spec.stride + kx) as isize - spec.padding as isize;
                            if y < 0 || x < 0 || y >= h as isize || x >= w as isize {
                                continue;
                            }
                            sum += input[(ic * h + y as usize) * w + x as usize]
                                * f64::from(
                                    conv.weight
                                        [((oc * c + ic) * spec.kernel + ky) * spec.kernel + kx],
                                );
                        }
                    }
                }
                output[(oc * oh + oy) * ow + ox] = sum;
            }
        }
    }
    output
}

#[test]
fn convolution_data_gradient_is_the_adjoint_of_the_convolution() {
    // <A x, y> = <x, A^T y> with A from the definition; AlexNet's first layer shape (the
    // stride leaves input pixels no output reads), a 3x3 and a 5x5.
    for (in_channels, out_channels, kernel, stride, padding, height, width) in [
        (3, 5, 11, 4, 2, 23, 30),
        (4, 6, 3, 1, 1, 7, 9),
        (2, 3, 5, 1, 2, 5, 4),
    ] {
        let conv = conv_weights(in_channels, out_channels, kernel, stride, padding);
        let (oh, ow) = (
            conv.spec.output_extent(height).unwrap(),
            conv.spec.output_extent(width).unwrap(),
        );
        let shape = [in_channels, height, width];
        for image in 0..2 {
            let x: Vec<f64> = values(in_channels * height * width, 50 + image)
                .into_iter()
                .map(f64::from)
                .collect();
            let y: Vec<f64> = values(out_channels * oh * ow, 60 + image)
                .into_iter()
                .map(f64::from)
                .collect();
            let ax = conv_linear_direct(&x, shape, &conv);
            let mut both_y = vec![0.0; 2 * y.len()];
            both_y[image as usize * y.len()..][..y.len()].copy_from_slice(&y);
            let at_y = cpu::ops::conv_data_backward_f64(&both_y, 2, shape, &conv, [oh, ow]);
            let own = &at_y[image as usize * x.len()..][..x.len()];
            let other = &at_y[(1 - image as usize) * x.len()..][..x.len()];
            assert!(other.iter().all(|v| *v == 0.0));
            let left: f64 = ax.iter().zip(&y).map(|(a, b)| a * b).sum();
            let right: f64 = x.iter().zip(own).map(|(a, b)| a * b).sum();
            assert!(
                (left - right).abs() < 1e-10 * (1.0 + left.abs()),
                "kernel {kernel}: {left} vs {right}"
            );
        }
    }
}

#[test]
fn max_pool_gradient_goes_to_the_first_maximum_and_overlaps_add() {
    // 3 x 5 plane, 3x3 windows with stride 2: output 1 x 2, windows share column 2.
    #[rustfmt::skip]
    let plane = [
        1.0, 7.0, 9.0, 0.0, 9.0,
        7.0, 2.0, 3.0, 4.0, 5.0,
        9.0, 0.0, 1.0, 2.0, 3.0,
    ];
    let d_output = [10.0, 100.0];
    let d_input = cpu::ops::max_pool_backward(&plane, &d_output, 1, [3, 5], 3, 2, [1, 2]);
    // Window 0 (columns 0..3): 9 at (0, 2) comes before the 9 at (2, 0) in scan order.
    // Window 1 (columns 2..5): 9 at (0, 2) again comes before the 9 at (0, 4).
    let mut expected = [0.0; 15];
    expected[2] = 110.0;
    assert_eq!(d_input, expected);
    assert_eq!(
        cpu::ops::max_pool(&plane, 1, [3, 5], 3, 2, [1, 2]),
        vec![9.0, 9.0]
    );
}

#[test]
fn unit_normalisation_gradient_matches_differences_including_tiny_and_zero_norms() {
    // One pair, 3 channels, 4 pixels: a generic vector, a tiny one (norm 1e-4), a zero one,
    // and one equal in direction to the target (zero distance, zero gradient).
    let channels = 3;
    let pixels = 4;
    let mut features = vec![0.0_f64; 2 * channels * pixels];
    let mut put = |image: usize, pixel: usize, vector: [f64; 3]| {
        for (channel, value) in vector.into_iter().enumerate() {
            features[(image * channels + channel) * pixels + pixel] = value;
        }
    };
    put(0, 0, [0.3, 1.2, 0.5]);
    put(1, 0, [1.0, 0.2, 0.7]);
    put(0, 1, [1e-4, 0.0, 2e-5]);
    put(1, 1, [0.1, 0.9, 0.3]);
    put(0, 2, [0.0, 0.0, 0.0]);
    put(1, 2, [0.5, 0.5, 0.1]);
    put(0, 3, [0.2, 0.4, 0.6]);
    put(1, 3, [0.4, 0.8, 1.2]);
    let lin = [0.7, 1.3, 0.4];
    let trunk_lin: Vec<f32> = lin.iter().map(|&v| v as f32).collect();
    let map = |features: &[f64]| cpu::ops::layer_distance_map(features, 1, channels, pixels, &lin);
    let gradient = cpu::ops::layer_distance_gradient(&features, channels, pixels, &trunk_lin);
    assert!(gradient.iter().all(|g| g.is_finite()));
    for pixel in 0..pixels {
        for channel in 0..channels {
            let index = channel * pixels + pixel;
            // Near the zero vector the function is linear only within |h| << eps = 1e-10.
            let step = if pixel == 2 { 1e-16 } else { 1e-9 };
            let mut plus = features.clone();
            plus[index] += step;
            let mut minus = features.clone();
            minus[index] -= step;
            let numeric = (map(&plus)[pixel] - map(&minus)[pixel]) / (2.0 * step);
            let analytic = gradient[index];
            assert!(
                (analytic - numeric).abs() <= 1e-5 * (1e-3 + analytic.abs()),
                "pixel {pixel} channel {channel}: analytic {analytic} numeric {numeric}"
            );
        }
    }
    // Same direction as the target: the distance and its gradient vanish.
    assert!(map(&features)[3].abs() < 1e-12);
    for channel in 0..channels {
        assert!(gradient[channel * pixels + 3].abs() < 1e-9);
    }
}

fn test_image(height: usize, width: usize, salt: u64) -> ImageF32 {
    let data = values(height * width * 3, salt)
        .into_iter()
        .map(|v| v * 0.5 + 0.5)
        .collect();
    ImageF32::from_f32("test", width, height, data).unwrap()
}

#[test]
fn image_gradient_matches_differences_for_both_input_mappings() {
    let (height, width) = (17, 22);
    let weights = seeded::seeded_weights(LpipsNet::Vgg, 12);
    let lpips = Lpips::new(weights.clone(), &Backend::Cpu).unwrap();
    let render = test_image(height, width, 70);
    let target = test_image(height, width, 71);
    for input in [LpipsInput::Unit, LpipsInput::UnitAsSigned] {
        let (distances, gradients) = lpips
            .distances_with_gradient(&[(&render, &target)], input)
            .unwrap();
        assert_eq!(gradients.len(), 1);
        assert_eq!(gradients[0].len(), render.data.len());
        if input == LpipsInput::Unit {
            assert_eq!(
                distances,
                lpips.distances(&[(&render, &target)]).unwrap(),
                "the gradient entry point computes the same distances"
            );
        }
        // The reference: the f64 chain image -> mapping -> scaling -> trunk -> total.
        let total = |image: &[f64]| {
            let mut data = vec![0.0; 2 * 3 * height * width];
            let (first, second) = data.split_at_mut(3 * height * width);
            image_to_trunk(&weights, image, input, first);
            let target64: Vec<f64> = target.data.iter().map(|&v| f64::from(v)).collect();
            image_to_trunk(&weights, &target64, input, second);
            cpu::totals_in::<f64>(&weights, &data, [2, height, width]).unwrap()[0]
        };
        let base: Vec<f64> = render.data.iter().map(|&v| f64::from(v)).collect();
        assert!((total(&base) - distances[0].total).abs() < 1e-5);
        let gradient = &gradients[0];
        let scale = gradient.iter().fold(0.0_f32, |m, g| m.max(g.abs()));
        let step = 1e-6;
        for index in [
            0,
            3 * (5 * width + 7) + 1,
            3 * (height * width) - 1,
            3 * 9 + 2,
        ] {
            let mut plus = base.clone();
            plus[index] += step;
            let mut minus = base.clone();
            minus[index] -= step;
            let numeric = (total(&plus) - total(&minus)) / (2.0 * step);
            assert!(
                (f64::from(gradient[index]) - numeric).abs() <= 1e-3 * f64::from(scale),
                "{input:?} value {index}: analytic {} numeric {numeric}",
                gradient[index]
            );
        }
    }
    // Without normalisation the network sees half the contrast: a different distance.
    let unit = lpips
        .distances_with_gradient(&[(&render, &target)], LpipsInput::Unit)
        .unwrap()
        .0[0]
        .total;
    let signed = lpips
        .distances_with_gradient(&[(&render, &target)], LpipsInput::UnitAsSigned)
        .unwrap()
        .0[0]
        .total;
    assert!((unit - signed).abs() > 1e-4, "{unit} vs {signed}");
}

#[test]
fn gradient_is_finite_at_the_extremes() {
    let (height, width) = (16, 16);
    let weights = seeded::seeded_weights(LpipsNet::Vgg, 3);
    let lpips = Lpips::new(weights.clone(), &Backend::Cpu).unwrap();
    let image = test_image(height, width, 80);
    let black = ImageF32::black(width, height);
    let white = ImageF32::from_f32("white", width, height, vec![1.0; height * width * 3]).unwrap();
    for input in [LpipsInput::Unit, LpipsInput::UnitAsSigned] {
        // Identical images: zero distance, exactly zero gradient.
        for same in [&image, &black, &white] {
            let (distances, gradients) = lpips
                .distances_with_gradient(&[(same, same)], input)
                .unwrap();
            assert_eq!(distances[0].total, 0.0);
            assert!(gradients[0].iter().all(|g| *g == 0.0), "{input:?}");
        }
        // Black and saturated renders against an image, and against each other.
        for (render, target) in [
            (&black, &image),
            (&image, &black),
            (&white, &image),
            (&black, &white),
            (&white, &black),
        ] {
            let (distances, gradients) = lpips
                .distances_with_gradient(&[(render, target)], input)
                .unwrap();
            assert!(distances[0].total.is_finite() && distances[0].total > 0.0);
            assert!(gradients[0].iter().all(|g| g.is_finite()), "{input:?}");
            assert!(gradients[0].iter().any(|g| *g != 0.0), "{input:?}");
        }
    }
    // A trunk whose first layer is dead everywhere (biases far below the inputs' reach):
    // every tapped feature vector is zero, the distance is 0 and the gradient is exactly 0.
    let mut dead = weights;
    dead.convs[0].bias.iter_mut().for_each(|b| *b = -1e4);
    let lpips = Lpips::new(dead, &Backend::Cpu).unwrap();
    let (distances, gradients) = lpips
        .distances_with_gradient(&[(&image, &black)], LpipsInput::Unit)
        .unwrap();
    assert_eq!(distances[0].layers[0], 0.0);
    assert!(gradients[0].iter().all(|g| g.is_finite()));
    // The first tap is dead, later ones see only the (dead) first layer: all zero.
    assert!(gradients[0].iter().all(|g| *g == 0.0));
}

#[test]
fn gradient_rejects_small_and_mismatched_images() {
    let lpips = Lpips::new(seeded::seeded_weights(LpipsNet::Vgg, 1), &Backend::Cpu).unwrap();
    let small = test_image(15, 40, 1);
    let error = lpips
        .distances_with_gradient(&[(&small, &small)], LpipsInput::Unit)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("15 x 40") && error.contains("vgg"),
        "{error}"
    );
    let (a, b) = (test_image(16, 16, 2), test_image(16, 17, 3));
    let error = lpips
        .distances_with_gradient(&[(&a, &b)], LpipsInput::Unit)
        .unwrap_err()
        .to_string();
    assert!(error.contains("pair 0"), "{error}");
    let (distances, gradients) = lpips
        .distances_with_gradient(&[], LpipsInput::Unit)
        .unwrap();
    assert!(distances.is_empty() && gradients.is_empty());
    let bad = TrunkInput {
        batch: 3,
        height: 16,
        width: 16,
        data: vec![0.0; 3 * 3 * 256],
    };
    assert!(cpu::distance_gradient(lpips.weights(), &bad).is_err());
}
