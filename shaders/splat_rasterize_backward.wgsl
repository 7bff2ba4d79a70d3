// Backward compositing: one 16x16 workgroup per tile, one thread per pixel, walking the
// tile's list back to front in workgroup-memory batches (mirrors the cpu backend's
// `BackwardState::walk`). Each (pixel, Gaussian) contribution to the Gaussian's screen-space
// gradient (mean x, mean y, conic A, B, C, opacity, colour r, g, b, depth: 10 values per
// Gaussian) is added atomically; the atomic add is native f32 or a compare-exchange loop
// (the region below is swapped by the host, see backend/shaders.rs).

//#include "splat_types.wgsl"

const TILE: u32 = 16u;
const BATCH: u32 = 256u;
const ALPHA_THRESHOLD: f32 = 0.003921568627450980; // 1/255
const MAX_ALPHA: f32 = 0.99;

@group(0) @binding(0) var<uniform> camera: SplatCamera;
@group(0) @binding(1) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> pair_gaussians: array<u32>;
@group(0) @binding(3) var<storage, read> projected: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read> d_colour_in: array<f32>;
// Gradients of alpha and depth, or one zero element each when the loss does not use them
// (flags.y and flags.z say whether they are present).
@group(0) @binding(5) var<storage, read> d_alpha_in: array<f32>;
@group(0) @binding(6) var<storage, read> d_depth_in: array<f32>;
@group(0) @binding(7) var<storage, read> final_transmittance: array<f32>;
@group(0) @binding(8) var<storage, read> contributors_in: array<u32>;

// @atomic-add-begin
//#include "atomic_add_cas.wgsl"
// @atomic-add-end

var<workgroup> batch_a: array<vec4<f32>, BATCH>;
var<workgroup> batch_b: array<vec4<f32>, BATCH>;
var<workgroup> batch_c: array<vec4<f32>, BATCH>;
var<workgroup> batch_gaussian: array<u32, BATCH>;
var<workgroup> max_contributors: atomic<u32>;
var<workgroup> max_snapshot: u32;

//#include "splat_pixel.wgsl"

@compute @workgroup_size(16, 16)
fn rasterize_backward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_id) local_id: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let tile_x = group.x;
    let tile_y = group.y + camera.counts.z;
    let width = camera.image.x;
    let height = camera.image.y;
    let px = tile_x * TILE + local_id.x;
    let py = tile_y * TILE + local_id.y;
    let inside = px < width && py < height;
    let pixel = vec2<f32>(f32(px), f32(py));
    let centre = pixel + 0.5;
    let range = ranges[tile_y * camera.image.z + tile_x];
    let smooth_cutoff = camera.flags.x != 0u;

    var t_final = 1.0;
    var contributors = 0u;
    var d_colour = vec3<f32>(0.0);
    var d_alpha_out = 0.0;
    var d_depth_out = 0.0;
    let background = camera.background.xyz;
    if local == 0u {
        atomicStore(&max_contributors, 0u);
    }
    workgroupBarrier();
    if inside {
        let index = py * width + px;
        t_final = final_transmittance[index];
        contributors = contributors_in[index];
        d_colour = vec3<f32>(d_colour_in[index * 3u], d_colour_in[index * 3u + 1u], d_colour_in[index * 3u + 2u]);
        if camera.flags.y != 0u {
            d_alpha_out = d_alpha_in[index];
        }
        if camera.flags.z != 0u {
            d_depth_out = d_depth_in[index];
        }
        atomicMax(&max_contributors, contributors);
    }
    workgroupBarrier();
    if local == 0u {
        max_snapshot = atomicLoad(&max_contributors);
    }
    let last = workgroupUniformLoad(&max_snapshot);
    // Transmittance after the Gaussian being visited, colour and depth composited behind it.
    var transmittance = t_final;
    var colour_behind = t_final * background;
    var depth_behind = 0.0;

    let batches = (last + BATCH - 1u) / BATCH;
    for (var done_batches = 0u; done_batches < batches; done_batches = done_batches + 1u) {
        let batch = batches - 1u - done_batches;
        let start = batch * BATCH;
        workgroupBarrier();
        let load = start + local;
        if load < last {
            let g = pair_gaussians[range.x + load];
            batch_gaussian[local] = g;
            batch_a[local] = projected[g * 3u];
            batch_b[local] = projected[g * 3u + 1u];
            batch_c[local] = projected[g * 3u + 2u];
        }
        workgroupBarrier();
        let count = min(BATCH, last - start);
        for (var back = 0u; back < count; back = back + 1u) {
            let j = count - 1u - back;
            if start + j >= contributors {
                continue;
            }
            let a = batch_a[j];
            let b = batch_b[j];
            let c = batch_c[j];
            if !in_box(pixel, a.xy, vec2<f32>(b.w, c.w)) {
                continue;
            }
            let d = a.xy - centre;
            let power = -0.5 * (b.x * d.x * d.x + b.z * d.y * d.y) - b.y * d.x * d.y;
            if power > 0.0 {
                continue;
            }
            let gaussian = exp(power);
            let raw = a.w * gaussian;
            let clamped = min(MAX_ALPHA, raw);
            if clamped < ALPHA_THRESHOLD {
                continue;
            }
            var alpha = clamped;
            var smoothing = vec2<f32>(1.0, 0.0);
            if smooth_cutoff {
                smoothing = smooth_step(clamped);
                alpha = clamped * smoothing.x;
            }
            let inv_one_minus = 1.0 / (1.0 - alpha);
            let t = transmittance * inv_one_minus;
            let weight = alpha * t;
            var d_alpha = dot(d_colour, c.xyz * t - colour_behind * inv_one_minus);
            d_alpha += d_alpha_out * t_final * inv_one_minus;
            d_alpha += d_depth_out * (a.z * t - depth_behind * inv_one_minus);
            colour_behind += weight * c.xyz;
            depth_behind += weight * a.z;
            transmittance = t;

            let base = batch_gaussian[j] * 10u;
            gradient_add(base + 6u, weight * d_colour.x);
            gradient_add(base + 7u, weight * d_colour.y);
            gradient_add(base + 8u, weight * d_colour.z);
            gradient_add(base + 9u, weight * d_depth_out);
            if raw >= MAX_ALPHA {
                continue;
            }
            var d_raw = d_alpha;
            if smooth_cutoff {
                d_raw = d_alpha * (smoothing.x + clamped * smoothing.y);
            }
            let d_power = d_raw * raw;
            gradient_add(base + 5u, d_raw * gaussian);
            gradient_add(base + 2u, -0.5 * d.x * d.x * d_power);
            gradient_add(base + 3u, -d.x * d.y * d_power);
            gradient_add(base + 4u, -0.5 * d.y * d.y * d_power);
            gradient_add(base + 0u, -(b.x * d.x + b.y * d.y) * d_power);
            gradient_add(base + 1u, -(b.y * d.x + b.z * d.y) * d_power);
        }
    }
}
