// Entry point of the colour pass, appended to `blend.wgsl`: composites (r, g, b, depth) and
// advances the transmittance.

@group(0) @binding(5) var<storage, read_write> color: array<vec4<f32>>;

fn payload_of(g: u32) -> vec4<f32> {
    return splats[3u * g + 2u];
}

fn sum_of(pixel: u32) -> vec4<f32> {
    return color[pixel];
}

@compute @workgroup_size(16, 16)
fn blend_color(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    let px = composite(wid, lid, li, start(wid, lid));
    if px.inside {
        transmittance[px.index] = select(px.t, -px.t, px.done);
        color[px.index] = px.sum;
    }
}
