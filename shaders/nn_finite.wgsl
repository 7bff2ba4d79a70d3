// Flags the first non-finite value of a tensor in a device status word, so a resident step
// keeps running and the host finds out when it reads the status with the logged scalars
// (src/compute/src/nn/gpu.rs, `NnGpu::flag_non_finite`).
//
// status[slot] = max(status[slot], 0xffffffff - i) over the non-finite values[i]: 0 means all
// finite, else the first bad index is 0xffffffff - status[slot]. The test is on the bits (an
// all-ones exponent is an infinity or a NaN), which no fast-math assumption can fold away.
// One thread per value; the grid may be 2D (`linear_index`).

struct Params {
    len: u32,
    slot: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> values: array<f32>;
@group(0) @binding(2) var<storage, read_write> status: array<atomic<u32>>;

const WORKGROUP: u32 = 256u;

//#include "linear_index.wgsl"
//#include "finite.wgsl"

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
    if (!finite(values[i])) {
        atomicMax(&status[params.slot], 0xffffffffu - i);
    }
}
