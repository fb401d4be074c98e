// The frame source: a clip's Gaussian sets at the viewer's times, fetched progressively. The rest
// of the viewer knows only this module's interface (times, get, has, want, onload, onerror,
// close), so the transport changes here alone.
//
// The sets come from the compact 4D stream, `POST /v1/clips/{id}/stream` (`C4GV`, decoded by
// c4gv.js as its chunked body arrives): one request for a run of consecutive times, each set
// usable as soon as its record is whole. Quantised: positions within `position_error` (default
// 1e-3 scene units), scales, rotations, opacities and colours within 4.9e-4. A run starts at the
// time the viewer wants (the one it shows or scrubs to) and goes to the end; one wanted far ahead
// of (or behind) what the running stream will bring soon aborts it and starts another there; the
// frames before are fetched last, wrapping around. A server without the stream (404) gets the
// older transport instead: `POST /v1/clips/{id}/gaussians`, a few times a request, in `C4GS`
// (c4gs.js), which a page can also ask for by precision (`f16`, or `f32`: exact sets).
//
// Every request names the clip's scene (`"scene"`: auto, feed-forward or fitted). The first
// answer's `X-C4G-Scene` says which one `auto` resolved to, and every later request of the source
// asks for that one outright: a fit that finishes while the frames load must not mix fitted sets
// into a feed-forward run.

import { postJson, ApiError } from './api.js';
import { decode } from './c4gs.js';
import { C4GVDecoder } from './c4gv.js';

/** C4GS: times per request (small, so the first frame and a scrub answer fast). */
const CHUNK = 4;
/** C4GS: requests in flight at once (decodes share the server's cores with everyone). */
const CONCURRENCY = 2;
/** Most frames a clip is viewed at; a long clip at a high rate is sampled more sparsely. */
const MAX_FRAMES = 600;
/** Stream: a wanted frame at most this many past the next one to arrive is waited for. */
const LOOKAHEAD = 16;
/** Stream: how long a far scrub settles before the running stream is given up for it, ms. */
const RESTART_DELAY_MS = 120;
/** Stream: a full set every this many (the server's default; a restart begins with one anyway). */
const KEYFRAME_INTERVAL = 16;
/** Stream: the default position error, scene units. */
export const POSITION_ERROR = 1e-3;
/** The header that names the scene that served an answer. */
const SCENE_HEADER = 'X-C4G-Scene';

/**
 * The times the viewer shows a clip at: its context span at the source's frame rate (both
 * ends included), at most MAX_FRAMES of them. Also the playback rate, frames per second, and
 * how many of the times lie on the grid `start + k / fps` (all but an appended end).
 */
export function frameTimes(clip) {
  const [start, end] = clip.span;
  const sourceFps = clip.source && clip.source.fps > 0 ? clip.source.fps : 10;
  const length = end - start;
  const fps = Math.min(sourceFps, (MAX_FRAMES - 1) / Math.max(length, 1e-9));
  const steps = Math.floor(length * fps + 1e-6);
  const times = [];
  for (let k = 0; k <= steps; k++) times.push(Math.min(end, start + k / fps));
  const grid = times.length;
  if (end - times[times.length - 1] > 1e-9) times.push(end);
  return { times, fps, grid };
}

export class FrameSource {
  /**
   * The sets of `clip` at `times`, of which the first `grid` are `1 / fps` apart. `precision`
   * ('f16' or 'f32') asks for C4GS sets instead of the stream; `positionError` is the stream's;
   * `scene` the clip's scene to ask for ('auto', 'feed-forward' or 'fitted').
   */
  constructor(
    clip,
    times,
    { fps, grid = times.length, precision = null, positionError = POSITION_ERROR, scene = 'auto' } = {},
  ) {
    this.clip = clip;
    /** The scene asked for, and the one that served the sets (null until the first answer). */
    this.scene = scene;
    this.served = null;
    /** Called with the served scene's name when the first answer names it. */
    this.onscene = null;
    this.times = times;
    this.step = 1 / fps;
    this.grid = grid;
    this.positionError = positionError;
    /** 'stream' (C4GV) or 'c4gs'. */
    this.kind = precision ? 'c4gs' : 'stream';
    this.precision = precision || 'f16';
    this.frames = new Array(times.length).fill(null);
    this.waiters = new Map();
    this.focus = 0;
    this.closed = false;
    this.loaded = 0;
    /** Bytes of set data received (response bodies), and the streams asked for. */
    this.bytes = 0;
    this.requests = 0;
    /** Called with the index of every frame that arrives. */
    this.onload = null;
    /** Called with an Error when frames stop loading. */
    this.onerror = null;
    this.abort = new AbortController();
    // Stream: the run on its way ({a, b, next, controller}) and a pending restart.
    this.run = null;
    this.restart = null;
    // C4GS: the indices asked for and the requests in flight.
    this.pending = new Set();
    this.inFlight = 0;
  }

