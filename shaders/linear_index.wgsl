// The flat index of a thread (and of its workgroup) in a kernel dispatched as a 2D grid of
// workgroups (rows of `num_workgroups.x` groups, so dispatches beyond the per-dimension
// limit of 65535 groups fit), included by such kernels with `//#include "linear_index.wgsl"`
// (src/compute/src/backend/shaders.rs). The including kernel declares `const WORKGROUP: u32`,
// its one-dimensional workgroup size; the caller still returns early for an index past its
// item count, since the last row of groups may run past it.

fn linear_index(workgroup: vec3<u32>, groups: vec3<u32>, local: u32) -> u32 {
    return block_index(workgroup, groups) * WORKGROUP + local;
}

// The flat index of the workgroup itself.
fn block_index(workgroup: vec3<u32>, groups: vec3<u32>) -> u32 {
    return workgroup.x + workgroup.y * groups.x;
}
