// Device-resident skinning of the avatar's Gaussians (src/avatar/src/resident/skinning.rs),
// f32, with the maths of src/avatar/src/skinning.rs (`skin_forward`, `skin_backward`, the
// oracle) and of `avatar::deform` (heads to deformed canonical Gaussians, activations).
//
// Layouts (row-major, the cpu layouts): positions N x 3, quaternions N x 4 [w x y z],
// covariances N x 6 upper triangle (xx xy xz yy yz zz; the gradient of an off-diagonal entry
// counts both halves), transforms J x 12 (3 x 4 row-major), template log weights V x J
// (ln(w + 1e-9), computed once in f64 on the host), SH N x 16 x 3 (stored) and N x k x 3
// (the splatting layout of the active degree), heads N x 10 ([d_xyz, d_rot - (1,0,0,0),
// d_scale], the trunk's output).
//
// Per-Gaussian kernels run WORKGROUP threads per workgroup; the Gaussian index is
// `linear_index` (2D dispatch beyond the per-dimension limit).

// The shape (a uniform written once, plain words so that no struct crosses the boundary):
// [joints, vertices, flags (HAS_HEADS | HAS_WEIGHT_OFFSETS), Gaussians per chunk of the
// per-joint reduction], [scale_min, scale_max (f32 bits), 0, 0].
// The per-iteration record (16 bytes): [Gaussian count, SH coefficients per channel of the
// active degree, chunks of the per-joint reduction, 0].
fn shape_joints() -> u32 {
    return shape[0].x;
}

fn shape_vertices() -> u32 {
    return shape[0].y;
}

fn shape_flags() -> u32 {
    return shape[0].z;
}

fn shape_chunk() -> u32 {
    return shape[0].w;
}

fn scale_min() -> f32 {
    return bitcast<f32>(shape[1].x);
}

fn scale_max() -> f32 {
    return bitcast<f32>(shape[1].y);
}

fn record_count() -> u32 {
    return record[0];
}

fn record_sh_coefficients() -> u32 {
    return record[1];
}

fn record_chunks() -> u32 {
    return record[2];
}

const HAS_HEADS: u32 = 1u;
const HAS_WEIGHT_OFFSETS: u32 = 2u;
const HEAD_WIDTH: u32 = 10u;
const SH_STORED: u32 = 16u;
// Status words (indices into `status`).
const STATUS_FORWARD_COUNT: u32 = 0u;
const STATUS_FORWARD_FIRST: u32 = 1u;
const STATUS_BACKWARD_COUNT: u32 = 2u;
const STATUS_BACKWARD_FIRST: u32 = 3u;

@group(0) @binding(0) var<uniform> shape: array<vec4<u32>, 2>;
@group(0) @binding(1) var<storage, read> record: array<u32>;
// Canonical Gaussians (the optimiser's columns) and the non-rigid heads.
@group(0) @binding(2) var<storage, read> xyz: array<f32>;
@group(0) @binding(3) var<storage, read> log_scales: array<f32>;
@group(0) @binding(4) var<storage, read> rotations: array<f32>;
@group(0) @binding(5) var<storage, read> heads: array<f32>;
// Deformed canonical Gaussians: written by `deform`, read by the skinning.
@group(0) @binding(6) var<storage, read_write> positions: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_rotations: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_scales: array<f32>;
// Skinning inputs.
@group(0) @binding(9) var<storage, read> weight_offsets: array<f32>;
@group(0) @binding(10) var<storage, read> nearest: array<u32>;
@group(0) @binding(11) var<storage, read> canonical_joints: array<f32>;
@group(0) @binding(12) var<storage, read> target_joints: array<f32>;
@group(0) @binding(13) var<storage, read> template_log_weights: array<f32>;
@group(0) @binding(14) var<storage, read> vertex_offsets: array<f32>;
// Binding 15: the vertex-offset gradient V x 3 (atomic-add region below).
// Forward outputs (the splatting's inputs); in the backward, their gradients.
@group(0) @binding(16) var<storage, read_write> means: array<f32>;
@group(0) @binding(17) var<storage, read_write> covariances: array<f32>;
@group(0) @binding(18) var<storage, read_write> opacities: array<f32>;
@group(0) @binding(19) var<storage, read_write> sh_out: array<f32>;
@group(0) @binding(20) var<storage, read> opacity_logits: array<f32>;
@group(0) @binding(21) var<storage, read> sh: array<f32>;
// Backward outputs.
@group(0) @binding(22) var<storage, read_write> grad_positions: array<f32>;
@group(0) @binding(23) var<storage, read_write> grad_log_scales: array<f32>;
@group(0) @binding(24) var<storage, read_write> grad_rotations: array<f32>;
@group(0) @binding(25) var<storage, read_write> grad_heads: array<f32>;
@group(0) @binding(26) var<storage, read_write> grad_weight_offsets: array<f32>;
// Per-Gaussian blend weights N x J and blended-target gradients N x 12, for the
// deterministic per-joint reduction; its partial sums chunks x J x 12; its result J x 12.
@group(0) @binding(27) var<storage, read_write> blend_weights: array<f32>;
@group(0) @binding(28) var<storage, read_write> grad_blend: array<f32>;
@group(0) @binding(29) var<storage, read_write> joint_partials: array<f32>;
@group(0) @binding(30) var<storage, read_write> grad_target_joints: array<f32>;
@group(0) @binding(31) var<storage, read_write> status: array<atomic<u32>>;

