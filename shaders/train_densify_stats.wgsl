// Densification statistics on the device (stages/train/src/resident/densify.rs; the cpu twin
// is `GaussianState::accumulate_gradient_stats` fed as `Trainer::densify_phase` feeds it):
// a Gaussian whose view-space gradient norm is > 0 was visible; its norm times half the
// image size (3DGS's NDC units) is added to `grad_accum` and 1 to `grad_count`. A NaN norm
// compares false and counts as not visible, as on the cpu. One thread per Gaussian; the
// grid may be 2D. The step record is the u32 array of train_adam.wgsl.

const R_COUNT: u32 = 0u;
const R_HALF_SIZE: u32 = 10u;

@group(0) @binding(0) var<storage, read> record: array<u32>;
@group(0) @binding(1) var<storage, read> mean_2d_norm: array<f32>;
@group(0) @binding(2) var<storage, read_write> grad_accum: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad_count: array<f32>;

@compute @workgroup_size(256)
fn accumulate(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = (group.x + group.y * groups.x) * 256u + local;
    if (i >= record[R_COUNT]) {
        return;
    }
    let g = mean_2d_norm[i];
    if (g > 0.0) {
        grad_accum[i] = grad_accum[i] + g * bitcast<f32>(record[R_HALF_SIZE]);
        grad_count[i] = grad_count[i] + 1.0;
    }
}
