// Flags the first non-finite value of a tensor in a device status word, so a resident step
// keeps running and the host finds out when it reads the status with the logged scalars
// (src/compute/src/nn/gpu.rs, `NnGpu::flag_non_finite`).
//
// status[slot] = max(status[slot], 0xffffffff - i) over the non-finite values[i]: 0 means all
// finite, else the first bad index is 0xffffffff - status[slot]. The test is on the bits (an
// all-ones exponent is an infinity or a NaN), which no fast-math assumption can fold away.
// One thread per value; the grid may be 2D (index = x + y * groups_x).

struct Params {
    len: u32,
    groups_x: u32,
    slot: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> values: array<f32>;
@group(0) @binding(2) var<storage, read_write> status: array<atomic<u32>>;

//#include "finite.wgsl"

@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = (group.x + group.y * params.groups_x) * 256u + local;
    if (i >= params.len) {
        return;
    }
    if (!finite(values[i])) {
        atomicMax(&status[params.slot], 0xffffffffu - i);
    }
}