// @atomic-add-begin
//#include "atomic_add_cas.wgsl"
// @atomic-add-end

const WORKGROUP: u32 = 64u;

//#include "linear_index.wgsl"
//#include "finite.wgsl"
//#include "quaternion.wgsl"

// Loads and stores of 3- and 4-vectors, one per buffer (WGSL has no pointer parameters
// into storage without an extension).
fn xyz_at(i: u32) -> vec3<f32> {
    return vec3<f32>(xyz[3u * i], xyz[3u * i + 1u], xyz[3u * i + 2u]);
}

fn log_scale_at(i: u32) -> vec3<f32> {
    return vec3<f32>(log_scales[3u * i], log_scales[3u * i + 1u], log_scales[3u * i + 2u]);
}

fn rotation_at(i: u32) -> vec4<f32> {
    return vec4<f32>(rotations[4u * i], rotations[4u * i + 1u], rotations[4u * i + 2u], rotations[4u * i + 3u]);
}

fn position_at(i: u32) -> vec3<f32> {
    return vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
}

fn d_scale_at(i: u32) -> vec3<f32> {
    return vec3<f32>(d_scales[3u * i], d_scales[3u * i + 1u], d_scales[3u * i + 2u]);
}

fn d_rotation_at(i: u32) -> vec4<f32> {
    return vec4<f32>(d_rotations[4u * i], d_rotations[4u * i + 1u], d_rotations[4u * i + 2u], d_rotations[4u * i + 3u]);
}

fn vertex_offset_at(v: u32) -> vec3<f32> {
    return vec3<f32>(vertex_offsets[3u * v], vertex_offsets[3u * v + 1u], vertex_offsets[3u * v + 2u]);
}

fn mean_at(i: u32) -> vec3<f32> {
    return vec3<f32>(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]);
}

// Hamilton product a (x) b of [w x y z] quaternions (vec4 holds w in .x).
fn quat_mul(a: vec4<f32>, b: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(
        a.x * b.x - a.y * b.y - a.z * b.z - a.w * b.w,
        a.x * b.y + a.y * b.x + a.z * b.w - a.w * b.z,
        a.x * b.z - a.y * b.w + a.z * b.x + a.w * b.y,
        a.x * b.w + a.y * b.z - a.z * b.y + a.w * b.x,
    );
}

// Gradients of a (x) b for a and b given that of the product (the product is bilinear).
fn quat_mul_backward_a(b: vec4<f32>, g: vec4<f32>) -> vec4<f32> {
    // Transpose of R(b), p = R(b) a.
    return vec4<f32>(
        b.x * g.x + b.y * g.y + b.z * g.z + b.w * g.w,
        -b.y * g.x + b.x * g.y - b.w * g.z + b.z * g.w,
        -b.z * g.x + b.w * g.y + b.x * g.z - b.y * g.w,
        -b.w * g.x - b.z * g.y + b.y * g.z + b.x * g.w,
    );
}

