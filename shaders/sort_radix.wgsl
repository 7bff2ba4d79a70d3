// Stable least-significant-digit radix sort of (u32 key, u32 value) pairs, 4 bits per pass.
// Per pass: `sort_count` writes each 256-element block's digit histogram digit-major
// (`counts[digit * blocks + block]`), the host scans `counts` exclusively (scan_exclusive.wgsl),
// and `sort_scatter` moves every pair to `counts[digit * blocks + block]` plus its stable rank
// among the block's pairs with the same digit. No subgroup operations: ranks come from a
// workgroup scan of one-hot digit counters packed two 16-bit lanes per u32.

struct SortParams {
    count: u32,
    shift: u32,
    blocks: u32,
    _pad: u32,
}

const BLOCK: u32 = 256u;
const DIGITS: u32 = 16u;
const WORDS: u32 = 8u; // 16 digits, two 16-bit counters per word

@group(0) @binding(0) var<uniform> params: SortParams;
@group(0) @binding(1) var<storage, read_write> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> values_in: array<u32>;
@group(0) @binding(3) var<storage, read_write> counts: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(5) var<storage, read_write> values_out: array<u32>;

var<workgroup> histogram: array<atomic<u32>, DIGITS>;
var<workgroup> packed: array<array<u32, WORDS>, BLOCK>;

const WORKGROUP: u32 = BLOCK;
//#include "linear_index.wgsl"

@compute @workgroup_size(256)
fn sort_count(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let block = block_index(group, groups);
    if local < DIGITS {
        atomicStore(&histogram[local], 0u);
    }
    workgroupBarrier();
    let index = block * BLOCK + local;
    if block < params.blocks && index < params.count {
        let digit = (keys_in[index] >> params.shift) & (DIGITS - 1u);
        atomicAdd(&histogram[digit], 1u);
    }
    workgroupBarrier();
    if block < params.blocks && local < DIGITS {
        counts[local * params.blocks + block] = atomicLoad(&histogram[local]);
    }
}

@compute @workgroup_size(256)
fn sort_scatter(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let block = block_index(group, groups);
    let index = block * BLOCK + local;
    let present = block < params.blocks && index < params.count;
    var key = 0u;
    var value = 0u;
    var digit = 0u;
    var mine: array<u32, WORDS>;
    for (var word = 0u; word < WORDS; word = word + 1u) {
        mine[word] = 0u;
    }
    if present {
        key = keys_in[index];
        value = values_in[index];
        digit = (key >> params.shift) & (DIGITS - 1u);
        mine[digit / 2u] = 1u << (16u * (digit % 2u));
    }
    packed[local] = mine;
    workgroupBarrier();
    // Inclusive Hillis-Steele scan of the packed counters (each lane stays <= 256).
    for (var offset = 1u; offset < BLOCK; offset = offset * 2u) {
        var add: array<u32, WORDS>;
        for (var word = 0u; word < WORDS; word = word + 1u) {
            add[word] = 0u;
        }
        if local >= offset {
            add = packed[local - offset];
        }
        workgroupBarrier();
        var sum = packed[local];
        for (var word = 0u; word < WORDS; word = word + 1u) {
            sum[word] = sum[word] + add[word];
        }
        packed[local] = sum;
        workgroupBarrier();
    }
    if present {
        let inclusive = (packed[local][digit / 2u] >> (16u * (digit % 2u))) & 0xffffu;
        let destination = counts[digit * params.blocks + block] + inclusive - 1u;
        keys_out[destination] = key;
        values_out[destination] = value;
    }
}
