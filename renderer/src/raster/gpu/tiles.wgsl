// Binning: which splats reach which tiles of a band of tile rows.
//
// Splats are visited in global depth order (`order`, the depth-sorted Gaussian indices) starting
// at `first`. `count` writes how many of the band's tiles each one's rectangle covers; after an
// exclusive scan of those counts, `emit` writes one (tile, Gaussian) pair per covered tile at its
// splat's offset, so the pair list is in depth order; a stable sort by tile keeps that order
// inside every tile, and `ranges` finds where each tile's run starts and ends.

struct Params {
    // Splats handled by this dispatch: order[first .. first + len].
    first: u32,
    len: u32,
    // The band: tile rows [row0, row0 + rows).
    row0: u32,
    rows: u32,
    tiles_x: u32,
    // Pairs in the list (for `ranges`).
    pairs: u32,
    groups_x: u32,
    unused: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> order: array<u32>;
@group(0) @binding(2) var<storage, read> rects: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read_write> counts: array<u32>;
@group(0) @binding(4) var<storage, read> offsets: array<u32>;
@group(0) @binding(5) var<storage, read_write> pair_tiles: array<u32>;
@group(0) @binding(6) var<storage, read_write> pair_splats: array<u32>;
@group(0) @binding(7) var<storage, read> sorted_tiles: array<u32>;
// Tile t's pairs are [ranges[2t], ranges[2t + 1]).
@group(0) @binding(8) var<storage, read_write> ranges: array<u32>;

fn index(wid: vec3<u32>, li: u32) -> u32 {
    return (wid.x + wid.y * p.groups_x) * 256u + li;
}

// The splat's rectangle cut to the band, in band-local tile rows.
fn band_rect(g: u32) -> vec4<u32> {
    let r = rects[g];
    let y0 = max(r.y, p.row0);
    let y1 = max(min(r.w, p.row0 + p.rows), y0);
    return vec4<u32>(r.x, y0 - p.row0, max(r.z, r.x), y1 - p.row0);
}

@compute @workgroup_size(256)
fn count(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let s = index(wid, li);
    if s >= p.len {
        return;
    }
    let r = band_rect(order[p.first + s]);
    counts[s] = (r.z - r.x) * (r.w - r.y);
}

@compute @workgroup_size(256)
fn emit(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let s = index(wid, li);
    if s >= p.len {
        return;
    }
    let g = order[p.first + s];
    let r = band_rect(g);
    var at = offsets[s];
    for (var ty = r.y; ty < r.w; ty++) {
        for (var tx = r.x; tx < r.z; tx++) {
            pair_tiles[at] = ty * p.tiles_x + tx;
            pair_splats[at] = g;
            at++;
        }
    }
}

@compute @workgroup_size(256)
fn ranges_of_tiles(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let i = index(wid, li);
    if i >= p.pairs {
        return;
    }
    let tile = sorted_tiles[i];
    if i == 0u || sorted_tiles[i - 1u] != tile {
        ranges[2u * tile] = i;
    }
    if i + 1u == p.pairs || sorted_tiles[i + 1u] != tile {
        ranges[2u * tile + 1u] = i + 1u;
    }
}
