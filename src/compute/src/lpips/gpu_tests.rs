//! Tests of the gpu LPIPS gradient (`shaders/lpips_backward.wgsl`): every backward kernel as
//! the adjoint of its forward kernel and against a host f64 scatter reference, the distance
//! gradient against its closed form (including `f = 0`), and the whole gradient against
//! central finite differences of the gpu forward. They run on any adapter (Mesa lavapipe in
//! CI) and skip cleanly without one.

use std::sync::Arc;

use crate::backend::GpuContext;
use crate::backend::test_support::{
    gpu_test_context, gpu_test_context_alone, gpu_test_context_with_dispatch_limit,
};

use super::gpu::{
    Call, ConvShape, Crop, CropPair, DeviceImage, GpuLpips, PoolShape, Slot, Workspace,
};
use super::*;

/// Deterministic values in [-1, 1).
fn values(count: usize, salt: u64) -> Vec<f32> {
    seeded::uniforms(salt, "gpu gradient test values", count)
        .into_iter()
        .map(|u| (2.0 * u - 1.0) as f32)
        .collect()
}

fn dot(a: &[f32], b: &[f32]) -> (f64, f64) {
    assert_eq!(a.len(), b.len());
    let mut sum = 0.0;
    let mut magnitude = 0.0;
    for (&x, &y) in a.iter().zip(b) {
        let product = f64::from(x) * f64::from(y);
        sum += product;
        magnitude += product.abs();
    }
    (sum, magnitude)
}

/// Records `calls` with `lpips`'s weights on the activations `[input, zeros]` and the
/// gradients `[upstream, zeros]` (`zeros` of `lens`), then downloads all four, in that order.
fn run_calls(
    context: &GpuContext,
    lpips: &GpuLpips,
    calls: &[Call],
    [input, upstream]: [&[f32]; 2],
    lens: [usize; 2],
) -> [Vec<f32>; 4] {
    let [input, upstream] = [input, upstream].map(|data| context.upload("data", data).unwrap());
    let [output, target] = lens.map(|len| context.zeros("zeros", len, 4).unwrap());
    let workspace = Workspace {
        activations: vec![input, output],
        gradients: [upstream, target],
        maps: Vec::new(),
    };
    let mut encoder = context.encoder();
    lpips.record(&mut encoder, &workspace, calls, None).unwrap();
    let buffers = workspace.activations.iter().chain(&workspace.gradients);
    let sources: Vec<_> = buffers.map(|b| (&b.buffer, b.len)).collect();
    let read = context.download_all(encoder, &sources).unwrap();
    read.try_into().unwrap()
}

/// A GpuLpips holding the op tests' weights: `convs` and `lins` (the net is a label only).
fn lpips_with(context: &Arc<GpuContext>, convs: Vec<ConvWeights>, lins: Vec<Vec<f32>>) -> GpuLpips {
    let weights = LpipsWeights {
        net: LpipsNet::Alex,
        convs,
        lins,
        shift: [0.0; 3],
        scale: [1.0; 3],
    };
    GpuLpips::new(context.clone(), &weights).unwrap()
}

/// Host f64 transposed convolution as a scatter (the opposite loop order of the kernel's
/// gather): `upstream` `(images, co, oh, ow)` -> `(images, ci, h, w)`.
fn conv_transpose_scatter(shape: ConvShape, weight: &[f32], upstream: &[f32]) -> Vec<f64> {
    let ConvShape {
        images,
        in_channels,
        in_height,
        in_width,
        out_channels,
        out_height,
        out_width,
        kernel,
        stride,
        padding,
    } = shape;
    let mut result = vec![0.0_f64; images * in_channels * in_height * in_width];
    for image in 0..images {
        for oc in 0..out_channels {
            for oy in 0..out_height {
                for ox in 0..out_width {
                    let g = f64::from(
                        upstream[((image * out_channels + oc) * out_height + oy) * out_width + ox],
                    );
                    for ic in 0..in_channels {
                        for ky in 0..kernel {
                            for kx in 0..kernel {
                                let y = (oy * stride + ky) as isize - padding as isize;
                                let x = (ox * stride + kx) as isize - padding as isize;
                                if y < 0
                                    || x < 0
                                    || y >= in_height as isize
                                    || x >= in_width as isize
                                {
                                    continue;
                                }
                                let w = f64::from(
                                    weight[((oc * in_channels + ic) * kernel + ky) * kernel + kx],
                                );
                                result[((image * in_channels + ic) * in_height + y as usize)
                                    * in_width
                                    + x as usize] += w * g;
                            }
                        }
                    }
                }
            }
        }
    }
    result
}

