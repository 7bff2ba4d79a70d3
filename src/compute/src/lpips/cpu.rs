//! The `cpu` LPIPS trunk and its gradient: convolutions as im2col + `gemm` (in row blocks, so
//! the column matrix stays small at any image size), max pools and the per-pixel layer
//! distance, with rayon over images; the backward is the exact adjoint of each step.
//!
//! Everything is generic over [`Scalar`]: production runs `f32` (the weights' precision),
//! gradient checks run the same code in `f64` (weights widened exactly).
//!
//! Backward conventions (documented because they pick among subgradients):
//! - ReLU passes the gradient only where its output is positive (PyTorch's choice at 0).
//! - A max pool routes each window's gradient to the first maximum in scan order (row by
//!   row, left to right), as PyTorch's cpu kernel does; overlapping windows (AlexNet's 3/2
//!   pools) accumulate.
//! - The unit normalisation `f / (|f| + eps)` at `f = 0` uses the limit of its directional
//!   derivatives, `1 / eps` times the identity (the `|f|` term drops out because it is
//!   multiplied by `f = 0`), instead of PyTorch's `0 * inf = NaN`. After a ReLU a zero
//!   feature vector has no active channel, so this value never reaches the input.

use std::any::Any;
use std::borrow::Cow;

use rayon::prelude::*;
use seqavatar_core::matmul::{Layout, Matrix, MatrixMut, matmul, parallelism_for};

use super::{
    ConvSpec, DistanceMaps, LpipsError, LpipsWeights, NORM_EPSILON, Step, TrunkInput, steps,
};
use crate::scalar::Scalar;

/// The largest im2col block, in values (32 MB of f32).
const COLUMN_BLOCK_VALUES: usize = 8 << 20;

/// Per-layer, per-pixel distance maps for the pairs in `input` (first half of the batch
/// against the second half).
pub fn distance_maps(
    weights: &LpipsWeights,
    input: &TrunkInput,
) -> Result<DistanceMaps, LpipsError> {
    let trunk = TrunkWeights::<f32>::new(weights);
    let shape = [input.batch, input.height, input.width];
    Ok(forward(&trunk, &input.data, shape, false)?.maps)
}

/// The distance maps and the gradient of each pair's total (the sum over layers of the
/// map's mean) with respect to the trunk input of the pair's first image, `(pairs, 3, h, w)`
/// like the first half of `input.data`. The second images are constants.
pub fn distance_gradient(
    weights: &LpipsWeights,
    input: &TrunkInput,
) -> Result<(DistanceMaps, Vec<f32>), LpipsError> {
    distance_gradient_in::<f32>(
        weights,
        &input.data,
        [input.batch, input.height, input.width],
    )
}

/// [`distance_gradient`] in any precision: `data` is the trunk input `(batch, 3, h, w)`.
pub fn distance_gradient_in<S: Scalar>(
    weights: &LpipsWeights,
    data: &[S],
    shape: [usize; 3],
) -> Result<(Vec<Vec<S>>, Vec<S>), LpipsError> {
    let trunk = TrunkWeights::<S>::new(weights);
    let pass = forward(&trunk, data, shape, true)?;
    let gradient = backward(&trunk, &pass, shape);
    Ok((pass.maps, gradient))
}

/// Per pair, the LPIPS total (sum over layers of the map's mean) in any precision: the
/// reference the finite-difference checks differentiate.
pub fn totals_in<S: Scalar>(
    weights: &LpipsWeights,
    data: &[S],
    shape: [usize; 3],
) -> Result<Vec<S>, LpipsError> {
    let trunk = TrunkWeights::<S>::new(weights);
    let pass = forward(&trunk, data, shape, false)?;
    let pairs = shape[0] / 2;
    let mut totals = vec![S::ZERO; pairs];
    for map in &pass.maps {
        let pixels = map.len() / pairs.max(1);
        for (pair, total) in totals.iter_mut().enumerate() {
            let sum: S = map[pair * pixels..(pair + 1) * pixels]
                .iter()
                .copied()
                .sum();
            *total += sum / S::from_f64(pixels as f64);
        }
    }
    Ok(totals)
}

/// `values` as `S`: borrowed when `S` is `f32`, widened otherwise.
#[allow(clippy::ptr_arg)] // `Any` needs the sized `Vec` to downcast.
fn as_scalar<S: Scalar>(values: &Vec<f32>) -> Cow<'_, [S]> {
    match (values as &dyn Any).downcast_ref::<Vec<S>>() {
        Some(same) => Cow::Borrowed(same.as_slice()),
        None => Cow::Owned(values.iter().map(|&v| S::from_f64(f64::from(v))).collect()),
    }
}

