// Projection: one invocation per Gaussian turns its 14 canonical parameters into a splat (what the
// pixels need), a tile rectangle (which tiles it may reach: around its 3-sigma ellipse, or its 3DGS
// tiles, by the footprint) and a depth key for the global sort. Skipped Gaussians get an empty
// rectangle and the largest key, so they sort last and emit nothing.
//
// The 2D covariance is built as M Mᵀ + EPS2D·I with M = J W R S (2×3), rescaled by the largest
// entry of M first: that keeps f32 from overflowing for huge scales or focal lengths, and the
// determinant |m0 × m1|² + eps (|m0|² + |m1|²) + eps² has no cancellation, even for zero scales.

const EPS2D: f32 = 0.3;
const SIGMA_EXTENT: f32 = 3.0;
const ALPHA_MIN: f32 = 1.0 / 255.0;
const DISCRIMINANT_FLOOR_3DGS: f32 = 0.1;
const TILE: u32 = 16u;
// `cam.keys.w`: the footprint (0 the ellipse, 1 the 3DGS tiles).
const FOOTPRINT_3DGS: u32 = 1u;

struct Camera {
    // Rows of the world-to-camera transform [R | t].
    view_x: vec4<f32>,
    view_y: vec4<f32>,
    view_z: vec4<f32>,
    // fx, fy, cx, cy in pixels.
    focal: vec4<f32>,
    // FOV-clamp limits of x/z and y/z, near, far.
    clip: vec4<f32>,
    // width, height, number of Gaussians, workgroups along x of this dispatch.
    image: vec4<u32>,
    // bits of near, the key of a skipped Gaussian, tiles along x, the footprint.
    keys: vec4<u32>,
}

@group(0) @binding(0) var<uniform> cam: Camera;
// 14 floats per Gaussian, the canonical layout (position, scale, rotation wxyz, opacity, rgb).
@group(0) @binding(1) var<storage, read> params: array<f32>;
// 3 vec4 per Gaussian: (u, v, opacity, depth), (conic a, b, c, 0), (r, g, b, depth).
@group(0) @binding(2) var<storage, read_write> splats: array<vec4<f32>>;
// Tile rectangle [x0, x1) × [y0, y1) as (x0, y0, x1, y1).
@group(0) @binding(3) var<storage, read_write> rects: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read_write> keys: array<u32>;
@group(0) @binding(5) var<storage, read_write> values: array<u32>;

fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn max_abs(v: vec3<f32>) -> f32 {
    let a = abs(v);
    return max(a.x, max(a.y, a.z));
}

fn skip(i: u32) {
    rects[i] = vec4<u32>(0u);
    keys[i] = cam.keys.y;
    values[i] = i;
}

// Pixel range [lo, hi] (inclusive, inside 0..size) whose centres may lie within `radius` of
// `centre`, with a pixel of slack for the f32 test in the blend; empty when lo > hi.
fn pixel_span(centre: f32, radius: f32, size: u32) -> vec2<i32> {
    let lo = floor(centre - radius - 0.5) - 1.0;
    let hi = ceil(centre + radius - 0.5) + 1.0;
    let last = f32(size) - 1.0;
    if !(hi >= 0.0 && lo <= last) {
        return vec2<i32>(1, 0);
    }
    return vec2<i32>(i32(max(lo, 0.0)), i32(min(hi, last)));
}

// The 3DGS tiles [first, end) along one axis of a splat centred at `centre` with radius `radius`
// (pixels), among `tiles`: 3DGS's pixel coordinates put pixel i at i, ours at i + 0.5.
fn tiles_3dgs(centre: f32, radius: f32, tiles: u32) -> vec2<u32> {
    let p = centre - 0.5;
    let t = f32(TILE);
    let n = f32(tiles);
    // Clamped as floats, so that off-screen or infinite ends convert exactly.
    let first = clamp(floor((p - radius) / t), 0.0, n);
    let end = clamp(floor((p + radius + t - 1.0) / t), 0.0, n);
    return vec2<u32>(u32(first), u32(end));
}