#[test]
fn conv_backward_is_the_adjoint_of_the_masked_convolution() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // AlexNet's first layer (k11 s4 p2), VGG's 3x3, AlexNet's 5x5 p2, a stride-2 3x3, and
    // more than four input channels with a partial last group of four.
    for (in_channels, out_channels, kernel, stride, padding, height, width) in [
        (3, 5, 11, 4, 2, 23, 30),
        (4, 6, 3, 1, 1, 7, 9),
        (6, 3, 5, 1, 2, 6, 5),
        (9, 7, 3, 2, 1, 9, 8),
    ] {
        let spec = ConvSpec {
            name: "test".to_owned(),
            in_channels,
            out_channels,
            kernel,
            stride,
            padding,
        };
        // The forward runs four images; the backward takes the first two, as in the trunk.
        let forward_shape = ConvShape {
            images: 4,
            in_channels,
            in_height: height,
            in_width: width,
            out_channels,
            out_height: spec.output_extent(height).unwrap(),
            out_width: spec.output_extent(width).unwrap(),
            kernel,
            stride,
            padding,
        };
        let shape = ConvShape {
            images: 2,
            ..forward_shape
        };
        let in_len = in_channels * height * width;
        let out_len = out_channels * forward_shape.out_height * forward_shape.out_width;
        let input = values(4 * in_len, 10 + kernel as u64);
        let weight = values(out_channels * in_channels * kernel * kernel, 11);
        let bias: Vec<f32> = values(out_channels, 12).iter().map(|b| 0.3 * b).collect();
        let upstream = values(2 * out_len, 13);
        let conv = ConvWeights {
            spec,
            weight: weight.clone(),
            bias: bias.clone(),
        };
        let lpips = lpips_with(&context, vec![conv], Vec::new());
        // Activation 0 into 1, then gradient 0 (masked in place) into 1.
        let mut calls = vec![Call::conv(forward_shape, 0, 0).unwrap()];
        calls.extend(Call::conv_backward(shape, 0, 1, 0).unwrap());
        let lens = [4 * out_len, 2 * in_len];
        let [_, forward, _, gradient] =
            run_calls(&context, &lpips, &calls, [&input, &upstream], lens);
        // The Jacobian of relu(conv(x) + b) at x is J = M conv with the mask M = [out > 0],
        // so J x = out - M b and <J x, g> must equal <x, J^T g> = <x, gradient>.
        let out_pixels = forward_shape.out_height * forward_shape.out_width;
        let mut linear_part = forward[..2 * out_len].to_vec();
        let mut active = 0;
        for (index, value) in linear_part.iter_mut().enumerate() {
            if *value > 0.0 {
                *value -= bias[(index / out_pixels) % out_channels];
                active += 1;
            }
        }
        assert!(
            active > 0 && active < linear_part.len(),
            "the mask must both pass and block ({active} of {})",
            linear_part.len()
        );
        let (left, left_magnitude) = dot(&linear_part, &upstream);
        let (right, right_magnitude) = dot(&input[..2 * in_len], &gradient);
        // f32 sums of a few hundred products on both sides: relative 1e-5 of the magnitude.
        let tolerance = 1e-5 * left_magnitude.max(right_magnitude);
        assert!(
            (left - right).abs() <= tolerance,
            "kernel {kernel} stride {stride}: <Jx, g> = {left} vs <x, J^T g> = {right}"
        );
        // Element by element against a host scatter of the masked upstream gradient.
        let masked: Vec<f32> = upstream
            .iter()
            .zip(&forward)
            .map(|(&g, &out)| if out > 0.0 { g } else { 0.0 })
            .collect();
        let expected = conv_transpose_scatter(shape, &weight, &masked);
        let scale = expected.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
        for (index, (&ours, &theirs)) in gradient.iter().zip(&expected).enumerate() {
            assert!(
                (f64::from(ours) - theirs).abs() <= 1e-5 * scale,
                "kernel {kernel} stride {stride} element {index}: {ours} vs {theirs}"
            );
        }
    }
}

