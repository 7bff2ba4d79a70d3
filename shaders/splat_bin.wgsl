// Tile binning for Gaussian splatting (SPLATTING.md, "Binning"). The host first sorts the
// Gaussians by depth (stable, so ties keep index order), then:
// `count_tiles` counts each depth-sorted Gaussian's tiles within the band of tile rows,
// the host scans the counts into offsets (the total stays on the device), `emit_pairs` writes
// one (tile, Gaussian) pair per touched tile in depth order, at most the band's pair capacity
// `pairs`, `finish_pairs` fills the slots past the total with the sentinel tile `tiles` (so
// they sort last), records the band's total and flags an overflow in the status buffer, the
// host sorts all `pairs` slots stably by tile (so each tile's list stays in depth order), and
// `tile_ranges` finds each tile's [start, end) in the sorted pairs, skipping the sentinels.
// Nothing is read back: an overflowed band renders without its last pairs until the host,
// reading the status with its logs, grows the capacity.

struct BinParams {
    gaussians: u32,
    pairs: u32,
    tiles_x: u32,
    row_begin: u32,
    row_end: u32,
    // Where `finish_pairs` records the band's pair total in `band_pairs`.
    slot: u32,
    // tiles_x * tiles_y: the sentinel tile of unused pair slots.
    tiles: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: BinParams;
@group(0) @binding(1) var<storage, read> sorted_indices: array<u32>;
@group(0) @binding(2) var<storage, read> rects: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read_write> counts: array<u32>;
@group(0) @binding(4) var<storage, read_write> tile_keys: array<u32>;
@group(0) @binding(5) var<storage, read_write> pair_gaussians: array<u32>;
@group(0) @binding(6) var<storage, read_write> ranges: array<vec2<u32>>;
// Element 0: the band's pair total (the scan's total of `counts`).
@group(0) @binding(7) var<storage, read> pair_total: array<u32>;
// [0] bands that overflowed their capacity, [1] the largest band total seen (SplatStatus).
@group(0) @binding(8) var<storage, read_write> status: array<atomic<u32>>;
// One pair total per (camera, band) slot.
@group(0) @binding(9) var<storage, read_write> band_pairs: array<u32>;

fn thread_index(group: vec3<u32>, groups: vec3<u32>, local: u32) -> u32 {
    return (group.x + group.y * groups.x) * 256u + local;
}

// The Gaussian's tile rectangle restricted to the band's rows (empty when outside).
fn band_rect(g: u32) -> vec4<u32> {
    let rect = rects[g];
    let y0 = max(rect.y, params.row_begin);
    let y1 = min(rect.w, params.row_end);
    if y0 >= y1 || rect.x >= rect.z {
        return vec4<u32>(0u);
    }
    return vec4<u32>(rect.x, y0, rect.z, y1);
}

@compute @workgroup_size(256)
fn count_tiles(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = thread_index(group, groups, local);
    if i >= params.gaussians {
        return;
    }
    let rect = band_rect(sorted_indices[i]);
    counts[i] = (rect.z - rect.x) * (rect.w - rect.y);
}

@compute @workgroup_size(256)
fn emit_pairs(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = thread_index(group, groups, local);
    if i >= params.gaussians {
        return;
    }
    let g = sorted_indices[i];
    let rect = band_rect(g);
    var offset = counts[i];
    for (var y = rect.y; y < rect.w; y = y + 1u) {
        for (var x = rect.x; x < rect.z; x = x + 1u) {
            if offset < params.pairs {
                tile_keys[offset] = y * params.tiles_x + x;
                pair_gaussians[offset] = g;
            }
            offset = offset + 1u;
        }
    }
}

@compute @workgroup_size(256)
fn finish_pairs(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = thread_index(group, groups, local);
    let total = pair_total[0];
    if i == 0u {
        band_pairs[params.slot] = total;
        atomicMax(&status[1], total);
        if total > params.pairs {
            atomicAdd(&status[0], 1u);
        }
    }
    if i < params.pairs && i >= total {
        tile_keys[i] = params.tiles;
        pair_gaussians[i] = 0u;
    }
}

@compute @workgroup_size(256)
fn tile_ranges(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let i = thread_index(group, groups, local);
    if i >= params.pairs {
        return;
    }
    let tile = tile_keys[i];
    if tile >= params.tiles {
        return;
    }
    if i == 0u || tile_keys[i - 1u] != tile {
        ranges[tile].x = i;
    }
    if i + 1u == params.pairs || tile_keys[i + 1u] != tile {
        ranges[tile].y = i + 1u;
    }
}