  /**
   * The request's `scene`: the one the first answer was served from, once known. A server that
   * labels nothing (from before fitted scenes) is not sent the field unless one was picked.
   */
  sceneField() {
    const scene = this.served || this.scene;
    return scene === 'auto' ? {} : { scene };
  }

  /** Notes the scene `response` was served from; a change within one source is an error. */
  noteScene(response) {
    const label = response.headers.get(SCENE_HEADER);
    if (!label) return;
    if (this.served === null) {
      this.served = label;
      this.onscene?.(label);
    } else if (label !== this.served) {
      throw new Error(`the server answered from the ${label} scene after the ${this.served} one`);
    }
  }

  /** What the sets come as, for the page's status line. */
  describe() {
    return this.kind === 'stream' ? `stream ±${this.positionError}` : `C4GS ${this.precision}`;
  }

  /** The set at index `i`, or null while it loads. */
  get(i) {
    return this.frames[i];
  }

  has(i) {
    return this.frames[i] !== null;
  }

  /** Loads frame `i` (and those after it) first; resolves with its set. */
  want(i) {
    this.focus = i;
    const ready = this.frames[i];
    const promise = ready
      ? Promise.resolve(ready)
      : new Promise((resolve, reject) => {
          const list = this.waiters.get(i) || [];
          list.push({ resolve, reject });
          this.waiters.set(i, list);
        });
    this.pump();
    return promise;
  }

  /** Stops loading (the viewer moved to another clip): aborts what is in flight. */
  close() {
    this.closed = true;
    clearTimeout(this.restart);
    this.abort.abort();
    this.run?.controller.abort();
    for (const list of this.waiters.values()) for (const w of list) w.reject(new Error('closed'));
    this.waiters.clear();
  }

  pump() {
    if (this.closed) return;
    if (this.kind === 'c4gs') {
      this.pumpChunks();
      return;
    }
    const run = this.run;
    if (!run) {
      this.startRun();
      return;
    }
    if (this.soon(run) || this.restart !== null) return;
    // The stream will not bring the wanted frame soon: after a moment (a scrub moves on), give
    // it up and start one there.
    this.restart = setTimeout(() => {
      this.restart = null;
      if (this.closed || this.run !== run || this.soon(run)) return;
      run.controller.abort();
      this.run = null;
      this.startRun();
    }, RESTART_DELAY_MS);
  }

  /** Whether the focus is loaded or among the next frames `run` brings. */
  soon(run) {
    const i = this.focus;
    return this.frames[i] !== null || (i >= run.next && i <= run.b && i - run.next <= LOOKAHEAD);
  }

  /** Delivers set `set` at index `i`. */
  arrive(i, set) {
    if (this.frames[i]) return;
    this.frames[i] = set;
    this.loaded++;
    for (const w of this.waiters.get(i) || []) w.resolve(set);
    this.waiters.delete(i);
    this.onload?.(i);
  }

  /** Ends loading with `error`. */
  stop(error) {
    this.closed = true;
    for (const list of this.waiters.values()) for (const w of list) w.reject(error);
    this.waiters.clear();
    this.onerror?.(error);
  }

  /** Whether `error` says to try again later (busy or overloaded): then it does so. */
  retried(error) {
    if (!(error instanceof ApiError && (error.status === 503 || error.status === 429))) return false;
    setTimeout(() => this.pump(), 1000 * (error.retryAfter || 1));
    return true;
  }

  // ----------------------------------------------------------------------------------------
  // The stream

