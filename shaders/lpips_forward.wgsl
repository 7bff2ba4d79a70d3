// The LPIPS trunk on the gpu (src/compute/src/lpips/gpu.rs): convolution + bias + ReLU, max
// pool, and the per-pixel layer distance. Tensors are NCHW f32 in storage buffers; the cpu
// twin is src/compute/src/lpips/cpu.rs and a parity test compares the two.
//
// Every entry point runs 64 threads per workgroup over a linear index
// `(workgroup.x + workgroup.y * groups.x) * 64 + local`, since GpuContext::dispatch lays
// large dispatches out in 2D; threads past `params.total` return.

//#include "lpips_types.wgsl"

@group(0) @binding(0) var<uniform> params: LpipsParams;
@group(0) @binding(1) var<storage, read> input: array<f32>;
@group(0) @binding(2) var<storage, read> weight: array<f32>;
@group(0) @binding(3) var<storage, read> bias: array<f32>;
@group(0) @binding(4) var<storage, read_write> output: array<f32>;

const WORKGROUP: u32 = 64u;
// Output channels per conv thread: one input load feeds four accumulators.
const CHANNELS_PER_THREAD: u32 = 4u;

//#include "linear_index.wgsl"

// One thread: output channels 4g..4g+3 of one pixel of one image (pixel index fastest).
// Weights are (out, in, k, k) row-major.
@compute @workgroup_size(64)
fn conv2d_relu(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    if (index >= params.total) {
        return;
    }
    let out_pixels = params.out_height * params.out_width;
    let channel_groups = (params.out_channels + CHANNELS_PER_THREAD - 1u) / CHANNELS_PER_THREAD;
    let pixel = index % out_pixels;
    let rest = index / out_pixels;
    let group = rest % channel_groups;
    let image = rest / channel_groups;
    let out_y = pixel / params.out_width;
    let out_x = pixel % params.out_width;
    let first_channel = group * CHANNELS_PER_THREAD;
    let kernel_area = params.kernel * params.kernel;
    let weight_stride = params.in_channels * kernel_area;
    // Channels past the end read channel 0's weights (harmless) and are not written.
    var channel_offsets: array<u32, 4>;
    for (var j = 0u; j < CHANNELS_PER_THREAD; j++) {
        let channel = select(0u, first_channel + j, first_channel + j < params.out_channels);
        channel_offsets[j] = channel * weight_stride;
    }
    var sums = vec4<f32>(0.0);
    let in_plane = params.in_height * params.in_width;
    let image_base = image * params.in_channels * in_plane;
    let y0 = i32(out_y * params.stride) - i32(params.padding);
    let x0 = i32(out_x * params.stride) - i32(params.padding);
    for (var ky = 0u; ky < params.kernel; ky++) {
        let y = y0 + i32(ky);
        if (y < 0 || y >= i32(params.in_height)) {
            continue;
        }
        for (var kx = 0u; kx < params.kernel; kx++) {
            let x = x0 + i32(kx);
            if (x < 0 || x >= i32(params.in_width)) {
                continue;
            }
            let tap = ky * params.kernel + kx;
            var source = image_base + u32(y) * params.in_width + u32(x);
            var tap_offset = tap;
            for (var channel = 0u; channel < params.in_channels; channel++) {
                let value = input[source];
                sums += value * vec4<f32>(
                    weight[channel_offsets[0] + tap_offset],
                    weight[channel_offsets[1] + tap_offset],
                    weight[channel_offsets[2] + tap_offset],
                    weight[channel_offsets[3] + tap_offset],
                );
                source += in_plane;
                tap_offset += kernel_area;
            }
        }
    }
    for (var j = 0u; j < CHANNELS_PER_THREAD; j++) {
        let channel = first_channel + j;
        if (channel < params.out_channels) {
            output[(image * params.out_channels + channel) * out_pixels + pixel] =
                max(sums[j] + bias[channel], 0.0);
        }
    }
}

// One thread: one output pixel of one plane (`images` counts planes here). No padding, floor
// mode. Binds only params, input and output (layouts are derived per entry point).
@compute @workgroup_size(64)
fn max_pool(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    if (index >= params.total) {
        return;
    }
    let out_pixels = params.out_height * params.out_width;
    let plane = index / out_pixels;
    let pixel = index % out_pixels;
    let out_y = pixel / params.out_width;
    let out_x = pixel % params.out_width;
    let base = plane * params.in_height * params.in_width;
    var best = -3.4028235e38;
    for (var ky = 0u; ky < params.kernel; ky++) {
        let row = base + (out_y * params.stride + ky) * params.in_width + out_x * params.stride;
        for (var kx = 0u; kx < params.kernel; kx++) {
            best = max(best, input[row + kx]);
        }
    }
    output[index] = best;
}

// One thread: one pixel of one pair. Pair p compares batch image p with image images + p
// (`images` counts pairs here, `in_channels` the channels, `in_height * in_width` the pixels);
// `weight` holds the lin layer. Writes sum_c w_c (f0_c / (|f0| + eps) - f1_c / (|f1| + eps))^2.
@compute @workgroup_size(64)
fn layer_distance(
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
        let a = input[first + channel * pixels];
        let b = input[second + channel * pixels];
        norm0 += a * a;
        norm1 += b * b;
    }
    let scale0 = 1.0 / (sqrt(norm0) + 1e-10);
    let scale1 = 1.0 / (sqrt(norm1) + 1e-10);
    var sum = 0.0;
    for (var channel = 0u; channel < params.in_channels; channel++) {
        let difference = normalised_difference(
            input[first + channel * pixels], scale0, input[second + channel * pixels], scale1);
        sum += weight[channel] * difference * difference;
    }
    output[index] = sum;
}