/// One convolution's parameters in precision `S`.
struct Conv<'w, S: Scalar> {
    spec: &'w ConvSpec,
    /// `(out, in * k * k)` row-major.
    weight: Cow<'w, [S]>,
    bias: Cow<'w, [S]>,
}

/// The trunk's parameters in precision `S`.
struct TrunkWeights<'w, S: Scalar> {
    net: super::LpipsNet,
    convs: Vec<Conv<'w, S>>,
    lins: Vec<Cow<'w, [S]>>,
}

impl<'w, S: Scalar> TrunkWeights<'w, S> {
    fn new(weights: &'w LpipsWeights) -> Self {
        Self {
            net: weights.net,
            convs: weights
                .convs
                .iter()
                .map(|conv| Conv {
                    spec: &conv.spec,
                    weight: as_scalar(&conv.weight),
                    bias: as_scalar(&conv.bias),
                })
                .collect(),
            lins: weights.lins.iter().map(as_scalar).collect(),
        }
    }
}

/// What the backward needs from the forward: per step, the first images' activation that
/// went into it (the stored `(pairs, c, h, w)` prefix) and its shape.
struct SavedStep<S> {
    input: Vec<S>,
    shape: [usize; 3],
    output_shape: [usize; 3],
}

struct ForwardPass<S> {
    maps: Vec<Vec<S>>,
    /// One entry per trunk step (empty unless the forward kept them).
    saved: Vec<SavedStep<S>>,
    /// The second images' unit-normalised features at each tap, `(pairs, c, pixels)`.
    targets: Vec<Vec<S>>,
}

fn forward<S: Scalar>(
    trunk: &TrunkWeights<'_, S>,
    data: &[S],
    [images, input_height, input_width]: [usize; 3],
    keep: bool,
) -> Result<ForwardPass<S>, LpipsError> {
    if images == 0
        || !images.is_multiple_of(2)
        || data.len() != images * 3 * input_height * input_width
    {
        return Err(LpipsError::Input {
            message: format!(
                "trunk input of {} values does not hold {images} (an even, non-zero number of) 3 x {input_height} x {input_width} images",
                data.len()
            ),
        });
    }
    let pairs = images / 2;
    let mut activation = data.to_vec();
    let (mut channels, mut height, mut width) = (3, input_height, input_width);
    let mut convs = trunk.convs.iter();
    let mut pass = ForwardPass {
        maps: Vec::with_capacity(5),
        saved: Vec::new(),
        targets: Vec::new(),
    };
    let too_small = |what: &str| LpipsError::Input {
        message: format!(
            "a {input_height} x {input_width} image is too small for the {} trunk ({what})",
            trunk.net.name()
        ),
    };
    for step in steps(trunk.net) {
        let extents = |step: &Step| match (step.extent(height), step.extent(width)) {
            (Some(out_height), Some(out_width)) => Ok([out_height, out_width]),
            _ => Err(too_small(step.label())),
        };
        let next = match &step {
            Step::Conv(spec) => {
                let conv = convs
                    .next()
                    .ok_or_else(|| too_small("missing convolution weights"))?;
                let [out_height, out_width] = extents(&step)?;
                let output = conv_relu(
                    &activation,
                    images,
                    [channels, height, width],
                    conv,
                    [out_height, out_width],
                );
                Some((output, [spec.out_channels, out_height, out_width]))
            }
            Step::MaxPool { kernel, stride } => {
                let [out_height, out_width] = extents(&step)?;
                let output = max_pool(
                    &activation,
                    images * channels,
                    [height, width],
                    *kernel,
                    *stride,
                    [out_height, out_width],
                );
                Some((output, [channels, out_height, out_width]))
            }
            Step::Tap => {
                let layer = pass.maps.len();
                let pixels = height * width;
                pass.maps.push(layer_distance_map(
                    &activation,
                    pairs,
                    channels,
                    pixels,
                    &trunk.lins[layer],
                ));
                if keep {
                    let second = &activation[pairs * channels * pixels..];
                    pass.targets
                        .push(unit_normalised(second, pairs, channels, pixels));
                }
                None
            }
        };
        let shape = [channels, height, width];
        let (mut input, output_shape) = match next {
            Some((output, output_shape)) => {
                (std::mem::replace(&mut activation, output), output_shape)
            }
            None => (Vec::new(), shape),
        };
        if keep {
            // The backward needs only the first images' activations.
            input.truncate(pairs * channels * height * width);
            pass.saved.push(SavedStep {
                input,
                shape,
                output_shape,
            });
        }
        [channels, height, width] = output_shape;
    }
    if keep {
        // The last tap's features: the final activation.
        activation.truncate(pairs * channels * height * width);
        pass.saved.push(SavedStep {
            input: activation,
            shape: [channels, height, width],
            output_shape: [channels, height, width],
        });
    }
    Ok(pass)
}

