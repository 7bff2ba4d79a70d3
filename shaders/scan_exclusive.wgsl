// Exclusive prefix sum of u32 values, one 256-element block per workgroup.
// `scan_blocks` scans each block in place and writes the block total to `block_sums`;
// the host scans `block_sums` the same way (recursively) and `scan_add` adds the scanned
// block totals back. Workgroups are laid out in 2D beyond the per-dimension limit.

struct ScanParams {
    count: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

const BLOCK: u32 = 256u;

@group(0) @binding(0) var<uniform> params: ScanParams;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;

var<workgroup> partial: array<u32, BLOCK>;

const WORKGROUP: u32 = BLOCK;
//#include "linear_index.wgsl"

@compute @workgroup_size(256)
fn scan_blocks(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let block = block_index(group, groups);
    let index = block * BLOCK + local;
    var value = 0u;
    if index < params.count {
        value = data[index];
    }
    partial[local] = value;
    workgroupBarrier();
    // Hillis-Steele inclusive scan: read, barrier, write, barrier.
    for (var offset = 1u; offset < BLOCK; offset = offset * 2u) {
        var add = 0u;
        if local >= offset {
            add = partial[local - offset];
        }
        workgroupBarrier();
        partial[local] = partial[local] + add;
        workgroupBarrier();
    }
    if index < params.count {
        data[index] = partial[local] - value;
    }
    if local == BLOCK - 1u && block * BLOCK < params.count {
        block_sums[block] = partial[local];
    }
}

@compute @workgroup_size(256)
fn scan_add(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let block = block_index(group, groups);
    let index = block * BLOCK + local;
    if index < params.count {
        data[index] = data[index] + block_sums[block];
    }
}