fn quat_mul_backward_b(a: vec4<f32>, g: vec4<f32>) -> vec4<f32> {
    // Transpose of L(a), p = L(a) b.
    return vec4<f32>(
        a.x * g.x + a.y * g.y + a.z * g.z + a.w * g.w,
        -a.y * g.x + a.x * g.y + a.w * g.z - a.z * g.w,
        -a.z * g.x - a.w * g.y + a.x * g.z + a.y * g.w,
        -a.w * g.x + a.z * g.y - a.y * g.z + a.x * g.w,
    );
}

fn lin_of(t: array<f32, 12>) -> mat3x3<f32> {
    return mat3x3<f32>(
        vec3<f32>(t[0], t[4], t[8]),
        vec3<f32>(t[1], t[5], t[9]),
        vec3<f32>(t[2], t[6], t[10]),
    );
}

fn trans_of(t: array<f32, 12>) -> vec3<f32> {
    return vec3<f32>(t[3], t[7], t[11]);
}

fn inverse3(m: mat3x3<f32>) -> mat3x3<f32> {
    let a = m[0];
    let b = m[1];
    let c = m[2];
    // Rows of the inverse are the cross products of the columns over the determinant.
    let r0 = cross(b, c);
    let r1 = cross(c, a);
    let r2 = cross(a, b);
    let inv_det = 1.0 / dot(a, r0);
    return transpose(mat3x3<f32>(r0, r1, r2)) * inv_det;
}

fn outer(a: vec3<f32>, b: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(a * b.x, a * b.y, a * b.z);
}

fn sym_from_upper(u0: f32, u1: f32, u2: f32, u3: f32, u4: f32, u5: f32) -> mat3x3<f32> {
    return mat3x3<f32>(vec3<f32>(u0, u1, u2), vec3<f32>(u1, u3, u4), vec3<f32>(u2, u4, u5));
}

fn scale_matrix(s: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(vec3<f32>(s.x, 0.0, 0.0), vec3<f32>(0.0, s.y, 0.0), vec3<f32>(0.0, 0.0, s.z));
}

fn logit(i: u32, v: u32, k: u32) -> f32 {
    var l = template_log_weights[v * shape_joints() + k];
    if (shape_flags() & HAS_WEIGHT_OFFSETS) != 0u {
        l += weight_offsets[i * shape_joints() + k];
    }
    return l;
}

// Softmax normaliser of Gaussian i's logits: (max, sum of exp(logit - max)).
fn softmax_normaliser(i: u32, v: u32) -> vec2<f32> {
    var m = -3.4e38;
    for (var k = 0u; k < shape_joints(); k++) {
        m = max(m, logit(i, v, k));
    }
    var sum = 0.0;
    for (var k = 0u; k < shape_joints(); k++) {
        sum += exp(logit(i, v, k) - m);
    }
    return vec2<f32>(m, sum);
}

fn weight(i: u32, v: u32, k: u32, normaliser: vec2<f32>) -> f32 {
    return exp(logit(i, v, k) - normaliser.x) / normaliser.y;
}

// One Gaussian's forward intermediates (skinning.rs `Forward`).
struct Forward {
    raw_scale: vec3<f32>,
    scale: vec3<f32>,
    rotation: vec4<f32>,
    a_lin: mat3x3<f32>,
    a_t: vec3<f32>,
    b_inv: mat3x3<f32>,
    b_t: vec3<f32>,
    rest: vec3<f32>,
    sigma: mat3x3<f32>,
    normaliser: vec2<f32>,
    vertex: u32,
}

