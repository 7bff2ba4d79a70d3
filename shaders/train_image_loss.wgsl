// The photometric losses of one training camera on the device
// (stages/train/src/resident/image_loss.rs): the ground truth composited onto the iteration's
// background, L1 and mask MSE on the bound-box rect, 1 - SSIM on the rect's crop (11-tap
// Gaussian window, zero padding, "same" output, as src/compute/src/ssim.rs), their gradients
// with respect to the rendered colour and alpha, PSNR on the rect, and the scalars added into
// the device log record. The cpu oracle is `losses::image_loss` (+ `gaussians::psnr`).
//
// Every pixel kernel runs 256 threads per workgroup over a linear index
// `(workgroup.x + workgroup.y * groups.x) * 256 + local` (GpuContext::dispatch lays large
// dispatches out in 2D); threads past the end do nothing. Every value is gathered (one
// thread per value written) and every sum is a fixed-order tree, so no atomics are needed
// and results do not depend on the subgroup size.
//
// SSIM planes live in two crop-sized workspaces of `plane_stride()` values per plane:
// `planes` (15: the row-blurred mu_x, mu_y, E[xx], E[yy], E[xy] per channel, quantity-major;
// later its first 9 hold the row-blurred adjoints) and `adjoints` (10: d/d mu_x, d/d E[xx],
// d/d E[xy] per channel, then the per-pixel SSIM summed over channels).

// One camera of the iteration (16 words of the record, packed by
// `ImageLoss::begin_iteration`).
struct LossCamera {
    // First pixel of the ground truth image in its chunk.
    image_offset: u32,
    // First pixel of the rendered image in the colour/alpha buffers and of its gradient in
    // the gradient buffers.
    render_offset: u32,
    width: u32,
    height: u32,
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
    background_r: f32,
    background_g: f32,
    background_b: f32,
    // 1 / cameras: how much of the camera's terms and gradients enter the iteration's.
    scale: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
    _pad3: u32,
}

// The per-iteration record, written once per iteration, bound as words: 8 header words
// (iteration, cameras, mask weight, SSIM weight, LPIPS weight, 3 unused), then one
// `LossCamera` (16 words) per camera. The buffers are bound as plain words rather than
// structs because their Rust side lives in the train crate (stages/train/src/resident/
// image_loss.rs packs them), outside compute's struct-twin layout test.
// Per camera slot, created once with the workspace (a uniform of 4 x vec4 words): camera
// index, plane stride, C1 and C2 (f32 bits), then the 11 normalised Gaussian window weights
// (compute::ssim::gaussian_window, f32 bits), padded.
//
// The log record, 20 words: `current` (words 0-7) the iteration being recorded (its
// cameras' terms times their scale, summed), `sum` (8-15) the sum of `current` over the
// iterations since the last reset, both f32 with entries 0 l1, 1 mask_mse, 2 dssim, 3 lpips,
// 4 psnr, 5 total, 6-7 free; then u32 iterations (16), non-finite iterations (17), first
// non-finite iteration (18), last iteration (19).

@group(0) @binding(0) var<uniform> slot: array<vec4<u32>, 4>;
@group(0) @binding(1) var<storage, read> record: array<u32>;
// Packed 8-bit ground truth: r | g << 8 | b << 16 | mask << 24 per pixel.
@group(0) @binding(2) var<storage, read> truth: array<u32>;
@group(0) @binding(3) var<storage, read> colour: array<f32>;
@group(0) @binding(4) var<storage, read> alpha: array<f32>;
@group(0) @binding(5) var<storage, read_write> planes: array<f32>;
@group(0) @binding(6) var<storage, read_write> adjoints: array<f32>;
@group(0) @binding(7) var<storage, read_write> colour_gradient: array<f32>;
@group(0) @binding(8) var<storage, read_write> alpha_gradient: array<f32>;
// Per workgroup of `image_loss_gradient`: (l1 sum, squared mask error sum, SSIM sum,
// squared colour error sum).
@group(0) @binding(9) var<storage, read_write> partials: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> loss_log: array<u32>;
// One f32: the LPIPS value of the camera (compute::lpips::gpu resident path).
@group(0) @binding(11) var<storage, read> lpips_value: array<f32>;
// The composited target of one image, `H x W x 3` (what the resident LPIPS compares with).
@group(0) @binding(12) var<storage, read_write> targets: array<f32>;

