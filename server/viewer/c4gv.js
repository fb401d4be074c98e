// `C4GV`, the compact 4D stream of `POST /v1/clips/{id}/stream`, decoded in the browser as its
// bytes arrive. The specification is the module doc of formats/src/c4gv/mod.rs; this follows
// its "Reading" section. Little endian. A header (`b"C4GV"`, u16 version 1, u8 predictor 0, u8
// reserved, u32 N, u32 S static Gaussians, five f64 grid steps, then the ⌈N/8⌉-byte static mask),
// then records, each a 6-byte head (u8 kind: 1 static, 2 keyframe, 3 delta frame, 4 index; u8
// body coding: 0 stored, 1 raw DEFLATE; u32 payload length) and its payload: the static record
// once, the frames (f64 time, u32 inflated length, body), and the index, which ends the stream. A
// body is 14 columns (position xyz, scale xyz, rotation wxyz, opacity, colour RGB) of zigzag
// LEB128 varints, one per Gaussian of the record: grid cells in the static record and keyframes,
// each cell's change from the frame before in a delta frame.
//
// Frames come out in c4gs.js's layout, `{t, count, means, scales, rotations, opacities, colors}`
// with Float32Array columns, which is what splats.js draws. Every length is checked against what
// it can be before anything is buffered for it, and a bad stream is an Error saying what is wrong.

const MAGIC = 'C4GV';
const INDEX_MAGIC = 'C4GI';
const VERSION = 1;
const HEADER_BYTES = 56;
const RECORD_HEAD = 6;
/** A frame record's payload before its body: time and inflated length. */
const FRAME_HEAD = 12;
/** The static record's payload before its body: inflated length. */
const STATIC_HEAD = 4;
const INDEX_ENTRY = 17;
const INDEX_TAIL = 12;
const CHANNELS = 14;
const VARINT_MAX = 5;
/** Cells lie strictly inside ± this. */
const CELL_LIMIT = 2 ** 30;

const KIND_STATIC = 1;
const KIND_KEYFRAME = 2;
const KIND_DELTA = 3;
const KIND_INDEX = 4;
const STORED = 0;
const DEFLATE = 1;

function fail(reason) {
  return new Error(`C4GV: ${reason}`);
}

/** Inflates a raw DEFLATE body that must give exactly `raw` bytes. */
async function inflate(stored, raw, what) {
  if (stored.length >= raw) {
    throw fail(`${what}: a deflated body of ${stored.length} bytes is not shorter than its ${raw} bytes inflated`);
  }
  const stream = new DecompressionStream('deflate-raw');
  const writer = stream.writable.getWriter();
  // Not awaited: the output is read below, and a corrupt input rejects there too.
  writer.write(stored).catch(() => {});
  writer.close().catch(() => {});
  const reader = stream.readable.getReader();
  const out = new Uint8Array(raw);
  let length = 0;
  for (;;) {
    let chunk;
    try {
      chunk = await reader.read();
    } catch (error) {
      throw fail(`${what}: corrupt DEFLATE data (${error.message || error})`);
    }
    if (chunk.done) break;
    if (length + chunk.value.length > raw) {
      reader.cancel().catch(() => {});
      throw fail(`${what}: the body inflates to more than ${raw} bytes, which its record says`);
    }
    out.set(chunk.value, length);
    length += chunk.value.length;
  }
  if (length !== raw) throw fail(`${what}: the body inflates to ${length} bytes; its record says ${raw}`);
  return out;
}

/**
 * The cells of `count` Gaussians from a record's payload after its time: u32 inflated length,
 * then the stored or deflated columns. Column-major: channel k of row g is at `k * count + g`.
 * Values are exact integers in doubles (a residual of 5 varint bytes exceeds 2^31).
 */
async function readBody(coding, payload, count, what) {
  const view = new DataView(payload.buffer, payload.byteOffset, payload.byteLength);
  const raw = view.getUint32(0, true);
  const stored = payload.subarray(4);
  const [min, max] = [count * CHANNELS, count * CHANNELS * VARINT_MAX];
  if (raw < min || raw > max) {
    throw fail(`${what}: a body of ${count} Gaussians inflates to ${min} to ${max} bytes; it claims ${raw}`);
  }
  let body;
  if (coding === STORED) {
    if (stored.length !== raw) throw fail(`${what}: a stored body of ${raw} bytes holds ${stored.length}`);
    body = stored;
  } else {
    body = await inflate(stored, raw, what);
  }
  const values = new Float64Array(count * CHANNELS);
  let at = 0;
  for (let v = 0; v < values.length; v++) {
    // Unsigned LEB128, low 7 bits first, at most 5 bytes: up to 2^35 - 1, by arithmetic.
    let u = 0;
    let scale = 1;
    let used = 0;
    for (;;) {
      if (used === VARINT_MAX || at >= body.length) throw fail(`${what}: a varint is cut short or too long`);
      const b = body[at++];
      used++;
      u += (b & 0x7f) * scale;
      scale *= 128;
      if (b < 0x80) break;
    }
    // Zigzag: even u is u/2, odd u is -(u+1)/2.
    values[v] = u % 2 === 0 ? u / 2 : -(u + 1) / 2;
  }
  if (at !== body.length) throw fail(`${what}: ${body.length - at} bytes after the last value`);
  return values;
}

