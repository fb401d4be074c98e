// The viewer's Gaussian splat renderer: WebGL2, the forward model of renderer/src/raster/mod.rs.
//
// Why our own and not a splatting library from npm: the viewer's "compare with server" puts this
// image beside the server's CPU (or wgpu) render of the same camera and time, and that comparison
// means something only if both draw the same forward model (the 0.3 dilation, the 3-sigma ellipse
// or 3DGS tile footprint, the 0.99 alpha clamp and the 1/255 skip, depth order with ties by index,
// OpenCV camera axes); web splat viewers each pick their own constants, culls and sort keys. A
// clip's scene is ~512-2K Gaussians, so one CPU depth sort a frame and plain instanced quads are
// enough: no tiling, no GPU radix sort, no workers. And it stays a plain ES module, no build step.
//
// How it follows the model:
// - projection runs on the CPU in f64, a port of renderer/src/raster/cpu/project.rs: the EWA
//   covariance J W R S Sᵀ Rᵀ Wᵀ Jᵀ + 0.3·I through M = J W R S (its determinant without
//   cancellation), the FOV clamp of x/z and y/z at 1.3 × the half-FOV tangent, the near and far
//   planes, and the pixel box (for the ellipse: the box around d ≤ 3 with a pixel of slack; for
//   3DGS: its tiles), rounded to f32 where the CPU rasterizer rounds;
// - one instanced quad a Gaussian covers exactly its pixel box; the fragment shader evaluates at
//   the pixel centre the same f32 expression, d² = a·(dx − k·dy)² + dy²/Σyy, cuts at d² > 9
//   (ellipse only), and gives alpha = min(0.99, opacity · exp(−d²/2)), skipping alpha < 1/255;
// - splats are sorted front to back by (f32 depth, index) and composited with premultiplied
//   "under" blending (dst += (1 − dst.a) · (α·c, α)) into a float target, so colour is Σ cᵢ αᵢ Tᵢ
//   and alpha 1 − T as in blend.rs, up to f32 rounding; a composite pass writes colour over the
//   black background, expected depth (Σ zᵢ αᵢ Tᵢ / alpha) through a colour ramp, or alpha.
// The one rule fixed-function blending cannot follow is the stop where transmittance would fall
// below 1e-4: here what lies behind keeps adding, at most 1e-4 of a pixel's value.

export const NEAR = 0.01;
export const FAR = 100.0;
export const EPS2D = 0.3;
export const FOV_CLAMP = 1.3;
export const SIGMA_EXTENT = 3.0;
export const DISCRIMINANT_FLOOR_3DGS = 0.1;
export const TILE_3DGS = 16;
export const ALPHA_MAX = 0.99;
export const ALPHA_MIN = 1.0 / 255.0;

/** Floats per splat instance: box (4), centre (2), conic (3), colour and opacity (4), depth (1). */
const STRIDE = 14;

/**
 * The splats of `set` as `view` sees them (renderer/src/raster/cpu/project.rs, in f64), front to
 * back: `{count, data}` with STRIDE floats each, and `depths`, their camera-space depths.
 */