/// The backward of [`forward`] for the first images: d(sum of layer means)/d(trunk input).
fn backward<S: Scalar>(
    trunk: &TrunkWeights<'_, S>,
    pass: &ForwardPass<S>,
    [images, height, width]: [usize; 3],
) -> Vec<S> {
    let pairs = images / 2;
    let step_list = steps(trunk.net);
    // The activation after step `i` is the input saved by the next step that is not a tap
    // (taps save nothing: they do not change the activation), or the final activation saved
    // after the last step (`saved[steps]`).
    let features_after = |index: usize| -> &[S] {
        let next = (index + 1..step_list.len())
            .find(|&later| !matches!(step_list[later], Step::Tap))
            .unwrap_or(step_list.len());
        &pass.saved[next].input
    };
    let mut convs_left = trunk.convs.len();
    let mut layer = pass.maps.len();
    // Gradient with respect to the current activation, `(pairs, c, h, w)`; starts at the
    // last tap's features.
    let last_shape = pass.saved[step_list.len()].shape;
    let mut gradient = vec![S::ZERO; pairs * last_shape.iter().product::<usize>()];
    for (index, step) in step_list.iter().enumerate().rev() {
        let saved = &pass.saved[index];
        match step {
            Step::Tap => {
                layer -= 1;
                let [channels, tap_height, tap_width] = saved.shape;
                let pixels = tap_height * tap_width;
                layer_distance_backward(
                    features_after(index),
                    &pass.targets[layer],
                    (pairs, channels, pixels),
                    &trunk.lins[layer],
                    S::ONE / S::from_f64(pixels as f64),
                    &mut gradient,
                );
            }
            Step::Conv(_) => {
                convs_left -= 1;
                let conv = &trunk.convs[convs_left];
                let output = features_after(index);
                // ReLU: only positive outputs pass the gradient.
                for (g, &out) in gradient.iter_mut().zip(output) {
                    if out <= S::ZERO {
                        *g = S::ZERO;
                    }
                }
                gradient = conv_data_backward(
                    &gradient,
                    pairs,
                    saved.shape,
                    conv,
                    [saved.output_shape[1], saved.output_shape[2]],
                );
            }
            Step::MaxPool { kernel, stride } => {
                let [channels, in_height, in_width] = saved.shape;
                gradient = max_pool_backward(
                    &saved.input,
                    &gradient,
                    pairs * channels,
                    [in_height, in_width],
                    *kernel,
                    *stride,
                    [saved.output_shape[1], saved.output_shape[2]],
                );
            }
        }
    }
    debug_assert_eq!(gradient.len(), pairs * 3 * height * width);
    gradient
}

/// Rows of output per im2col block so the column matrix stays under the block budget.
fn rows_per_block(depth: usize, out_width: usize, out_height: usize) -> usize {
    (COLUMN_BLOCK_VALUES / (depth * out_width).max(1)).clamp(1, out_height.max(1))
}