function checkCells(cells, count, ids, what) {
  for (let v = 0; v < cells.length; v++) {
    if (Math.abs(cells[v]) >= CELL_LIMIT) {
      throw fail(`${what}: Gaussian ${ids[v % count]}'s cell ${cells[v]} is outside ±2^30`);
    }
  }
}

/**
 * Writes the values of `count` Gaussians' cells (column-major) into `frame`'s columns at the
 * Gaussians `ids`: in f64, then rounded to f32 (positions cell·Δ, scales exp(cell·Δ), rotation
 * components cell·Δ divided by the four's norm, opacity and colour cell·Δ).
 */
function reconstruct(cells, count, ids, steps, frame, what) {
  const { means, scales, rotations, opacities, colors } = frame;
  const [dp, dl, dr, dop, dc] = steps;
  const f = Math.fround;
  const finite = Number.isFinite;
  for (let g = 0; g < count; g++) {
    const i = ids[g];
    let ok = true;
    for (let k = 0; k < 3; k++) {
      const p = (means[3 * i + k] = f(cells[k * count + g] * dp));
      const s = (scales[3 * i + k] = f(Math.exp(cells[(3 + k) * count + g] * dl)));
      const c = (colors[3 * i + k] = f(cells[(11 + k) * count + g] * dc));
      // What GaussianSet::validate holds the Rust decoder's sets to (rotations are unit below).
      ok = ok && finite(p) && finite(s) && finite(c) && c >= 0;
    }
    const w = cells[6 * count + g] * dr;
    const x = cells[7 * count + g] * dr;
    const y = cells[8 * count + g] * dr;
    const z = cells[9 * count + g] * dr;
    const norm = Math.sqrt(w * w + x * x + y * y + z * z);
    if (norm === 0 || !finite(norm)) throw fail(`${what}: Gaussian ${i}'s rotation has zero norm`);
    rotations[4 * i] = f(w / norm);
    rotations[4 * i + 1] = f(x / norm);
    rotations[4 * i + 2] = f(y / norm);
    rotations[4 * i + 3] = f(z / norm);
    const o = (opacities[i] = f(cells[10 * count + g] * dop));
    if (!ok || !(o >= 0 && o <= 1)) throw fail(`${what}: Gaussian ${i} decodes to values outside the canonical layout`);
  }
}

function emptyFrame(count) {
  return {
    t: 0,
    count,
    means: new Float32Array(3 * count),
    scales: new Float32Array(3 * count),
    rotations: new Float32Array(4 * count),
    opacities: new Float32Array(count),
    colors: new Float32Array(3 * count),
  };
}

/**
 * An incremental reader: `feed(bytes)` as they arrive, then `await next()` until it answers null
 * (more bytes are needed, or the stream has ended: `done`). `finish()` throws unless the stream
 * ended with its index record and nothing after it. Not reentrant: await each `next()`.
 */
export class C4GVDecoder {
  constructor() {
    this.buffer = new Uint8Array(1 << 16);
    this.start = 0;
    this.end = 0;
    /** Bytes of the stream consumed, from its first. */
    this.position = 0;
    this.stage = 'header';
    this.count = 0;
    this.statics = null;
    this.movers = null;
    this.steps = null;
    /** A frame with the static Gaussians filled in, copied for every frame. */
    this.template = null;
    this.previous = null;
    this.frames = 0;
    this.lastTime = null;
    /** Time and record offset of every frame read, as the index must list them. */
    this.seen = [];
  }

  /** Whether the index record has been read. */
  get done() {
    return this.stage === 'done';
  }

  /** Takes the next bytes of the stream (a Uint8Array, copied). */
  feed(bytes) {
    const pending = this.end - this.start;
    if (this.end + bytes.length > this.buffer.length) {
      if (pending + bytes.length <= this.buffer.length / 2) {
        this.buffer.copyWithin(0, this.start, this.end);
      } else {
        let size = this.buffer.length;
        while (size < 2 * (pending + bytes.length)) size *= 2;
        const grown = new Uint8Array(size);
        grown.set(this.buffer.subarray(this.start, this.end));
        this.buffer = grown;
      }
      this.start = 0;
      this.end = pending;
    }
    this.buffer.set(bytes, this.end);
    this.end += bytes.length;
  }