export function project(set, view, footprint) {
  const n = set.count;
  const { rotation: w, translation: tr, fx, fy, cx, cy, width, height } = view;
  const limX = (FOV_CLAMP * width) / (2 * fx);
  const limY = (FOV_CLAMP * height) / (2 * fy);
  const raw = new Float32Array(n * STRIDE);
  const keys = [];
  const { means: P, scales: S, rotations: Q, opacities: O, colors: C } = set;
  let count = 0;
  for (let i = 0; i < n; i++) {
    const o = O[i];
    const px = P[3 * i], py = P[3 * i + 1], pz = P[3 * i + 2];
    const sx = S[3 * i], sy = S[3 * i + 1], sz = S[3 * i + 2];
    let qw = Q[4 * i], qx = Q[4 * i + 1], qy = Q[4 * i + 2], qz = Q[4 * i + 3];
    const r = C[3 * i], g = C[3 * i + 1], b = C[3 * i + 2];
    if (![o, px, py, pz, sx, sy, sz, qw, qx, qy, qz, r, g, b].every(Number.isFinite)) continue;
    // Alpha never exceeds the opacity: a Gaussian this faint reaches no pixel.
    if (o < ALPHA_MIN) continue;
    const norm = Math.hypot(qw, qx, qy, qz);
    if (norm === 0) continue;
    qw /= norm; qx /= norm; qy /= norm; qz /= norm;
    const x = w[0] * px + w[1] * py + w[2] * pz + tr[0];
    const y = w[3] * px + w[4] * py + w[5] * pz + tr[1];
    const z = w[6] * px + w[7] * py + w[8] * pz + tr[2];
    if (!(z >= NEAR && z <= FAR)) continue;

    const tx = Math.min(limX, Math.max(-limX, x / z)) * z;
    const ty = Math.min(limY, Math.max(-limY, y / z)) * z;
    const j00 = fx / z, j02 = (-fx * tx) / (z * z);
    const j11 = fy / z, j12 = (-fy * ty) / (z * z);
    // R S, the quaternion's rotation with its columns scaled.
    const rs = [
      (1 - 2 * (qy * qy + qz * qz)) * sx, 2 * (qx * qy - qw * qz) * sy, 2 * (qx * qz + qw * qy) * sz,
      2 * (qx * qy + qw * qz) * sx, (1 - 2 * (qx * qx + qz * qz)) * sy, 2 * (qy * qz - qw * qx) * sz,
      2 * (qx * qz - qw * qy) * sx, 2 * (qy * qz + qw * qx) * sy, (1 - 2 * (qx * qx + qy * qy)) * sz,
    ];
    // M = J W R S, rows m0 and m1: J's rows are (j00, 0, j02) and (0, j11, j12).
    const m0 = [0, 0, 0], m1 = [0, 0, 0];
    for (let c = 0; c < 3; c++) {
      const wrs0 = w[0] * rs[c] + w[1] * rs[3 + c] + w[2] * rs[6 + c];
      const wrs1 = w[3] * rs[c] + w[4] * rs[3 + c] + w[5] * rs[6 + c];
      const wrs2 = w[6] * rs[c] + w[7] * rs[3 + c] + w[8] * rs[6 + c];
      m0[c] = j00 * wrs0 + j02 * wrs2;
      m1[c] = j11 * wrs1 + j12 * wrs2;
    }
    const mxx = m0[0] * m0[0] + m0[1] * m0[1] + m0[2] * m0[2];
    const myy = m1[0] * m1[0] + m1[1] * m1[1] + m1[2] * m1[2];
    const sxx = mxx + EPS2D;
    const sxy = m0[0] * m1[0] + m0[1] * m1[1] + m0[2] * m1[2];
    const syy = myy + EPS2D;
    const c0 = m0[1] * m1[2] - m0[2] * m1[1];
    const c1 = m0[2] * m1[0] - m0[0] * m1[2];
    const c2 = m0[0] * m1[1] - m0[1] * m1[0];
    const det = c0 * c0 + c1 * c1 + c2 * c2 + EPS2D * (mxx + myy) + EPS2D * EPS2D;
    if (!(Number.isFinite(det) && det > 0)) continue;
    const a = Math.fround(syy / det), k = Math.fround(sxy / syy), invSyy = Math.fround(1 / syy);
    if (!(Number.isFinite(a) && Number.isFinite(k) && Number.isFinite(invSyy))) continue;

    const u = (fx * x) / z + cx;
    const v = (fy * y) / z + cy;
    // Alpha is at least 1/255 only where opacity · exp(−d²/2) is.
    const alphaReach2 = 2 * Math.log(o / ALPHA_MIN);
    let spanX, spanY;
    if (footprint === '3dgs') {
      const tiles = tiles3dgs(u, v, mxx, sxy, myy, width, height);
      if (!tiles) continue;
      [spanX, spanY] = tiles;
    } else {
      const extent = Math.sqrt(Math.min(SIGMA_EXTENT * SIGMA_EXTENT, alphaReach2));
      spanX = pixelSpan(u, extent * Math.sqrt(sxx), width);
      spanY = pixelSpan(v, extent * Math.sqrt(syy), height);
      if (!spanX || !spanY) continue;
    }
    const at = count * STRIDE;
    raw.set([spanX[0], spanY[0], spanX[1] + 1, spanY[1] + 1, u - spanX[0], v - spanY[0], a, k, invSyy, r, g, b, o, z], at);
    keys.push({ depth: Math.fround(z), index: i, at });
    count++;
  }
  // Front to back by (f32 depth, index), as the CPU rasterizer's sort key.
  keys.sort((p, q) => p.depth - q.depth || p.index - q.index);
  const data = new Float32Array(count * STRIDE);
  const depths = new Float32Array(count);
  keys.forEach((key, j) => {
    data.set(raw.subarray(key.at, key.at + STRIDE), j * STRIDE);
    depths[j] = key.depth;
  });
  return { count, data, depths };
}