fn forward_one(i: u32) -> Forward {
    var f: Forward;
    let log_scale = log_scale_at(i);
    f.raw_scale = exp(log_scale) + d_scale_at(i);
    f.scale = clamp(f.raw_scale, vec3<f32>(scale_min()), vec3<f32>(scale_max()));
    f.rotation = quat_mul(d_rotation_at(i), rotation_at(i));
    let r = quat_matrix(f.rotation);
    f.sigma = r * scale_matrix(f.scale * f.scale) * transpose(r);
    f.vertex = nearest[i];
    f.normaliser = softmax_normaliser(i, f.vertex);
    var a: array<f32, 12>;
    var b: array<f32, 12>;
    for (var e = 0u; e < 12u; e++) {
        a[e] = 0.0;
        b[e] = 0.0;
    }
    for (var k = 0u; k < shape_joints(); k++) {
        let w = weight(i, f.vertex, k, f.normaliser);
        for (var e = 0u; e < 12u; e++) {
            a[e] += w * target_joints[12u * k + e];
            b[e] += w * canonical_joints[12u * k + e];
        }
    }
    f.a_lin = lin_of(a);
    f.a_t = trans_of(a);
    f.b_inv = inverse3(lin_of(b));
    f.b_t = trans_of(b);
    let x = position_at(i);
    f.rest = f.b_inv * (x - f.b_t) + vertex_offset_at(f.vertex);
    return f;
}

// dL/dw_k of joint k's blend weight, from the gradients of the blended target (d_a) and
// canonical (d_b) transforms.
fn blend_weight_gradient(k: u32, d_a: array<f32, 12>, d_b: array<f32, 12>) -> f32 {
    var d_w = 0.0;
    for (var e = 0u; e < 12u; e++) {
        d_w += d_a[e] * target_joints[12u * k + e] + d_b[e] * canonical_joints[12u * k + e];
    }
    return d_w;
}

fn flag(count_word: u32, first_word: u32, i: u32) {
    atomicAdd(&status[count_word], 1u);
    atomicMin(&status[first_word], i);
}

// Heads to deformed canonical Gaussians (avatar::deform with non_rigid::split_heads):
// positions = xyz + d_xyz, d_rot = head + (1, 0, 0, 0), d_scale = head; without heads the
// identity offsets.
@compute @workgroup_size(WORKGROUP)
fn deform(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if i >= record_count() {
        return;
    }
    // The identity offsets, replaced by the head's where there are heads.
    var x = xyz_at(i);
    var d_rot = vec4<f32>(1.0, 0.0, 0.0, 0.0);
    var d_scale = vec3<f32>(0.0);
    if (shape_flags() & HAS_HEADS) != 0u {
        let h = HEAD_WIDTH * i;
        x += vec3<f32>(heads[h], heads[h + 1u], heads[h + 2u]);
        d_rot = vec4<f32>(heads[h + 3u] + 1.0, heads[h + 4u], heads[h + 5u], heads[h + 6u]);
        d_scale = vec3<f32>(heads[h + 7u], heads[h + 8u], heads[h + 9u]);
    }
    for (var a = 0u; a < 3u; a++) {
        positions[3u * i + a] = x[a];
        d_scales[3u * i + a] = d_scale[a];
    }
    for (var a = 0u; a < 4u; a++) {
        d_rotations[4u * i + a] = d_rot[a];
    }
}

// World means and covariances (skin_forward), opacities sigmoid(logit) and the SH of the
// active degree in the splatting layout N x k x 3. A non-finite mean or covariance is counted
// in the status words (forward count, first Gaussian).
@compute @workgroup_size(WORKGROUP)
fn skin_forward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if i >= record_count() {
        return;
    }
    let f = forward_one(i);
    let mean = f.a_lin * f.rest + f.a_t;
    let m = f.a_lin * f.b_inv;
    let cov = m * f.sigma * transpose(m);
    for (var a = 0u; a < 3u; a++) {
        means[3u * i + a] = mean[a];
    }
    var c = array<f32, 6>(cov[0][0], cov[1][0], cov[2][0], cov[1][1], cov[2][1], cov[2][2]);
    var ok = finite(mean.x) && finite(mean.y) && finite(mean.z);
    for (var e = 0u; e < 6u; e++) {
        covariances[6u * i + e] = c[e];
        ok = ok && finite(c[e]);
    }
    if !ok {
        flag(STATUS_FORWARD_COUNT, STATUS_FORWARD_FIRST, i);
    }
    opacities[i] = 1.0 / (1.0 + exp(-opacity_logits[i]));
    let active_len = 3u * record_sh_coefficients();
    for (var e = 0u; e < active_len; e++) {
        sh_out[i * active_len + e] = sh[3u * SH_STORED * i + e];
    }
}