  pending() {
    return this.buffer.subarray(this.start, this.end);
  }

  consume(bytes) {
    this.start += bytes;
    this.position += bytes;
  }

  /** The next frame once its record is whole; null while more bytes are needed and after the index. */
  async next() {
    for (;;) {
      const pending = this.pending();
      if (this.stage === 'header') {
        if (!this.readHeader(pending)) return null;
        continue;
      }
      if (this.stage === 'done') {
        if (pending.length > 0) throw fail(`${pending.length} bytes after the index record, which ends a stream`);
        return null;
      }
      const head = this.recordHead(pending);
      if (!head) return null;
      const { kind, coding, length } = head;
      if (pending.length < RECORD_HEAD + length) return null;
      const payload = pending.slice(RECORD_HEAD, RECORD_HEAD + length);
      const offset = this.position;
      this.consume(RECORD_HEAD + length);
      if (kind === KIND_STATIC) await this.readStatic(coding, payload);
      else if (kind === KIND_INDEX) this.readIndex(payload);
      else return this.readFrame(offset, kind, coding, payload);
    }
  }

  /** Throws unless the stream ended with its index and nothing after it. */
  finish() {
    const pending = this.end - this.start;
    if (this.stage === 'done') {
      if (pending > 0) throw fail(`${pending} bytes after the index record, which ends a stream`);
      return;
    }
    if (this.stage === 'header') throw fail(`truncated: the stream ended inside its header (${pending} bytes)`);
    throw fail(
      `truncated: the stream ended after ${this.frames} frames` +
        (pending > 0 ? ` and ${pending} bytes of an incomplete record` : '') +
        ', before its index record',
    );
  }

  readHeader(bytes) {
    const prefix = String.fromCharCode(...bytes.subarray(0, 4));
    if (prefix !== MAGIC.slice(0, prefix.length)) throw fail(`not a C4GV stream (starts with ${JSON.stringify(prefix)})`);
    if (bytes.length < HEADER_BYTES) return false;
    const view = new DataView(bytes.buffer, bytes.byteOffset, HEADER_BYTES);
    const version = view.getUint16(4, true);
    if (version !== VERSION) throw fail(`version ${version}; this reader reads version ${VERSION} only`);
    if (bytes[6] !== 0) throw fail(`unknown predictor ${bytes[6]} (version 1 has 0 only)`);
    // bytes[7] is reserved.
    const count = view.getUint32(8, true);
    const statics = view.getUint32(12, true);
    const steps = [0, 1, 2, 3, 4].map((k) => view.getFloat64(16 + 8 * k, true));
    const bad = steps.find((s) => !(Number.isFinite(s) && s > 0));
    if (bad !== undefined) throw fail(`grid steps must be finite and positive; the header has ${bad}`);
    if (statics > count) throw fail(`the header claims ${statics} static Gaussians of ${count}`);
    const length = HEADER_BYTES + Math.ceil(count / 8);
    if (bytes.length < length) return false;
    const mask = bytes.subarray(HEADER_BYTES, length);
    const staticIds = [];
    const moverIds = [];
    for (let i = 0; i < count; i++) (mask[i >> 3] & (1 << (i & 7)) ? staticIds : moverIds).push(i);
    if (staticIds.length !== statics) {
      throw fail(`the header claims ${statics} static Gaussians; its mask marks ${staticIds.length}`);
    }
    if (count % 8 !== 0 && mask[mask.length - 1] >> (count % 8) !== 0) {
      throw fail('the static mask sets bits past the last Gaussian');
    }
    this.count = count;
    this.statics = Uint32Array.from(staticIds);
    this.movers = Uint32Array.from(moverIds);
    this.steps = steps;
    this.template = emptyFrame(count);
    this.consume(length);
    this.stage = 'static';
    return true;
  }