/** Pixels (inclusive, inside 0..size) whose centre may lie within `radius` of `centre` (project.rs). */
function pixelSpan(centre, radius, size) {
  const lo = Math.floor(centre - radius - 0.5) - 1;
  const hi = Math.ceil(centre + radius - 0.5) + 1;
  if (!(Number.isFinite(lo) && Number.isFinite(hi)) || hi < 0 || lo > size - 1) return null;
  return [Math.max(lo, 0), Math.min(hi, size - 1)];
}

/** The pixels of a splat's 3DGS tiles, inclusive on each axis, or null (project.rs `tiles_3dgs`). */
function tiles3dgs(u, v, mxx, mxy, myy, width, height) {
  const mid = 0.5 * (mxx + myy) + EPS2D;
  const halfGap = 0.5 * (mxx - myy);
  const discriminant = halfGap * halfGap + mxy * mxy;
  const lambda = mid + Math.sqrt(Math.max(DISCRIMINANT_FLOOR_3DGS, discriminant));
  const radius = Math.ceil(SIGMA_EXTENT * Math.sqrt(lambda));
  const span = (c, size) => {
    const p = c - 0.5;
    const tiles = Math.ceil(size / TILE_3DGS);
    const first = Math.min(tiles, Math.max(0, Math.floor((p - radius) / TILE_3DGS)));
    const end = Math.min(tiles, Math.max(0, Math.floor((p + radius + TILE_3DGS - 1) / TILE_3DGS)));
    return first < end ? [first * TILE_3DGS, Math.min(end * TILE_3DGS, size) - 1] : null;
  };
  const x = span(u, width);
  const y = span(v, height);
  return x && y ? [x, y] : null;
}

/**
 * The depth display's colours: a ramp from near (0, warm) to far (1, blue), the same in GLSL
 * (DEPTH_RAMP_GLSL) and here, where compare.js maps the server's raw depth through it.
 */
const RAMP = [
  [0.99, 0.91, 0.15],
  [0.96, 0.52, 0.22],
  [0.8, 0.28, 0.47],
  [0.42, 0.17, 0.6],
  [0.13, 0.14, 0.42],
];

export function depthRamp(n) {
  const x = Math.min(1, Math.max(0, n)) * (RAMP.length - 1);
  const i = Math.min(RAMP.length - 2, Math.floor(x));
  const f = x - i;
  return RAMP[i].map((c, j) => c + (RAMP[i + 1][j] - c) * f);
}

const DEPTH_RAMP_GLSL = `
const vec3 RAMP[5] = vec3[5](${RAMP.map((c) => `vec3(${c.map((v) => v.toFixed(4)).join(', ')})`).join(', ')});
vec3 depthRamp(float n) {
  float x = clamp(n, 0.0, 1.0) * 4.0;
  int i = min(3, int(floor(x)));
  return mix(RAMP[i], RAMP[i + 1], x - float(i));
}`;

