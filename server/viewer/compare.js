// What the WebGL view is held against. "Compare with server": the server renders the view the
// canvas shows (same camera, time, size, view mode and scene) with its own rasterizer, and the two
// are shown side by side with their PSNR, or the server's image is replaced by their difference,
// amplified: the two renderers draw the same Gaussians, so they differ by a few levels at most,
// and an unamplified difference is black to the eye. The server answers colour as PNG and depth
// and alpha as raw f32 planes (docs/api.md), which are mapped here exactly as the WebGL composite
// pass maps its own. And the input: the clip's context frame nearest the time shown
// (`GET /v1/clips/{id}/frames/{k}`), what the scene was reconstructed from.

import { postJson, getBlob } from './api.js';
import { depthRamp } from './splats.js';

/** The largest gain a difference is shown at: a one-level difference is then a quarter grey. */
const MAX_GAIN = 64;
/** The difference that sets the gain: this quantile of the channels' differences (not the
 * largest, so that a few outlying pixels do not leave the rest black). */
const GAIN_QUANTILE = 0.999;

/**
 * The render request (`POST /v1/clips/{id}/render`) for a view: t, camera, size, format, and the
 * scene the view shows (`null`: the server's default, auto).
 */
export function renderRequest({ t, worldToCamera, intrinsics, width, height, mode, scene = null }) {
  const format = { color: 'png', depth: 'depth', alpha: 'alpha' }[mode];
  return {
    t,
    camera: { world_to_camera: worldToCamera, intrinsics },
    width,
    height,
    format,
    ...(scene ? { scene } : {}),
  };
}

/** The server's render of `request` as RGBA ImageData, mapped for `mode` with `depthRange`. */
export async function serverImage(clipId, request, mode, depthRange) {
  const response = await postJson(`/v1/clips/${encodeURIComponent(clipId)}/render`, request);
  const { width, height } = request;
  if (mode === 'color') {
    const bitmap = await createImageBitmap(await response.blob(), {
      colorSpaceConversion: 'none',
      premultiplyAlpha: 'none',
    });
    return pixelsOf(bitmap, width, height);
  }
  const plane = new Float32Array(await response.arrayBuffer());
  if (plane.length !== width * height) throw new Error(`the server sent ${plane.length} values for ${width}×${height}`);
  const image = new ImageData(width, height);
  const [lo, hi] = depthRange;
  for (let p = 0; p < plane.length; p++) {
    let rgb;
    if (mode === 'depth') {
      // Expected depth is 0 where nothing was drawn (alpha 0): black, as in the WebGL view.
      rgb = plane[p] > 0 ? depthRamp((plane[p] - lo) / Math.max(hi - lo, 1e-6)) : [0, 0, 0];
    } else {
      rgb = [plane[p], plane[p], plane[p]];
    }
    for (let c = 0; c < 3; c++) image.data[4 * p + c] = Math.round(Math.min(1, Math.max(0, rgb[c])) * 255);
    image.data[4 * p + 3] = 255;
  }
  return image;
}

/** RGBA pixels of anything drawable (the WebGL canvas, a bitmap), top row first. */
export function pixelsOf(source, width, height) {
  const canvas = new OffscreenCanvas(width, height);
  const context = canvas.getContext('2d', { willReadFrequently: true });
  context.drawImage(source, 0, 0);
  return context.getImageData(0, 0, width, height);
}

/** PSNR in dB over RGB of two same-sized RGBA images, peak 255 (Infinity when identical). */
export function psnr(a, b) {
  if (a.width !== b.width || a.height !== b.height) throw new Error('the images differ in size');
  let sum = 0;
  for (let p = 0; p < a.data.length; p += 4) {
    for (let c = 0; c < 3; c++) {
      const d = a.data[p + c] - b.data[p + c];
      sum += d * d;
    }
  }
  const mse = sum / ((a.data.length / 4) * 3) / (255 * 255);
  return -10 * Math.log10(mse);
}

/**
 * |a − b| per RGB channel of two same-sized RGBA images, times a power-of-two `gain` (saturating
 * at 255), opaque; with the gain, the largest difference and the one the gain was chosen for, in
 * 8-bit levels. The gain brings that one (the GAIN_QUANTILE of all) to at least half of 255, up
 * to MAX_GAIN; 1 when the images are equal.
 */
export function difference(a, b) {
  if (a.width !== b.width || a.height !== b.height) throw new Error('the images differ in size');
  const counts = new Uint32Array(256);
  for (let p = 0; p < a.data.length; p += 4) {
    for (let c = 0; c < 3; c++) counts[Math.abs(a.data[p + c] - b.data[p + c])]++;
  }
  const values = (a.data.length / 4) * 3;
  let largest = 0;
  for (let d = 255; d > 0 && largest === 0; d--) if (counts[d]) largest = d;
  let [quantile, below] = [0, 0];
  while (quantile < 255 && (below += counts[quantile]) < GAIN_QUANTILE * values) quantile++;
  const basis = Math.max(1, quantile);
  const gain = largest === 0 ? 1 : Math.min(MAX_GAIN, 2 ** Math.floor(Math.log2(255 / basis)));
  const image = new ImageData(a.width, a.height);
  for (let p = 0; p < a.data.length; p += 4) {
    for (let c = 0; c < 3; c++) image.data[p + c] = Math.min(255, gain * Math.abs(a.data[p + c] - b.data[p + c]));
    image.data[p + 3] = 255;
  }
  return { image, gain, largest, quantile };
}

/** The index of the time in `times` nearest `t` (the earlier of two as near). */
export function nearest(times, t) {
  let best = 0;
  for (let k = 1; k < times.length; k++) if (Math.abs(times[k] - t) < Math.abs(times[best] - t)) best = k;
  return best;
}

/**
 * A clip's context frames as object URLs, each fetched once, when first asked for (they are the
 * source's size: a handful of PNGs). `close()` lets them go.
 */
export class InputFrames {
  constructor(clipId) {
    this.clipId = clipId;
    this.urls = new Map();
    this.abort = new AbortController();
  }

  /** Resolves with an object URL of context frame `k`. */
  url(k) {
    if (!this.urls.has(k)) {
      const path = `/v1/clips/${encodeURIComponent(this.clipId)}/frames/${k}`;
      const promise = getBlob(path, this.abort.signal).then((blob) => URL.createObjectURL(blob));
      // A failed fetch is asked again next time rather than remembered.
      promise.catch(() => {
        if (this.urls.get(k) === promise) this.urls.delete(k);
      });
      this.urls.set(k, promise);
    }
    return this.urls.get(k);
  }

  close() {
    this.abort.abort();
    for (const promise of this.urls.values()) promise.then((url) => URL.revokeObjectURL(url), () => {});
    this.urls.clear();
  }
}
