// One pass of a stable least-significant-digit radix sort of (key, value) pairs, 4 bits a pass.
//
// `histogram` counts each block's digits into `counts` digit-major (all blocks' count of digit 0,
// then digit 1, ...); an exclusive scan of that array is, for every (digit, block), where the
// block's first element with that digit goes. `scatter` then places each element at that offset
// plus its rank among the block's earlier elements with the same digit. The rank comes from a
// workgroup prefix sum of per-invocation digit counts (16 counters of 16 bits packed in 8 words)
// and a count within the invocation, so equal digits keep their input order: the sort is
// stable, which is what makes depth ties come out in index order and tiles keep their depth
// order.

const ITEMS: u32 = 8u;
const BLOCK: u32 = 256u * ITEMS;

struct Params {
    len: u32,
    shift: u32,
    blocks: u32,
    groups_x: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> keys_in: array<u32>;
@group(0) @binding(2) var<storage, read_write> counts: array<u32>;
@group(0) @binding(3) var<storage, read> values_in: array<u32>;
@group(0) @binding(4) var<storage, read> offsets: array<u32>;
@group(0) @binding(5) var<storage, read_write> keys_out: array<u32>;
@group(0) @binding(6) var<storage, read_write> values_out: array<u32>;

var<workgroup> hist: array<atomic<u32>, 16>;
// Packed digit counters: word w of the 8 holds digits 2w (low half) and 2w + 1 (high half).
var<workgroup> low: array<vec4<u32>, 256>;
var<workgroup> high: array<vec4<u32>, 256>;
var<workgroup> base: array<u32, 16>;

@compute @workgroup_size(256)
fn histogram(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let block = wid.x + wid.y * p.groups_x;
    if li < 16u {
        atomicStore(&hist[li], 0u);
    }
    workgroupBarrier();
    for (var r = 0u; r < ITEMS; r++) {
        let i = block * BLOCK + r * 256u + li;
        if i < p.len {
            atomicAdd(&hist[(keys_in[i] >> p.shift) & 15u], 1u);
        }
    }
    workgroupBarrier();
    if li < 16u && block < p.blocks {
        counts[li * p.blocks + block] = atomicLoad(&hist[li]);
    }
}

fn packed_count(l: vec4<u32>, h: vec4<u32>, digit: u32) -> u32 {
    let word = digit >> 1u;
    var w: u32;
    if word < 4u {
        w = l[word];
    } else {
        w = h[word - 4u];
    }
    return (w >> ((digit & 1u) * 16u)) & 0xffffu;
}

@compute @workgroup_size(256)
fn scatter(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let block = wid.x + wid.y * p.groups_x;
    if block >= p.blocks {
        return;
    }
    if li < 16u {
        base[li] = offsets[li * p.blocks + block];
    }
    // Each invocation takes ITEMS consecutive elements, so invocation order is element order.
    let first = block * BLOCK + li * ITEMS;
    var keys: array<u32, ITEMS>;
    var ranks: array<u32, ITEMS>;
    var l = vec4<u32>(0u);
    var h = vec4<u32>(0u);
    for (var k = 0u; k < ITEMS; k++) {
        if first + k < p.len {
            let key = keys_in[first + k];
            let digit = (key >> p.shift) & 15u;
            keys[k] = key;
            ranks[k] = packed_count(l, h, digit);
            let one = 1u << ((digit & 1u) * 16u);
            let word = digit >> 1u;
            if word < 4u {
                l[word] += one;
            } else {
                h[word - 4u] += one;
            }
        }
    }
    low[li] = l;
    high[li] = h;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off = off << 1u) {
        var a = low[li];
        var b = high[li];
        if li >= off {
            a += low[li - off];
            b += high[li - off];
        }
        workgroupBarrier();
        low[li] = a;
        high[li] = b;
        workgroupBarrier();
    }
    // Inclusive minus this invocation's own counts: what earlier invocations hold. Every 16-bit
    // field of the inclusive sum is at least the own one, so no borrow crosses fields.
    let before_l = low[li] - l;
    let before_h = high[li] - h;
    for (var k = 0u; k < ITEMS; k++) {
        if first + k < p.len {
            let digit = (keys[k] >> p.shift) & 15u;
            let dst = base[digit] + packed_count(before_l, before_h, digit) + ranks[k];
            keys_out[dst] = keys[k];
            values_out[dst] = values_in[first + k];
        }
    }
}
