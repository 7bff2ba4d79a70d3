// The as-isometric-as-possible loss on the device (stages/train/src/resident/aiap.rs; the cpu
// twin is `aiap_gaussians` in stages/train/src/losses.rs with its neighbours from
// `MovingKnn`): the k nearest canonical neighbours of every Gaussian (itself first), the
// canonical covariances, the mean over neighbour pairs of `|d(a_i, a_j) - d(b_i, b_j)|` for
// centres and covariance upper triangles, its gradients into the canonical and deformed
// centres and covariances (accumulated with `gradient_add`), the canonical covariances'
// gradient carried back to log-scales and rotations, and the loss value reduced in a fixed
// order into the log record. The neighbours come from train_aiap_knn.wgsl. Entry points, in
// recording order: `covariances`, `pairs`, `reduce_loss`, `finish`. One thread per Gaussian
// (`reduce_loss`: one workgroup); grids may be 2D.
//
// `params` (shared with train_aiap_knn.wgsl, written when the count changes): [0] = N, k,
// the scratch's capacity C (rows), the dispatch limit; [1] = centre weight / pairs,
// covariance weight / pairs, centre weight, covariance weight (f32 bits); [2] = candidates
// per Gaussian, unused x 3. The gradient scratch holds, at row offsets of C:
// canonical centres 3C | deformed centres 3C | canonical covariances 6C | deformed
// covariances 6C.

@group(0) @binding(0) var<uniform> params: array<vec4<u32>, 3>;
@group(0) @binding(1) var<storage, read> xyz: array<f32>;
@group(0) @binding(2) var<storage, read> log_scale: array<f32>;
@group(0) @binding(3) var<storage, read> rotation: array<f32>;
@group(0) @binding(4) var<storage, read> deformed_centres: array<f32>;
@group(0) @binding(5) var<storage, read> deformed_covariances: array<f32>;
@group(0) @binding(6) var<storage, read> neighbours: array<u32>;
@group(0) @binding(7) var<storage, read_write> canonical_covariances: array<f32>;
// Per Gaussian: the sums of its pairs' centre and covariance terms.
@group(0) @binding(8) var<storage, read_write> partials: array<f32>;
// [weighted value, centre term, covariance term].
@group(0) @binding(9) var<storage, read_write> loss_log: array<f32>;
// The gradient scratch, read back as floats by `finish`.
@group(0) @binding(10) var<storage, read> accumulated: array<f32>;
@group(0) @binding(11) var<storage, read_write> d_xyz: array<f32>;
@group(0) @binding(12) var<storage, read_write> d_log_scale: array<f32>;
@group(0) @binding(13) var<storage, read_write> d_rotation: array<f32>;


fn count() -> u32 {
    return params[0].x;
}

const WORKGROUP: u32 = 256u;

//#include "linear_index.wgsl"
//#include "finite.wgsl"
//#include "quaternion.wgsl"

// ---------------------------------------------------------------------------------------
// Canonical covariances `R diag(exp(log_scale)^2) R^T` (`covariance_from_scale_rotation`:
// the quaternion normalised, a degenerate one taken as the identity: `quat_matrix`).

fn quaternion(i: u32) -> vec4<f32> {
    return vec4<f32>(rotation[4u * i], rotation[4u * i + 1u], rotation[4u * i + 2u],
        rotation[4u * i + 3u]);
}

fn scale_of(i: u32) -> vec3<f32> {
    return exp(vec3<f32>(log_scale[3u * i], log_scale[3u * i + 1u], log_scale[3u * i + 2u]));
}

@compute @workgroup_size(WORKGROUP)
fn covariances(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= count()) {
        return;
    }
    let r = quat_matrix(quaternion(i));
    let s = scale_of(i);
    let sigma = r * mat3x3<f32>(vec3<f32>(s.x * s.x, 0.0, 0.0), vec3<f32>(0.0, s.y * s.y, 0.0),
        vec3<f32>(0.0, 0.0, s.z * s.z)) * transpose(r);
    canonical_covariances[6u * i] = sigma[0][0];
    canonical_covariances[6u * i + 1u] = sigma[1][0];
    canonical_covariances[6u * i + 2u] = sigma[2][0];
    canonical_covariances[6u * i + 3u] = sigma[1][1];
    canonical_covariances[6u * i + 4u] = sigma[2][1];
    canonical_covariances[6u * i + 5u] = sigma[2][2];
}

// ---------------------------------------------------------------------------------------
// The pair terms of Gaussian i (`aiap_term`): a zero distance has a zero subgradient.

// The gradient scratch's atomic add (shaders/atomic_add_cas.wgsl; the host swaps in
// atomic_add_float.wgsl when the adapter has native f32 atomics).
// @atomic-add-begin
//#include "atomic_add_cas.wgsl"
// @atomic-add-end

fn sign_of(v: f32) -> f32 {
    if (v > 0.0) {
        return 1.0;
    }
    if (v < 0.0) {
        return -1.0;
    }
    return 0.0;
}

