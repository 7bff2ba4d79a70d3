// Reductions for the dense-layer backward (src/compute/src/nn/gpu.rs), f32, no atomics.
//
// `column_sums`: partial column sums of a rows x cols matrix (the bias gradient
// db = sum over rows of dY'), with the ReLU mask fused: element (r, j) counts only where
// mask[r * cols + j] > 0 when MASK is set. Workgroup (x, y) sums columns 64 x .. 64 x + 63 over
// rows y * rows_per_chunk .. and writes partials[y * cols + j]; neighbouring threads read
// neighbouring columns.
//
// `accumulate_partials`: destination[dst_offset + i] (+)= sum over s of source[s * len + i], in
// slice order (deterministic), for the k-split weight gradient and the column sums above.

struct Params {
    // column_sums: rows, cols, rows_per_chunk, flags.
    // accumulate_partials: len, slices, dst_offset, groups_x (workgroups per grid row),
    // accumulate (0: overwrite the destination).
    p0: u32,
    p1: u32,
    p2: u32,
    p3: u32,
    p4: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

const MASK: u32 = 1u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> source: array<f32>;
@group(0) @binding(2) var<storage, read> mask: array<f32>;
@group(0) @binding(3) var<storage, read_write> destination: array<f32>;

@compute @workgroup_size(64)
fn column_sums(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let rows = params.p0;
    let cols = params.p1;
    let col = group.x * 64u + local;
    if (col >= cols) {
        return;
    }
    let row_begin = group.y * params.p2;
    let row_end = min(rows, row_begin + params.p2);
    let masked = (params.p3 & MASK) != 0u;
    var sum = 0.0;
    for (var row = row_begin; row < row_end; row++) {
        let index = row * cols + col;
        let value = source[index];
        if (!masked || mask[index] > 0.0) {
            sum += value;
        }
    }
    destination[group.y * cols + col] = sum;
}

@compute @workgroup_size(256)
fn accumulate_partials(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let len = params.p0;
    let i = (group.x + group.y * params.p3) * 256u + local;
    if (i >= len) {
        return;
    }
    var sum = 0.0;
    if (params.p4 != 0u) {
        sum = destination[params.p2 + i];
    }
    for (var s = 0u; s < params.p1; s++) {
        sum += source[s * len + i];
    }
    destination[params.p2 + i] = sum;
}