// The exact backward of `skin_forward` (skin_backward) from the gradients of the means
// (`means`, N x 3) and covariances (`covariances`, N x 6): per-Gaussian gradients of the
// deformed positions, log scales, rotations, the heads (d_xyz, d_rot, d_scale) and the weight
// offsets; per-vertex offset gradients through `gradient_add`; the blend weights and blended-
// target gradients that `reduce_joints` sums. A non-finite gradient is counted in the status.
@compute @workgroup_size(WORKGROUP)
fn skin_backward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if i >= record_count() {
        return;
    }
    let f = forward_one(i);
    let g_pos = mean_at(i);
    let o = 6u * i;
    let g_cov = sym_from_upper(
        covariances[o],
        0.5 * covariances[o + 1u],
        0.5 * covariances[o + 2u],
        covariances[o + 3u],
        0.5 * covariances[o + 4u],
        covariances[o + 5u],
    );
    let x = position_at(i);
    let m = f.a_lin * f.b_inv;
    // Position chain.
    var d_a_lin = outer(g_pos, f.rest);
    let d_a_t = g_pos;
    let d_rest = transpose(f.a_lin) * g_pos;
    let d_x = transpose(f.b_inv) * d_rest;
    let d_b_t = -d_x;
    var d_b_inv = outer(d_rest, x - f.b_t);
    // Covariance chain: Sigma_o = M Sigma M^T.
    let d_m = g_cov * m * f.sigma * 2.0;
    let d_sigma = transpose(m) * g_cov * m;
    d_a_lin += d_m * transpose(f.b_inv);
    d_b_inv += transpose(f.a_lin) * d_m;
    var d_b_lin = transpose(f.b_inv) * d_b_inv * transpose(f.b_inv) * -1.0;
    var d_a: array<f32, 12>;
    var d_b: array<f32, 12>;
    for (var r = 0u; r < 3u; r++) {
        for (var c = 0u; c < 3u; c++) {
            d_a[4u * r + c] = d_a_lin[c][r];
            d_b[4u * r + c] = d_b_lin[c][r];
        }
        d_a[4u * r + 3u] = d_a_t[r];
        d_b[4u * r + 3u] = d_b_t[r];
    }
    var ok = true;
    for (var e = 0u; e < 12u; e++) {
        grad_blend[12u * i + e] = d_a[e];
        ok = ok && finite(d_a[e]);
    }
    // Blend weights: dL/dw_k, then the softmax backward.
    var dot_w = 0.0;
    for (var k = 0u; k < shape_joints(); k++) {
        let w = weight(i, f.vertex, k, f.normaliser);
        dot_w += w * blend_weight_gradient(k, d_a, d_b);
        blend_weights[i * shape_joints() + k] = w;
    }
    if (shape_flags() & HAS_WEIGHT_OFFSETS) != 0u {
        for (var k = 0u; k < shape_joints(); k++) {
            let w = blend_weights[i * shape_joints() + k];
            let g = w * (blend_weight_gradient(k, d_a, d_b) - dot_w);
            grad_weight_offsets[i * shape_joints() + k] = g;
            ok = ok && finite(g);
        }
    }
    // Scale and rotation: Sigma = R diag(scale^2) R^T.
    let r = quat_matrix(f.rotation);
    let gs = (d_sigma + transpose(d_sigma)) * 0.5;
    let rt_g_r = transpose(r) * gs * r;
    let d_scale_clamped = 2.0 * f.scale * vec3<f32>(rt_g_r[0][0], rt_g_r[1][1], rt_g_r[2][2]);
    let d_r = gs * r * scale_matrix(f.scale * f.scale) * 2.0;
    let d_rot_product = quat_matrix_backward(f.rotation, d_r);
    let inside = f.raw_scale > vec3<f32>(scale_min()) & f.raw_scale < vec3<f32>(scale_max());
    let d_scale = select(vec3<f32>(0.0), d_scale_clamped, inside);
    let d_log_scale = d_scale * exp(log_scale_at(i));
    let d_rot = d_rotation_at(i);
    let canonical = rotation_at(i);
    let d_d_rot = quat_mul_backward_a(canonical, d_rot_product);
    let d_rotation = quat_mul_backward_b(d_rot, d_rot_product);
    for (var a = 0u; a < 3u; a++) {
        grad_positions[3u * i + a] = d_x[a];
        grad_log_scales[3u * i + a] = d_log_scale[a];
    }
    for (var a = 0u; a < 4u; a++) {
        grad_rotations[4u * i + a] = d_rotation[a];
    }
    let h = HEAD_WIDTH * i;
    var head = array<f32, 10>(
        d_x.x, d_x.y, d_x.z,
        d_d_rot.x, d_d_rot.y, d_d_rot.z, d_d_rot.w,
        d_scale.x, d_scale.y, d_scale.z,
    );
    for (var e = 0u; e < HEAD_WIDTH; e++) {
        grad_heads[h + e] = head[e];
        ok = ok && finite(head[e]);
    }
    for (var e = 0u; e < 4u; e++) {
        ok = ok && finite(d_rotation[e]);
    }
    for (var a = 0u; a < 3u; a++) {
        gradient_add(3u * f.vertex + a, d_rest[a]);
        ok = ok && finite(d_log_scale[a]);
    }
    if !ok {
        flag(STATUS_BACKWARD_COUNT, STATUS_BACKWARD_FIRST, i);
    }
}