/// `relu(conv2d(input, weight) + bias)` for every image; `input` is `(images, c, h, w)`.
fn conv_relu<S: Scalar>(
    input: &[S],
    images: usize,
    [in_channels, height, width]: [usize; 3],
    conv: &Conv<'_, S>,
    [out_height, out_width]: [usize; 2],
) -> Vec<S> {
    let spec = conv.spec;
    let kernel = spec.kernel;
    let depth = in_channels * kernel * kernel;
    let out_pixels = out_height * out_width;
    let out_channels = spec.out_channels;
    let mut output = vec![S::ZERO; images * out_channels * out_pixels];
    let rows_per_block = rows_per_block(depth, out_width, out_height);
    output
        .par_chunks_mut(out_channels * out_pixels)
        .enumerate()
        .for_each(|(image, out)| {
            let source = &input
                [image * in_channels * height * width..(image + 1) * in_channels * height * width];
            let mut columns = vec![S::ZERO; depth * rows_per_block * out_width];
            for row_start in (0..out_height).step_by(rows_per_block) {
                let rows = rows_per_block.min(out_height - row_start);
                let block = rows * out_width;
                // im2col: columns[(c, ky, kx)][(row, col)] is the input under that tap.
                columns[..depth * block].fill(S::ZERO);
                let rows = (row_start, rows, out_width);
                im2col(spec, [in_channels, height, width], rows, |at, pixel| {
                    columns[at] = source[pixel];
                });
                // out[:, block] (out x block) = W (out x depth) * columns (depth x block).
                let offset = row_start * out_width;
                matmul(
                    MatrixMut::new(
                        &mut *out,
                        Layout::strided(out_channels, block, out_pixels, 1).at(offset),
                    ),
                    Matrix::new(&conv.weight, Layout::row_major(out_channels, depth)),
                    Matrix::new(&columns, Layout::row_major(depth, block)),
                    false,
                    parallelism_for(out_channels * block * depth),
                );
            }
            for (channel, plane) in out.chunks_exact_mut(out_pixels).enumerate() {
                let bias = conv.bias[channel];
                for value in plane {
                    *value = Scalar::max(*value + bias, S::ZERO);
                }
            }
        });
    output
}

/// The data gradient of a convolution (weights frozen): `col2im(W^T d_output)` per image,
/// in the forward's row blocks. `d_output` is `(images, out, oh, ow)` (already through the
/// ReLU), the result `(images, c, h, w)`.
fn conv_data_backward<S: Scalar>(
    d_output: &[S],
    images: usize,
    [in_channels, height, width]: [usize; 3],
    conv: &Conv<'_, S>,
    [out_height, out_width]: [usize; 2],
) -> Vec<S> {
    let spec = conv.spec;
    let kernel = spec.kernel;
    let depth = in_channels * kernel * kernel;
    let out_pixels = out_height * out_width;
    let out_channels = spec.out_channels;
    let mut d_input = vec![S::ZERO; images * in_channels * height * width];
    let rows_per_block = rows_per_block(depth, out_width, out_height);
    d_input
        .par_chunks_mut(in_channels * height * width)
        .enumerate()
        .for_each(|(image, d_in)| {
            let upstream =
                &d_output[image * out_channels * out_pixels..][..out_channels * out_pixels];
            let mut d_columns = vec![S::ZERO; depth * rows_per_block * out_width];
            for row_start in (0..out_height).step_by(rows_per_block) {
                let rows = rows_per_block.min(out_height - row_start);
                let block = rows * out_width;
                let offset = row_start * out_width;
                // d_columns (depth x block) = W^T (depth x out) * d_out[:, block] (out x block).
                matmul(
                    MatrixMut::new(&mut d_columns, Layout::row_major(depth, block)),
                    Matrix::new(&conv.weight, Layout::strided(depth, out_channels, 1, depth)),
                    Matrix::new(
                        upstream,
                        Layout::strided(out_channels, block, out_pixels, 1).at(offset),
                    ),
                    false,
                    parallelism_for(out_channels * block * depth),
                );
                // col2im: every tap adds its column back onto the input pixel it read.
                let rows = (row_start, rows, out_width);
                im2col(spec, [in_channels, height, width], rows, |at, pixel| {
                    d_in[pixel] += d_columns[at];
                });
            }
        });
    d_input
}

/// Calls `f(at, pixel)` for every im2col entry of output rows `row_start..row_start + rows`
/// (rows of `out_width`) that reads an input pixel (padding reads none), in the order
/// `(channel, ky, kx)`, row, column: `at` indexes the `(depth, rows * out_width)` column
/// block, `pixel` the `(c, h, w)` image.
fn im2col(
    spec: &ConvSpec,
    [in_channels, height, width]: [usize; 3],
    (row_start, rows, out_width): (usize, usize, usize),
    mut f: impl FnMut(usize, usize),
) {
    let (kernel, block) = (spec.kernel, rows * out_width);
    for channel in 0..in_channels {
        for ky in 0..kernel {
            for kx in 0..kernel {
                let tap = (channel * kernel + ky) * kernel + kx;
                for row in 0..rows {
                    let y = ((row_start + row) * spec.stride + ky) as isize - spec.padding as isize;
                    if y < 0 || y as usize >= height {
                        continue;
                    }
                    for col in 0..out_width {
                        let x = (col * spec.stride + kx) as isize - spec.padding as isize;
                        if x >= 0 && (x as usize) < width {
                            let pixel = (channel * height + y as usize) * width + x as usize;
                            f(tap * block + row * out_width + col, pixel);
                        }
                    }
                }
            }
        }
    }
}

