// Gaussian splatting projection, one thread per Gaussian (src/compute/SPLATTING.md,
// "Projection"). `project_forward` writes what binning and compositing need;
// `project_backward` recomputes the projection and chains the per-Gaussian screen-space
// gradients (written by splat_rasterize_backward.wgsl) to the inputs, adding to the output
// gradients so that several cameras accumulate.

//#include "splat_types.wgsl"

const NEAR_PLANE: f32 = 0.01;
const FAR_PLANE: f32 = 1e10;
const BLUR_VARIANCE: f32 = 0.3;
const GUARD_BAND: f32 = 0.3;
const ALPHA_THRESHOLD: f32 = 0.003921568627450980; // 1/255
const MAX_EXTENT_SIGMAS: f32 = 3.33;
const TILE_SIZE: f32 = 16.0;

// Diagnostics counters (indices into `diagnostics`).
const DIAG_NON_FINITE_INPUT: u32 = 0u;
const DIAG_NON_FINITE_PROJECTION: u32 = 1u;
const DIAG_CULLED_DEPTH: u32 = 2u;
const DIAG_CULLED_COVARIANCE: u32 = 3u;
const DIAG_CULLED_OPACITY: u32 = 4u;
const DIAG_CULLED_OFFSCREEN: u32 = 5u;
const DIAG_VISIBLE: u32 = 6u;
const DIAG_NON_FINITE_GRADIENT: u32 = 7u;

const SH_C0: f32 = 0.28209479177387814;
const SH_C1: f32 = 0.4886025119029199;
const SH_C2: array<f32, 5> = array<f32, 5>(1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396);
const SH_C3: array<f32, 7> = array<f32, 7>(-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658, 1.445305721320277, -0.5900435899266435);

@group(0) @binding(0) var<uniform> camera: SplatCamera;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> covariances: array<f32>;
@group(0) @binding(3) var<storage, read> opacities: array<f32>;
@group(0) @binding(4) var<storage, read> sh: array<f32>;
// Forward outputs.
@group(0) @binding(5) var<storage, read_write> projected: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> rects: array<vec4<u32>>;
@group(0) @binding(7) var<storage, read_write> depth_keys: array<u32>;
@group(0) @binding(8) var<storage, read_write> indices: array<u32>;
@group(0) @binding(9) var<storage, read_write> diagnostics: array<atomic<u32>>;
// Backward: screen-space gradients in, input gradients out (accumulated).
@group(0) @binding(10) var<storage, read> screen_gradients: array<f32>;
@group(0) @binding(11) var<storage, read_write> grad_means: array<f32>;
@group(0) @binding(12) var<storage, read_write> grad_covariances: array<f32>;
@group(0) @binding(13) var<storage, read_write> grad_opacities: array<f32>;
@group(0) @binding(14) var<storage, read_write> grad_sh: array<f32>;
@group(0) @binding(15) var<storage, read_write> grad_mean_2d_norm: array<f32>;

fn gaussian_index(group: vec3<u32>, groups: vec3<u32>, local: u32) -> u32 {
    return (group.x + group.y * groups.x) * 256u + local;
}

//#include "finite.wgsl"

fn rotation() -> mat3x3<f32> {
    // Columns of R from its rows.
    let r0 = camera.rotation0.xyz;
    let r1 = camera.rotation1.xyz;
    let r2 = camera.rotation2.xyz;
    return transpose(mat3x3<f32>(r0, r1, r2));
}

fn world_covariance(g: u32) -> mat3x3<f32> {
    let c = array<f32, 6>(
        covariances[g * 6u], covariances[g * 6u + 1u], covariances[g * 6u + 2u],
        covariances[g * 6u + 3u], covariances[g * 6u + 4u], covariances[g * 6u + 5u],
    );
    return mat3x3<f32>(
        vec3<f32>(c[0], c[1], c[2]),
        vec3<f32>(c[1], c[3], c[4]),
        vec3<f32>(c[2], c[4], c[5]),
    );
}

fn inputs_finite(g: u32) -> bool {
    var ok = finite(means[g * 3u]) && finite(means[g * 3u + 1u]) && finite(means[g * 3u + 2u]);
    for (var i = 0u; i < 6u; i = i + 1u) {
        ok = ok && finite(covariances[g * 6u + i]);
    }
    ok = ok && finite(opacities[g]);
    let sh_values = camera.counts.y * 3u;
    for (var i = 0u; i < sh_values; i = i + 1u) {
        ok = ok && finite(sh[g * sh_values + i]);
    }
    return ok;
}