/// Host max-pool backward: each window's gradient to its first maximum in row-major order.
fn max_pool_scatter(shape: PoolShape, input: &[f32], upstream: &[f32]) -> Vec<f64> {
    let PoolShape {
        planes,
        in_height,
        in_width,
        out_height,
        out_width,
        kernel,
        stride,
    } = shape;
    let mut result = vec![0.0_f64; planes * in_height * in_width];
    for plane in 0..planes {
        let base = plane * in_height * in_width;
        for oy in 0..out_height {
            for ox in 0..out_width {
                let mut best = (f32::NEG_INFINITY, 0);
                for ky in 0..kernel {
                    for kx in 0..kernel {
                        let at = base + (oy * stride + ky) * in_width + ox * stride + kx;
                        if input[at] > best.0 {
                            best = (input[at], at);
                        }
                    }
                }
                result[best.1] += f64::from(upstream[(plane * out_height + oy) * out_width + ox]);
            }
        }
    }
    result
}

#[test]
fn max_pool_backward_is_the_adjoint_and_routes_ties_to_the_first_maximum() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let lpips = lpips_with(&context, Vec::new(), Vec::new());
    // VGG's 2/2 and AlexNet's overlapping 3/2, with sizes floor mode truncates.
    for (kernel, stride, height, width) in [(2, 2, 7, 9), (3, 2, 9, 11), (3, 2, 8, 8)] {
        let forward_shape = PoolShape {
            planes: 6,
            in_height: height,
            in_width: width,
            out_height: Step::pool_extent(kernel, stride, height).unwrap(),
            out_width: Step::pool_extent(kernel, stride, width).unwrap(),
            kernel,
            stride,
        };
        let shape = PoolShape {
            planes: 3,
            ..forward_shape
        };
        let plane = height * width;
        let out_plane = forward_shape.out_height * forward_shape.out_width;
        // Three levels only, so most windows hold ties.
        let input: Vec<f32> = seeded::uniforms(30 + kernel as u64, "pool ties", 6 * plane)
            .into_iter()
            .map(|u| (u * 3.0).floor() as f32)
            .collect();
        let upstream = values(3 * out_plane, 31);
        let calls = [
            Call::pool(forward_shape, 0).unwrap(),
            Call::pool_backward(shape, 0, 0).unwrap(),
        ];
        let lens = [6 * out_plane, 3 * plane];
        let [_, pooled, _, gradient] =
            run_calls(&context, &lpips, &calls, [&input, &upstream], lens);
        // The pool is positively homogeneous, so J x = pool(x): <pool(x), g> = <x, J^T g>.
        let (left, magnitude) = dot(&pooled[..3 * out_plane], &upstream);
        let (right, _) = dot(&input[..3 * plane], &gradient);
        assert!(
            (left - right).abs() <= 1e-6 * magnitude,
            "kernel {kernel}: {left} vs {right}"
        );
        let expected = max_pool_scatter(shape, &input, &upstream);
        for (index, (&ours, &theirs)) in gradient.iter().zip(&expected).enumerate() {
            assert!(
                (f64::from(ours) - theirs).abs() <= 1e-6,
                "kernel {kernel} element {index}: {ours} vs {theirs} (tie rule?)"
            );
        }
    }
}

/// The layer distance of one pixel in f64, `sum_c w_c (a_c / (|a| + eps) - b_c / (|b| + eps))^2`.
fn pixel_distance(a: &[f64], b: &[f64], lin: &[f32]) -> f64 {
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt() + f64::from(NORM_EPSILON);
    let (na, nb) = (norm(a), norm(b));
    a.iter()
        .zip(b)
        .zip(lin)
        .map(|((x, y), &w)| f64::from(w) * (x / na - y / nb).powi(2))
        .sum()
}

