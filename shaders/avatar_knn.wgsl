// Device-resident motion inputs of the avatar (src/avatar/src/resident/motion.rs), f32:
// the frame's skeleton-motion window (motion::schema::MotionTrack::gather), the k nearest
// template vertices of query points (motion::knn::KnnGrid::query_all: sorted by squared
// distance, then index) and the velocity gather (avatar::knn_velocity).
//
// Layouts (row-major): skeleton motion of the sequence F x S x J x 3 and vertex velocity
// F x S x V x 3 (only the scale slots in use, in the order used, largest scale first);
// template vertices V x 3; queries N x 3; neighbours N x k (nearest first); the window
// L x S x J x 3; velocity block l: N x (tau S 3), `[neighbour][scale][xyz]` per Gaussian.

// The shape (a uniform written once, plain words so that no struct crosses the boundary):
// [length L, scales S, joints J, vertices V], [k (neighbours per query of this search),
// window element of this gather, fallback (what a non-finite query gets k times: the cpu
// search's first reference point), 0].
// The per-iteration record (16 bytes): [frame index, Gaussian count, 0, 0].
fn shape_length() -> u32 {
    return shape[0].x;
}

fn shape_scales() -> u32 {
    return shape[0].y;
}

fn shape_joints() -> u32 {
    return shape[0].z;
}

fn shape_vertices() -> u32 {
    return shape[0].w;
}

fn shape_k() -> u32 {
    return shape[1].x;
}

fn shape_element() -> u32 {
    return shape[1].y;
}

fn shape_fallback() -> u32 {
    return shape[1].z;
}

fn record_frame() -> u32 {
    return record[0];
}

fn record_count() -> u32 {
    return record[1];
}

const MAX_K: u32 = 64u;
const TILE: u32 = 64u;

@group(0) @binding(0) var<uniform> shape: array<vec4<u32>, 2>;
@group(0) @binding(1) var<storage, read> record: array<u32>;
// Per scale slot in use: its step on the frame axis.
@group(0) @binding(2) var<storage, read> steps: array<u32>;
@group(0) @binding(3) var<storage, read> skeleton_motion: array<f32>;
@group(0) @binding(4) var<storage, read> vertex_velocity: array<f32>;
@group(0) @binding(5) var<storage, read> template_vertices: array<f32>;
@group(0) @binding(6) var<storage, read> queries: array<f32>;
@group(0) @binding(7) var<storage, read_write> neighbours: array<u32>;
@group(0) @binding(8) var<storage, read_write> window: array<f32>;

// Threads per workgroup of every entry point here.
const WORKGROUP: u32 = 64u;

//#include "linear_index.wgsl"
//#include "finite.wgsl"

// The frame row of window element l at scale slot s: frame - l step, clamped at 0 (the host
// checked that clamping is allowed: MotionTrack::gather's rule).
fn window_row(l: u32, s: u32) -> u32 {
    let back = l * steps[s];
    return select(0u, record_frame() - back, record_frame() >= back);
}

// The skeleton-motion window L x S x J x 3 of the record's frame.
@compute @workgroup_size(WORKGROUP)
fn gather_skeleton(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let o = linear_index(group, groups, local);
    let per_scale = shape_joints() * 3u;
    if o >= shape_length() * shape_scales() * per_scale {
        return;
    }
    let inner = o % per_scale;
    let s = (o / per_scale) % shape_scales();
    let l = o / (per_scale * shape_scales());
    let row = window_row(l, s);
    window[o] = skeleton_motion[(row * shape_scales() + s) * per_scale + inner];
}

// Velocity block of window element `shape_element()`: for Gaussian i, neighbour n (of the
// tau = shape_k() nearest in `neighbours`) and scale s, the velocity of that vertex at the
// window row.
@compute @workgroup_size(WORKGROUP)
fn gather_velocity(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let o = linear_index(group, groups, local);
    let width = shape_k() * shape_scales() * 3u;
    if o >= record_count() * width {
        return;
    }
    let i = o / width;
    let inner = o % width;
    let c = inner % 3u;
    let s = (inner / 3u) % shape_scales();
    let n = inner / (3u * shape_scales());
    let vertex = neighbours[i * shape_k() + n];
    let row = window_row(shape_element(), s);
    window[o] = vertex_velocity[((row * shape_scales() + s) * shape_vertices() + vertex) * 3u + c];
}

var<workgroup> tile: array<vec3<f32>, 64>;

// The shape_k() nearest template vertices of each query, nearest first, ties by index: a tiled
// brute force (every query against every vertex, vertices staged through workgroup memory).
// Vertices are visited in index order and a candidate enters only when strictly nearer than
// the current k-th, behind every kept one at the same distance, so equal distances keep the
// lower index first, as the cpu grid search orders them. Non-finite vertices never enter; a
// non-finite query gets `shape_fallback()` k times.
@compute @workgroup_size(WORKGROUP)
fn knn(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = linear_index(group, groups, local);
    let k = min(shape_k(), MAX_K);
    let active_query = i < record_count();
    var q = vec3<f32>(0.0);
    var valid = false;
    if active_query {
        q = vec3<f32>(queries[3u * i], queries[3u * i + 1u], queries[3u * i + 2u]);
        valid = finite(q.x) && finite(q.y) && finite(q.z);
    }
    // Far queries are compared in units of a power of two (exact scaling) so that squared
    // distances never overflow; the order is that of the unscaled distances.
    let largest = max(max(abs(q.x), abs(q.y)), abs(q.z));
    var exponent = 0;
    if valid && largest > 1e18 {
        exponent = frexp(largest).exp;
    }
    var best_d: array<f32, 64>;
    var best_i: array<u32, 64>;
    for (var n = 0u; n < MAX_K; n++) {
        best_d[n] = 3.4e38;
        best_i[n] = shape_fallback();
    }
    var filled = 0u;
    for (var base = 0u; base < shape_vertices(); base += TILE) {
        workgroupBarrier();
        let v = base + local;
        if v < shape_vertices() {
            tile[local] = vec3<f32>(template_vertices[3u * v], template_vertices[3u * v + 1u], template_vertices[3u * v + 2u]);
        }
        workgroupBarrier();
        if !valid {
            continue;
        }
        let count = min(TILE, shape_vertices() - base);
        for (var t = 0u; t < count; t++) {
            let p = tile[t];
            if !(finite(p.x) && finite(p.y) && finite(p.z)) {
                continue;
            }
            let diff = ldexp(q - p, vec3<i32>(-exponent));
            let d = dot(diff, diff);
            // While filling, every vertex enters; once full, one strictly nearer than the
            // k-th replaces it. Either way it goes behind every kept one at a distance <= d.
            if filled < k || d < best_d[k - 1u] {
                var j = min(filled, k - 1u);
                while j > 0u && best_d[j - 1u] > d {
                    best_d[j] = best_d[j - 1u];
                    best_i[j] = best_i[j - 1u];
                    j -= 1u;
                }
                best_d[j] = d;
                best_i[j] = base + t;
                filled = min(filled + 1u, k);
            }
        }
    }
    if active_query {
        for (var n = 0u; n < k; n++) {
            neighbours[i * shape_k() + n] = best_i[n];
        }
    }
}