struct ShBasis {
    values: array<f32, 16>,
    // d Y_k / d dir, the direction components treated as independent.
    gradients: array<vec3<f32>, 16>,
}

fn sh_basis(dir: vec3<f32>, coefficients: u32) -> ShBasis {
    var out: ShBasis;
    for (var k = 0u; k < 16u; k = k + 1u) {
        out.values[k] = 0.0;
        out.gradients[k] = vec3<f32>(0.0);
    }
    let x = dir.x;
    let y = dir.y;
    let z = dir.z;
    out.values[0] = SH_C0;
    if coefficients >= 4u {
        out.values[1] = -SH_C1 * y;
        out.values[2] = SH_C1 * z;
        out.values[3] = -SH_C1 * x;
        out.gradients[1] = vec3<f32>(0.0, -SH_C1, 0.0);
        out.gradients[2] = vec3<f32>(0.0, 0.0, SH_C1);
        out.gradients[3] = vec3<f32>(-SH_C1, 0.0, 0.0);
    }
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    if coefficients >= 9u {
        let k = SH_C2;
        out.values[4] = k[0] * x * y;
        out.values[5] = k[1] * y * z;
        out.values[6] = k[2] * (2.0 * zz - xx - yy);
        out.values[7] = k[3] * x * z;
        out.values[8] = k[4] * (xx - yy);
        out.gradients[4] = vec3<f32>(k[0] * y, k[0] * x, 0.0);
        out.gradients[5] = vec3<f32>(0.0, k[1] * z, k[1] * y);
        out.gradients[6] = vec3<f32>(-2.0 * k[2] * x, -2.0 * k[2] * y, 4.0 * k[2] * z);
        out.gradients[7] = vec3<f32>(k[3] * z, 0.0, k[3] * x);
        out.gradients[8] = vec3<f32>(2.0 * k[4] * x, -2.0 * k[4] * y, 0.0);
    }
    if coefficients >= 16u {
        let k = SH_C3;
        out.values[9] = k[0] * y * (3.0 * xx - yy);
        out.values[10] = k[1] * x * y * z;
        out.values[11] = k[2] * y * (4.0 * zz - xx - yy);
        out.values[12] = k[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
        out.values[13] = k[4] * x * (4.0 * zz - xx - yy);
        out.values[14] = k[5] * z * (xx - yy);
        out.values[15] = k[6] * x * (xx - 3.0 * yy);
        out.gradients[9] = vec3<f32>(k[0] * 6.0 * x * y, k[0] * 3.0 * (xx - yy), 0.0);
        out.gradients[10] = vec3<f32>(k[1] * y * z, k[1] * x * z, k[1] * x * y);
        out.gradients[11] = vec3<f32>(-k[2] * 2.0 * x * y, k[2] * (4.0 * zz - xx - 3.0 * yy), k[2] * 8.0 * y * z);
        out.gradients[12] = vec3<f32>(-k[3] * 6.0 * x * z, -k[3] * 6.0 * y * z, k[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy));
        out.gradients[13] = vec3<f32>(k[4] * (4.0 * zz - 3.0 * xx - yy), -k[4] * 2.0 * x * y, k[4] * 8.0 * x * z);
        out.gradients[14] = vec3<f32>(k[5] * 2.0 * x * z, -k[5] * 2.0 * y * z, k[5] * (xx - yy));
        out.gradients[15] = vec3<f32>(k[6] * 3.0 * (xx - yy), -k[6] * 6.0 * x * y, 0.0);
    }
    return out;
}

// Everything the projection computes for one Gaussian, shared by forward and backward.
struct Projection {
    visible: bool,
    // Which diagnostics counter explains a cull.
    cull_reason: u32,
    p: vec3<f32>,
    // Guard-band-clamped x/z and y/z, and whether each clamp was inactive.
    uv: vec2<f32>,
    uv_free: vec2<bool>,
    jacobian: mat3x2<f32>,
    camera_covariance: mat3x3<f32>,
    // (a, b, c) of the 2D covariance and its conic (A, B, C).
    cov2d: vec3<f32>,
    conic: vec3<f32>,
    mean2d: vec2<f32>,
    radius: vec2<f32>,
    dir: vec3<f32>,
    dir_length: f32,
    colour_raw: vec3<f32>,
    rect: vec4<u32>,
}

fn project(g: u32) -> Projection {
    var out: Projection;
    out.visible = false;
    out.rect = vec4<u32>(0u);
    if !inputs_finite(g) {
        out.cull_reason = DIAG_NON_FINITE_INPUT;
        return out;
    }
    let mean = vec3<f32>(means[g * 3u], means[g * 3u + 1u], means[g * 3u + 2u]);
    let r = rotation();
    let t = vec3<f32>(camera.rotation0.w, camera.rotation1.w, camera.rotation2.w);
    let p = r * mean + t;
    out.p = p;
    if !(finite(p.x) && finite(p.y) && finite(p.z)) {
        out.cull_reason = DIAG_NON_FINITE_PROJECTION;
        return out;
    }
    if !(p.z >= NEAR_PLANE && p.z <= FAR_PLANE) {
        out.cull_reason = DIAG_CULLED_DEPTH;
        return out;
    }
    let fx = camera.intrinsics.x;
    let fy = camera.intrinsics.y;
    let cx = camera.intrinsics.z;
    let cy = camera.intrinsics.w;
    let width = f32(camera.image.x);
    let height = f32(camera.image.y);
    let sigma_cam = r * world_covariance(g) * transpose(r);
    out.camera_covariance = sigma_cam;
    let lim_x_pos = (width - cx) / fx + GUARD_BAND * width / (2.0 * fx);
    let lim_x_neg = cx / fx + GUARD_BAND * width / (2.0 * fx);
    let lim_y_pos = (height - cy) / fy + GUARD_BAND * height / (2.0 * fy);
    let lim_y_neg = cy / fy + GUARD_BAND * height / (2.0 * fy);
    let inv_z = 1.0 / p.z;
    let x_over_z = p.x * inv_z;
    let y_over_z = p.y * inv_z;
    let u = clamp(x_over_z, -lim_x_neg, lim_x_pos);
    let v = clamp(y_over_z, -lim_y_neg, lim_y_pos);
    out.uv = vec2<f32>(u, v);
    out.uv_free = vec2<bool>(
        x_over_z >= -lim_x_neg && x_over_z <= lim_x_pos,
        y_over_z >= -lim_y_neg && y_over_z <= lim_y_pos,
    );
    // Column-major 3x2: columns are d/dx, d/dy, d/dz of the two screen coordinates.
    let jacobian = mat3x2<f32>(
        vec2<f32>(fx * inv_z, 0.0),
        vec2<f32>(0.0, fy * inv_z),
        vec2<f32>(-fx * u * inv_z, -fy * v * inv_z),
    );
    out.jacobian = jacobian;
    let cov = jacobian * sigma_cam * transpose(jacobian);
    let a = cov[0][0] + BLUR_VARIANCE;
    let b = cov[1][0];
    let c = cov[1][1] + BLUR_VARIANCE;
    out.cov2d = vec3<f32>(a, b, c);
    let det = a * c - b * b;
    if !(finite(a) && finite(c) && finite(det)) {
        out.cull_reason = DIAG_NON_FINITE_PROJECTION;
        return out;
    }
    if !(a > 0.0 && c > 0.0 && det > 0.0) {
        out.cull_reason = DIAG_CULLED_COVARIANCE;
        return out;
    }
    let inv_det = 1.0 / det;
    out.conic = vec3<f32>(c * inv_det, -b * inv_det, a * inv_det);
    out.mean2d = vec2<f32>(fx * p.x * inv_z + cx, fy * p.y * inv_z + cy);
    if !(finite(out.conic.x) && finite(out.conic.y) && finite(out.conic.z) && finite(out.mean2d.x)
        && finite(out.mean2d.y)) {
        out.cull_reason = DIAG_NON_FINITE_PROJECTION;
        return out;
    }
    let opacity = opacities[g];
    if opacity < ALPHA_THRESHOLD {
        out.cull_reason = DIAG_CULLED_OPACITY;
        return out;
    }
    let extent = min(MAX_EXTENT_SIGMAS, sqrt(max(0.0, 2.0 * log(255.0 * opacity))));
    let radius = vec2<f32>(ceil(extent * sqrt(a)), ceil(extent * sqrt(c)));
    out.radius = radius;
    if !(radius.x > 0.0 && radius.y > 0.0) {
        out.cull_reason = DIAG_CULLED_OFFSCREEN;
        return out;
    }
    // [floor((m - r) / 16), ceil((m + r) / 16)) per axis, clamped to the tile grid.
    let tiles = vec2<f32>(f32(camera.image.z), f32(camera.image.w));
    let tile_low = clamp(floor((out.mean2d - radius) / TILE_SIZE), vec2<f32>(0.0), tiles);
    let tile_high = clamp(ceil((out.mean2d + radius) / TILE_SIZE), vec2<f32>(0.0), tiles);
    let rect = vec4<u32>(u32(tile_low.x), u32(tile_low.y), u32(tile_high.x), u32(tile_high.y));
    if rect.x >= rect.z || rect.y >= rect.w {
        out.cull_reason = DIAG_CULLED_OFFSCREEN;
        return out;
    }
    // Colour along the viewing direction.
    let offset = mean - camera.center.xyz;
    out.dir_length = length(offset);
    out.dir = offset / out.dir_length;
    let basis = sh_basis(out.dir, camera.counts.y);
    var colour = vec3<f32>(0.5);
    let base = g * camera.counts.y * 3u;
    for (var k = 0u; k < camera.counts.y; k = k + 1u) {
        colour = colour + basis.values[k] * vec3<f32>(sh[base + k * 3u], sh[base + k * 3u + 1u], sh[base + k * 3u + 2u]);
    }
    out.colour_raw = colour;
    if !(finite(colour.x) && finite(colour.y) && finite(colour.z)) {
        out.cull_reason = DIAG_NON_FINITE_PROJECTION;
        return out;
    }
    out.rect = rect;
    out.visible = true;
    return out;
}

@compute @workgroup_size(256)
fn project_forward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let g = gaussian_index(group, groups, local);
    if g >= camera.counts.x {
        return;
    }
    let projection = project(g);
    indices[g] = g;
    if !projection.visible {
        atomicAdd(&diagnostics[projection.cull_reason], 1u);
        projected[g * 3u] = vec4<f32>(0.0);
        projected[g * 3u + 1u] = vec4<f32>(0.0);
        projected[g * 3u + 2u] = vec4<f32>(0.0);
        rects[g] = vec4<u32>(0u);
        depth_keys[g] = 0xffffffffu;
        return;
    }
    atomicAdd(&diagnostics[DIAG_VISIBLE], 1u);
    projected[g * 3u] = vec4<f32>(projection.mean2d, projection.p.z, opacities[g]);
    projected[g * 3u + 1u] = vec4<f32>(projection.conic, projection.radius.x);
    projected[g * 3u + 2u] = vec4<f32>(max(projection.colour_raw, vec3<f32>(0.0)), projection.radius.y);
    rects[g] = projection.rect;
    // Positive floats order like their bit patterns.
    depth_keys[g] = bitcast<u32>(projection.p.z);
}