#[test]
fn distance_backward_matches_finite_differences_and_is_finite_at_zero() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let (pairs, channels, height, width) = (2, 5, 2, 3);
    let pixels = height * width;
    let mut features: Vec<f32> = values(2 * pairs * channels * pixels, 40)
        .into_iter()
        .map(|v| v.abs() * 2.0)
        .collect();
    let at =
        |image: usize, channel: usize, pixel: usize| (image * channels + channel) * pixels + pixel;
    // Pair 0 pixel 1: the first feature vector is zero (a pixel all ReLUs switched off).
    // Pair 1 pixel 2: a tiny but non-zero first vector. Pair 1 pixel 4: both vectors equal.
    for channel in 0..channels {
        features[at(0, channel, 1)] = 0.0;
        features[at(1, channel, 2)] *= 1e-20;
        features[at(3, channel, 4)] = features[at(1, channel, 4)];
    }
    let lin: Vec<f32> = seeded::uniforms(41, "lin", channels)
        .into_iter()
        .map(|u| u as f32)
        .collect();
    // The kernel accumulates: start from a known gradient.
    let prior = values(pairs * channels * pixels, 42);
    let lpips = lpips_with(&context, Vec::new(), vec![lin.clone()]);
    let size = [channels, height, width];
    let calls = [Call::distance(pairs, size, 0, 0, Slot::Gradient(0)).unwrap()];
    let [_, _, gradient, _] = run_calls(&context, &lpips, &calls, [&features, &prior], [1, 1]);
    assert!(gradient.iter().all(|g| g.is_finite()), "{gradient:?}");
    for pair in 0..pairs {
        for pixel in 0..pixels {
            let gather = |image: usize| -> Vec<f64> {
                (0..channels)
                    .map(|channel| f64::from(features[at(image, channel, pixel)]))
                    .collect()
            };
            let (first, second) = (gather(pair), gather(pairs + pair));
            let first_norm = first.iter().map(|x| x * x).sum::<f64>().sqrt();
            for channel in 0..channels {
                let index = at(pair, channel, pixel);
                let ours = f64::from(gradient[index]) - f64::from(prior[index]);
                let expected = if first_norm == 0.0 {
                    // The normaliser's derivative at 0 is identity / eps (the limit of its
                    // directional derivatives): d/df_c = 2 w_c (0 - v_c) / eps / pixels.
                    let norm1 =
                        second.iter().map(|x| x * x).sum::<f64>().sqrt() + f64::from(NORM_EPSILON);
                    2.0 * f64::from(lin[channel]) * (-second[channel] / norm1)
                        / f64::from(NORM_EPSILON)
                        / pixels as f64
                } else {
                    // Central differences in f64 with a step of 1e-7 of the normaliser's scale
                    // |f0| + eps: for the tiny vector the step exceeds |f0|, which biases the
                    // quotient by ~step / eps = 1e-7 relative; rounding of the O(1) distance
                    // adds ~1e-16 / (step * slope) ~ 1e-8 relative.
                    let step = 1e-7 * (first_norm + f64::from(NORM_EPSILON));
                    let mut plus = first.clone();
                    let mut minus = first.clone();
                    plus[channel] += step;
                    minus[channel] -= step;
                    (pixel_distance(&plus, &second, &lin) - pixel_distance(&minus, &second, &lin))
                        / (2.0 * step)
                        / pixels as f64
                };
                // The derivative scales like 1 / |f0|; the tiny vector's entries reach 1e20.
                let scale = expected.abs().max(1.0);
                let difference = (ours - expected).abs();
                // Accumulated onto the prior, so an absolute 1e-6 from its rounding too.
                assert!(
                    difference <= 1e-5 * scale + 2e-6,
                    "pair {pair} pixel {pixel} channel {channel}: {ours} vs {expected}"
                );
            }
        }
    }
}

