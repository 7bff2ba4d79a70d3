// The pose refiner's regularised Rodrigues map and its backward (the cpu twins are
// `regularised_rodrigues` / `regularised_rodrigues_backward` in
// src/avatar/src/model/pose_refiner.rs):
//   theta = sqrt(epsilon + |v|^2),  k = v / theta,
//   R = cos(theta) I + (1 - cos(theta)) k k^T + sin(theta) [k]x      (row-major 3 x 3)
// One thread per rotation vector; `vectors` is count x 3, `matrices` count x 9. The grid may
// be 2D (`linear_index`).

struct Params {
    count: u32,
    epsilon: f32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> vectors: array<f32>;
@group(0) @binding(2) var<storage, read> gradient: array<f32>;
@group(0) @binding(3) var<storage, read_write> destination: array<f32>;

const WORKGROUP: u32 = 64u;

//#include "linear_index.wgsl"

// The angle, axis and its sine and cosine of rotation vector j.
struct AxisAngle {
    theta: f32,
    k: vec3<f32>,
    s: f32,
    c: f32,
}

fn axis_angle(j: u32) -> AxisAngle {
    let v = vec3<f32>(vectors[3u * j], vectors[3u * j + 1u], vectors[3u * j + 2u]);
    let theta = sqrt(params.epsilon + dot(v, v));
    return AxisAngle(theta, v / theta, sin(theta), cos(theta));
}

// destination = R(v), count x 9.
@compute @workgroup_size(WORKGROUP)
fn forward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let j = linear_index(group, groups, local);
    if (j >= params.count) {
        return;
    }
    let r = axis_angle(j);
    let k = r.k;
    let s = r.s;
    let c = r.c;
    let t = 1.0 - c;
    let base = 9u * j;
    destination[base + 0u] = c + t * k.x * k.x;
    destination[base + 1u] = t * k.x * k.y - s * k.z;
    destination[base + 2u] = t * k.x * k.z + s * k.y;
    destination[base + 3u] = t * k.y * k.x + s * k.z;
    destination[base + 4u] = c + t * k.y * k.y;
    destination[base + 5u] = t * k.y * k.z - s * k.x;
    destination[base + 6u] = t * k.z * k.x - s * k.y;
    destination[base + 7u] = t * k.z * k.y + s * k.x;
    destination[base + 8u] = c + t * k.z * k.z;
}

// destination = dL/dv (count x 3, overwritten) from gradient = dL/dR (count x 9, row-major).
@compute @workgroup_size(WORKGROUP)
fn backward(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let j = linear_index(group, groups, local);
    if (j >= params.count) {
        return;
    }
    let r = axis_angle(j);
    let k = r.k;
    let s = r.s;
    let c = r.c;
    let base = 9u * j;
    // Rows of G.
    let g0 = vec3<f32>(gradient[base + 0u], gradient[base + 1u], gradient[base + 2u]);
    let g1 = vec3<f32>(gradient[base + 3u], gradient[base + 4u], gradient[base + 5u]);
    let g2 = vec3<f32>(gradient[base + 6u], gradient[base + 7u], gradient[base + 8u]);
    // <G, [k]x> = k . a with a = (G21 - G12, G02 - G20, G10 - G01).
    let a = vec3<f32>(g2.y - g1.z, g0.z - g2.x, g1.x - g0.y);
    let trace = g0.x + g1.y + g2.z;
    let g_k = vec3<f32>(dot(g0, k), dot(g1, k), dot(g2, k));
    let gt_k = g0 * k.x + g1 * k.y + g2 * k.z;
    let d_theta = -s * trace + s * dot(k, g_k) + c * dot(k, a);
    let d_k = (g_k + gt_k) * (1.0 - c) + a * s;
    let d_v = k * d_theta + (d_k - k * dot(k, d_k)) / r.theta;
    destination[3u * j] = d_v.x;
    destination[3u * j + 1u] = d_v.y;
    destination[3u * j + 2u] = d_v.z;
}
