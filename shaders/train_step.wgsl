// Element-wise steps of the resident training iteration (stages/train/src/resident/step.rs).

// `x`: the number of values.
@group(0) @binding(0) var<uniform> length: vec4<u32>;
@group(0) @binding(1) var<storage, read> source: array<f32>;
@group(0) @binding(2) var<storage, read_write> destination: array<f32>;

// destination += source over `length.x` values: a gradient with two paths joined. One
// thread per value; the grid may be 2D (index = x + y * groups_x).
@compute @workgroup_size(256)
fn add_into(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = (group.x + group.y * groups.x) * 256u + local;
    if (i >= length.x) {
        return;
    }
    destination[i] = destination[i] + source[i];
}