var<workgroup> partial_sums: array<array<f32, 12>, 64>;

// Per-joint partial sums of dL/dG_k = sum_i w_ik dL/dA_i over one chunk of Gaussians:
// workgroup (chunk, joint) writes joint_partials[(chunk J + joint) 12 + e]. A fixed tree,
// so the result does not depend on scheduling.
@compute @workgroup_size(64)
fn reduce_joints(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let chunk = group.x;
    let k = group.y;
    let begin = chunk * shape_chunk();
    let end = min(record_count(), begin + shape_chunk());
    var sums: array<f32, 12>;
    for (var e = 0u; e < 12u; e++) {
        sums[e] = 0.0;
    }
    for (var i = begin + local; i < end; i += 64u) {
        let w = blend_weights[i * shape_joints() + k];
        for (var e = 0u; e < 12u; e++) {
            sums[e] += w * grad_blend[12u * i + e];
        }
    }
    partial_sums[local] = sums;
    workgroupBarrier();
    for (var stride = 32u; stride > 0u; stride /= 2u) {
        if local < stride {
            for (var e = 0u; e < 12u; e++) {
                partial_sums[local][e] += partial_sums[local + stride][e];
            }
        }
        workgroupBarrier();
    }
    if local == 0u {
        for (var e = 0u; e < 12u; e++) {
            joint_partials[(chunk * shape_joints() + k) * 12u + e] = partial_sums[0][e];
        }
    }
}

// grad_target_joints[j] = sum over chunks of joint_partials, in chunk order.
@compute @workgroup_size(WORKGROUP)
fn finish_joints(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let index = linear_index(group, groups, local);
    let len = 12u * shape_joints();
    if index >= len {
        return;
    }
    var sum = 0.0;
    for (var chunk = 0u; chunk < record_chunks(); chunk++) {
        sum += joint_partials[chunk * len + index];
    }
    grad_target_joints[index] = sum;
}

@group(0) @binding(32) var<storage, read_write> grad_opacity_logits: array<f32>;
@group(0) @binding(33) var<storage, read_write> grad_sh: array<f32>;

// Backward of the activations from the splatting's gradients of the opacities (`opacities`,
// N) and of the active SH (`sh_out`, N x k x 3): dL/dlogit = dL/dopacity s (1 - s) with
// s = sigmoid(logit), and the SH gradient scattered into the stored layout N x 16 x 3 (zeros
// beyond the active degree).
@compute @workgroup_size(WORKGROUP)
fn activations_backward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if i >= record_count() {
        return;
    }
    let s = 1.0 / (1.0 + exp(-opacity_logits[i]));
    grad_opacity_logits[i] = opacities[i] * s * (1.0 - s);
    let active_len = 3u * record_sh_coefficients();
    for (var e = 0u; e < 3u * SH_STORED; e++) {
        var g = 0.0;
        if e < active_len {
            g = sh_out[i * active_len + e];
        }
        grad_sh[3u * SH_STORED * i + e] = g;
    }
}
