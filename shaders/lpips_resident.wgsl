// The ends of the device-resident LPIPS loss (src/compute/src/lpips/gpu.rs, `ResidentLpips`):
// the trunk input cut from device images, the distance reduced to one value on the device,
// and the image gradient added into a device gradient buffer. The trunk between them is the
// kernels of lpips_forward.wgsl and lpips_backward.wgsl.
//
// Images are interleaved `H x W x 3` f32 buffers; an image starts at pixel `*_offset` and has
// rows of `*_width` pixels. The crop is `crop_width x crop_height` at (x0, y0) of both images.
// Pixel kernels run WORKGROUP threads per workgroup over `linear_index` (GpuContext::dispatch
// goes 2D beyond the per-dimension limit).

struct LpipsResidentParams {
    render_offset: u32,
    render_width: u32,
    target_offset: u32,
    target_width: u32,
    x0: u32,
    y0: u32,
    crop_width: u32,
    crop_height: u32,
    // What the gradient is multiplied by before it is added (the loss weight / cameras).
    gradient_factor: f32,
    // 1: inputs in [0, 1] mapped by 2x - 1 (LpipsInput::Unit); 0: fed unchanged.
    signed_mapping: u32,
    _pad0: u32,
    _pad1: u32,
    // The scaling layer, `(x - shift) / scale` per channel (w unused).
    shift: vec4<f32>,
    scale: vec4<f32>,
    // Pixels of each tapped layer's distance map (5 used).
    layer_pixels0: vec4<u32>,
    layer_pixels1: vec4<u32>,
}

@group(0) @binding(0) var<uniform> params: LpipsResidentParams;
@group(0) @binding(1) var<storage, read> render: array<f32>;
@group(0) @binding(2) var<storage, read> target_image: array<f32>;
// Two NCHW images: the render crop, then the target crop (the trunk's input).
@group(0) @binding(3) var<storage, read_write> trunk_input: array<f32>;
// The gradient of the distance with respect to the render crop's trunk input, (3, h, w).
@group(0) @binding(4) var<storage, read> trunk_gradient: array<f32>;
@group(0) @binding(5) var<storage, read_write> colour_gradient: array<f32>;
@group(0) @binding(6) var<storage, read> map0: array<f32>;
@group(0) @binding(7) var<storage, read> map1: array<f32>;
@group(0) @binding(8) var<storage, read> map2: array<f32>;
@group(0) @binding(9) var<storage, read> map3: array<f32>;
@group(0) @binding(10) var<storage, read> map4: array<f32>;
// One f32: the LPIPS distance (sum over layers of each map's mean).
@group(0) @binding(11) var<storage, read_write> value: array<f32>;

const WORKGROUP: u32 = 64u;
const REDUCE: u32 = 256u;

var<workgroup> partial: array<f32, 256>;

//#include "linear_index.wgsl"

// The first of the three values of crop pixel `index` in an image that starts at pixel
// `offset` and has rows of `width` pixels.
fn pixel_base(offset: u32, width: u32, index: u32) -> u32 {
    let row = params.y0 + index / params.crop_width;
    let col = params.x0 + index % params.crop_width;
    return 3u * (offset + row * width + col);
}

fn trunk_value(unit: f32, channel: u32) -> f32 {
    var signed = unit;
    if (params.signed_mapping == 1u) {
        signed = unit * 2.0 - 1.0;
    }
    return (signed - params.shift[channel]) / params.scale[channel];
}

// One thread: one crop pixel; writes its three trunk input values of both images.
@compute @workgroup_size(WORKGROUP)
fn crop_to_trunk(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    let pixels = params.crop_width * params.crop_height;
    if (index >= pixels) {
        return;
    }
    let render_base = pixel_base(params.render_offset, params.render_width, index);
    let target_base = pixel_base(params.target_offset, params.target_width, index);
    for (var c = 0u; c < 3u; c++) {
        trunk_input[c * pixels + index] = trunk_value(render[render_base + c], c);
        trunk_input[(3u + c) * pixels + index] = trunk_value(target_image[target_base + c], c);
    }
}

fn map_value(layer: u32, index: u32) -> f32 {
    switch layer {
        case 0u: { return map0[index]; }
        case 1u: { return map1[index]; }
        case 2u: { return map2[index]; }
        case 3u: { return map3[index]; }
        default: { return map4[index]; }
    }
}

fn layer_pixels(layer: u32) -> u32 {
    if (layer < 4u) {
        return params.layer_pixels0[layer];
    }
    return params.layer_pixels1[layer - 4u];
}

// One workgroup: each layer's map summed in a fixed order and divided by its pixels, the
// five means summed into `value[0]` (lpips::reduce_maps).
@compute @workgroup_size(256)
fn reduce_distance(@builtin(local_invocation_index) local: u32) {
    var total = 0.0;
    for (var layer = 0u; layer < 5u; layer++) {
        let pixels = layer_pixels(layer);
        var sum = 0.0;
        for (var i = local; i < pixels; i += REDUCE) {
            sum += map_value(layer, i);
        }
        partial[local] = sum;
        workgroupBarrier();
        for (var width = REDUCE / 2u; width > 0u; width /= 2u) {
            if (local < width) {
                partial[local] += partial[local + width];
            }
            workgroupBarrier();
        }
        total += partial[0] / f32(pixels);
        workgroupBarrier();
    }
    if (local == 0u) {
        value[0] = total;
    }
}

// One thread: one crop pixel; adds `gradient_factor` times the image gradient (the trunk
// gradient through the scaling layer and the input mapping, lpips::trunk_gradient_to_image)
// into the render's colour gradient.
@compute @workgroup_size(WORKGROUP)
fn add_image_gradient(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    let pixels = params.crop_width * params.crop_height;
    if (index >= pixels) {
        return;
    }
    let base = pixel_base(params.render_offset, params.render_width, index);
    var slope = 1.0;
    if (params.signed_mapping == 1u) {
        slope = 2.0;
    }
    for (var c = 0u; c < 3u; c++) {
        let image_gradient = trunk_gradient[c * pixels + index] * (slope / params.scale[c]);
        colour_gradient[base + c] += params.gradient_factor * image_gradient;
    }
}
