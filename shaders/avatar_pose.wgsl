// The pose path of the avatar on the device (`avatar::resident::pose`): the frame's local
// rotations refined by the pose refiner, forward kinematics, the target joint transforms
// with the frame's world transform, the per-vertex rest offsets (shape and pose blend
// shapes), and the backward of all of it to the refiner's matrices. The maths is
// `BodyRig::pose_with_chain` and `BodyRig::pose_backward` (src/avatar/src/rig.rs), in f32.
//
// Matrices are row-major in every buffer: a 3 x 3 is `[r00 r01 r02 r10 ... r22]`, a 3 x 4
// transform `[r00 r01 r02 t0 r10 ... t2]`. WGSL's `mat3x3f` is column-major: `m[c][r]` is
// element (r, c).
//
// Entry points, in the order an iteration records them:
// - `pose_forward` (one workgroup): refined rotations `R'_j = R_j R_ref_j` (j >= 1), the
//   pose feature `vec(R'_j - I)`, the global frames `(M_j, g_j)` and the target joints;
// - `pose_offsets` (one thread per vertex coordinate): `base + P f`;
// - `pose_blend_backward` (one workgroup per `BLEND_ROWS` rows): partial sums of
//   `dL/df = P^T dL/d offsets` over each workgroup's rows;
// - `pose_backward` (one workgroup): the partial sums reduced in a fixed order, the chain
//   backward, and `dL/dR_ref_j = R_j^T dL/dR'_j`.

// The kernels' uniforms are plain words rather than structs: their Rust side lives in the
// avatar crate, which the struct-layout test of `compute::backend::shaders` cannot see, and
// an array of `vec4u` has the layout of the `u32` array pose.rs writes, with no padding.
//
// Sizes and offsets, fixed per sequence (`PoseParams::words` in pose.rs), in this order:
// joints, vertices, features (9 (J - 1), or 0 without pose blend shapes), blend_groups
// (workgroups of `pose_blend_backward`); offsets in floats into `sequence`:
// frame_rotations_at, frame_world_at, rest_joints_at; offsets in floats into `chain`:
// rotations_at, globals_at, feature_at, d_globals_at, d_rotations_at; 4 unused.
fn joint_count() -> u32 { return params[0].x; }
fn vertex_count() -> u32 { return params[0].y; }
fn feature_count() -> u32 { return params[0].z; }
fn blend_groups() -> u32 { return params[0].w; }
fn frame_rotations_at() -> u32 { return params[1].x; }
fn frame_world_at() -> u32 { return params[1].y; }
fn rest_joints_at() -> u32 { return params[1].z; }
fn rotations_at() -> u32 { return params[1].w; }
fn globals_at() -> u32 { return params[2].x; }
fn feature_at() -> u32 { return params[2].y; }
fn d_globals_at() -> u32 { return params[2].z; }
fn d_rotations_at() -> u32 { return params[2].w; }

// The iteration's record (`PoseRecord` in pose.rs), written once per iteration: frame,
// shape, refine (1 when `refinements` holds the refiner's matrices, 0 to use the frame's
// own pose), unused.
fn record_frame() -> u32 { return record.x; }
fn record_shape() -> u32 { return record.y; }
fn record_refine() -> u32 { return record.z; }

// Status counters (`PoseStatus` in pose.rs).
const STATUS_TARGET_JOINTS: u32 = 0u;
const STATUS_VERTEX_OFFSETS: u32 = 1u;
const STATUS_REFINEMENT_GRADIENTS: u32 = 2u;

const NO_PARENT: u32 = 0xffffffffu;
const CHAIN_GROUP: u32 = 64u;
const OFFSET_GROUP: u32 = 256u;
const BLEND_ROWS: u32 = 128u;

