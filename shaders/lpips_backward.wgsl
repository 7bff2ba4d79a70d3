// The LPIPS image gradient on the gpu (src/compute/src/lpips/gpu.rs): the adjoints of the
// kernels of lpips_forward.wgsl, run in reverse trunk order for the FIRST image of every pair
// (the second image is a constant). Gradient tensors are NCHW f32 holding only those `pairs`
// images; the forward activations hold all `2 * pairs` images, first images first, so a
// first image has the same offset in both.
//
// Every kernel gathers (one thread per value it writes), so no atomics are needed. Every
// entry point runs 64 threads per workgroup over a linear index
// `(workgroup.x + workgroup.y * groups.x) * 64 + local`, since GpuContext::dispatch lays
// large dispatches out in 2D; threads past `params.total` return.

//#include "lpips_types.wgsl"

@group(0) @binding(0) var<uniform> params: LpipsParams;
// What the forward computed: tapped features, ReLU outputs or max-pool inputs.
@group(0) @binding(1) var<storage, read> forward_values: array<f32>;
// The lin layer or the convolution weights `(out, in, k, k)` row-major.
@group(0) @binding(2) var<storage, read> weight: array<f32>;
// The gradient arriving from the layer after this one.
@group(0) @binding(3) var<storage, read> upstream: array<f32>;
// The gradient this kernel produces (or accumulates into).
@group(0) @binding(4) var<storage, read_write> gradient: array<f32>;

const WORKGROUP: u32 = 64u;
// Input channels per convolution-gradient thread: one upstream load feeds four accumulators.
const CHANNELS_PER_THREAD: u32 = 4u;
// normalize_tensor's epsilon, added to the channel norm (the forward's 1e-10).
const NORM_EPSILON: f32 = 1e-10;

//#include "linear_index.wgsl"

// One thread: one pixel of one pair (`images` counts pairs, `in_channels` the channels,
// `in_height * in_width` the pixels). Adds to `gradient` (pairs, C, pixels) the derivative of
// the layer's spatial mean of sum_c w_c (u_c - v_c)^2, u = f0 / (|f0| + eps),
// v = f1 / (|f1| + eps), with respect to f0:
//   g_c = 2 w_c (u_c - v_c) / pixels,   d/df0_k = s0 (g_k - u_k (g . f0) / |f0|),
// s0 = 1 / (|f0| + eps). At f0 = 0 the normaliser's derivative is s0 times the identity (the
// second term vanishes with g . f0), so the gradient stays finite.
@compute @workgroup_size(64)
fn distance_backward(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    if (index >= params.total) {
        return;
    }
    let pixels = params.in_height * params.in_width;
    let pair = index / pixels;
    let pixel = index % pixels;
    let first = pair * params.in_channels * pixels + pixel;
    let second = (params.images + pair) * params.in_channels * pixels + pixel;
    var norm0 = 0.0;
    var norm1 = 0.0;
    for (var channel = 0u; channel < params.in_channels; channel++) {
        let a = forward_values[first + channel * pixels];
        let b = forward_values[second + channel * pixels];
        norm0 += a * a;
        norm1 += b * b;
    }
    let length0 = sqrt(norm0);
    let scale0 = 1.0 / (length0 + NORM_EPSILON);
    let scale1 = 1.0 / (sqrt(norm1) + NORM_EPSILON);
    let mean = 1.0 / f32(pixels);
    var dot = 0.0;
    for (var channel = 0u; channel < params.in_channels; channel++) {
        let a = forward_values[first + channel * pixels];
        let b = forward_values[second + channel * pixels];
        let g = 2.0 * weight[channel] * normalised_difference(a, scale0, b, scale1) * mean;
        dot += g * a;
    }
    // |dot / length0| <= |g|, so the product below cannot overflow even as length0 -> 0.
    var projection = 0.0;
    if (length0 > 0.0) {
        projection = dot / length0;
    }
    for (var channel = 0u; channel < params.in_channels; channel++) {
        let a = forward_values[first + channel * pixels];
        let b = forward_values[second + channel * pixels];
        let u = a * scale0;
        let g = 2.0 * weight[channel] * normalised_difference(a, scale0, b, scale1) * mean;
        gradient[first + channel * pixels] += scale0 * (g - u * projection);
    }
}

// One thread: one value of the first images' gradient (`total` = pairs * C * H * W). Zeroes
// the gradient where the forward's ReLU output is not positive (PyTorch's rule: the ReLU
// passes the gradient where its output is > 0).
@compute @workgroup_size(64)
fn relu_mask(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    if (index >= params.total) {
        return;
    }
    if (!(forward_values[index] > 0.0)) {
        gradient[index] = 0.0;
    }
}