@compute @workgroup_size(256)
fn project(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let i = (wid.x + wid.y * cam.image.w) * 256u + li;
    if i >= cam.image.z {
        return;
    }
    let b = i * 14u;
    var ok = true;
    for (var k = 0u; k < 14u; k++) {
        ok = ok && finite(params[b + k]);
    }
    let opacity = params[b + 10u];
    // Alpha never exceeds the opacity: a Gaussian this faint reaches no pixel.
    if !ok || !(opacity >= ALPHA_MIN) {
        skip(i);
        return;
    }
    let mean = vec3<f32>(params[b], params[b + 1u], params[b + 2u]);
    let scale = vec3<f32>(params[b + 3u], params[b + 4u], params[b + 5u]);
    var q = vec4<f32>(params[b + 6u], params[b + 7u], params[b + 8u], params[b + 9u]);
    let color = vec3<f32>(params[b + 11u], params[b + 12u], params[b + 13u]);

    let qmax = max(max(abs(q.x), abs(q.y)), max(abs(q.z), abs(q.w)));
    if !(qmax > 0.0) {
        skip(i);
        return;
    }
    // Normalised after dividing by the largest component, so |q|² cannot overflow.
    q = q / qmax;
    q = q / sqrt(dot(q, q));

    let p = vec3<f32>(
        dot(cam.view_x.xyz, mean) + cam.view_x.w,
        dot(cam.view_y.xyz, mean) + cam.view_y.w,
        dot(cam.view_z.xyz, mean) + cam.view_z.w,
    );
    let z = p.z;
    if !(z >= cam.clip.z && z <= cam.clip.w) {
        skip(i);
        return;
    }

    let w = q.x;
    let x = q.y;
    let y = q.z;
    let zq = q.w;
    // Columns of R (rotation of the Gaussian), each scaled by its standard deviation.
    let c0 = vec3<f32>(1.0 - 2.0 * (y * y + zq * zq), 2.0 * (x * y + w * zq), 2.0 * (x * zq - w * y)) * scale.x;
    let c1 = vec3<f32>(2.0 * (x * y - w * zq), 1.0 - 2.0 * (x * x + zq * zq), 2.0 * (y * zq + w * x)) * scale.y;
    let c2 = vec3<f32>(2.0 * (x * zq + w * y), 2.0 * (y * zq - w * x), 1.0 - 2.0 * (x * x + y * y)) * scale.z;

    let fx = cam.focal.x;
    let fy = cam.focal.y;
    let rx = clamp(p.x / z, -cam.clip.x, cam.clip.x);
    let ry = clamp(p.y / z, -cam.clip.y, cam.clip.y);
    // Rows of J W, in world axes.
    let t0 = (fx / z) * (cam.view_x.xyz - rx * cam.view_z.xyz);
    let t1 = (fy / z) * (cam.view_y.xyz - ry * cam.view_z.xyz);
    let m0 = vec3<f32>(dot(t0, c0), dot(t0, c1), dot(t0, c2));
    let m1 = vec3<f32>(dot(t1, c0), dot(t1, c1), dot(t1, c2));

    let s = max(max(max_abs(m0), max_abs(m1)), 1.0);
    let n0 = m0 / s;
    let n1 = m1 / s;
    let e = EPS2D / s / s;
    let l0 = dot(n0, n0);
    let l1 = dot(n1, n1);
    let sxx = l0 + e;
    let sxy = dot(n0, n1);
    let syy = l1 + e;
    let cr = cross(n0, n1);
    let det = dot(cr, cr) + e * (l0 + l1) + e * e;
    if !(det > 0.0) || !finite(det) {
        skip(i);
        return;
    }
    let conic = vec3<f32>(syy / det / s / s, -sxy / det / s / s, sxx / det / s / s);
    let u = fx * (p.x / z) + cam.focal.z;
    let v = fy * (p.y / z) + cam.focal.w;
    if !(finite(conic.x) && finite(conic.y) && finite(conic.z) && finite(u) && finite(v)) {
        skip(i);
        return;
    }

    var rect: vec4<u32>;
    if cam.keys.w == FOOTPRINT_3DGS {
        // λ = mid + √max(floor, ((a − c)/2)² + b²) in pixels², from the rescaled entries
        // (the sum of squares is 3DGS's mid² − det without its cancellation); r = ⌈3√λ⌉.
        let half_gap = 0.5 * (l0 - l1);
        let discriminant = half_gap * half_gap + sxy * sxy;
        let floor_n = DISCRIMINANT_FLOOR_3DGS / (s * s) / (s * s);
        let lambda_n = 0.5 * (sxx + syy) + sqrt(max(floor_n, discriminant));
        let radius = ceil(SIGMA_EXTENT * s * sqrt(lambda_n));
        let tiles_y = (cam.image.y + TILE - 1u) / TILE;
        let x = tiles_3dgs(u, radius, cam.keys.z);
        let y = tiles_3dgs(v, radius, tiles_y);
        if x.x >= x.y || y.x >= y.y {
            skip(i);
            return;
        }
        rect = vec4<u32>(x.x, y.x, x.y, y.y);
    } else {
        // Pixels are reached only where d² ≤ 9 and opacity · exp(-d²/2) ≥ 1/255; along x the
        // ellipse d² ≤ r² spans u ± r·√Σxx (and likewise along y).
        let extent = sqrt(clamp(2.0 * log(opacity / ALPHA_MIN), 0.0, SIGMA_EXTENT * SIGMA_EXTENT));
        let span_x = pixel_span(u, extent * s * sqrt(sxx), cam.image.x);
        let span_y = pixel_span(v, extent * s * sqrt(syy), cam.image.y);
        if span_x.x > span_x.y || span_y.x > span_y.y {
            skip(i);
            return;
        }
        rect = vec4<u32>(
            u32(span_x.x) / TILE,
            u32(span_y.x) / TILE,
            u32(span_x.y) / TILE + 1u,
            u32(span_y.y) / TILE + 1u,
        );
    }

    splats[3u * i] = vec4<f32>(u, v, opacity, z);
    splats[3u * i + 1u] = vec4<f32>(conic, 0.0);
    splats[3u * i + 2u] = vec4<f32>(color, z);
    rects[i] = rect;
    // z ≥ near > 0, so its bits order like its value.
    keys[i] = bitcast<u32>(z) - cam.keys.x;
    values[i] = i;
}
