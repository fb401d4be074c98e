// Blending: one 16×16 workgroup per tile of a band, one invocation per pixel. The tile's splats
// (front to back) are staged through workgroup memory 256 at a time; every pixel composites them
// with the forward model's cuts (the 3-sigma cut for the ellipse footprint; for the 3DGS one none,
// but its skip where the exponent is positive) and stops at the transmittance floor; the tile
// stops when all its pixels have.
//
// Per-pixel state lives in storage buffers so that a frame can be blended in several depth-ordered
// chunks of splats (when its pairs exceed what one pass can hold): transmittance, negated once the
// pixel has stopped; colour and alpha-weighted depth; feature channels, 4 per pass. `first` starts
// from T = 1 and zero sums instead of reading the state.
//
// This file is the shared part; an entry point file is appended to it and supplies what rides
// along with alpha (`payload_of`, `sum_of`) and what is written at the end:
// `blend_color.wgsl` composites (r, g, b, depth) and advances T; `blend_features.wgsl` composites
// one group of 4 feature channels, replaying the same T sequence from the state as it was before
// this chunk (so it runs before the colour pass of the same chunk) without writing it.

const SIGMA_EXTENT: f32 = 3.0;
const ALPHA_MAX: f32 = 0.99;
const ALPHA_MIN: f32 = 1.0 / 255.0;
const TRANSMITTANCE_MIN: f32 = 1e-4;
const TILE: u32 = 16u;
const BATCH: u32 = 256u;
// `p.footprint`: 0 the ellipse, 1 the 3DGS tiles.
const FOOTPRINT_3DGS: u32 = 1u;

struct Params {
    width: u32,
    // Pixel rows of the band: [y0, y0 + rows) of the image.
    y0: u32,
    rows: u32,
    tiles_x: u32,
    first: u32,
    // Feature group of this pass and how many groups a pixel holds.
    group: u32,
    groups: u32,
    footprint: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> splats: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> pair_splats: array<u32>;
@group(0) @binding(3) var<storage, read> ranges: array<u32>;
@group(0) @binding(4) var<storage, read_write> transmittance: array<f32>;

var<workgroup> centre: array<vec4<f32>, BATCH>;
var<workgroup> conic: array<vec4<f32>, BATCH>;
var<workgroup> payload: array<vec4<f32>, BATCH>;
var<workgroup> live_count: atomic<u32>;

struct Pixel {
    inside: bool,
    index: u32,
    t: f32,
    done: bool,
    sum: vec4<f32>,
}

fn start(wid: vec3<u32>, lid: vec3<u32>) -> Pixel {
    var px: Pixel;
    let x = wid.x * TILE + lid.x;
    let row = wid.y * TILE + lid.y;
    px.inside = x < p.width && row < p.rows;
    px.index = row * p.width + x;
    px.t = 1.0;
    px.done = !px.inside;
    px.sum = vec4<f32>(0.0);
    if px.inside && p.first == 0u {
        let t = transmittance[px.index];
        px.done = t < 0.0;
        px.t = abs(t);
        px.sum = sum_of(px.index);
    }
    return px;
}

// Composites the tile's splats into `px`.
fn composite(wid: vec3<u32>, lid: vec3<u32>, li: u32, px_in: Pixel) -> Pixel {
    var px = px_in;
    let tile = wid.y * p.tiles_x + wid.x;
    // Read-only storage read at a uniform index: uniform, as the barriers below need.
    let range = vec2<u32>(ranges[2u * tile], ranges[2u * tile + 1u]);
    let fx = f32(wid.x * TILE + lid.x) + 0.5;
    let fy = f32(p.y0 + wid.y * TILE + lid.y) + 0.5;
    let cut = SIGMA_EXTENT * SIGMA_EXTENT;
    let tiles_3dgs = p.footprint == FOOTPRINT_3DGS;
    for (var batch = range.x; batch < range.y; batch += BATCH) {
        let k = batch + li;
        if k < range.y {
            let g = pair_splats[k];
            centre[li] = splats[3u * g];
            conic[li] = splats[3u * g + 1u];
            payload[li] = payload_of(g);
        }
        if li == 0u {
            atomicStore(&live_count, 0u);
        }
        workgroupBarrier();
        if !px.done {
            let n = min(BATCH, range.y - batch);
            for (var j = 0u; j < n; j++) {
                let c = centre[j];
                let q = conic[j];
                let dx = fx - c.x;
                let dy = fy - c.y;
                let d2 = q.x * dx * dx + 2.0 * q.y * dx * dy + q.z * dy * dy;
                // 3DGS evaluates every pixel of its tiles but skips where the exponent -d²/2 is
                // positive: never in exact arithmetic, sometimes in f32 (as here) very near the
                // centre of an extremely thin footprint.
                if select(d2 > cut, d2 < 0.0, tiles_3dgs) {
                    continue;
                }
                // d² ≥ 0 exactly; clamping keeps a rounding error from lifting alpha above opacity.
                let alpha = min(ALPHA_MAX, c.z * exp(-0.5 * max(d2, 0.0)));
                if alpha < ALPHA_MIN {
                    continue;
                }
                let next = px.t * (1.0 - alpha);
                if next < TRANSMITTANCE_MIN {
                    px.done = true;
                    break;
                }
                px.sum += payload[j] * (alpha * px.t);
                px.t = next;
            }
        }
        // Barriers are the expensive part on some devices (lavapipe): the last batch needs none.
        if batch + BATCH >= range.y {
            break;
        }
        // More batches follow. Counting live pixels doubles as the barrier that keeps the next
        // batch from overwriting splats still being read; with none live, the tile is done.
        if !px.done {
            atomicAdd(&live_count, 1u);
        }
        if workgroupUniformLoad(&live_count) == 0u {
            break;
        }
    }
    return px;
}