/// Max pool without padding (floor mode) of `planes` planes of `height x width`.
pub(in crate::lpips) fn max_pool<S: Scalar>(
    input: &[S],
    planes: usize,
    [height, width]: [usize; 2],
    kernel: usize,
    stride: usize,
    [out_height, out_width]: [usize; 2],
) -> Vec<S> {
    let mut output = vec![S::ZERO; planes * out_height * out_width];
    output
        .par_chunks_mut(out_height * out_width)
        .enumerate()
        .for_each(|(plane, out)| {
            let source = &input[plane * height * width..(plane + 1) * height * width];
            for y in 0..out_height {
                for x in 0..out_width {
                    let at = window_argmax(source, width, kernel, stride, y, x);
                    out[y * out_width + x] = source[at];
                }
            }
        });
    output
}

/// Index in `plane` of the first maximum (scan order: row by row, left to right) of the
/// pooling window of output pixel `(y, x)`.
fn window_argmax<S: Scalar>(
    plane: &[S],
    width: usize,
    kernel: usize,
    stride: usize,
    y: usize,
    x: usize,
) -> usize {
    let mut best = (y * stride) * width + x * stride;
    for ky in 0..kernel {
        for kx in 0..kernel {
            let at = (y * stride + ky) * width + x * stride + kx;
            if plane[at] > plane[best] {
                best = at;
            }
        }
    }
    best
}

/// Routes each pooled gradient to its window's first maximum (windows may overlap).
pub(in crate::lpips) fn max_pool_backward<S: Scalar>(
    input: &[S],
    d_output: &[S],
    planes: usize,
    [height, width]: [usize; 2],
    kernel: usize,
    stride: usize,
    [out_height, out_width]: [usize; 2],
) -> Vec<S> {
    let mut d_input = vec![S::ZERO; planes * height * width];
    d_input
        .par_chunks_mut(height * width)
        .enumerate()
        .for_each(|(plane, d_in)| {
            let source = &input[plane * height * width..(plane + 1) * height * width];
            let upstream = &d_output[plane * out_height * out_width..][..out_height * out_width];
            for y in 0..out_height {
                for x in 0..out_width {
                    let at = window_argmax(source, width, kernel, stride, y, x);
                    d_in[at] += upstream[y * out_width + x];
                }
            }
        });
    d_input
}

/// `1 / (|f| + eps)` of one pixel's channel vector (`channels` values `pixels` apart).
fn inverse_norm<S: Scalar>(features: &[S], channels: usize, pixels: usize, pixel: usize) -> S {
    let mut squares = S::ZERO;
    for channel in 0..channels {
        let value = features[channel * pixels + pixel];
        squares += value * value;
    }
    S::ONE / (squares.sqrt() + S::from_f64(f64::from(NORM_EPSILON)))
}

/// Unit-normalised features `f / (|f| + eps)` of `images` images `(c, pixels)`.
fn unit_normalised<S: Scalar>(
    features: &[S],
    images: usize,
    channels: usize,
    pixels: usize,
) -> Vec<S> {
    let mut output = features.to_vec();
    output.par_chunks_mut(channels * pixels).for_each(|image| {
        for pixel in 0..pixels {
            let scale = inverse_norm(image, channels, pixels, pixel);
            for channel in 0..channels {
                image[channel * pixels + pixel] *= scale;
            }
        }
    });
    debug_assert_eq!(output.len(), images * channels * pixels);
    output
}

/// Per pair and pixel: `sum_c lin_c (f0_c / (|f0| + eps) - f1_c / (|f1| + eps))^2`, where
/// pair `p` compares batch image `p` with image `pairs + p`. Output `(pairs, pixels)`.
pub(in crate::lpips) fn layer_distance_map<S: Scalar>(
    features: &[S],
    pairs: usize,
    channels: usize,
    pixels: usize,
    lin: &[S],
) -> Vec<S> {
    let mut map = vec![S::ZERO; pairs * pixels];
    map.par_chunks_mut(pixels)
        .enumerate()
        .for_each(|(pair, out)| {
            let first = &features[pair * channels * pixels..(pair + 1) * channels * pixels];
            let second = &features
                [(pairs + pair) * channels * pixels..(pairs + pair + 1) * channels * pixels];
            for (pixel, value) in out.iter_mut().enumerate() {
                let scale0 = inverse_norm(first, channels, pixels, pixel);
                let scale1 = inverse_norm(second, channels, pixels, pixel);
                let mut sum = S::ZERO;
                for (channel, &weight) in lin.iter().enumerate() {
                    let difference = first[channel * pixels + pixel] * scale0
                        - second[channel * pixels + pixel] * scale1;
                    sum += weight * difference * difference;
                }
                *value = sum;
            }
        });
    map
}

