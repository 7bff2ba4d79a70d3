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
        let fast = cpu::conv2d_relu(&input, 2, [in_channels, height, width], &conv, [oh, ow]);
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
    let pooled = cpu::max_pool(&input, 1, [5, 7], 3, 2, [2, 3]);
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
    let map = cpu::layer_distance_map(&features, 2, 3, 2, &lin);
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
    let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    let bytes = |values: &[f32]| {
        values
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect::<Vec<u8>>()
    };
    for conv in &weights.convs {
        let spec = &conv.spec;
        tensors.push((
            format!("{}.weight", spec.name),
            vec![
                spec.out_channels,
                spec.in_channels,
                spec.kernel,
                spec.kernel,
            ],
            bytes(&conv.weight),
        ));
        tensors.push((
            format!("{}.bias", spec.name),
            vec![spec.out_channels],
            bytes(&conv.bias),
        ));
    }
    for (layer, lin) in weights.lins.iter().enumerate() {
        tensors.push((
            format!("lin{layer}.model.1.weight"),
            vec![1, lin.len(), 1, 1],
            bytes(lin),
        ));
    }
    let write = |tensors: &[(String, Vec<usize>, Vec<u8>)]| {
        let views: Vec<(&str, crate::safetensors::Dtype, &[usize], &[u8])> = tensors
            .iter()
            .map(|(name, shape, data)| {
                (
                    name.as_str(),
                    crate::safetensors::Dtype::F32,
                    shape.as_slice(),
                    data.as_slice(),
                )
            })
            .collect();
        crate::safetensors::write(&path, &views, &Default::default()).unwrap();
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
    let input = trunk_input(&weights, &pairs).unwrap();
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