const WORKGROUP: u32 = 256u;
const HALF_WINDOW: i32 = 5;

var<workgroup> shared_sums: array<vec4<f32>, 256>;

//#include "linear_index.wgsl"

const LOG_SUM: u32 = 8u;
const LOG_ITERATIONS: u32 = 16u;
const LOG_NONFINITE_ITERATIONS: u32 = 17u;
const LOG_FIRST_NONFINITE: u32 = 18u;
const LOG_LAST_ITERATION: u32 = 19u;

fn slot_camera() -> u32 {
    return slot[0].x;
}

fn plane_stride() -> u32 {
    return slot[0].y;
}

fn ssim_c1() -> f32 {
    return bitcast<f32>(slot[0].z);
}

fn ssim_c2() -> f32 {
    return bitcast<f32>(slot[0].w);
}

fn window(tap: i32) -> f32 {
    return bitcast<f32>(slot[1u + u32(tap) / 4u][u32(tap) % 4u]);
}

fn iteration() -> u32 {
    return record[0];
}

fn mask_weight() -> f32 {
    return bitcast<f32>(record[2]);
}

fn ssim_weight() -> f32 {
    return bitcast<f32>(record[3]);
}

fn lpips_weight() -> f32 {
    return bitcast<f32>(record[4]);
}

fn load_camera(index: u32) -> LossCamera {
    let b = 8u + 16u * index;
    return LossCamera(
        record[b], record[b + 1u], record[b + 2u], record[b + 3u],
        record[b + 4u], record[b + 5u], record[b + 6u], record[b + 7u],
        bitcast<f32>(record[b + 8u]), bitcast<f32>(record[b + 9u]),
        bitcast<f32>(record[b + 10u]), bitcast<f32>(record[b + 11u]),
        0u, 0u, 0u, 0u,
    );
}

fn log_add(index: u32, value: f32) {
    loss_log[index] = bitcast<u32>(bitcast<f32>(loss_log[index]) + value);
}

fn background(camera: LossCamera) -> vec3<f32> {
    return vec3<f32>(camera.background_r, camera.background_g, camera.background_b);
}

// The target of image pixel `pixel`: `m c + (1 - m) b` with `c = rgb / 255`, `m = mask / 255`
// (data::ImageRecord::colour_on).
fn target_colour(camera: LossCamera, pixel: u32) -> vec3<f32> {
    let word = truth[camera.image_offset + pixel];
    let rgb = vec3<f32>(
        f32(word & 255u),
        f32((word >> 8u) & 255u),
        f32((word >> 16u) & 255u),
    ) / 255.0;
    let mask = f32(word >> 24u) / 255.0;
    return mask * rgb + (1.0 - mask) * background(camera);
}

fn target_mask(camera: LossCamera, pixel: u32) -> f32 {
    return f32(truth[camera.image_offset + pixel] >> 24u) / 255.0;
}

// The bound-box rect's (crop's) width and height.
fn crop_size(camera: LossCamera) -> vec2<u32> {
    return vec2<u32>(camera.x1 - camera.x0, camera.y1 - camera.y0);
}

fn rendered_colour(camera: LossCamera, pixel: u32) -> vec3<f32> {
    let base = 3u * (camera.render_offset + pixel);
    return vec3<f32>(colour[base], colour[base + 1u], colour[base + 2u]);
}