/// A tiny trunk input: `pairs` pairs of `height x width` images in the trunk's range.
fn tiny_input(pairs: usize, height: usize, width: usize, salt: u64) -> TrunkInput {
    let batch = 2 * pairs;
    TrunkInput {
        batch,
        height,
        width,
        data: values(batch * 3 * height * width, salt)
            .into_iter()
            .map(|v| 1.5 * v)
            .collect(),
    }
}

/// Per pair, central differences in f64 of the cpu forward's total (`cpu::totals_in`, an
/// implementation independent of the gpu's) along `direction` over the first images.
fn differences_f64(weights: &LpipsWeights, input: &TrunkInput, direction: &[f64]) -> Vec<f64> {
    // In f64 a step of 1e-6 leaves round-off ~1e-10 relative and makes crossing a ReLU or
    // max-pool kink unlikely; truncation is ~1e-12.
    let step = 1e-6;
    let shape = [input.batch, input.height, input.width];
    let shifted = |sign: f64| {
        let mut moved: Vec<f64> = input.data.iter().map(|&v| f64::from(v)).collect();
        for (value, d) in moved.iter_mut().zip(direction) {
            *value += sign * step * d;
        }
        cpu::totals_in::<f64>(weights, &moved, shape).unwrap()
    };
    let (plus, minus) = (shifted(1.0), shifted(-1.0));
    plus.iter()
        .zip(&minus)
        .map(|(p, m)| (p - m) / (2.0 * step))
        .collect()
}

#[test]
fn gradient_matches_finite_differences_of_the_forward() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // Tolerance: the gpu gradient is f32 (unit round-off 6e-8) through 8-18 layers of sums
    // of up to 4608 products, ~1e-5 of the largest entry; the f64 differences are exact to
    // ~1e-9. So 1e-4 of the largest entry (of the summed magnitude for a direction).
    // The smallest images each trunk takes with five taps (VGG 16, AlexNet 31), not square.
    for (net, height, width) in [(LpipsNet::Vgg, 16, 18), (LpipsNet::Alex, 31, 35)] {
        let weights = seeded::seeded_weights(net, 5);
        let lpips = GpuLpips::new(context.clone(), &weights).unwrap();
        let input = tiny_input(2, height, width, 50);
        let (maps, gradient) = lpips.distance_gradient(&input).unwrap();
        // The forward's maps are returned unchanged.
        assert_eq!(maps, lpips.distance_maps(&input).unwrap(), "{net:?}");
        let image_values = 3 * height * width;
        assert_eq!(gradient.len(), 2 * image_values);
        assert!(gradient.iter().all(|g| g.is_finite()));
        let largest = gradient.iter().fold(0.0_f32, |m, g| m.max(g.abs()));
        assert!(largest > 0.0, "{net:?}: zero gradient");
        // A random direction over both first images at once (each pair's total depends on
        // its own first image only).
        let direction: Vec<f64> = values(2 * image_values, 51)
            .into_iter()
            .map(f64::from)
            .chain(std::iter::repeat_n(0.0, 2 * image_values))
            .collect();
        let numeric = differences_f64(&weights, &input, &direction);
        for (pair, numeric) in numeric.iter().enumerate() {
            let range = pair * image_values..(pair + 1) * image_values;
            let along: Vec<f32> = direction[range.clone()].iter().map(|&d| d as f32).collect();
            let (analytic, magnitude) = dot(&gradient[range], &along);
            eprintln!(
                "{net:?} pair {pair}: <grad, d> = {analytic:.9e}, differences {numeric:.9e}, relative to the magnitude {:.2e}",
                (analytic - numeric).abs() / magnitude
            );
            assert!(
                (analytic - numeric).abs() <= 1e-4 * magnitude,
                "{net:?} pair {pair}: <grad, d> = {analytic} vs differences {numeric}"
            );
        }
        // Single coordinates of pair 1's first image: corners, borders, interior, each channel.
        for (channel, y, x) in [
            (0, 0, 0),
            (1, height / 2, width / 3),
            (2, height - 1, width - 1),
            (0, height / 3, width - 1),
            (2, 1, width / 2),
        ] {
            let index = image_values + (channel * height + y) * width + x;
            let mut direction = vec![0.0; input.data.len()];
            direction[index] = 1.0;
            let numeric = differences_f64(&weights, &input, &direction);
            assert!(
                (f64::from(gradient[index]) - numeric[1]).abs() <= 1e-4 * f64::from(largest),
                "{net:?} channel {channel} ({y}, {x}): {} vs differences {}",
                gradient[index],
                numeric[1]
            );
            // Pair 0's total does not see pair 1's image.
            assert!(numeric[0].abs() < 1e-9, "{net:?}: {}", numeric[0]);
        }
    }
}

