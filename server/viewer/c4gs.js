// `C4GS`, the service's packed binary Gaussian sets (docs/api.md; the codec is
// formats/src/c4gs.rs), decoded in the browser. Little endian: `b"C4GS"`, u16 version
// (1), u8 precision (0 f32, 1 f16), u8 reserved, u32 frames, u32 N; then per frame an f64 time and
// the columns means (N×3), scales (N×3), rotations (N×4, w x y z), opacities (N), colours (N×3).
// Every length is checked against the header before anything is read.

const HEADER_BYTES = 16;
const COLUMNS = [
  ['means', 3],
  ['scales', 3],
  ['rotations', 4],
  ['opacities', 1],
  ['colors', 3],
];
const VALUES_PER_GAUSSIAN = 14;

/** Every half-precision bit pattern as a float, built once (256 KiB). */
let halfTable = null;

function halves() {
  if (halfTable) return halfTable;
  halfTable = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const sign = h & 0x8000 ? -1 : 1;
    const exponent = (h >> 10) & 0x1f;
    const mantissa = h & 0x3ff;
    let value;
    if (exponent === 0) value = mantissa * 2 ** -24;
    else if (exponent === 31) value = mantissa ? NaN : Infinity;
    else value = (1 + mantissa / 1024) * 2 ** (exponent - 15);
    halfTable[h] = sign * value;
  }
  return halfTable;
}

/**
 * The frames of a `C4GS` payload: `[{t, count, means, scales, rotations, opacities, colors}]`,
 * each column a Float32Array. Throws an Error that says what is wrong with a bad payload.
 */
export function decode(buffer) {
  const view = new DataView(buffer);
  if (buffer.byteLength < HEADER_BYTES) throw new Error(`C4GS: ${buffer.byteLength} bytes is shorter than the header`);
  const magic = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  if (magic !== 'C4GS') throw new Error(`C4GS: bad magic ${JSON.stringify(magic)}`);
  const version = view.getUint16(4, true);
  if (version !== 1) throw new Error(`C4GS: version ${version} is not 1`);
  const precision = view.getUint8(6);
  if (precision > 1) throw new Error(`C4GS: unknown precision code ${precision}`);
  const frames = view.getUint32(8, true);
  const count = view.getUint32(12, true);
  const valueBytes = precision === 0 ? 4 : 2;
  const frameBytes = 8 + count * VALUES_PER_GAUSSIAN * valueBytes;
  const expected = HEADER_BYTES + frames * frameBytes;
  if (buffer.byteLength !== expected) {
    throw new Error(`C4GS: ${frames} frames of ${count} Gaussians need ${expected} bytes, got ${buffer.byteLength}`);
  }
  const table = precision === 1 ? halves() : null;
  const out = [];
  let at = HEADER_BYTES;
  for (let f = 0; f < frames; f++) {
    const frame = { t: view.getFloat64(at, true), count };
    at += 8;
    for (const [name, width] of COLUMNS) {
      const values = new Float32Array(count * width);
      if (table) {
        for (let i = 0; i < values.length; i++, at += 2) values[i] = table[view.getUint16(at, true)];
      } else {
        for (let i = 0; i < values.length; i++, at += 4) values[i] = view.getFloat32(at, true);
      }
      frame[name] = values;
    }
    out.push(frame);
  }
  return out;
}
