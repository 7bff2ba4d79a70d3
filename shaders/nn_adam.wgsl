// One Adam update of one tensor (src/compute/src/nn/adam.rs has the cpu twin and the formula),
// PyTorch's operation order:
//   m = beta1 m + (1 - beta1) g;  v = beta2 v + (1 - beta2) g^2;
//   p -= step_size * m / (sqrt(v) / correction + eps)
// with step_size = lr / (1 - beta1^t) and correction = sqrt(1 - beta2^t) computed in f64 on
// the host. They change every update, so they are read from a storage record
// (`factors[2 slot]`, `factors[2 slot + 1]`) that a resident step writes once per iteration
// for all its tensors, while the per-tensor uniform block is created once. One thread per
// value; the grid may be 2D (`linear_index`).

struct Params {
    len: u32,
    slot: u32,
    _pad0: u32,
    _pad1: u32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    eps: f32,
    _pad2: u32,
    _pad3: u32,
    _pad4: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> parameters: array<f32>;
@group(0) @binding(2) var<storage, read> gradients: array<f32>;
@group(0) @binding(3) var<storage, read_write> first_moment: array<f32>;
@group(0) @binding(4) var<storage, read_write> second_moment: array<f32>;
@group(0) @binding(5) var<storage, read> factors: array<f32>;

const WORKGROUP: u32 = 256u;

//#include "linear_index.wgsl"

@compute @workgroup_size(WORKGROUP)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= params.len) {
        return;
    }
    let step_size = factors[2u * params.slot];
    let correction = factors[2u * params.slot + 1u];
    let g = gradients[i];
    let m = params.beta1 * first_moment[i] + params.one_minus_beta1 * g;
    let v = params.beta2 * second_moment[i] + params.one_minus_beta2 * g * g;
    first_moment[i] = m;
    second_moment[i] = v;
    let denominator = sqrt(v) / correction + params.eps;
    parameters[i] = parameters[i] - step_size * m / denominator;
}