/// Adds `pixel_weight x d(map)/d(first features)` to `gradient` (both `(pairs, c, pixels)`,
/// `dims = (pairs, c, pixels)`).
///
/// With `n = |a|`, `s = 1 / (n + eps)`, `u = s a`, `g_c = 2 lin_c (u_c - b_c)` (`b` the
/// target's unit features): `d/da_k = s g_k - s^2 (a_k / n) sum_c g_c a_c`; at `n = 0` the
/// second term is dropped (see the module docs).
fn layer_distance_backward<S: Scalar>(
    first: &[S],
    target_units: &[S],
    (pairs, channels, pixels): (usize, usize, usize),
    lin: &[S],
    pixel_weight: S,
    gradient: &mut [S],
) {
    let two = S::from_f64(2.0);
    gradient
        .par_chunks_mut(channels * pixels)
        .enumerate()
        .take(pairs)
        .for_each(|(pair, grad)| {
            let a = &first[pair * channels * pixels..(pair + 1) * channels * pixels];
            let b = &target_units[pair * channels * pixels..(pair + 1) * channels * pixels];
            let mut g = vec![S::ZERO; channels];
            for pixel in 0..pixels {
                let mut squares = S::ZERO;
                for channel in 0..channels {
                    squares += a[channel * pixels + pixel] * a[channel * pixels + pixel];
                }
                let norm = squares.sqrt();
                let scale = S::ONE / (norm + S::from_f64(f64::from(NORM_EPSILON)));
                let mut projection = S::ZERO;
                for channel in 0..channels {
                    let value = a[channel * pixels + pixel];
                    g[channel] = pixel_weight
                        * two
                        * lin[channel]
                        * (value * scale - b[channel * pixels + pixel]);
                    projection += g[channel] * value;
                }
                let radial = if norm > S::ZERO {
                    scale * scale * projection / norm
                } else {
                    S::ZERO
                };
                for channel in 0..channels {
                    grad[channel * pixels + pixel] +=
                        scale * g[channel] - radial * a[channel * pixels + pixel];
                }
            }
        });
}

/// Test access to the single steps in `f32` (the forward's exact code).
#[cfg(test)]
pub(super) mod ops {
    use super::*;
    use crate::lpips::ConvWeights;

    pub fn conv2d_relu(
        input: &[f32],
        images: usize,
        shape: [usize; 3],
        conv: &ConvWeights,
        out: [usize; 2],
    ) -> Vec<f32> {
        let conv = Conv {
            spec: &conv.spec,
            weight: Cow::Borrowed(&conv.weight),
            bias: Cow::Borrowed(&conv.bias),
        };
        conv_relu(input, images, shape, &conv, out)
    }

    pub fn conv_data_backward_f64(
        d_output: &[f64],
        images: usize,
        shape: [usize; 3],
        conv: &ConvWeights,
        out: [usize; 2],
    ) -> Vec<f64> {
        let conv = Conv {
            spec: &conv.spec,
            weight: as_scalar(&conv.weight),
            bias: as_scalar(&conv.bias),
        };
        conv_data_backward(d_output, images, shape, &conv, out)
    }

    /// The gradient of one pair's summed per-pixel map with respect to the first image's
    /// features (`features` holds both images).
    pub fn layer_distance_gradient(
        features: &[f64],
        channels: usize,
        pixels: usize,
        lin: &[f32],
    ) -> Vec<f64> {
        let lin: Vec<f64> = lin.iter().map(|&v| f64::from(v)).collect();
        let targets = unit_normalised(&features[channels * pixels..], 1, channels, pixels);
        let mut gradient = vec![0.0; channels * pixels];
        layer_distance_backward(
            &features[..channels * pixels],
            &targets,
            (1, channels, pixels),
            &lin,
            1.0,
            &mut gradient,
        );
        gradient
    }

    pub(in crate::lpips) use super::{layer_distance_map, max_pool, max_pool_backward};
}
