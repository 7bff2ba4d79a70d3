// Tensor-core matrix product of the dense layers' mixed-precision path
// (src/compute/src/nn/gpu.rs, `MatmulPath::TensorCores`): cooperative 16 x 16 x 16 matrices,
// f16 operands, f32 accumulation.
//
//   partials[split] = A[:, k slice] * B[k slice, :]
//
// A (m_pad x k_pad) and B (k_pad x n_pad) are row-major f16 copies of the operands, scaled and
// zero-padded to multiples of 32 (rows of A, columns of B) and 16 (k) by `pack` in
// nn_matmul_f16.wgsl, which also resolves strides, transposition and the ReLU mask: this
// kernel reads whole tiles with no bounds or layout cases. Its f32 products go to a scratch
// buffer, one m_pad x n_pad slice per k split; `epilogue` in nn_matmul_f16.wgsl unscales them,
// sums the splits in order and applies accumulate, bias and ReLU.
//
// A workgroup is exactly one subgroup (SUBGROUP_SIZE, set by the host to the adapter's fixed
// subgroup size; the path is not taken where the size may vary), so the cooperative operations,
// which need the whole subgroup in uniform control flow, see only workgroup-uniform values:
// no subgroup index, no shared memory, no barriers. It computes a 32 x 32 block of C as four
// accumulators, reusing each loaded tile of A and B twice.
//
// naga 30 types a cooperative matrix by its role and scalar (`coop_mat16x16<f16, A>`); the
// multiply-add takes its result type from C, so f16 A and B with an f32 C is one
// OpCooperativeMatrixMulAddKHR, the configuration (M = N = K = 16, A/B f16, C/result f32) the
// host requires among the adapter's cooperative-matrix properties.

enable f16;
enable wgpu_cooperative_matrix;

struct Params {
    k_pad: u32,
    n_pad: u32,
    m_blocks: u32,
    k_per_split: u32,
    partial_stride: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

const BLOCK: u32 = 32u;
const TILE: u32 = 16u;

// The adapter's subgroup size (a fixed one); 32 on NVIDIA, the only default that matters for
// validation.
override SUBGROUP_SIZE: u32 = 32u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> a: array<f16>;
@group(0) @binding(2) var<storage, read> b: array<f16>;
@group(0) @binding(3) var<storage, read_write> partials: array<f32>;

@compute @workgroup_size(SUBGROUP_SIZE)
fn multiply(@builtin(workgroup_id) group: vec3<u32>) {
    let block_row = group.y % params.m_blocks;
    let split = group.y / params.m_blocks;
    let row0 = block_row * BLOCK;
    let row1 = row0 + TILE;
    let col0 = group.x * BLOCK;
    let col1 = col0 + TILE;
    let k_begin = split * params.k_per_split;
    let k_end = min(params.k_pad, k_begin + params.k_per_split);
    let k_pad = params.k_pad;
    let n_pad = params.n_pad;

    // c_uv is the 16 x 16 tile of C at rows row_u, columns col_v.
    var c_00 = coop_mat16x16<f32, C>();
    var c_01 = coop_mat16x16<f32, C>();
    var c_10 = coop_mat16x16<f32, C>();
    var c_11 = coop_mat16x16<f32, C>();
    for (var k = k_begin; k < k_end; k += TILE) {
        // Row-major loads (`T`): element (r, c) of a tile at pointer + r * stride + c.
        let a_at = row0 * k_pad + k;
        let b_at = k * n_pad + col0;
        let a_0 = coopLoadT<coop_mat16x16<f16, A>>(&a[a_at], k_pad);
        let a_1 = coopLoadT<coop_mat16x16<f16, A>>(&a[a_at + TILE * k_pad], k_pad);
        let b_0 = coopLoadT<coop_mat16x16<f16, B>>(&b[b_at], n_pad);
        let b_1 = coopLoadT<coop_mat16x16<f16, B>>(&b[b_at + TILE], n_pad);
        c_00 = coopMultiplyAdd(a_0, b_0, c_00);
        c_01 = coopMultiplyAdd(a_0, b_1, c_01);
        c_10 = coopMultiplyAdd(a_1, b_0, c_10);
        c_11 = coopMultiplyAdd(a_1, b_1, c_11);
    }
    let base = split * params.partial_stride;
    store_tile(c_00, base + row0 * n_pad + col0, n_pad);
    store_tile(c_01, base + row0 * n_pad + col1, n_pad);
    store_tile(c_10, base + row1 * n_pad + col0, n_pad);
    store_tile(c_11, base + row1 * n_pad + col1, n_pad);
}

// Stores a tile of C row-major at partials[at], rows `stride` apart. A function of its own
// because naga 30's WGSL front end records `coopStore` before the expressions it reads are
// emitted, and its SPIR-V writer then fails on them ("Expression [..] is not cached"):
// function arguments need no emitting.
fn store_tile(tile: coop_mat16x16<f32, C>, at: u32, stride: u32) {
    coopStoreT(tile, &partials[at], stride);
}