  /** The record head at the read position, its length checked against its kind; null if short. */
  recordHead(bytes) {
    if (bytes.length < RECORD_HEAD) return null;
    const kind = bytes[0];
    const coding = bytes[1];
    const length = new DataView(bytes.buffer, bytes.byteOffset, RECORD_HEAD).getUint32(2, true);
    const at = this.position;
    let min;
    let max;
    const bodyRange = (head, count) => [head + (count > 0 ? 1 : 0), head + count * CHANNELS * VARINT_MAX];
    if (this.stage === 'static' && kind === KIND_STATIC) [min, max] = bodyRange(STATIC_HEAD, this.statics.length);
    else if (this.stage === 'frames' && (kind === KIND_KEYFRAME || kind === KIND_DELTA)) {
      [min, max] = bodyRange(FRAME_HEAD, this.movers.length);
    } else if (kind === KIND_INDEX) {
      min = max = this.frames * INDEX_ENTRY + INDEX_TAIL;
    } else if (this.stage === 'static' && (kind === KIND_KEYFRAME || kind === KIND_DELTA)) {
      throw fail(`the record at byte ${at} is a frame, but the static record comes first`);
    } else if (kind === KIND_STATIC) {
      throw fail(`a second static record at byte ${at}`);
    } else {
      throw fail(`unknown record kind ${kind} at byte ${at}`);
    }
    if (coding > DEFLATE || (kind === KIND_INDEX && coding !== STORED)) {
      throw fail(`record at byte ${at}: unknown body coding ${coding}`);
    }
    if (length < min || length > max) {
      const need = min === max ? `it must hold ${min}` : `it must hold ${min} to ${max}`;
      throw fail(`record at byte ${at} (kind ${kind}) claims ${length} bytes: ${need}`);
    }
    return { kind, coding, length };
  }

  async readStatic(coding, payload) {
    const what = 'the static record';
    const n = this.statics.length;
    const cells = await readBody(coding, payload, n, what);
    checkCells(cells, n, this.statics, what);
    reconstruct(cells, n, this.statics, this.steps, this.template, what);
    this.stage = 'frames';
  }

  async readFrame(offset, kind, coding, payload) {
    const what = `frame ${this.frames} (byte ${offset})`;
    const view = new DataView(payload.buffer, payload.byteOffset, payload.byteLength);
    const t = view.getFloat64(0, true);
    if (!Number.isFinite(t)) throw fail(`${what}: time ${t} is not finite`);
    if (this.lastTime !== null && !(t > this.lastTime)) {
      throw fail(`${what}: time ${t} does not come after ${this.lastTime}: frames come in strictly increasing time`);
    }
    const m = this.movers.length;
    const values = await readBody(coding, payload.subarray(8), m, what);
    let cells;
    if (kind === KIND_KEYFRAME) {
      checkCells(values, m, this.movers, what);
      cells = values;
    } else {
      if (!this.previous) throw fail(`${what} is a delta frame, but no keyframe came before it`);
      cells = values;
      for (let v = 0; v < cells.length; v++) {
        // Exact: both terms are integers far under 2^53.
        const cell = this.previous[v] + values[v];
        if (Math.abs(cell) >= CELL_LIMIT) {
          throw fail(`${what}: Gaussian ${this.movers[v % m]}'s cell ${cell} is outside ±2^30`);
        }
        cells[v] = cell;
      }
    }
    const t0 = this.template;
    const frame = {
      t,
      count: this.count,
      means: t0.means.slice(),
      scales: t0.scales.slice(),
      rotations: t0.rotations.slice(),
      opacities: t0.opacities.slice(),
      colors: t0.colors.slice(),
    };
    reconstruct(cells, m, this.movers, this.steps, frame, what);
    this.previous = cells;
    this.frames++;
    this.lastTime = t;
    this.seen.push([t, offset, kind === KIND_KEYFRAME ? 1 : 0]);
    return frame;
  }

  readIndex(payload) {
    const view = new DataView(payload.buffer, payload.byteOffset, payload.byteLength);
    const tail = payload.length - INDEX_TAIL;
    const magic = String.fromCharCode(...payload.subarray(tail + 8));
    if (magic !== INDEX_MAGIC) throw fail('the index record does not end with C4GI');
    // The record's own offset (u64; a stream this reader holds is far under 2^53 bytes).
    const own = view.getUint32(tail, true) + view.getUint32(tail + 4, true) * 2 ** 32;
    const expected = this.position - RECORD_HEAD - payload.length;
    if (own !== expected) throw fail(`the index record says it starts at byte ${own}; it starts at ${expected}`);
    // Its length was checked against the frames read: one entry each, which must list them.
    this.seen.forEach(([t, offset, keyframe], k) => {
      const at = k * INDEX_ENTRY;
      const listed = view.getUint32(at + 8, true) + view.getUint32(at + 12, true) * 2 ** 32;
      if (view.getFloat64(at, true) !== t || listed !== offset || payload[at + 16] !== keyframe) {
        throw fail(`the index does not list the frames as they came (first difference at frame ${k})`);
      }
    });
    this.stage = 'done';
  }
}
