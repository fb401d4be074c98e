// Entry point of a feature pass, appended to `blend.wgsl`: composites feature group `p.group`
// (4 channels) and leaves the transmittance as it found it.

// Feature group `p.group` of every Gaussian.
@group(0) @binding(5) var<storage, read> feature_group: array<vec4<f32>>;
// Every group of every pixel of the band: `p.groups` vec4 a pixel.
@group(0) @binding(6) var<storage, read_write> features: array<vec4<f32>>;

fn payload_of(g: u32) -> vec4<f32> {
    return feature_group[g];
}

fn sum_of(pixel: u32) -> vec4<f32> {
    return features[pixel * p.groups + p.group];
}

@compute @workgroup_size(16, 16)
fn blend_features(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    let px = composite(wid, lid, li, start(wid, lid));
    if px.inside {
        features[px.index * p.groups + p.group] = px.sum;
    }
}