// One thread: one crop pixel. The row pass of the five SSIM window means, per channel.
@compute @workgroup_size(256)
fn ssim_rows(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    let camera = load_camera(slot_camera());
    let crop = crop_size(camera);
    if (index >= crop.x * crop.y) {
        return;
    }
    let crop_width = crop.x;
    let row = index / crop_width;
    let col = index % crop_width;
    var mu_x = vec3<f32>(0.0);
    var mu_y = vec3<f32>(0.0);
    var e_xx = vec3<f32>(0.0);
    var e_yy = vec3<f32>(0.0);
    var e_xy = vec3<f32>(0.0);
    let line = (camera.y0 + row) * camera.width + camera.x0;
    for (var tap = 0; tap < 2 * HALF_WINDOW + 1; tap++) {
        let source = i32(col) + tap - HALF_WINDOW;
        if (source < 0 || source >= i32(crop_width)) {
            continue;
        }
        let weight = window(tap);
        let pixel = line + u32(source);
        let x = rendered_colour(camera, pixel);
        let y = target_colour(camera, pixel);
        mu_x += weight * x;
        mu_y += weight * y;
        e_xx += weight * (x * x);
        e_yy += weight * (y * y);
        e_xy += weight * (x * y);
    }
    let stride = plane_stride();
    for (var c = 0u; c < 3u; c++) {
        planes[(0u + c) * stride + index] = mu_x[c];
        planes[(3u + c) * stride + index] = mu_y[c];
        planes[(6u + c) * stride + index] = e_xx[c];
        planes[(9u + c) * stride + index] = e_yy[c];
        planes[(12u + c) * stride + index] = e_xy[c];
    }
}

// The column pass of `planes[first..first + count]` at crop pixel (row, col) of a crop
// `crop_width x crop_height`, into `out[0..count]`.
fn column_blur_planes(
    first: u32,
    row: u32,
    col: u32,
    crop_width: u32,
    crop_height: u32,
    values: ptr<function, array<f32, 15>>,
    count: u32,
) {
    for (var q = 0u; q < count; q++) {
        (*values)[q] = 0.0;
    }
    let stride = plane_stride();
    for (var tap = 0; tap < 2 * HALF_WINDOW + 1; tap++) {
        let source = i32(row) + tap - HALF_WINDOW;
        if (source < 0 || source >= i32(crop_height)) {
            continue;
        }
        let weight = window(tap);
        let at = u32(source) * crop_width + col;
        for (var q = 0u; q < count; q++) {
            (*values)[q] += weight * planes[(first + q) * stride + at];
        }
    }
}

// One thread: one crop pixel. The column pass of the window means, the SSIM of each channel
// and its partial derivatives (times d mean / d S = 1 / (3 n)) with respect to mu_x, E[xx]
// and E[xy], as compute::ssim::ssim_planes.
@compute @workgroup_size(256)
fn ssim_columns(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    let camera = load_camera(slot_camera());
    let crop = crop_size(camera);
    if (index >= crop.x * crop.y) {
        return;
    }
    let crop_width = crop.x;
    var values: array<f32, 15>;
    column_blur_planes(0u, index / crop_width, index % crop_width, crop_width, crop.y, &values, 15u);
    let mean_factor = 1.0 / (3.0 * f32(crop.x * crop.y));
    let stride = plane_stride();
    var ssim_sum = 0.0;
    for (var c = 0u; c < 3u; c++) {
        let m = values[c];
        let k = values[3u + c];
        let sxx = values[6u + c] - m * m;
        let syy = values[9u + c] - k * k;
        let sxy = values[12u + c] - m * k;
        let a1 = 2.0 * m * k + ssim_c1();
        let a2 = 2.0 * sxy + ssim_c2();
        let b1 = m * m + k * k + ssim_c1();
        let b2 = sxx + syy + ssim_c2();
        let inv = 1.0 / (b1 * b2);
        let s = a1 * a2 * inv;
        ssim_sum += s;
        adjoints[(0u + c) * stride + index] =
            ((2.0 * k * a2 - 2.0 * k * a1) * inv - s * (2.0 * m / b1 - 2.0 * m / b2)) * mean_factor;
        adjoints[(3u + c) * stride + index] = -s / b2 * mean_factor;
        adjoints[(6u + c) * stride + index] = 2.0 * a1 * inv * mean_factor;
    }
    adjoints[9u * stride + index] = ssim_sum;
}

