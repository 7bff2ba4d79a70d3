// NeRF positional encoding (src/compute/src/nn/encoding.rs has the cpu twin and the layout):
// per row [x, sin(2^0 x), cos(2^0 x), ..., sin(2^(F-1) x), cos(2^(F-1) x)], each block
// `in_features` wide. One thread per (row, input feature); the grid may be 2D.
//
// Phases reach 2^(F-1) |x| (512 |x| for F = 10), beyond the range where GPU sin/cos are
// accurate, so the phase is first reduced to [-pi, pi] with a three-part (Cody-Waite) 2 pi:
// 2^k x is exact in f32, and k * TWO_PI_HI is exact for |k| < 2^16.

struct Params {
    rows: u32,
    in_features: u32,
    frequencies: u32,
    include_input: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

const TWO_PI_HI: f32 = 6.28125;
const TWO_PI_MID: f32 = 1.9353071693331003e-3;
const TWO_PI_LO: f32 = 1.0253131677018246e-11;
const INV_TWO_PI: f32 = 0.15915494309189535;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> source: array<f32>;
@group(0) @binding(2) var<storage, read> gradient: array<f32>;
@group(0) @binding(3) var<storage, read_write> destination: array<f32>;

fn reduce_phase(phase: f32) -> f32 {
    let turns = round(phase * INV_TWO_PI);
    return ((phase - turns * TWO_PI_HI) - turns * TWO_PI_MID) - turns * TWO_PI_LO;
}

const WORKGROUP: u32 = 64u;

//#include "linear_index.wgsl"

fn width() -> u32 {
    return params.in_features * (params.include_input + 2u * params.frequencies);
}

// source = input (rows x d), destination = encoding (rows x width).
@compute @workgroup_size(WORKGROUP)
fn forward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(group, groups, local);
    let d = params.in_features;
    if (index >= params.rows * d) {
        return;
    }
    let row = index / d;
    let feature = index % d;
    let x = source[index];
    let base = row * width();
    if (params.include_input != 0u) {
        destination[base + feature] = x;
    }
    var scale = 1.0;
    for (var band = 0u; band < params.frequencies; band++) {
        let sine = base + d * (params.include_input + 2u * band) + feature;
        let phase = reduce_phase(x * scale);
        destination[sine] = sin(phase);
        destination[sine + d] = cos(phase);
        scale *= 2.0;
    }
}

// source = the forward encoding, gradient = dL/d(encoding), destination = dL/dx (written).
@compute @workgroup_size(WORKGROUP)
fn backward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(group, groups, local);
    let d = params.in_features;
    if (index >= params.rows * d) {
        return;
    }
    let row = index / d;
    let feature = index % d;
    let base = row * width();
    var sum = 0.0;
    if (params.include_input != 0u) {
        sum = gradient[base + feature];
    }
    var scale = 1.0;
    for (var band = 0u; band < params.frequencies; band++) {
        let sine = base + d * (params.include_input + 2u * band) + feature;
        let cosine = sine + d;
        sum += scale * (source[cosine] * gradient[sine] - source[sine] * gradient[cosine]);
        scale *= 2.0;
    }
    destination[index] = sum;
}