const SPLAT_VS = `#version 300 es
layout(location = 0) in vec2 corner;
layout(location = 1) in vec4 box;
layout(location = 2) in vec2 centre;
layout(location = 3) in vec3 conic;
layout(location = 4) in vec4 colorOpacity;
layout(location = 5) in float depth;
uniform vec2 size;
uniform vec2 depthRange;
uniform int mode;
flat out vec2 vOrigin;
flat out vec2 vCentre;
flat out vec3 vConic;
flat out vec3 vValue;
flat out float vOpacity;
void main() {
  // Pixel coordinates, y down, to clip space: the quad's edges are whole pixels.
  vec2 p = mix(box.xy, box.zw, corner);
  gl_Position = vec4(2.0 * p.x / size.x - 1.0, 1.0 - 2.0 * p.y / size.y, 0.0, 1.0);
  vOrigin = box.xy;
  vCentre = centre;
  vConic = conic;
  vOpacity = colorOpacity.a;
  float n = (depth - depthRange.x) / max(depthRange.y - depthRange.x, 1e-6);
  // Colour, depth (normalised: blending a linear map of z is the map of the blended z) or 1.
  vValue = mode == 0 ? colorOpacity.rgb : (mode == 1 ? vec3(n) : vec3(1.0));
}`;

const SPLAT_FS = `#version 300 es
precision highp float;
uniform vec2 size;
uniform float cut;
flat in vec2 vOrigin;
flat in vec2 vCentre;
flat in vec3 vConic;
flat in vec3 vValue;
flat in float vOpacity;
out vec4 outColor;
void main() {
  // The pixel centre's offsets from the box corner, y down: exact in f32, as in blend.rs.
  float dy = ((size.y - gl_FragCoord.y) - vOrigin.y) - vCentre.y;
  float rowD2 = dy * dy * vConic.z;
  float e = (gl_FragCoord.x - vOrigin.x) - vCentre.x - vConic.y * dy;
  float d2 = vConic.x * e * e + rowD2;
  if (d2 > cut) discard;
  float alpha = min(${ALPHA_MAX.toFixed(2)}, vOpacity * exp(-0.5 * d2));
  if (alpha < 1.0 / 255.0) discard;
  outColor = vec4(vValue * alpha, alpha);
}`;

const COMPOSITE_VS = `#version 300 es
void main() {
  vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}`;

const COMPOSITE_FS = `#version 300 es
precision highp float;
uniform highp sampler2D accum;
uniform int mode;
out vec4 outColor;
${DEPTH_RAMP_GLSL}
void main() {
  vec4 s = texelFetch(accum, ivec2(gl_FragCoord.xy), 0);
  vec3 rgb;
  if (mode == 0) rgb = s.rgb;                          // over the black background
  else if (mode == 1) rgb = s.a > 0.0 ? depthRamp(s.r / s.a) : vec3(0.0);
  else rgb = vec3(s.a);
  outColor = vec4(clamp(rgb, 0.0, 1.0), 1.0);
}`;

const MODES = { color: 0, depth: 1, alpha: 2 };