// One thread: one crop pixel. The row pass of the nine adjoint planes into planes 0..9.
@compute @workgroup_size(256)
fn ssim_gradient_rows(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    let camera = load_camera(slot_camera());
    let crop = crop_size(camera);
    if (index >= crop.x * crop.y) {
        return;
    }
    let crop_width = crop.x;
    let col = index % crop_width;
    let line = index - col;
    let stride = plane_stride();
    var values: array<f32, 9>;
    for (var tap = 0; tap < 2 * HALF_WINDOW + 1; tap++) {
        let source = i32(col) + tap - HALF_WINDOW;
        if (source < 0 || source >= i32(crop_width)) {
            continue;
        }
        let weight = window(tap);
        for (var q = 0u; q < 9u; q++) {
            values[q] += weight * adjoints[q * stride + line + u32(source)];
        }
    }
    for (var q = 0u; q < 9u; q++) {
        planes[q * stride + index] = values[q];
    }
}

// One thread: one pixel of the whole image. Inside the rect: the L1, mask and (when its
// weight is not 0) SSIM gradients, times the camera's scale; outside: zeros. Each workgroup
// writes its sums (l1, squared mask error, SSIM, squared colour error) to `partials`.
@compute @workgroup_size(256)
fn image_loss_gradient(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let group_index = workgroup.x + workgroup.y * groups.x;
    let index = group_index * WORKGROUP + local;
    let camera = load_camera(slot_camera());
    let pixels = camera.width * camera.height;
    var sums = vec4<f32>(0.0);
    if (index < pixels) {
        let row = index / camera.width;
        let col = index % camera.width;
        let inside = col >= camera.x0 && col < camera.x1 && row >= camera.y0 && row < camera.y1;
        var gradient = vec3<f32>(0.0);
        var alpha_grad = 0.0;
        if (inside) {
            let crop = crop_size(camera);
            let crop_width = crop.x;
            let count = f32(crop.x * crop.y);
            let x = rendered_colour(camera, index);
            let y = target_colour(camera, index);
            let difference = x - y;
            sums.x = abs(difference.x) + abs(difference.y) + abs(difference.z);
            sums.w = dot(difference, difference);
            gradient = sign(difference) / (3.0 * count);
            if (ssim_weight() != 0.0) {
                let crop_row = row - camera.y0;
                let crop_col = col - camera.x0;
                var values: array<f32, 15>;
                column_blur_planes(0u, crop_row, crop_col, crop_width, crop.y, &values, 9u);
                let g_mu = vec3<f32>(values[0], values[1], values[2]);
                let g_exx = vec3<f32>(values[3], values[4], values[5]);
                let g_exy = vec3<f32>(values[6], values[7], values[8]);
                gradient -= ssim_weight() * (g_mu + 2.0 * x * g_exx + y * g_exy);
                sums.z = adjoints[9u * plane_stride() + crop_row * crop_width + crop_col];
            }
            let mask_difference = alpha[camera.render_offset + index] - target_mask(camera, index);
            sums.y = mask_difference * mask_difference;
            alpha_grad = mask_weight() * 2.0 * mask_difference / count;
        }
        let base = 3u * (camera.render_offset + index);
        colour_gradient[base] = camera.scale * gradient.x;
        colour_gradient[base + 1u] = camera.scale * gradient.y;
        colour_gradient[base + 2u] = camera.scale * gradient.z;
        alpha_gradient[camera.render_offset + index] = camera.scale * alpha_grad;
    }
    sum_over_workgroup(local, sums);
    let partial_count = (pixels + WORKGROUP - 1u) / WORKGROUP;
    if (local == 0u && group_index < partial_count) {
        partials[group_index] = shared_sums[0];
    }
}