@compute @workgroup_size(256)
fn project_backward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let g = gaussian_index(group, groups, local);
    if g >= camera.counts.x {
        return;
    }
    var screen: array<f32, 10>;
    var any_gradient = false;
    for (var i = 0u; i < 10u; i = i + 1u) {
        screen[i] = screen_gradients[g * 10u + i];
        any_gradient = any_gradient || screen[i] != 0.0;
    }
    if !any_gradient {
        return;
    }
    let projection = project(g);
    if !projection.visible {
        return;
    }
    let d_mean2d = vec2<f32>(screen[0], screen[1]);
    let d_conic = vec3<f32>(screen[2], screen[3], screen[4]);
    let d_opacity = screen[5];
    let d_colour = vec3<f32>(screen[6], screen[7], screen[8])
        * select(vec3<f32>(0.0), vec3<f32>(1.0), projection.colour_raw > vec3<f32>(0.0));
    let d_depth = screen[9];

    let r = rotation();
    let fx = camera.intrinsics.x;
    let fy = camera.intrinsics.y;
    let p = projection.p;
    let z = p.z;

    // Conic = inverse(Sigma_2d): dSigma = -M G M with G the symmetric gradient of M.
    let conic = mat2x2<f32>(projection.conic.xy, projection.conic.yz);
    let g_conic = mat2x2<f32>(vec2<f32>(d_conic.x, 0.5 * d_conic.y), vec2<f32>(0.5 * d_conic.y, d_conic.z));
    let d_cov2d = (conic * g_conic * conic) * -1.0;
    // Sigma_2d = J W J^T (+ blur): dW = J^T G J, dJ = 2 G J W.
    let jacobian = projection.jacobian;
    let d_camera_cov = transpose(jacobian) * d_cov2d * jacobian;
    let d_jacobian = 2.0 * d_cov2d * jacobian * projection.camera_covariance;
    // World covariance: dSigma = R^T dW R; off-diagonal entries count (i, j) and (j, i).
    let d_world = transpose(r) * d_camera_cov * r;
    let d_covariance = array<f32, 6>(
        d_world[0][0],
        d_world[1][0] + d_world[0][1],
        d_world[2][0] + d_world[0][2],
        d_world[1][1],
        d_world[2][1] + d_world[1][2],
        d_world[2][2],
    );

    // Camera-space point: 2D mean, composited depth and the Jacobian entries.
    var d_p = vec3<f32>(
        fx / z * d_mean2d.x,
        fy / z * d_mean2d.y,
        -(fx * p.x * d_mean2d.x + fy * p.y * d_mean2d.y) / (z * z) + d_depth,
    );
    // J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]] with u, v the clamped x/z, y/z;
    // d_jacobian[column][row]. The clamp passes gradient only inside the guard band.
    let inv_z = 1.0 / z;
    let inv_z2 = inv_z * inv_z;
    let u = projection.uv.x;
    let v = projection.uv.y;
    let d_j00 = d_jacobian[0][0];
    let d_j11 = d_jacobian[1][1];
    let d_j02 = d_jacobian[2][0];
    let d_j12 = d_jacobian[2][1];
    d_p.z -= d_j00 * fx * inv_z2 + d_j11 * fy * inv_z2;
    d_p.z += d_j02 * fx * u * inv_z2 + d_j12 * fy * v * inv_z2;
    let d_u = -d_j02 * fx * inv_z;
    let d_v = -d_j12 * fy * inv_z;
    if projection.uv_free.x {
        d_p.x += d_u * inv_z;
        d_p.z -= d_u * p.x * inv_z2;
    }
    if projection.uv_free.y {
        d_p.y += d_v * inv_z;
        d_p.z -= d_v * p.y * inv_z2;
    }
    var d_mean = transpose(r) * d_p;

    // SH colour: coefficients and, through the view direction, the mean.
    let basis = sh_basis(projection.dir, camera.counts.y);
    let sh_base = g * camera.counts.y * 3u;
    var d_dir = vec3<f32>(0.0);
    for (var k = 0u; k < camera.counts.y; k = k + 1u) {
        let coefficient = vec3<f32>(sh[sh_base + k * 3u], sh[sh_base + k * 3u + 1u], sh[sh_base + k * 3u + 2u]);
        d_dir += basis.gradients[k] * dot(coefficient, d_colour);
    }
    let dir = projection.dir;
    d_mean += (d_dir - dir * dot(dir, d_dir)) / projection.dir_length;

    let norm = length(d_mean2d);
    var ok = finite(d_mean.x) && finite(d_mean.y) && finite(d_mean.z) && finite(norm) && finite(d_opacity);
    for (var i = 0u; i < 6u; i = i + 1u) {
        ok = ok && finite(d_covariance[i]);
    }
    for (var i = 0u; i < 10u; i = i + 1u) {
        ok = ok && finite(screen[i]);
    }
    if !ok {
        // This camera's gradient of this Gaussian is dropped (SPLATTING.md: nothing
        // non-finite leaves an operation).
        atomicAdd(&diagnostics[DIAG_NON_FINITE_GRADIENT], 1u);
        return;
    }
    let cov_base = g * 6u;
    for (var i = 0u; i < 6u; i = i + 1u) {
        grad_covariances[cov_base + i] += d_covariance[i];
    }
    grad_means[g * 3u] += d_mean.x;
    grad_means[g * 3u + 1u] += d_mean.y;
    grad_means[g * 3u + 2u] += d_mean.z;
    grad_opacities[g] += d_opacity;
    for (var k = 0u; k < camera.counts.y; k = k + 1u) {
        let y = basis.values[k];
        grad_sh[sh_base + k * 3u] += y * d_colour.x;
        grad_sh[sh_base + k * 3u + 1u] += y * d_colour.y;
        grad_sh[sh_base + k * 3u + 2u] += y * d_colour.z;
    }
    grad_mean_2d_norm[g] += norm;
}