@group(0) @binding(0) var<uniform> params: array<vec4u, 4>;
@group(0) @binding(1) var<uniform> record: vec4u;
// Per sequence: per frame `J x 9` local rotations, per frame `12` world `(W row-major, T)`,
// per shape `J x 3` rest joints.
@group(0) @binding(2) var<storage, read> sequence: array<f32>;
// Parent of each joint, `NO_PARENT` for the root.
@group(0) @binding(3) var<storage, read> parents: array<u32>;
// The pose refiner's `(J - 1) x 9` matrices (bound to a dummy when `refine` is 0).
@group(0) @binding(4) var<storage, read> refinements: array<f32>;
// Workspace: refined rotations `J x 9`, global frames `J x 12` (`M` row-major, then `g`),
// the pose feature, their gradients `J x 12` and the rotation gradients `J x 9`.
@group(0) @binding(5) var<storage, read_write> chain: array<f32>;
@group(0) @binding(6) var<storage, read_write> target_joints: array<f32>;
@group(0) @binding(7) var<storage, read_write> status: array<atomic<u32>>;
// Per shape `V x 3`: shape offsets minus the big pose's pose blend shapes.
@group(0) @binding(8) var<storage, read> base_offsets: array<f32>;
// SMPL's `posedirs`, `(V x 3) x 9 (J - 1)` row-major (a dummy without pose blend shapes).
@group(0) @binding(9) var<storage, read> pose_dirs: array<f32>;
@group(0) @binding(10) var<storage, read_write> vertex_offsets: array<f32>;
@group(0) @binding(11) var<storage, read> d_vertex_offsets: array<f32>;
// `blend_groups x features` partial sums of `P^T dL/d offsets`.
@group(0) @binding(12) var<storage, read_write> partials: array<f32>;
@group(0) @binding(13) var<storage, read> d_target_joints: array<f32>;
@group(0) @binding(14) var<storage, read_write> d_refinements: array<f32>;

//#include "finite.wgsl"

fn sequence_matrix(at: u32) -> mat3x3f {
    return transpose(mat3x3f(
        sequence[at], sequence[at + 1u], sequence[at + 2u],
        sequence[at + 3u], sequence[at + 4u], sequence[at + 5u],
        sequence[at + 6u], sequence[at + 7u], sequence[at + 8u],
    ));
}

fn sequence_vector(at: u32) -> vec3f {
    return vec3f(sequence[at], sequence[at + 1u], sequence[at + 2u]);
}

fn chain_matrix(at: u32) -> mat3x3f {
    return transpose(mat3x3f(
        chain[at], chain[at + 1u], chain[at + 2u],
        chain[at + 3u], chain[at + 4u], chain[at + 5u],
        chain[at + 6u], chain[at + 7u], chain[at + 8u],
    ));
}

fn chain_vector(at: u32) -> vec3f {
    return vec3f(chain[at], chain[at + 1u], chain[at + 2u]);
}

fn store_chain_matrix(at: u32, m: mat3x3f) {
    for (var r = 0u; r < 3u; r++) {
        for (var c = 0u; c < 3u; c++) {
            chain[at + 3u * r + c] = m[c][r];
        }
    }
}

fn store_chain_vector(at: u32, v: vec3f) {
    chain[at] = v.x;
    chain[at + 1u] = v.y;
    chain[at + 2u] = v.z;
}

fn refinement(j: u32) -> mat3x3f {
    let at = 9u * (j - 1u);
    return transpose(mat3x3f(
        refinements[at], refinements[at + 1u], refinements[at + 2u],
        refinements[at + 3u], refinements[at + 4u], refinements[at + 5u],
        refinements[at + 6u], refinements[at + 7u], refinements[at + 8u],
    ));
}

// `a b^T`.
fn outer(a: vec3f, b: vec3f) -> mat3x3f {
    return mat3x3f(a * b.x, a * b.y, a * b.z);
}

fn frame_rotation(j: u32) -> mat3x3f {
    return sequence_matrix(frame_rotations_at() + 9u * (joint_count() * record_frame() + j));
}

fn world_rotation() -> mat3x3f {
    return sequence_matrix(frame_world_at() + 12u * record_frame());
}

fn world_translation() -> vec3f {
    return sequence_vector(frame_world_at() + 12u * record_frame() + 9u);
}

fn rest_joint(j: u32) -> vec3f {
    return sequence_vector(rest_joints_at() + 3u * (joint_count() * record_shape() + j));
}