#[test]
fn gpu_gradient_matches_the_cpu_gradient_on_odd_shapes() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // Through the public API, so the backend dispatch and the image mapping are covered too.
    for (net, height, width) in [(LpipsNet::Vgg, 19, 23), (LpipsNet::Alex, 67, 71)] {
        let weights = seeded::seeded_weights(net, 7);
        let images: Vec<ImageF32> = (0..4)
            .map(|salt| {
                let data = values(height * width * 3, 70 + salt)
                    .into_iter()
                    .map(|v| v * 0.5 + 0.5)
                    .collect();
                ImageF32::from_f32("test", width, height, data).unwrap()
            })
            .collect();
        let pairs = [(&images[0], &images[1]), (&images[2], &images[3])];
        let cpu = Lpips::new(weights.clone(), &Backend::Cpu).unwrap();
        let gpu = Lpips::new(weights, &Backend::Gpu(context.clone())).unwrap();
        for mapping in [LpipsInput::Unit, LpipsInput::UnitAsSigned] {
            let (cpu_distances, cpu_gradients) =
                cpu.distances_with_gradient(&pairs, mapping).unwrap();
            let (gpu_distances, gpu_gradients) =
                gpu.distances_with_gradient(&pairs, mapping).unwrap();
            for (ours, theirs) in gpu_distances.iter().zip(&cpu_distances) {
                assert!(
                    (ours.total - theirs.total).abs() <= 1e-5 * theirs.total.abs(),
                    "{net:?}: {} vs {}",
                    ours.total,
                    theirs.total
                );
            }
            assert_eq!(gpu_gradients.len(), 2);
            for (pair, (ours, theirs)) in gpu_gradients.iter().zip(&cpu_gradients).enumerate() {
                assert_eq!(ours.len(), height * width * 3);
                let largest = theirs.iter().fold(0.0_f32, |m, g| m.max(g.abs()));
                assert!(largest > 0.0);
                let worst = ours
                    .iter()
                    .zip(theirs)
                    .fold(0.0_f32, |m, (a, b)| m.max((a - b).abs()));
                eprintln!(
                    "{net:?} {mapping:?} pair {pair}: largest gpu-cpu difference {:.2e} of the largest entry",
                    worst / largest
                );
                for (index, (a, b)) in ours.iter().zip(theirs).enumerate() {
                    assert!(
                        (a - b).abs() <= 1e-4 * largest,
                        "{net:?} {mapping:?} pair {pair} element {index}: gpu {a} vs cpu {b}"
                    );
                }
            }
        }
    }
}