// One pair's term `|d(a_i, a_j) - d(b_i, b_j)|` of vectors of `width` entries (3 for centres,
// 6 for covariance upper triangles) from their differences `du = a_i - a_j` (canonical) and
// `dv = b_i - b_j` (deformed), returned; its gradient times `scale` added into the scratch's
// canonical rows from `canonical` and deformed rows from `deformed`.
fn pair_term(
    i: u32,
    j: u32,
    width: u32,
    du: array<f32, 6>,
    dv: array<f32, 6>,
    scale: f32,
    canonical: u32,
    deformed: u32,
) -> f32 {
    var lu = 0.0;
    var lv = 0.0;
    for (var d = 0u; d < width; d = d + 1u) {
        lu = lu + du[d] * du[d];
        lv = lv + dv[d] * dv[d];
    }
    lu = sqrt(lu);
    lv = sqrt(lv);
    let g = scale * sign_of(lu - lv);
    if (g != 0.0) {
        for (var d = 0u; d < width; d = d + 1u) {
            if (lu > 0.0) {
                let t = g * du[d] / lu;
                gradient_add(canonical + width * i + d, t);
                gradient_add(canonical + width * j + d, -t);
            }
            if (lv > 0.0) {
                let t = g * dv[d] / lv;
                gradient_add(deformed + width * i + d, -t);
                gradient_add(deformed + width * j + d, t);
            }
        }
    }
    return abs(lu - lv);
}

@compute @workgroup_size(WORKGROUP)
fn pairs(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= count()) {
        return;
    }
    let k = params[0].y;
    let c = params[0].z;
    let centre_scale = bitcast<f32>(params[1].x);
    let covariance_scale = bitcast<f32>(params[1].y);
    var centre_sum = 0.0;
    var covariance_sum = 0.0;
    for (var slot = 1u; slot < k; slot = slot + 1u) {
        let j = neighbours[i * k + slot];
        // Centres.
        var du: array<f32, 6>;
        var dv: array<f32, 6>;
        for (var d = 0u; d < 3u; d = d + 1u) {
            du[d] = xyz[3u * i + d] - xyz[3u * j + d];
            dv[d] = deformed_centres[3u * i + d] - deformed_centres[3u * j + d];
        }
        centre_sum = centre_sum + pair_term(i, j, 3u, du, dv, centre_scale, 0u, 3u * c);
        // Covariance upper triangles.
        for (var d = 0u; d < 6u; d = d + 1u) {
            du[d] = canonical_covariances[6u * i + d] - canonical_covariances[6u * j + d];
            dv[d] = deformed_covariances[6u * i + d] - deformed_covariances[6u * j + d];
        }
        covariance_sum = covariance_sum + pair_term(i, j, 6u, du, dv, covariance_scale, 6u * c, 12u * c);
    }
    partials[2u * i] = centre_sum;
    partials[2u * i + 1u] = covariance_sum;
}

// ---------------------------------------------------------------------------------------
// The loss value: the partial sums added in a fixed order (strided per thread, then a tree),
// divided by the pair count and weighted.

var<workgroup> sums: array<vec2<f32>, 256>;

@compute @workgroup_size(256)
fn reduce_loss(@builtin(local_invocation_index) local: u32) {
    let n = count();
    var sum = vec2<f32>(0.0);
    for (var i = local; i < n; i = i + 256u) {
        sum = sum + vec2<f32>(partials[2u * i], partials[2u * i + 1u]);
    }
    sums[local] = sum;
    workgroupBarrier();
    for (var width = 128u; width > 0u; width = width / 2u) {
        if (local < width) {
            sums[local] = sums[local] + sums[local + width];
        }
        workgroupBarrier();
    }
    if (local == 0u) {
        let k = params[0].y;
        let pair_count = f32(n) * f32(k - 1u);
        let centres = sums[0].x / pair_count;
        let covariances = sums[0].y / pair_count;
        loss_log[1] = centres;
        loss_log[2] = covariances;
        loss_log[0] = bitcast<f32>(params[1].z) * centres + bitcast<f32>(params[1].w) * covariances;
    }
}

// ---------------------------------------------------------------------------------------
// The canonical gradients: the centres' copied out, the covariances' carried back to the
// log-scales and rotations (`canonical_covariances_backward`).

@compute @workgroup_size(WORKGROUP)
fn finish(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    if (i >= count()) {
        return;
    }
    let c = params[0].z;
    for (var d = 0u; d < 3u; d = d + 1u) {
        d_xyz[3u * i + d] = accumulated[3u * i + d];
    }
    let u = 6u * c + 6u * i;
    // The full symmetric gradient of the upper triangle (off-diagonals count both halves).
    let gxy = 0.5 * accumulated[u + 1u];
    let gxz = 0.5 * accumulated[u + 2u];
    let gyz = 0.5 * accumulated[u + 4u];
    let g = mat3x3<f32>(
        vec3<f32>(accumulated[u], gxy, gxz),
        vec3<f32>(gxy, accumulated[u + 3u], gyz),
        vec3<f32>(gxz, gyz, accumulated[u + 5u]),
    );
    let q = quaternion(i);
    let r = quat_matrix(q);
    let s = scale_of(i);
    let rt_g_r = transpose(r) * g * r;
    d_log_scale[3u * i] = 2.0 * s.x * rt_g_r[0][0] * s.x;
    d_log_scale[3u * i + 1u] = 2.0 * s.y * rt_g_r[1][1] * s.y;
    d_log_scale[3u * i + 2u] = 2.0 * s.z * rt_g_r[2][2] * s.z;
    // dL/dR = 2 G R D, then the derivative of R(q / |q|) (zero for a degenerate q).
    let e = g * r * mat3x3<f32>(vec3<f32>(2.0 * s.x * s.x, 0.0, 0.0),
        vec3<f32>(0.0, 2.0 * s.y * s.y, 0.0), vec3<f32>(0.0, 0.0, 2.0 * s.z * s.z));
    let d_q = quat_matrix_backward(q, e);
    d_rotation[4u * i] = d_q.x;
    d_rotation[4u * i + 1u] = d_q.y;
    d_rotation[4u * i + 2u] = d_q.z;
    d_rotation[4u * i + 3u] = d_q.w;
}
