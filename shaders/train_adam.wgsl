// Adam on one trainable column of the device-resident Gaussians (stages/train/src/resident/
// adam.rs; the cpu twins are `adam_update` in src/compute/src/nn/adam.rs and `update_sh` in
// stages/train/src/trainer.rs), in PyTorch's operation order:
//   m = beta1 m + (1 - beta1) g;  v = beta2 v + (1 - beta2) g^2;
//   p -= step_size * m / (sqrt(v) / correction + eps)
// with step_size = lr / (1 - beta1^t) and correction = sqrt(1 - beta2^t) computed in f64 on
// the host and written into the step record once per iteration. The gradient is assembled
// here: a sum of two sources (skinning + AIAP), one source, the opacity-logit chain rule
// `d * o * (1 - o)`, or the SH gradient of the active degree (`N x k x 3`) scattered into
// the stored `N x 16 x 3` layout (zero beyond `k`). Non-finite gradients and parameters are
// flagged in the status buffer (see `flag`). One thread per value; the grid may be 2D.
//
// No struct is bound: the step record and the column's constants are u32 arrays whose word
// indices are the constants below (mirrored in stages/train/src/resident/state.rs).

// Step record words (floats as their bit patterns).
const R_COUNT: u32 = 0u;
const R_ITERATION: u32 = 1u;
const R_SH_COEFFICIENTS: u32 = 2u;
const R_BETA1: u32 = 4u;
const R_BETA2: u32 = 5u;
const R_ONE_MINUS_BETA1: u32 = 6u;
const R_ONE_MINUS_BETA2: u32 = 7u;
const R_EPS: u32 = 8u;
const R_CORRECTION: u32 = 9u;
// Step sizes from this word on, indexed by the column's `C_STEP` (the SH rest rate follows
// the DC one).
const R_STEP_SIZE: u32 = 16u;

// Column constant words.
const C_ID: u32 = 0u;
const C_WIDTH: u32 = 1u;
const C_STEP: u32 = 2u;

// Columns in the status buffer: slot `id` for its gradient, `COLUMNS + id` for its values.
const COLUMNS: u32 = 5u;
const SH_STORED: u32 = 16u;

@group(0) @binding(0) var<storage, read> record: array<u32>;
@group(0) @binding(1) var<storage, read> column: array<u32>;
@group(0) @binding(2) var<storage, read_write> parameters: array<f32>;
@group(0) @binding(3) var<storage, read_write> first_moment: array<f32>;
@group(0) @binding(4) var<storage, read_write> second_moment: array<f32>;
@group(0) @binding(5) var<storage, read> gradient_a: array<f32>;
@group(0) @binding(6) var<storage, read> gradient_b: array<f32>;
// Per slot two words: `0xffffffff - iteration` of the first iteration that found a
// non-finite value (0: none) and `0xffffffff - Gaussian` of the smallest such Gaussian in
// that iteration.
@group(0) @binding(7) var<storage, read_write> status: array<atomic<u32>>;

fn record_f32(word: u32) -> f32 {
    return bitcast<f32>(record[word]);
}

//#include "finite.wgsl"

// Records a non-finite value of Gaussian `gaussian` in `slot`: the first iteration wins
// (later iterations have smaller keys), and within it the smallest Gaussian.
fn flag(slot: u32, gaussian: u32) {
    let key = 0xffffffffu - record[R_ITERATION];
    let previous = atomicMax(&status[2u * slot], key);
    if (previous <= key) {
        atomicMax(&status[2u * slot + 1u], 0xffffffffu - gaussian);
    }
}

fn update(i: u32, g: f32, step_size: f32) {
    let gaussian = i / column[C_WIDTH];
    if (!finite(g)) {
        flag(column[C_ID], gaussian);
    }
    let m = record_f32(R_BETA1) * first_moment[i] + record_f32(R_ONE_MINUS_BETA1) * g;
    let v = record_f32(R_BETA2) * second_moment[i] + record_f32(R_ONE_MINUS_BETA2) * g * g;
    first_moment[i] = m;
    second_moment[i] = v;
    let denominator = sqrt(v) / record_f32(R_CORRECTION) + record_f32(R_EPS);
    let p = parameters[i] - step_size * m / denominator;
    parameters[i] = p;
    if (!finite(p)) {
        flag(COLUMNS + column[C_ID], gaussian);
    }
}

const WORKGROUP: u32 = 256u;

//#include "linear_index.wgsl"

// The step size of the column (for SH, of its DC coefficient).
fn column_step_size() -> f32 {
    return record_f32(R_STEP_SIZE + column[C_STEP]);
}

fn values() -> u32 {
    return record[R_COUNT] * column[C_WIDTH];
}

// g = a + b (positions, log-scales, rotations: skinning plus AIAP).
@compute @workgroup_size(WORKGROUP)
fn sum_of_two(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= values()) {
        return;
    }
    update(i, gradient_a[i] + gradient_b[i], column_step_size());
}

// g = a.
@compute @workgroup_size(WORKGROUP)
fn single(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= values()) {
        return;
    }
    update(i, gradient_a[i], column_step_size());
}

// g = a * o * (1 - o), o = sigmoid(logit): `a` is the gradient of the activated opacity.
@compute @workgroup_size(WORKGROUP)
fn opacity(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= values()) {
        return;
    }
    let o = 1.0 / (1.0 + exp(-parameters[i]));
    update(i, gradient_a[i] * o * (1.0 - o), column_step_size());
}

// The stored SH row `16 x 3` from the active degree's `k x 3` gradient rows; the DC
// coefficient at the DC rate, the others at the rest rate.
@compute @workgroup_size(WORKGROUP)
fn sh(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= values()) {
        return;
    }
    let gaussian = i / (3u * SH_STORED);
    let within = i % (3u * SH_STORED);
    let coefficient = within / 3u;
    let k = record[R_SH_COEFFICIENTS];
    var g = 0.0;
    if (coefficient < k) {
        g = gradient_a[gaussian * 3u * k + within];
    }
    var step = column[C_STEP];
    if (coefficient > 0u) {
        step = step + 1u;
    }
    update(i, g, record_f32(R_STEP_SIZE + step));
}