  /**
   * Starts a stream over the unloaded frames from the focus on (wrapping around): up to the next
   * loaded one or the grid's end. The appended end time, off the grid, is a stream of its own.
   */
  startRun() {
    const n = this.times.length;
    let a = -1;
    for (let k = 0; k < n && a < 0; k++) {
      const i = (this.focus + k) % n;
      if (!this.frames[i]) a = i;
    }
    if (a < 0) return;
    let b = a;
    if (a < this.grid) while (b + 1 < this.grid && !this.frames[b + 1]) b++;
    const run = { a, b, next: a, controller: new AbortController() };
    this.run = run;
    this.stream(run).then(
      () => {
        if (this.run !== run) return;
        this.run = null;
        this.pump();
      },
      (error) => {
        // Given up for another run, or closed (the run stays, aborted).
        if (this.run !== run || this.closed) return;
        this.run = null;
        if (this.retried(error)) return;
        if (error instanceof ApiError && error.status === 404 && this.requests === 1) {
          // A server from before the stream: the C4GS decodes it has.
          console.warn(`the server has no compact stream (${error.message}): C4GS sets instead`);
          this.kind = 'c4gs';
          this.pump();
          return;
        }
        this.stop(error);
      },
    );
  }

  /** Fetches `run`'s frames as one C4GV stream, delivering each as it is decoded. */
  async stream(run) {
    const { a, b } = run;
    const expected = b - a + 1;
    this.requests++;
    const response = await postJson(
      `/v1/clips/${encodeURIComponent(this.clip.id)}/stream`,
      {
        start: this.times[a],
        end: this.times[b],
        step: this.step,
        position_error: this.positionError,
        keyframe_interval: KEYFRAME_INTERVAL,
        ...this.sceneField(),
      },
      run.controller.signal,
    );
    this.noteScene(response);
    const announced = response.headers.get('X-C4G-Sets');
    if (announced !== null && Number(announced) !== expected) {
      throw new Error(`the stream announces ${announced} sets from t = ${this.times[a]}; the viewer needs ${expected}`);
    }
    const reader = response.body.getReader();
    const decoder = new C4GVDecoder();
    // The tolerance between the server's times (start + step·k) and the viewer's (start + k/fps).
    const slack = 1e-6 * this.step;
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      this.bytes += value.length;
      decoder.feed(value);
      for (let set = await decoder.next(); set; set = await decoder.next()) {
        if (run.controller.signal.aborted) throw new Error('aborted');
        const i = run.next;
        if (i > b) throw new Error(`the stream sends more than the ${expected} sets asked for`);
        if (Math.abs(set.t - this.times[i]) > slack) {
          throw new Error(`the stream's set ${i - a} is at t = ${set.t}, not ${this.times[i]}`);
        }
        run.next++;
        this.arrive(i, set);
      }
    }
    decoder.finish();
    if (run.next !== b + 1) throw new Error(`the stream ended after ${run.next - a} of ${expected} sets`);
  }

  // ----------------------------------------------------------------------------------------
  // C4GS decodes (older servers, or a precision asked for)

  /** The next chunk to fetch: unloaded indices from the focus on, wrapping around. */
  nextChunk() {
    const n = this.times.length;
    const chunk = [];
    for (let k = 0; k < n && chunk.length < CHUNK; k++) {
      const i = (this.focus + k) % n;
      if (!this.frames[i] && !this.pending.has(i)) chunk.push(i);
    }
    return chunk;
  }

  pumpChunks() {
    while (!this.closed && this.inFlight < CONCURRENCY) {
      const chunk = this.nextChunk();
      if (chunk.length === 0) return;
      for (const i of chunk) this.pending.add(i);
      this.inFlight++;
      this.fetchChunk(chunk)
        .then(() => {
          this.inFlight--;
          this.pump();
        })
        .catch((error) => {
          this.inFlight--;
          for (const i of chunk) this.pending.delete(i);
          if (this.closed || this.retried(error)) return;
          this.stop(error);
        });
    }
  }

  async fetchChunk(indices) {
    const times = indices.map((i) => this.times[i]);
    const response = await postJson(
      `/v1/clips/${encodeURIComponent(this.clip.id)}/gaussians`,
      { times, format: 'binary', precision: this.precision, ...this.sceneField() },
      this.abort.signal,
    );
    this.noteScene(response);
    const buffer = await response.arrayBuffer();
    this.bytes += buffer.byteLength;
    const sets = decode(buffer);
    if (sets.length !== indices.length) {
      throw new Error(`asked for ${indices.length} sets, got ${sets.length}`);
    }
    indices.forEach((i, k) => {
      this.pending.delete(i);
      this.arrive(i, sets[k]);
    });
  }
}
