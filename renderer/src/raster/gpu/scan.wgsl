// Exclusive prefix sums of u32 arrays of any length, in blocks of 1024 (256 invocations × 4).
// `scan_blocks` scans each block in place and writes the block's total to `sums`; the host scans
// `sums` the same way (recursively) and `add_block_sums` adds each block's offset back.
// Additions saturate at u32::MAX, so a sum too large to count is seen as such, never as a wrap.

const BLOCK: u32 = 1024u;

struct Params {
    len: u32,
    blocks: u32,
    groups_x: u32,
    unused: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

var<workgroup> partial: array<u32, 256>;

fn sat_add(a: u32, b: u32) -> u32 {
    let s = a + b;
    return select(s, 0xffffffffu, s < a);
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let block = wid.x + wid.y * p.groups_x;
    let base = block * BLOCK + li * 4u;
    var own: array<u32, 4>;
    var run = 0u;
    for (var k = 0u; k < 4u; k++) {
        var x = 0u;
        if base + k < p.len {
            x = data[base + k];
        }
        own[k] = run;
        run = sat_add(run, x);
    }
    partial[li] = run;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off = off << 1u) {
        var t = partial[li];
        if li >= off {
            t = sat_add(partial[li - off], t);
        }
        workgroupBarrier();
        partial[li] = t;
        workgroupBarrier();
    }
    var before = 0u;
    if li > 0u {
        before = partial[li - 1u];
    }
    for (var k = 0u; k < 4u; k++) {
        if base + k < p.len {
            data[base + k] = sat_add(before, own[k]);
        }
    }
    if li == 255u && block < p.blocks {
        sums[block] = partial[255];
    }
}

@compute @workgroup_size(256)
fn add_block_sums(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let block = wid.x + wid.y * p.groups_x;
    if block >= p.blocks {
        return;
    }
    let offset = sums[block];
    for (var k = 0u; k < 4u; k++) {
        let i = block * BLOCK + k * 256u + li;
        if i < p.len {
            data[i] = sat_add(data[i], offset);
        }
    }
}