#[test]
fn pairs_are_independent_and_two_dimensional_dispatch_agrees() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // A dispatch limit of 3 workgroups per dimension sends every kernel's grid to 2D.
    let Some(narrow) = gpu_test_context_with_dispatch_limit(3) else {
        return;
    };
    let weights = seeded::seeded_weights(LpipsNet::Alex, 6);
    let lpips = GpuLpips::new(context, &weights).unwrap();
    let narrow_lpips = GpuLpips::new(narrow, &weights).unwrap();
    let (height, width) = (33, 31);
    let input = tiny_input(2, height, width, 60);
    let (maps, gradient) = lpips.distance_gradient(&input).unwrap();
    let (narrow_maps, narrow_gradient) = narrow_lpips.distance_gradient(&input).unwrap();
    assert_eq!(maps, narrow_maps);
    assert_eq!(gradient, narrow_gradient);
    // Pair 1 alone gives the same gradient as in the batch of two.
    let image_values = 3 * height * width;
    let single = TrunkInput {
        batch: 2,
        height,
        width,
        data: [
            &input.data[image_values..2 * image_values],
            &input.data[3 * image_values..],
        ]
        .concat(),
    };
    let (_, single_gradient) = lpips.distance_gradient(&single).unwrap();
    assert_eq!(single_gradient, gradient[image_values..]);
    // Identical images: zero distance and a zero gradient, exactly on every adapter (the
    // kernels' `normalised_difference` keeps a compiler's fma contraction from leaving the
    // rounding error of one product).
    let same = TrunkInput {
        data: [&input.data[..image_values], &input.data[..image_values]].concat(),
        ..single
    };
    let (same_maps, same_gradient) = lpips.distance_gradient(&same).unwrap();
    assert!(same_maps.iter().flatten().all(|&value| value == 0.0));
    assert!(same_gradient.iter().all(|&value| value == 0.0));
    // Bad input is an error, not a panic.
    let odd = TrunkInput {
        batch: 3,
        data: vec![0.0; 3 * image_values],
        ..single
    };
    assert!(lpips.distance_gradient(&odd).is_err());
}

