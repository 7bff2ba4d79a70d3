//! The `cpu` LPIPS trunk: convolutions as im2col + `gemm` (in row blocks, so the column
//! matrix stays small at any image size), max pools and the per-pixel layer distance, with
//! rayon over images.

use rayon::prelude::*;

use super::{
    ConvWeights, DistanceMaps, LpipsError, LpipsWeights, NORM_EPSILON, Step, TrunkInput, steps,
};

/// The largest im2col block, in f32 values (32 MB).
const COLUMN_BLOCK_VALUES: usize = 8 << 20;

/// Per-layer, per-pixel distance maps for the pairs in `input` (first half of the batch
/// against the second half).
pub fn distance_maps(
    weights: &LpipsWeights,
    input: &TrunkInput,
) -> Result<DistanceMaps, LpipsError> {
    let images = input.batch;
    if !images.is_multiple_of(2) || input.data.len() != images * 3 * input.height * input.width {
        return Err(LpipsError::Input {
            message: format!(
                "trunk input of {} values does not hold {images} (an even number of) 3 x {} x {} images",
                input.data.len(),
                input.height,
                input.width
            ),
        });
    }
    let pairs = images / 2;
    let mut activation = input.data.clone();
    let (mut channels, mut height, mut width) = (3, input.height, input.width);
    let mut convs = weights.convs.iter();
    let mut maps = Vec::with_capacity(5);
    let too_small = |what: &str| LpipsError::Input {
        message: format!(
            "a {} x {} image is too small for the {} trunk ({what})",
            input.height,
            input.width,
            weights.net.name()
        ),
    };
    for step in steps(weights.net) {
        match step {
            Step::Conv(spec) => {
                let conv = convs
                    .next()
                    .ok_or_else(|| too_small("missing convolution weights"))?;
                let out_height = spec
                    .output_extent(height)
                    .ok_or_else(|| too_small(&spec.name))?;
                let out_width = spec
                    .output_extent(width)
                    .ok_or_else(|| too_small(&spec.name))?;
                activation = conv2d_relu(
                    &activation,
                    images,
                    [channels, height, width],
                    conv,
                    [out_height, out_width],
                );
                (channels, height, width) = (spec.out_channels, out_height, out_width);
            }
            Step::MaxPool { kernel, stride } => {
                let out_height = Step::pool_extent(kernel, stride, height)
                    .ok_or_else(|| too_small("max pool"))?;
                let out_width = Step::pool_extent(kernel, stride, width)
                    .ok_or_else(|| too_small("max pool"))?;
                activation = max_pool(
                    &activation,
                    images * channels,
                    [height, width],
                    kernel,
                    stride,
                    [out_height, out_width],
                );
                (height, width) = (out_height, out_width);
            }
            Step::Tap => {
                let lin = &weights.lins[maps.len()];
                maps.push(layer_distance_map(
                    &activation,
                    pairs,
                    channels,
                    height * width,
                    lin,
                ));
            }
        }
    }
    Ok(maps)
}

