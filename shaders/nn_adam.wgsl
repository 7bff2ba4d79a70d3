// One Adam update of one tensor (src/compute/src/nn/adam.rs has the cpu twin and the formula),
// PyTorch's operation order:
//   m = beta1 m + (1 - beta1) g;  v = beta2 v + (1 - beta2) g^2;
//   p -= step_size * m / (sqrt(v) / correction + eps)
// with step_size = lr / (1 - beta1^t) and correction = sqrt(1 - beta2^t) computed in f64 on
// the host. One thread per value; the grid may be 2D (index = x + y * groups_x).

struct Params {
    len: u32,
    groups_x: u32,
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    eps: f32,
    step_size: f32,
    correction: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> parameters: array<f32>;
@group(0) @binding(2) var<storage, read> gradients: array<f32>;
@group(0) @binding(3) var<storage, read_write> first_moment: array<f32>;
@group(0) @binding(4) var<storage, read_write> second_moment: array<f32>;

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = (group.x + group.y * params.groups_x) * 256u + local;
    if (i >= params.len) {
        return;
    }
    let g = gradients[i];
    let m = params.beta1 * first_moment[i] + params.one_minus_beta1 * g;
    let v = params.beta2 * second_moment[i] + params.one_minus_beta2 * g * g;
    first_moment[i] = m;
    second_moment[i] = v;
    let denominator = sqrt(v) / params.correction + params.eps;
    parameters[i] = parameters[i] - params.step_size * m / denominator;
}