// One thread: input channels 4g..4g+3 of one input pixel of one image (pixel index fastest),
// the transposed convolution as a gather:
//   gradient[n, ci, y, x] = sum_{co, ky, kx} weight[co, ci, ky, kx] upstream[n, co, oy, ox]
// over the output pixels with oy * stride + ky - padding = y (and the same along x) inside
// the output. `in_*` describe the convolution's input (this gradient), `out_*` its output.
@compute @workgroup_size(64)
fn conv2d_backward_data(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    if (index >= params.total) {
        return;
    }
    let in_pixels = params.in_height * params.in_width;
    let channel_groups = (params.in_channels + CHANNELS_PER_THREAD - 1u) / CHANNELS_PER_THREAD;
    let pixel = index % in_pixels;
    let rest = index / in_pixels;
    let group = rest % channel_groups;
    let image = rest / channel_groups;
    let y = i32(pixel / params.in_width);
    let x = i32(pixel % params.in_width);
    let first_channel = group * CHANNELS_PER_THREAD;
    let kernel_area = params.kernel * params.kernel;
    let weight_stride = params.in_channels * kernel_area;
    // Channels past the end read channel 0's weights (harmless) and are not written.
    var channel_offsets: array<u32, 4>;
    for (var j = 0u; j < CHANNELS_PER_THREAD; j++) {
        let channel = select(0u, first_channel + j, first_channel + j < params.in_channels);
        channel_offsets[j] = channel * kernel_area;
    }
    let out_pixels = params.out_height * params.out_width;
    let image_base = image * params.out_channels * out_pixels;
    let stride = i32(params.stride);
    let padding = i32(params.padding);
    var sums = vec4<f32>(0.0);
    // Only taps with ky = (y + padding) mod stride (mod stride) land on an output row.
    for (var ky = u32((y + padding) % stride); ky < params.kernel; ky += params.stride) {
        let row_scaled = y + padding - i32(ky);
        if (row_scaled < 0) {
            break;
        }
        let out_y = row_scaled / stride;
        if (out_y >= i32(params.out_height)) {
            continue;
        }
        for (var kx = u32((x + padding) % stride); kx < params.kernel; kx += params.stride) {
            let col_scaled = x + padding - i32(kx);
            if (col_scaled < 0) {
                break;
            }
            let out_x = col_scaled / stride;
            if (out_x >= i32(params.out_width)) {
                continue;
            }
            var source = image_base + u32(out_y) * params.out_width + u32(out_x);
            var weight_offset = ky * params.kernel + kx;
            for (var channel = 0u; channel < params.out_channels; channel++) {
                let value = upstream[source];
                sums += value * vec4<f32>(
                    weight[channel_offsets[0] + weight_offset],
                    weight[channel_offsets[1] + weight_offset],
                    weight[channel_offsets[2] + weight_offset],
                    weight[channel_offsets[3] + weight_offset],
                );
                source += out_pixels;
                weight_offset += weight_stride;
            }
        }
    }
    for (var j = 0u; j < CHANNELS_PER_THREAD; j++) {
        let channel = first_channel + j;
        if (channel < params.in_channels) {
            gradient[(image * params.in_channels + channel) * in_pixels + pixel] = sums[j];
        }
    }
}

// One thread: one input pixel of one plane (`images` counts the first images' planes, pairs *
// C). Sums the upstream gradient of every pooling window (no padding, floor mode) whose
// arg-max is this pixel; the arg-max is the first maximum in row-major window order, and
// windows are visited in row-major order.
@compute @workgroup_size(64)
fn max_pool_backward(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    if (index >= params.total) {
        return;
    }
    let in_pixels = params.in_height * params.in_width;
    let out_pixels = params.out_height * params.out_width;
    let plane = index / in_pixels;
    let pixel = index % in_pixels;
    let y = pixel / params.in_width;
    let x = pixel % params.in_width;
    let kernel = params.kernel;
    let stride = params.stride;
    // Window oy covers rows oy * stride .. oy * stride + kernel - 1.
    var first_y = 0u;
    if (y + 1u > kernel) {
        first_y = (y + 1u - kernel + stride - 1u) / stride;
    }
    let last_y = min(y / stride, params.out_height - 1u);
    var first_x = 0u;
    if (x + 1u > kernel) {
        first_x = (x + 1u - kernel + stride - 1u) / stride;
    }
    let last_x = min(x / stride, params.out_width - 1u);
    let base = plane * in_pixels;
    var sum = 0.0;
    for (var out_y = first_y; out_y <= last_y; out_y++) {
        for (var out_x = first_x; out_x <= last_x; out_x++) {
            let top = out_y * stride;
            let left = out_x * stride;
            var best = forward_values[base + top * params.in_width + left];
            var best_y = top;
            var best_x = left;
            for (var ky = 0u; ky < kernel; ky++) {
                for (var kx = 0u; kx < kernel; kx++) {
                    let value = forward_values[base + (top + ky) * params.in_width + left + kx];
                    if (value > best) {
                        best = value;
                        best_y = top + ky;
                        best_x = left + kx;
                    }
                }
            }
            if (best_y == y && best_x == x) {
                sum += upstream[plane * out_pixels + out_y * params.out_width + out_x];
            }
        }
    }
    gradient[index] = sum;
}
