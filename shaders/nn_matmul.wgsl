// Tiled f32 matrix product with a fused epilogue, for the dense layers (src/compute/src/nn/gpu.rs).
//
//   C[i][j] (+)= sum_k A[i][k] * B[k][j]   then optionally + bias[j], then optionally ReLU.
//
// Operands are strided views into storage buffers, so one kernel serves the forward pass
// (Y = X W), the input gradient (dX = dY' W^T: B is W read transposed) and the weight gradient
// (dW = X^T dY': A is X read transposed). The ReLU mask of backward is fused into the operand
// loads: the masked operand's element is zeroed where `mask` (the layer output Y, indexed like
// the operand) is not positive. The weight gradient reduces over all rows, so it is split
// along k: workgroup row `y` covers tile row `y % m_tiles` and k slice `y / m_tiles`, and slice
// `s` writes its partial product at `c_offset + s * split_stride` (summed by nn_reduce.wgsl).
//
// Each workgroup of 16 x 16 threads computes a 64 x 64 tile of C, 4 x 4 values per thread at
// rows ty + 16 u and columns tx + 16 v (strided, so neighbouring threads read neighbouring
// shared-memory words), stepping through k 16 at a time via workgroup-shared tiles. No
// subgroup operations, no f16.
//
// The 16 accumulators are four vec4 values, never an array indexed in a loop: a private
// array indexed by a loop counter stays in registers only if the driver unrolls the loop,
// which is not guaranteed for naga's output. The shared tiles' rows are TILE_STRIDE = 65
// words apart, so the loads that write a tile along k (stride one row) fall in different
// banks instead of one.

struct Params {
    m: u32,
    n: u32,
    k: u32,
    flags: u32,
    a_offset: u32,
    a_row_stride: u32,
    a_col_stride: u32,
    b_offset: u32,
    b_row_stride: u32,
    b_col_stride: u32,
    c_offset: u32,
    c_row_stride: u32,
    k_per_split: u32,
    m_tiles: u32,
    split_stride: u32,
    _pad: u32,
}

// Bits of Params.flags.
const ACCUMULATE: u32 = 1u;   // C += product (else C = product)
const ADD_BIAS: u32 = 2u;     // + bias[j]
const RELU: u32 = 4u;         // max(., 0) last
const MASK_A: u32 = 8u;       // A[i][k] *= (mask[same index] > 0)
const MASK_B: u32 = 16u;      // B[k][j] *= (mask[same index] > 0)

const TILE_M: u32 = 64u;
const TILE_N: u32 = 64u;
const TILE_K: u32 = 16u;
const TILE_STRIDE: u32 = 65u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read> mask: array<f32>;
@group(0) @binding(4) var<storage, read> bias: array<f32>;
@group(0) @binding(5) var<storage, read_write> c: array<f32>;

// Shared tiles, k-major: a_tile[kk * TILE_STRIDE + i], b_tile[kk * TILE_STRIDE + j].
var<workgroup> a_tile: array<f32, 1040>;
var<workgroup> b_tile: array<f32, 1040>;

fn load_a(row: u32, kk: u32, k_end: u32) -> f32 {
    if (row >= params.m || kk >= k_end) {
        return 0.0;
    }
    let index = params.a_offset + row * params.a_row_stride + kk * params.a_col_stride;
    let value = a[index];
    if ((params.flags & MASK_A) != 0u && !(mask[index] > 0.0)) {
        return 0.0;
    }
    return value;
}

fn load_b(kk: u32, col: u32, k_end: u32) -> f32 {
    if (col >= params.n || kk >= k_end) {
        return 0.0;
    }
    let index = params.b_offset + kk * params.b_row_stride + col * params.b_col_stride;
    let value = b[index];
    if ((params.flags & MASK_B) != 0u && !(mask[index] > 0.0)) {
        return 0.0;
    }
    return value;
}

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let tile_row = group.y % params.m_tiles;
    let split = group.y / params.m_tiles;
    let row0 = tile_row * TILE_M;
    let col0 = group.x * TILE_N;
    let k_begin = split * params.k_per_split;
    let k_end = min(params.k, k_begin + params.k_per_split);
    let tx = local % 16u;
    let ty = local / 16u;

    // acc_u[v] is C at row ty + 16 u, column tx + 16 v.
    var acc_0 = vec4<f32>(0.0);
    var acc_1 = vec4<f32>(0.0);
    var acc_2 = vec4<f32>(0.0);
    var acc_3 = vec4<f32>(0.0);

    // Which of the tile's dimensions runs along memory decides the load mapping, so that
    // consecutive threads read consecutive addresses (uniform branches).
    let a_k_contiguous = params.a_col_stride == 1u;
    let b_n_contiguous = params.b_col_stride == 1u;

    for (var k0 = k_begin; k0 < k_end; k0 += TILE_K) {
        for (var r = 0u; r < 4u; r++) {
            let e = local + 256u * r;
            var i: u32;
            var kk: u32;
            if (a_k_contiguous) {
                i = e / TILE_K;
                kk = e % TILE_K;
            } else {
                kk = e / TILE_M;
                i = e % TILE_M;
            }
            a_tile[kk * TILE_STRIDE + i] = load_a(row0 + i, k0 + kk, k_end);
            var j: u32;
            if (b_n_contiguous) {
                kk = e / TILE_N;
                j = e % TILE_N;
            } else {
                j = e / TILE_K;
                kk = e % TILE_K;
            }
            b_tile[kk * TILE_STRIDE + j] = load_b(k0 + kk, col0 + j, k_end);
        }
        workgroupBarrier();
        for (var kk = 0u; kk < TILE_K; kk++) {
            let a_row = kk * TILE_STRIDE + ty;
            let b_row = kk * TILE_STRIDE + tx;
            let b_values = vec4<f32>(b_tile[b_row], b_tile[b_row + 16u], b_tile[b_row + 32u],
                b_tile[b_row + 48u]);
            acc_0 = fma(vec4<f32>(a_tile[a_row]), b_values, acc_0);
            acc_1 = fma(vec4<f32>(a_tile[a_row + 16u]), b_values, acc_1);
            acc_2 = fma(vec4<f32>(a_tile[a_row + 32u]), b_values, acc_2);
            acc_3 = fma(vec4<f32>(a_tile[a_row + 48u]), b_values, acc_3);
        }
        workgroupBarrier();
    }

    let c_base = params.c_offset + split * params.split_stride;
    store_row(c_base, row0 + ty, col0 + tx, acc_0);
    store_row(c_base, row0 + ty + 16u, col0 + tx, acc_1);
    store_row(c_base, row0 + ty + 32u, col0 + tx, acc_2);
    store_row(c_base, row0 + ty + 48u, col0 + tx, acc_3);
}

// Writes a thread's four values of C row `row`, at columns col + 16 v, through the epilogue.
fn store_row(c_base: u32, row: u32, col: u32, values: vec4<f32>) {
    if (row >= params.m) {
        return;
    }
    store(c_base, row, col, values.x);
    store(c_base, row, col + 16u, values.y);
    store(c_base, row, col + 32u, values.z);
    store(c_base, row, col + 48u, values.w);
}

fn store(c_base: u32, row: u32, col: u32, product: f32) {
    if (col >= params.n) {
        return;
    }
    let index = c_base + row * params.c_row_stride + col;
    var value = product;
    if ((params.flags & ACCUMULATE) != 0u) {
        value += c[index];
    }
    if ((params.flags & ADD_BIAS) != 0u) {
        value += bias[col];
    }
    if ((params.flags & RELU) != 0u) {
        value = max(value, 0.0);
    }
    c[index] = value;
}
