// Forward compositing (SPLATTING.md, "Compositing"): one 16x16 workgroup per tile, one
// thread per pixel; the tile's depth-sorted Gaussians are loaded into workgroup memory in
// batches of 256, and the workgroup stops early once every pixel is done.
// Each Gaussian is only evaluated on pixels within one pixel of its screen box, exactly as the
// cpu backend does.

//#include "splat_types.wgsl"

const TILE: u32 = 16u;
const BATCH: u32 = 256u;
const ALPHA_THRESHOLD: f32 = 0.003921568627450980; // 1/255
const MAX_ALPHA: f32 = 0.99;
const MIN_TRANSMITTANCE: f32 = 1e-4;

@group(0) @binding(0) var<uniform> camera: SplatCamera;
@group(0) @binding(1) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> pair_gaussians: array<u32>;
// Three vec4 per Gaussian: (mean x, mean y, depth, opacity), (conic A, B, C, radius x),
// (colour r, g, b, radius y).
@group(0) @binding(3) var<storage, read> projected: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> out_colour: array<f32>;
@group(0) @binding(5) var<storage, read_write> out_alpha: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_depth: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_transmittance: array<f32>;
@group(0) @binding(8) var<storage, read_write> out_contributors: array<u32>;

var<workgroup> batch_a: array<vec4<f32>, BATCH>;
var<workgroup> batch_b: array<vec4<f32>, BATCH>;
var<workgroup> batch_c: array<vec4<f32>, BATCH>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> done_snapshot: u32;

//#include "splat_pixel.wgsl"

@compute @workgroup_size(16, 16)
fn rasterize_forward(
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

    if local == 0u {
        atomicStore(&done_count, 0u);
    }
    workgroupBarrier();
    var done = !inside;
    if done {
        atomicAdd(&done_count, 1u);
    }
    var transmittance = 1.0;
    var colour = vec3<f32>(0.0);
    var depth = 0.0;
    var contributors = 0u;

    let total = range.y - range.x;
    let batches = (total + BATCH - 1u) / BATCH;
    for (var batch = 0u; batch < batches; batch = batch + 1u) {
        workgroupBarrier();
        if local == 0u {
            done_snapshot = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&done_snapshot) == TILE * TILE {
            break;
        }
        let start = batch * BATCH;
        let load = start + local;
        if load < total {
            let g = pair_gaussians[range.x + load];
            batch_a[local] = projected[g * 3u];
            batch_b[local] = projected[g * 3u + 1u];
            batch_c[local] = projected[g * 3u + 2u];
        }
        workgroupBarrier();
        let count = min(BATCH, total - start);
        for (var j = 0u; j < count && !done; j = j + 1u) {
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
            var alpha = min(MAX_ALPHA, a.w * exp(power));
            if alpha < ALPHA_THRESHOLD {
                continue;
            }
            if smooth_cutoff {
                alpha = alpha * smooth_step(alpha).x;
            }
            let next = transmittance * (1.0 - alpha);
            if next <= MIN_TRANSMITTANCE {
                done = true;
                atomicAdd(&done_count, 1u);
                break;
            }
            let weight = alpha * transmittance;
            colour = colour + weight * c.xyz;
            depth = depth + weight * a.z;
            transmittance = next;
            contributors = start + j + 1u;
        }
    }
    if inside {
        let index = py * width + px;
        let background = camera.background.xyz;
        out_colour[index * 3u] = colour.x + transmittance * background.x;
        out_colour[index * 3u + 1u] = colour.y + transmittance * background.y;
        out_colour[index * 3u + 2u] = colour.z + transmittance * background.z;
        out_alpha[index] = 1.0 - transmittance;
        out_depth[index] = depth;
        out_transmittance[index] = transmittance;
        out_contributors[index] = contributors;
    }
}
