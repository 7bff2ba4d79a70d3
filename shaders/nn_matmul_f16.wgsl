// The f16 staging around the tensor-core matrix product (nn_matmul_coop.wgsl), for the dense
// layers' mixed-precision path (src/compute/src/nn/gpu.rs, `MatmulPath::TensorCores`).
//
//   operand_max: scales[slot] = max over the operand's finite elements of |x| (f32 bits).
//   pack:        packed = f16(x * 2^e) of the operand, row-major, zero-padded to
//                rows_pad x cols_pad, where e = scale_exponent(scales[slot]).
//   epilogue:    C[i][j] (+)= 2^-(e_a + e_b) * sum over k slices of partials, then + bias[j],
//                then ReLU: the fused epilogue of nn_matmul.wgsl on the f32 products.
//
// The operand is a strided view into an f32 buffer (offset, row and column strides), as in
// nn_matmul.wgsl, so the forward pass and both backward products read X, W, dY unchanged and
// transposed; the ReLU mask of backward is fused into the loads the same way (MASK: zero where
// mask[same index] is not positive).
//
// Why a power-of-two scale per operand: f16 holds magnitudes up to 65504 and has normal
// numbers down to 6.1e-5 only. Activations can exceed the first, and the loss gradients dY
// of a training step are often below the second, where f16 keeps few or no bits. Scaling the
// whole operand by 2^e, e chosen from its largest finite magnitude so that it lands in
// [2^14, 2^15), makes every finite element representable (no overflow to infinity, so no
// clamping changes a value) and uses the top of f16's range for the bulk of the values. A
// power of two is exact in both directions: the epilogue divides the f32 sum by 2^(e_a + e_b)
// without rounding. Infinities and NaNs are left out of the maximum, so one of them cannot
// flush every finite value to zero; what they become in f16 is the implementation's (WGSL
// leaves converting a value f16 cannot hold to it), and the f32 path stays the reference for
// non-finite inputs.
//
// The products themselves (f16 x f16 with f32 accumulation, nn_matmul_coop.wgsl) cannot
// overflow: each is below 2^30 and a sum of 2^32 of them stays far below f32's 2^128.

enable f16;

struct Params {
    // operand_max and pack: the operand view (rows x cols), its scale slot and the padded
    // size of its f16 copy.
    rows: u32,
    cols: u32,
    offset: u32,
    row_stride: u32,
    col_stride: u32,
    mask_flags: u32,
    slot: u32,
    rows_pad: u32,
    cols_pad: u32,
    // epilogue: C is m x n at c_offset with rows c_row_stride apart; the partial products
    // are `splits` slices of m_pad x n_pad (rows n_pad apart), partial_stride apart.
    m: u32,
    n: u32,
    n_pad: u32,
    splits: u32,
    partial_stride: u32,
    c_offset: u32,
    c_row_stride: u32,
    c_flags: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

// Bits of Params.mask_flags.
const MASK: u32 = 1u;
// Bits of Params.c_flags, as in nn_matmul.wgsl.
const ACCUMULATE: u32 = 1u;
const ADD_BIAS: u32 = 2u;
const RELU: u32 = 4u;

// The largest scaled magnitude is below 2^(TARGET_EXPONENT + 1) = 32768 < 65504.
const TARGET_EXPONENT: i32 = 14;
const WORKGROUP: u32 = 256u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> source: array<f32>;
@group(0) @binding(2) var<storage, read> mask: array<f32>;
// Two slots per product: the largest finite magnitudes of A and B as f32 bits (the bits of
// non-negative floats order as the floats do, so atomicMax on u32 is a float maximum).
@group(0) @binding(3) var<storage, read_write> scales: array<atomic<u32>>;
@group(0) @binding(4) var<storage, read_write> packed: array<f16>;
@group(0) @binding(5) var<storage, read> partials: array<f32>;
@group(0) @binding(6) var<storage, read> bias: array<f32>;
@group(0) @binding(7) var<storage, read_write> c: array<f32>;

//#include "linear_index.wgsl"
//#include "finite.wgsl"

// The scale exponent e of an operand whose largest finite magnitude has the f32 bits
// `max_bits`: 2^e times that magnitude is in [2^14, 2^15). Zero for an all-zero operand. It
// is at most 126 (an operand of subnormals only is scaled by 2^126 and stays below 1), so
// 2^e, and 2^-e, are normal f32 numbers however a driver implements ldexp.
fn scale_exponent(max_bits: u32) -> i32 {
    if (max_bits == 0u) {
        return 0;
    }
    let biased = i32((max_bits >> 23u) & 0xffu);
    return min(TARGET_EXPONENT - (biased - 127), 126);
}

// The operand's element (row, col), masked.
fn operand(row: u32, col: u32) -> f32 {
    let index = params.offset + row * params.row_stride + col * params.col_stride;
    let value = source[index];
    if ((params.mask_flags & MASK) != 0u && !(mask[index] > 0.0)) {
        return 0.0;
    }
    return value;
}

var<workgroup> group_max: atomic<u32>;

@compute @workgroup_size(256)
fn operand_max(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(group, groups, local);
    if (index < params.rows * params.cols) {
        let value = operand(index / params.cols, index % params.cols);
        if (finite(value)) {
            atomicMax(&group_max, bitcast<u32>(abs(value)));
        }
    }
    workgroupBarrier();
    if (local == 0u) {
        let value = atomicLoad(&group_max);
        if (value != 0u) {
            atomicMax(&scales[params.slot], value);
        }
    }
}

@compute @workgroup_size(256)
fn pack(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(group, groups, local);
    if (index >= params.rows_pad * params.cols_pad) {
        return;
    }
    let row = index / params.cols_pad;
    let col = index % params.cols_pad;
    var value = 0.0;
    if (row < params.rows && col < params.cols) {
        value = operand(row, col);
    }
    let exponent = scale_exponent(atomicLoad(&scales[params.slot]));
    packed[index] = f16(ldexp(value, exponent));
}

@compute @workgroup_size(256)
fn epilogue(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(group, groups, local);
    if (index >= params.m * params.n) {
        return;
    }
    let row = index / params.n;
    let col = index % params.n;
    // Slices summed in order: deterministic, as the f32 path's accumulate_partials.
    var sum = 0.0;
    let at = row * params.n_pad + col;
    for (var s = 0u; s < params.splits; s++) {
        sum += partials[s * params.partial_stride + at];
    }
    // 2^-(e_a + e_b) in two halves within [-126, 126] each: the intermediate lies between
    // the sum and the result, so it overflows or underflows only where the result does.
    let exponent = -(scale_exponent(atomicLoad(&scales[0])) + scale_exponent(atomicLoad(&scales[1])));
    let half = exponent / 2;
    var value = ldexp(ldexp(sum, half), exponent - half);
    let destination = params.c_offset + row * params.c_row_stride + col;
    if ((params.c_flags & ACCUMULATE) != 0u) {
        value += c[destination];
    }
    if ((params.c_flags & ADD_BIAS) != 0u) {
        value += bias[col];
    }
    if ((params.c_flags & RELU) != 0u) {
        value = max(value, 0.0);
    }
    c[destination] = value;
}