/// `relu(conv2d(input, weight) + bias)` for every image; `input` is `(images, c, h, w)`.
pub fn conv2d_relu(
    input: &[f32],
    images: usize,
    [in_channels, height, width]: [usize; 3],
    conv: &ConvWeights,
    [out_height, out_width]: [usize; 2],
) -> Vec<f32> {
    let spec = &conv.spec;
    let kernel = spec.kernel;
    let depth = in_channels * kernel * kernel;
    let out_pixels = out_height * out_width;
    let out_channels = spec.out_channels;
    let mut output = vec![0.0_f32; images * out_channels * out_pixels];
    let rows_per_block =
        (COLUMN_BLOCK_VALUES / (depth * out_width).max(1)).clamp(1, out_height.max(1));
    let threads = rayon::current_num_threads();
    output
        .par_chunks_mut(out_channels * out_pixels)
        .enumerate()
        .for_each(|(image, out)| {
            let source = &input
                [image * in_channels * height * width..(image + 1) * in_channels * height * width];
            let mut columns = vec![0.0_f32; depth * rows_per_block * out_width];
            for row_start in (0..out_height).step_by(rows_per_block) {
                let rows = rows_per_block.min(out_height - row_start);
                let block = rows * out_width;
                // im2col: columns[(c, ky, kx)][(row, col)] is the input under that tap.
                for channel in 0..in_channels {
                    for ky in 0..kernel {
                        for kx in 0..kernel {
                            let tap = (channel * kernel + ky) * kernel + kx;
                            let destination = &mut columns[tap * block..(tap + 1) * block];
                            for row in 0..rows {
                                let y = ((row_start + row) * spec.stride + ky) as isize
                                    - spec.padding as isize;
                                for col in 0..out_width {
                                    let x =
                                        (col * spec.stride + kx) as isize - spec.padding as isize;
                                    destination[row * out_width + col] = if y >= 0
                                        && (y as usize) < height
                                        && x >= 0
                                        && (x as usize) < width
                                    {
                                        source[(channel * height + y as usize) * width + x as usize]
                                    } else {
                                        0.0
                                    };
                                }
                            }
                        }
                    }
                }
                let offset = row_start * out_width;
                assert!(
                    conv.weight.len() == out_channels * depth
                        && columns.len() >= depth * block
                        && out.len() >= (out_channels - 1) * out_pixels + offset + block,
                    "conv2d_relu: operand sizes (internal invariant)"
                );
                // SAFETY: the assertion above shows every element gemm reads or writes lies
                // inside `conv.weight`, `columns` and `out`; `out` is uniquely borrowed.
                unsafe {
                    gemm::gemm(
                        out_channels,
                        block,
                        depth,
                        out.as_mut_ptr().add(offset),
                        1,
                        out_pixels as isize,
                        false,
                        conv.weight.as_ptr(),
                        1,
                        depth as isize,
                        columns.as_ptr(),
                        1,
                        block as isize,
                        0.0,
                        1.0,
                        false,
                        false,
                        false,
                        if threads > 1 && out_channels * block * depth > 1 << 20 {
                            gemm::Parallelism::Rayon(threads)
                        } else {
                            gemm::Parallelism::None
                        },
                    );
                }
            }
            for (channel, plane) in out.chunks_exact_mut(out_pixels).enumerate() {
                let bias = conv.bias[channel];
                for value in plane {
                    *value = (*value + bias).max(0.0);
                }
            }
        });
    output
}

/// Max pool without padding (floor mode) of `planes` planes of `height x width`.
pub fn max_pool(
    input: &[f32],
    planes: usize,
    [height, width]: [usize; 2],
    kernel: usize,
    stride: usize,
    [out_height, out_width]: [usize; 2],
) -> Vec<f32> {
    let mut output = vec![0.0_f32; planes * out_height * out_width];
    output
        .par_chunks_mut(out_height * out_width)
        .enumerate()
        .for_each(|(plane, out)| {
            let source = &input[plane * height * width..(plane + 1) * height * width];
            for y in 0..out_height {
                for x in 0..out_width {
                    let mut best = f32::NEG_INFINITY;
                    for ky in 0..kernel {
                        for kx in 0..kernel {
                            best = best.max(source[(y * stride + ky) * width + x * stride + kx]);
                        }
                    }
                    out[y * out_width + x] = best;
                }
            }
        });
    output
}

/// Per pair and pixel: `sum_c lin_c (f0_c / (|f0| + eps) - f1_c / (|f1| + eps))^2`, where
/// pair `p` compares batch image `p` with image `pairs + p`. Output `(pairs, pixels)`.
pub fn layer_distance_map(
    features: &[f32],
    pairs: usize,
    channels: usize,
    pixels: usize,
    lin: &[f32],
) -> Vec<f32> {
    let mut map = vec![0.0_f32; pairs * pixels];
    map.par_chunks_mut(pixels)
        .enumerate()
        .for_each(|(pair, out)| {
            let first = &features[pair * channels * pixels..(pair + 1) * channels * pixels];
            let second = &features
                [(pairs + pair) * channels * pixels..(pairs + pair + 1) * channels * pixels];
            for (pixel, value) in out.iter_mut().enumerate() {
                let (mut norm0, mut norm1) = (0.0_f32, 0.0_f32);
                for channel in 0..channels {
                    norm0 += first[channel * pixels + pixel] * first[channel * pixels + pixel];
                    norm1 += second[channel * pixels + pixel] * second[channel * pixels + pixel];
                }
                let (scale0, scale1) = (
                    1.0 / (norm0.sqrt() + NORM_EPSILON),
                    1.0 / (norm1.sqrt() + NORM_EPSILON),
                );
                let mut sum = 0.0_f32;
                for (channel, weight) in lin.iter().enumerate() {
                    let difference = first[channel * pixels + pixel] * scale0
                        - second[channel * pixels + pixel] * scale1;
                    sum += weight * difference * difference;
                }
                *value = sum;
            }
        });
    map
}