// Leaves the sum of every thread's `sums` in `shared_sums[0]`, by a fixed tree (the result
// does not depend on scheduling). Called by all threads of the workgroup.
fn sum_over_workgroup(local: u32, sums: vec4<f32>) {
    shared_sums[local] = sums;
    workgroupBarrier();
    for (var width = WORKGROUP / 2u; width > 0u; width /= 2u) {
        if (local < width) {
            shared_sums[local] += shared_sums[local + width];
        }
        workgroupBarrier();
    }
}

//#include "finite.wgsl"

// One workgroup: sums the partials of `image_loss_gradient` in a fixed order, turns them into
// the camera's terms and adds them, times the camera's scale, into the log's `current`.
@compute @workgroup_size(256)
fn image_loss_reduce(@builtin(local_invocation_index) local: u32) {
    let camera = load_camera(slot_camera());
    let partial_count = (camera.width * camera.height + WORKGROUP - 1u) / WORKGROUP;
    var sums = vec4<f32>(0.0);
    for (var i = local; i < partial_count; i += WORKGROUP) {
        sums += partials[i];
    }
    sum_over_workgroup(local, sums);
    if (local == 0u) {
        let total_sums = shared_sums[0];
        let crop = crop_size(camera);
        let count = f32(crop.x * crop.y);
        let l1 = total_sums.x / (3.0 * count);
        let mask_mse = total_sums.y / count;
        var dssim = 0.0;
        if (ssim_weight() != 0.0) {
            dssim = 1.0 - total_sums.z / (3.0 * count);
        }
        let mse = max(total_sums.w / (3.0 * count), 1e-20);
        let psnr = -10.0 * log2(mse) / log2(10.0);
        let total = l1 + mask_weight() * mask_mse + ssim_weight() * dssim;
        log_add(0u, camera.scale * l1);
        log_add(1u, camera.scale * mask_mse);
        log_add(2u, camera.scale * dssim);
        log_add(4u, camera.scale * psnr);
        log_add(5u, camera.scale * total);
    }
}

// One thread: one pixel of the whole image; writes its composited target into `targets`.
@compute @workgroup_size(256)
fn composite_target(
    @builtin(workgroup_id) workgroup: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(workgroup, groups, local);
    let camera = load_camera(slot_camera());
    if (index >= camera.width * camera.height) {
        return;
    }
    let value = target_colour(camera, index);
    targets[3u * index] = value.x;
    targets[3u * index + 1u] = value.y;
    targets[3u * index + 2u] = value.z;
}

// One thread: adds the camera's LPIPS value (unweighted) and its weighted share of the total,
// times the camera's scale, into the log's `current`.
@compute @workgroup_size(1)
fn add_lpips() {
    let camera = load_camera(slot_camera());
    let value = lpips_value[0];
    log_add(3u, camera.scale * value);
    log_add(5u, camera.scale * lpips_weight() * value);
}

// One thread: closes the iteration: `sum += current`, one more iteration, and the first
// iteration whose total is not finite remembered (the host reports it as a divergence).
@compute @workgroup_size(1)
fn finish_iteration() {
    var all_finite = true;
    for (var i = 0u; i < 8u; i++) {
        let value = bitcast<f32>(loss_log[i]);
        log_add(LOG_SUM + i, value);
        if (i < 6u) {
            all_finite = all_finite && finite(value);
        }
    }
    loss_log[LOG_ITERATIONS] += 1u;
    loss_log[LOG_LAST_ITERATION] = iteration();
    if (!all_finite) {
        if (loss_log[LOG_NONFINITE_ITERATIONS] == 0u) {
            loss_log[LOG_FIRST_NONFINITE] = iteration();
        }
        loss_log[LOG_NONFINITE_ITERATIONS] += 1u;
    }
}
