// The exact k nearest canonical neighbours of every Gaussian for the AIAP loss
// (stages/train/src/resident/aiap.rs; the cpu twin is `MovingKnn`), ordered by (squared
// distance, index) as `knn_brute_force` and `KnnGrid` order them, with Verlet candidate lists
// kept on the device and their rebuild decided on the device:
//
// - `check` (one workgroup) measures the largest displacement `delta` of any Gaussian since
//   the lists were built and writes the grids of `rebuild` and `finalize`: full when the lists
//   are invalid or `4 delta >= min_i slack_i`, empty otherwise (indirect dispatches, no
//   read-back);
// - `rebuild` (indirect) searches all Gaussians (a tiled brute force) for the `M` nearest of
//   each (its candidates), stores the positions as anchors and `slack_i = R_i - d_k(i)`
//   (`R_i` the M-th candidate's distance, `d_k(i)` the k-th's), less a relative 1e-5 of
//   `R_i` for rounding; +inf when the list holds every finite Gaussian;
// - `finalize` (indirect, one workgroup) keeps the smallest slack and marks the lists valid;
// - `select` picks the k nearest among each Gaussian's candidates at the current positions.
//
// Why that is exact: with every Gaussian within `delta` of its anchor, distances changed by at
// most `2 delta`, so the current k nearest of `i` are within `d_k(i) + 2 delta` now and were
// within `d_k(i) + 4 delta < R_i` at the rebuild: they are candidates, ties included (a
// non-candidate was at least `R_i` away and is now farther than any of them). A non-finite
// position makes `delta` infinite and forces a rebuild, which skips non-finite references.
//
// `params`: the uniform of train_aiap.wgsl ([0] = N, k, capacity, dispatch limit; [2].x = M).

@group(0) @binding(0) var<uniform> params: array<vec4<u32>, 3>;
@group(0) @binding(1) var<storage, read> xyz: array<f32>;
// Positions at the last rebuild, N x 3.
@group(0) @binding(2) var<storage, read_write> anchors: array<f32>;
// N x MAX_CANDIDATES u32, the first M used, nearest first at the rebuild.
@group(0) @binding(3) var<storage, read_write> candidates: array<u32>;
// Per Gaussian `R_i - d_k(i)` (less the rounding allowance) at the rebuild.
@group(0) @binding(4) var<storage, read_write> slack: array<f32>;
// [valid (0 or 1), smallest slack (f32 bits), rebuilds, calls].
@group(0) @binding(5) var<storage, read_write> lists: array<u32>;
// [rebuild x, y, z, finalize x, y, z].
@group(0) @binding(6) var<storage, read_write> grids: array<u32>;
@group(0) @binding(7) var<storage, read_write> neighbours: array<u32>;

// The largest k (aiap.rs MAX_NEIGHBOURS) and M (aiap.rs CANDIDATES); `select_nearest`'s k
// nearest fit in the `Nearest` list that `rebuild` fills with M.
const MAX_K: u32 = 16u;
const MAX_CANDIDATES: u32 = 32u;
const_assert MAX_K <= MAX_CANDIDATES;
const TILE: u32 = 256u;
const INFINITY_BITS: u32 = 0x7f800000u;

//#include "finite.wgsl"

fn position(i: u32) -> vec3<f32> {
    return vec3<f32>(xyz[3u * i], xyz[3u * i + 1u], xyz[3u * i + 2u]);
}

fn nearer(d: f32, j: u32, best_d: f32, best_j: u32) -> bool {
    return d < best_d || (d == best_d && j < best_j);
}

const WORKGROUP: u32 = 256u;

//#include "linear_index.wgsl"

// A list of the nearest points seen so far, sorted by (squared distance, index) with
// `nearer`: the first `found` entries of `d` and `j`. `rebuild` fills up to M of them,
// `select_nearest` up to k.
struct Nearest {
    d: array<f32, MAX_CANDIDATES>,
    j: array<u32, MAX_CANDIDATES>,
    found: u32,
}

// Inserts point `j` at squared distance `d` into `list` of at most `capacity` entries (from
// the end, shifting the farther ones); a point no nearer than the last of a full list is left.
fn insert_nearest(list: ptr<function, Nearest>, capacity: u32, d: f32, j: u32) {
    let found = (*list).found;
    if (found == capacity && !nearer(d, j, (*list).d[capacity - 1u], (*list).j[capacity - 1u])) {
        return;
    }
    var slot = min(found, capacity - 1u);
    loop {
        if (slot == 0u || !nearer(d, j, (*list).d[slot - 1u], (*list).j[slot - 1u])) {
            break;
        }
        (*list).d[slot] = (*list).d[slot - 1u];
        (*list).j[slot] = (*list).j[slot - 1u];
        slot = slot - 1u;
    }
    (*list).d[slot] = d;
    (*list).j[slot] = j;
    (*list).found = min(found + 1u, capacity);
}

// ---------------------------------------------------------------------------------------

var<workgroup> reduced: array<f32, 256>;