/// The resident LPIPS (crops cut from device images, value and gradient kept on the device)
/// against the cpu `distances_with_gradient` on the same crops: two cameras' slots in one
/// submission, images at pixel offsets of shared buffers, the gradient added (`+=`) on the
/// crop only; and a steady-state call reads nothing back and uploads only its record.
#[test]
fn resident_lpips_matches_the_cpu_on_device_crops() {
    // A context of its own, so that its traffic counters see only this test.
    let Some(context) = gpu_test_context_alone() else {
        return;
    };
    let (width, height) = (41, 37);
    let pixels = width * height;
    let image = |salt: u64| -> Vec<f32> {
        values(3 * pixels, salt)
            .into_iter()
            .map(|v| v * 0.5 + 0.5)
            .collect()
    };
    // Two renders at pixel offsets 5 and 5 + pixels of one buffer, two targets in another
    // at offsets 0 and pixels.
    let lead = 5;
    let renders = [image(90), image(91)];
    let targets = [image(92), image(93)];
    let mut render_values = vec![0.0_f32; 3 * lead];
    renders.iter().for_each(|r| render_values.extend(r));
    let target_values: Vec<f32> = targets.concat();
    let render_buffer = context.upload("renders", &render_values).unwrap();
    let target_buffer = context.upload("targets", &target_values).unwrap();
    let cut = |data: &[f32], crop: Crop| -> ImageF32 {
        let mut values = Vec::new();
        for row in crop.y0..crop.y0 + crop.height {
            values.extend_from_slice(
                &data[3 * (row * width + crop.x0)..3 * (row * width + crop.x0 + crop.width)],
            );
        }
        ImageF32::from_f32("crop", crop.width, crop.height, values).unwrap()
    };
    for (net, crops) in [
        (
            LpipsNet::Vgg,
            [
                Crop {
                    x0: 3,
                    y0: 5,
                    width: 20,
                    height: 18,
                },
                // Touching the right and bottom borders.
                Crop {
                    x0: 25,
                    y0: 21,
                    width: 16,
                    height: 16,
                },
            ],
        ),
        (
            LpipsNet::Alex,
            [
                Crop {
                    x0: 0,
                    y0: 2,
                    width: 33,
                    height: 31,
                },
                Crop {
                    x0: 8,
                    y0: 0,
                    width: 31,
                    height: 37,
                },
            ],
        ),
    ] {
        let weights = seeded::seeded_weights(net, 7);
        let cpu = Lpips::new(weights.clone(), &Backend::Cpu).unwrap();
        for mapping in [LpipsInput::Unit, LpipsInput::UnitAsSigned] {
            let gpu = GpuLpips::new(context.clone(), &weights).unwrap();
            let resident = gpu.resident(mapping, 37, 41, 2).unwrap();
            let gradient = context
                .upload("gradient", &vec![0.5_f32; render_values.len()])
                .unwrap();
            let factors = [0.3_f32, -0.7];
            let record_all = |encoder: &mut wgpu::CommandEncoder| {
                for slot in 0..2 {
                    resident
                        .record(
                            encoder,
                            slot,
                            CropPair {
                                render: DeviceImage {
                                    buffer: &render_buffer,
                                    offset: lead + slot * pixels,
                                    width,
                                    height,
                                },
                                target: DeviceImage {
                                    buffer: &target_buffer,
                                    offset: slot * pixels,
                                    width,
                                    height,
                                },
                                crop: crops[slot],
                            },
                            factors[slot],
                            &gradient,
                        )
                        .unwrap();
                }
            };
            let mut encoder = context.encoder();
            record_all(&mut encoder);
            let read = context
                .download_all::<f32>(
                    encoder,
                    &[
                        (&resident.value(0).buffer, 1),
                        (&resident.value(1).buffer, 1),
                        (&gradient.buffer, gradient.len),
                    ],
                )
                .unwrap();
            let got_gradient = &read[2];
            let mut want_gradient = vec![0.5_f32; render_values.len()];
            for slot in 0..2 {
                let crop = crops[slot];
                let (distances, gradients) = cpu
                    .distances_with_gradient(
                        &[(&cut(&renders[slot], crop), &cut(&targets[slot], crop))],
                        mapping,
                    )
                    .unwrap();
                let value = f64::from(read[slot][0]);
                assert!(
                    (value - distances[0].total).abs() <= 1e-5 * distances[0].total.abs(),
                    "{net:?} {mapping:?} slot {slot}: value {value} vs cpu {}",
                    distances[0].total
                );
                for row in 0..crop.height {
                    for col in 0..crop.width {
                        let pixel = lead + slot * pixels + (crop.y0 + row) * width + crop.x0 + col;
                        for c in 0..3 {
                            want_gradient[3 * pixel + c] +=
                                factors[slot] * gradients[0][3 * (row * crop.width + col) + c];
                        }
                    }
                }
            }
            let largest = want_gradient
                .iter()
                .fold(0.0_f32, |m, g| m.max((g - 0.5).abs()));
            assert!(largest > 0.0);
            for (index, (&ours, &theirs)) in got_gradient.iter().zip(&want_gradient).enumerate() {
                if theirs == 0.5 {
                    assert_eq!(
                        ours, 0.5,
                        "{net:?} {mapping:?} value {index} outside the crops"
                    );
                }
                assert!(
                    (ours - theirs).abs() <= 1e-4 * largest,
                    "{net:?} {mapping:?} value {index}: resident {ours} vs cpu {theirs}"
                );
            }
            // Steady state: a second submission reads nothing back and uploads only the two
            // calls' records (the 112-byte crop parameters and one 48-byte kernel block per
            // op).
            let ops = match net {
                LpipsNet::Vgg => 57,
                LpipsNet::Alex => 29,
            };
            let before = context.transfers();
            let mut encoder = context.encoder();
            record_all(&mut encoder);
            context.submit_and_wait(encoder).unwrap();
            let traffic = context.transfers().since(&before);
            assert_eq!(traffic.readbacks, 0, "{traffic:?}");
            assert_eq!(traffic.bytes_down, 0, "{traffic:?}");
            assert_eq!(
                traffic.bytes_up,
                2 * (112 + 48 * ops),
                "{net:?}: {traffic:?}"
            );
        }
    }
    // A crop larger than the workspace is an error naming both sizes.
    let weights = seeded::seeded_weights(LpipsNet::Vgg, 7);
    let gpu = GpuLpips::new(context.clone(), &weights).unwrap();
    let resident = gpu.resident(LpipsInput::Unit, 20, 20, 1).unwrap();
    let image = DeviceImage {
        buffer: &target_buffer,
        offset: 0,
        width,
        height,
    };
    let error = resident
        .record(
            &mut context.encoder(),
            0,
            CropPair {
                render: image,
                target: image,
                crop: Crop {
                    x0: 0,
                    y0: 0,
                    width: 24,
                    height: 18,
                },
            },
            1.0,
            &render_buffer,
        )
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("18 x 24") && error.contains("20 x 20"),
        "{error}"
    );
}