export class SplatRenderer {
  constructor(canvas) {
    const gl = canvas.getContext('webgl2', {
      alpha: false,
      antialias: false,
      depth: false,
      stencil: false,
      premultipliedAlpha: false,
      // Kept after presenting, so that a comparison or a screenshot reads what is shown.
      preserveDrawingBuffer: true,
    });
    if (!gl) throw new Error('this browser has no WebGL2');
    this.gl = gl;
    this.canvas = canvas;
    this.target = chooseTarget(gl);
    this.splatProgram = program(gl, SPLAT_VS, SPLAT_FS);
    this.compositeProgram = program(gl, COMPOSITE_VS, COMPOSITE_FS);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const corners = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    this.instances = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    const layout = [[1, 4, 0], [2, 2, 4], [3, 3, 6], [4, 4, 9], [5, 1, 13]];
    for (const [location, size, offset] of layout) {
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, size, gl.FLOAT, false, STRIDE * 4, offset * 4);
      gl.vertexAttribDivisor(location, 1);
    }
    gl.bindVertexArray(null);
    this.size = [0, 0];
  }

  /** What the float target is (for the page's status line). */
  get targetFormat() {
    return this.target.name;
  }

  resize(width, height) {
    if (this.size[0] === width && this.size[1] === height) return;
    const gl = this.gl;
    this.canvas.width = width;
    this.canvas.height = height;
    if (this.texture) gl.deleteTexture(this.texture);
    if (this.framebuffer) gl.deleteFramebuffer(this.framebuffer);
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.target.format, width, height);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    this.framebuffer = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.framebuffer);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.texture, 0);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`the ${this.target.name} target is incomplete (${status})`);
    this.size = [width, height];
  }

  /**
   * Draws `set` from `view` (camera.js `view()`) in `mode` ('color', 'depth', 'alpha').
   * `depthRange` [near, far] maps depth to the ramp; without it, the splats' own (5%-95%).
   * Gives what was drawn: `{splats, depthRange}`.
   */
  render(set, view, { mode = 'color', footprint = 'ellipse', depthRange = null } = {}) {
    const gl = this.gl;
    this.resize(view.width, view.height);
    const splats = project(set, view, footprint);
    const range = depthRange || quantileRange(splats.depths);

    gl.bindFramebuffer(gl.FRAMEBUFFER, this.framebuffer);
    gl.viewport(0, 0, view.width, view.height);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.useProgram(this.splatProgram);
    gl.uniform2f(gl.getUniformLocation(this.splatProgram, 'size'), view.width, view.height);
    gl.uniform2f(gl.getUniformLocation(this.splatProgram, 'depthRange'), range[0], range[1]);
    gl.uniform1i(gl.getUniformLocation(this.splatProgram, 'mode'), MODES[mode]);
    // The ellipse cuts at 3 sigma; the 3DGS tiles evaluate every pixel of their boxes.
    const cut = footprint === '3dgs' ? 3.0e38 : SIGMA_EXTENT * SIGMA_EXTENT;
    gl.uniform1f(gl.getUniformLocation(this.splatProgram, 'cut'), cut);
    gl.enable(gl.BLEND);
    // Front to back "under": dst += (1 − dst.a) · src, with src = (α·value, α).
    gl.blendEquation(gl.FUNC_ADD);
    gl.blendFunc(gl.ONE_MINUS_DST_ALPHA, gl.ONE);
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    gl.bufferData(gl.ARRAY_BUFFER, splats.data, gl.DYNAMIC_DRAW);
    if (splats.count > 0) gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, splats.count);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);

    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.useProgram(this.compositeProgram);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.uniform1i(gl.getUniformLocation(this.compositeProgram, 'accum'), 0);
    gl.uniform1i(gl.getUniformLocation(this.compositeProgram, 'mode'), MODES[mode]);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    return { splats: splats.count, depthRange: range };
  }
}

/** The depths between the 5% and 95% quantiles (the ramp's ends), or [0, 1] with none. */
function quantileRange(depths) {
  if (depths.length === 0) return [0, 1];
  const sorted = Float32Array.from(depths).sort();
  const at = (q) => sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  const [lo, hi] = [at(0.05), at(0.95)];
  return hi > lo ? [lo, hi] : [lo, lo + 1];
}

/** The most precise blendable target: RGBA32F, RGBA16F, else 8 bits (blending then rounds). */
function chooseTarget(gl) {
  const float = gl.getExtension('EXT_color_buffer_float');
  if (float && gl.getExtension('EXT_float_blend')) return { name: 'RGBA32F', format: gl.RGBA32F };
  if (float || gl.getExtension('EXT_color_buffer_half_float')) return { name: 'RGBA16F', format: gl.RGBA16F };
  return { name: 'RGBA8', format: gl.RGBA8 };
}

function program(gl, vertex, fragment) {
  const compile = (type, source) => {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(shader)}`);
    return shader;
  };
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl.VERTEX_SHADER, vertex));
  gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fragment));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(p)}`);
  return p;
}