@compute @workgroup_size(256)
fn check(@builtin(local_invocation_index) local: u32) {
    let n = params[0].x;
    var moved = 0.0;
    for (var i = local; i < n; i = i + 256u) {
        let d = position(i) - vec3<f32>(anchors[3u * i], anchors[3u * i + 1u],
            anchors[3u * i + 2u]);
        let d2 = dot(d, d);
        if (!finite(d2)) {
            moved = bitcast<f32>(INFINITY_BITS);
        } else {
            moved = max(moved, d2);
        }
    }
    reduced[local] = moved;
    workgroupBarrier();
    for (var width = 128u; width > 0u; width = width / 2u) {
        if (local < width) {
            reduced[local] = max(reduced[local], reduced[local + width]);
        }
        workgroupBarrier();
    }
    if (local == 0u) {
        let delta = sqrt(reduced[0]);
        let smallest = bitcast<f32>(lists[1]);
        // NaN slack or delta compares false: rebuild.
        let keep = lists[0] == 1u && 4.0 * delta * (1.0 + 1e-5) < smallest;
        lists[3] = lists[3] + 1u;
        var x = 0u;
        var y = 1u;
        var finalize = 0u;
        if (!keep) {
            lists[0] = 0u;
            let groups = (n + 255u) / 256u;
            let limit = params[0].w;
            x = groups;
            if (groups > limit) {
                y = (groups + limit - 1u) / limit;
                x = (groups + y - 1u) / y;
            }
            finalize = 1u;
        }
        grids[0] = x;
        grids[1] = y;
        grids[2] = 1u;
        grids[3] = finalize;
        grids[4] = 1u;
        grids[5] = 1u;
    }
}

// ---------------------------------------------------------------------------------------

var<workgroup> tile_points: array<vec4<f32>, TILE>;

@compute @workgroup_size(WORKGROUP)
fn rebuild(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let n = params[0].x;
    let k = params[0].y;
    let m = params[2].x;
    let i = linear_index(group, groups, local);
    let in_range = i < n;
    var query = vec3<f32>(0.0);
    if (in_range) {
        query = position(i);
    }
    var best: Nearest;
    best.found = 0u;
    var finite_points = 0u;
    for (var start = 0u; start < n; start = start + TILE) {
        let load = start + local;
        var point = vec4<f32>(0.0, 0.0, 0.0, 0.0);
        if (load < n) {
            let p = position(load);
            if (finite(p.x) && finite(p.y) && finite(p.z)) {
                point = vec4<f32>(p, 1.0);
            }
        }
        workgroupBarrier();
        tile_points[local] = point;
        workgroupBarrier();
        if (in_range) {
            let end = min(TILE, n - start);
            for (var t = 0u; t < end; t = t + 1u) {
                let p = tile_points[t];
                if (p.w == 0.0) {
                    continue;
                }
                finite_points = finite_points + 1u;
                let delta = query - p.xyz;
                let d = delta.x * delta.x + delta.y * delta.y + delta.z * delta.z;
                insert_nearest(&best, m, d, start + t);
            }
        }
    }
    if (!in_range) {
        return;
    }
    for (var s = 0u; s < m; s = s + 1u) {
        // Fewer finite points than M: the Gaussian itself fills the rest.
        var j = i;
        if (s < best.found) {
            j = best.j[s];
        }
        candidates[i * MAX_CANDIDATES + s] = j;
    }
    anchors[3u * i] = query.x;
    anchors[3u * i + 1u] = query.y;
    anchors[3u * i + 2u] = query.z;
    // A list holding every finite Gaussian stays valid while the count does.
    var room = bitcast<f32>(INFINITY_BITS);
    if (!finite(query.x + query.y + query.z)) {
        room = -1.0;
    } else if (best.found < finite_points) {
        let reach = sqrt(best.d[m - 1u]);
        room = reach - sqrt(best.d[k - 1u]) - 1e-5 * reach;
    }
    slack[i] = room;
}

// ---------------------------------------------------------------------------------------

@compute @workgroup_size(256)
fn finalize(@builtin(local_invocation_index) local: u32) {
    let n = params[0].x;
    var smallest = bitcast<f32>(INFINITY_BITS);
    for (var i = local; i < n; i = i + 256u) {
        let s = slack[i];
        if (!(s >= smallest)) {
            // Smaller, or NaN (kept as -1: the lists are then rebuilt every call).
            smallest = select(s, -1.0, s != s);
        }
    }
    reduced[local] = smallest;
    workgroupBarrier();
    for (var width = 128u; width > 0u; width = width / 2u) {
        if (local < width) {
            reduced[local] = min(reduced[local], reduced[local + width]);
        }
        workgroupBarrier();
    }
    if (local == 0u) {
        lists[0] = 1u;
        lists[1] = bitcast<u32>(reduced[0]);
        lists[2] = lists[2] + 1u;
    }
}

// ---------------------------------------------------------------------------------------

@compute @workgroup_size(WORKGROUP)
fn select_nearest(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let n = params[0].x;
    let k = params[0].y;
    let m = params[2].x;
    let i = linear_index(group, groups, local);
    if (i >= n) {
        return;
    }
    let query = position(i);
    var best: Nearest;
    best.found = 0u;
    for (var c = 0u; c < m; c = c + 1u) {
        let j = candidates[i * MAX_CANDIDATES + c];
        let p = position(j);
        if (!(finite(p.x) && finite(p.y) && finite(p.z))) {
            continue;
        }
        let delta = query - p;
        let d = delta.x * delta.x + delta.y * delta.y + delta.z * delta.z;
        insert_nearest(&best, k, d, j);
    }
    for (var s = 0u; s < k; s = s + 1u) {
        var j = i;
        if (s < best.found) {
            j = best.j[s];
        }
        neighbours[i * k + s] = j;
    }
}
