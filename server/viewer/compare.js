// "Compare with server": the server renders the view the WebGL canvas shows (same camera, time,
// size and view mode) with its own rasterizer, and the two are shown side by side (or one over
// the other as a difference) with their PSNR. The server answers colour as PNG and depth and
// alpha as raw f32 planes (docs/api.md), which are mapped here exactly as the WebGL composite
// pass maps its own.

import { postJson } from './api.js';
import { depthRamp } from './splats.js';

/** The render request (`POST /v1/clips/{id}/render`) for a view: t, camera, size, format. */
export function renderRequest({ t, worldToCamera, intrinsics, width, height, mode }) {
  const format = { color: 'png', depth: 'depth', alpha: 'alpha' }[mode];
  return {
    t,
    camera: { world_to_camera: worldToCamera, intrinsics },
    width,
    height,
    format,
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