@compute @workgroup_size(64)
fn pose_forward(@builtin(local_invocation_index) t: u32) {
    let joints = joint_count();
    // Refined local rotations and the pose feature.
    for (var j = t; j < joints; j += CHAIN_GROUP) {
        var r = frame_rotation(j);
        if record_refine() != 0u && j > 0u {
            r = r * refinement(j);
        }
        store_chain_matrix(rotations_at() + 9u * j, r);
        if feature_count() != 0u && j > 0u {
            let d = r - mat3x3f(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
            store_chain_matrix(feature_at() + 9u * (j - 1u), d);
        }
    }
    storageBarrier();
    // Forward kinematics down the tree (parents come first): M_j = M_p R_j,
    // g_j = M_p (J_j - J_p) + g_p; the root's frame is (R_0, J_0).
    if t == 0u {
        for (var j = 0u; j < joints; j++) {
            let r = chain_matrix(rotations_at() + 9u * j);
            let rest = rest_joint(j);
            let p = parents[j];
            var m = r;
            var g = rest;
            if p != NO_PARENT {
                let m_p = chain_matrix(globals_at() + 12u * p);
                let g_p = chain_vector(globals_at() + 12u * p + 9u);
                m = m_p * r;
                g = m_p * (rest - rest_joint(p)) + g_p;
            }
            store_chain_matrix(globals_at() + 12u * j, m);
            store_chain_vector(globals_at() + 12u * j + 9u, g);
        }
    }
    storageBarrier();
    // Target joints W [M_j | g_j - M_j J_j] + T.
    let w = world_rotation();
    let translation = world_translation();
    for (var j = t; j < joints; j += CHAIN_GROUP) {
        let m = chain_matrix(globals_at() + 12u * j);
        let g = chain_vector(globals_at() + 12u * j + 9u);
        let linear = w * m;
        let offset = w * (g - m * rest_joint(j)) + translation;
        var bad = 0u;
        for (var r = 0u; r < 3u; r++) {
            for (var c = 0u; c < 3u; c++) {
                target_joints[12u * j + 4u * r + c] = linear[c][r];
                bad += select(1u, 0u, finite(linear[c][r]));
            }
            target_joints[12u * j + 4u * r + 3u] = offset[r];
            bad += select(1u, 0u, finite(offset[r]));
        }
        if bad != 0u {
            atomicAdd(&status[STATUS_TARGET_JOINTS], bad);
        }
    }
}

@compute @workgroup_size(256)
fn pose_offsets(
    @builtin(workgroup_id) group: vec3u,
    @builtin(num_workgroups) groups: vec3u,
    @builtin(local_invocation_index) t: u32,
) {
    let row = (group.x + group.y * groups.x) * OFFSET_GROUP + t;
    if row >= 3u * vertex_count() {
        return;
    }
    let features = feature_count();
    var blend = 0.0;
    for (var k = 0u; k < features; k++) {
        blend += pose_dirs[row * features + k] * chain[feature_at() + k];
    }
    let value = base_offsets[3u * vertex_count() * record_shape() + row] + blend;
    vertex_offsets[row] = value;
    if !finite(value) {
        atomicAdd(&status[STATUS_VERTEX_OFFSETS], 1u);
    }
}

var<workgroup> blend_gradient: array<f32, BLEND_ROWS>;

@compute @workgroup_size(128)
fn pose_blend_backward(
    @builtin(workgroup_id) group: vec3u,
    @builtin(num_workgroups) groups: vec3u,
    @builtin(local_invocation_index) t: u32,
) {
    // Uniform across the workgroup: every thread reaches the barrier or none does.
    let block = group.x + group.y * groups.x;
    if block >= blend_groups() {
        return;
    }
    let rows = 3u * vertex_count();
    let first = block * BLEND_ROWS;
    let row = first + t;
    var gradient = 0.0;
    if row < rows {
        gradient = d_vertex_offsets[row];
    }
    blend_gradient[t] = gradient;
    workgroupBarrier();
    let features = feature_count();
    let count = min(BLEND_ROWS, rows - first);
    for (var k = t; k < features; k += BLEND_ROWS) {
        var sum = 0.0;
        for (var i = 0u; i < count; i++) {
            sum += blend_gradient[i] * pose_dirs[(first + i) * features + k];
        }
        partials[block * features + k] = sum;
    }
}

@compute @workgroup_size(64)
fn pose_backward(@builtin(local_invocation_index) t: u32) {
    let joints = joint_count();
    let wt = transpose(world_rotation());
    // Target = W [M_j | g_j - M_j J_j] + T: dL/dM_j = W^T dLin - (W^T dt) J_j^T,
    // dL/dg_j = W^T dt.
    for (var j = t; j < joints; j += CHAIN_GROUP) {
        let at = 12u * j;
        let d_linear = transpose(mat3x3f(
            d_target_joints[at], d_target_joints[at + 1u], d_target_joints[at + 2u],
            d_target_joints[at + 4u], d_target_joints[at + 5u], d_target_joints[at + 6u],
            d_target_joints[at + 8u], d_target_joints[at + 9u], d_target_joints[at + 10u],
        ));
        let d_t = wt * vec3f(d_target_joints[at + 3u], d_target_joints[at + 7u], d_target_joints[at + 11u]);
        store_chain_matrix(d_globals_at() + at, wt * d_linear - outer(d_t, rest_joint(j)));
        store_chain_vector(d_globals_at() + at + 9u, d_t);
        store_chain_matrix(d_rotations_at() + 9u * j, mat3x3f());
    }
    storageBarrier();
    // Pose blend shapes: dL/dR_j += unvec(dL/df) for j >= 1 (feature k is joint 1 + k / 9,
    // entry k % 9 row-major), the partial sums added in workgroup order.
    let features = feature_count();
    for (var k = t; k < features; k += CHAIN_GROUP) {
        var sum = 0.0;
        for (var b = 0u; b < blend_groups(); b++) {
            sum += partials[b * features + k];
        }
        chain[d_rotations_at() + 9u + k] = sum;
    }
    storageBarrier();
    // The chain, leaves first: dL/dR_j += M_p^T dL/dM_j,
    // dL/dM_p += dL/dM_j R_j^T + dL/dg_j (J_j - J_p)^T, dL/dg_p += dL/dg_j; the root's
    // M_0 = R_0.
    if t == 0u {
        for (var step = 0u; step < joints; step++) {
            let j = joints - 1u - step;
            let d_m = chain_matrix(d_globals_at() + 12u * j);
            let d_g = chain_vector(d_globals_at() + 12u * j + 9u);
            let d_r_at = d_rotations_at() + 9u * j;
            let p = parents[j];
            if p == NO_PARENT {
                store_chain_matrix(d_r_at, chain_matrix(d_r_at) + d_m);
            } else {
                let m_p = chain_matrix(globals_at() + 12u * p);
                store_chain_matrix(d_r_at, chain_matrix(d_r_at) + transpose(m_p) * d_m);
                let r = chain_matrix(rotations_at() + 9u * j);
                let p_at = d_globals_at() + 12u * p;
                let d_m_p = chain_matrix(p_at) + d_m * transpose(r)
                    + outer(d_g, rest_joint(j) - rest_joint(p));
                store_chain_matrix(p_at, d_m_p);
                store_chain_vector(p_at + 9u, chain_vector(p_at + 9u) + d_g);
            }
        }
    }
    storageBarrier();
    // R'_j = R_j R_ref_j: dL/dR_ref_j = R_j^T dL/dR'_j.
    for (var j = t + 1u; j < joints; j += CHAIN_GROUP) {
        let g = transpose(frame_rotation(j)) * chain_matrix(d_rotations_at() + 9u * j);
        var bad = 0u;
        for (var r = 0u; r < 3u; r++) {
            for (var c = 0u; c < 3u; c++) {
                d_refinements[9u * (j - 1u) + 3u * r + c] = g[c][r];
                bad += select(1u, 0u, finite(g[c][r]));
            }
        }
        if bad != 0u {
            atomicAdd(&status[STATUS_REFINEMENT_GRADIENTS], bad);
        }
    }
}
