// The viewer page: pick or upload a clip, orbit about its scene, scrub or play its time, and
// compare the WebGL view with the server's render of the same view. This module wires the page;
// frames.js fetches the Gaussian sets, camera.js holds the camera, splats.js draws, compare.js
// asks the server for the same view, api.js talks to the REST API.
//
// URL: /viewer (the newest clip) or /viewer/{clip}; `?size=N` sets the square canvas's side in
// pixels (default 512); `?position_error=E` the compact stream's position bound (default 1e-3
// scene units; the server takes 1e-5 to 1); `?precision=f32` (exact) or `f16` fetches C4GS sets
// instead of the stream.
//
// `window.c4gViewer` lets a test (tests/browser/viewer.mjs) see what the page shows.

import { apiKey, setApiKey, getJson, postJson, upload } from './api.js';
import { FrameSource, frameTimes } from './frames.js';
import { OrbitCamera, C4G_INTRINSICS } from './camera.js';
import { SplatRenderer, NEAR } from './splats.js';
import { renderRequest, serverImage, pixelsOf, psnr } from './compare.js';

const params = new URLSearchParams(location.search);
const SIZE = Math.min(2048, Math.max(16, Number.parseInt(params.get('size'), 10) || 512));
const PRECISION = ['f32', 'f16'].includes(params.get('precision')) ? params.get('precision') : null;
const POSITION_ERROR_PARAM = Number.parseFloat(params.get('position_error'));
const POSITION_ERROR = Number.isFinite(POSITION_ERROR_PARAM) ? POSITION_ERROR_PARAM : undefined;

const $ = (id) => document.getElementById(id);
const ui = {
  clip: $('clip'),
  upload: $('upload'),
  progress: $('upload-progress'),
  key: $('api-key'),
  stage: $('stage'),
  canvas: $('view'),
  serverFigure: $('server-figure'),
  serverCanvas: $('server-view'),
  serverCaption: $('server-caption'),
  play: $('play'),
  time: $('time'),
  timeLabel: $('time-label'),
  mode: $('mode'),
  home: $('home'),
  compare: $('compare'),
  overlay: $('overlay'),
  ply: $('download-ply'),
  splat: $('download-splat'),
  exports: ['ply_zip', 'spz_zip', 'splatv'].map((format) => [format, $(`download-${format}`)]),
  status: $('status'),
};

const state = {
  clip: null,
  source: null,
  times: [],
  fps: 10,
  index: 0,
  playing: false,
  lastStep: 0,
  footprint: 'ellipse',
  rasterizer: 'server',
  dirty: true,
  draws: 0,
  shown: null,
  comparison: null,
  error: null,
  broken: false,
  played: [],
  opening: 0,
};

const camera = new OrbitCamera();
let renderer = null;

function showStatus(text, isError = false) {
  ui.status.textContent = text;
  ui.status.classList.toggle('error', isError);
  if (isError) state.error = text;
}

function fail(error) {
  console.error(error);
  showStatus(error.message || String(error), true);
}

function clipPath(id) {
  return `/viewer/${encodeURIComponent(id)}${location.search}`;
}

function clipFromPath() {
  const match = /^\/viewer\/([^/]+)\/?$/.exec(location.pathname);
  return match ? decodeURIComponent(match[1]) : null;
}

/** The model's footprint and rasterizer, so the WebGL view draws what the server draws. */
async function loadModel() {
  const { models } = await getJson('/v1/models');
  state.footprint = models[0]?.footprint || 'ellipse';
  state.rasterizer = models[0]?.renderer || 'server';
}

async function refreshClips(selected) {
  const { clips } = await getJson('/v1/clips');
  clips.sort((a, b) => (b.created_at || 0) - (a.created_at || 0));
  ui.clip.replaceChildren();
  if (clips.length === 0) ui.clip.append(new Option('no clips yet: upload one', ''));
  for (const c of clips) {
    const s = c.source || {};
    const label = `${c.id.slice(0, 12)} · ${s.kind || '?'} ${s.width}×${s.height} · ${(c.span[1] - c.span[0]).toFixed(2)} s`;
    ui.clip.append(new Option(label, c.id, false, c.id === selected));
  }
  return clips;
}

/** Camera-space depth (first camera) at the middle of the scene: the orbit's centre. */
function sceneDepth(set) {
  const depths = [];
  for (let i = 0; i < set.count; i++) {
    const z = set.means[3 * i + 2];
    if (set.opacities[i] >= 0.05 && z > NEAR && Number.isFinite(z)) depths.push(z);
  }
  if (depths.length === 0) return 2;
  depths.sort((a, b) => a - b);
  return depths[Math.floor(depths.length / 2)];
}

/** Opens clip `id`; `url`: 'push' or 'replace' the page's address with the clip's, or leave it. */
async function openClip(id, { url = null } = {}) {
  const opening = ++state.opening;
  state.source?.close();
  state.source = null;
  state.shown = null;
  state.playing = false;
  state.error = null;
  setControls(false);
  ui.serverFigure.hidden = true;
  showStatus(`opening ${id.slice(0, 12)}…`);
  const clip = await getJson(`/v1/clips/${encodeURIComponent(id)}`);
  if (opening !== state.opening) return;
  if (url === 'push') history.pushState({ clip: id }, '', clipPath(id));
  if (url === 'replace') history.replaceState({ clip: id }, '', clipPath(id));
  ui.clip.value = id;
  const { times, fps, grid } = frameTimes(clip);
  state.clip = clip;
  state.times = times;
  state.fps = fps;
  state.index = 0;
  ui.time.max = String(times.length - 1);
  ui.time.value = '0';
  const source = new FrameSource(clip, times, { fps, grid, precision: PRECISION, positionError: POSITION_ERROR });
  state.source = source;
  source.onload = (i) => {
    if (i === state.index) state.dirty = true;
    updateStatus();
  };
  source.onerror = fail;
  const first = await source.want(0);
  if (opening !== state.opening) return;
  camera.home(sceneDepth(first));
  setControls(true);
  updateStatus();
}

function setControls(enabled) {
  const exports = ui.exports.map(([, button]) => button);
  for (const control of [ui.play, ui.time, ui.compare, ui.ply, ui.splat, ...exports]) control.disabled = !enabled;
  ui.play.textContent = state.playing ? 'Pause' : 'Play';
}

function updateStatus() {
  if (state.error || !state.source) return;
  const [loaded, times] = [state.source.loaded, state.times];
  const drawn = state.shown ? `${state.shown.splats} of ${state.shown.count} Gaussians drawn` : 'loading…';
  showStatus(
    `${loaded}/${times.length} frames loaded (${state.source.describe()}) · ${drawn} · ${state.footprint} footprint · ` +
      `${renderer.targetFormat} target · ${state.fps.toFixed(1)} fps`,
  );
}

function setIndex(index) {
  state.index = index;
  ui.time.value = String(index);
  state.source?.want(index).catch(() => {});
  state.dirty = true;
}

function draw(set) {
  const view = camera.view(SIZE, SIZE);
  const mode = ui.mode.value;
  const drawn = renderer.render(set, view, { mode, footprint: state.footprint });
  state.draws++;
  state.dirty = false;
  if (state.playing && state.played.at(-1) !== state.index) state.played = [...state.played, state.index].slice(-32);
  state.shown = {
    index: state.index,
    t: state.times[state.index],
    mode,
    worldToCamera: camera.worldToCamera(),
    depthRange: drawn.depthRange,
    splats: drawn.splats,
    count: set.count,
    draw: state.draws,
  };
  const t = state.times[state.index];
  ui.timeLabel.value = `t = ${t.toFixed(3)} s (${state.index + 1}/${state.times.length})`;
  markStaleComparison();
  updateStatus();
}

function tick(now) {
  const source = state.source;
  if (source && state.playing) {
    const next = (state.index + 1) % state.times.length;
    if (now - state.lastStep >= 1000 / state.fps && source.has(next)) {
      state.lastStep = now;
      setIndex(next);
    } else if (!source.has(next)) {
      source.want(next).catch(() => {});
    }
  }
  const set = source?.get(state.index);
  if (set && !state.broken && (state.dirty || state.shown?.index !== state.index)) {
    try {
      draw(set);
    } catch (error) {
      // A shader or context failure does not mend itself: stop drawing, say why.
      state.broken = true;
      fail(error);
    }
  }
  requestAnimationFrame(tick);
}

/** The render request for what the canvas shows now (the comparison's, and the test's). */
function currentRequest() {
  const shown = state.shown;
  if (!shown) return null;
  return renderRequest({
    t: shown.t,
    worldToCamera: shown.worldToCamera,
    intrinsics: { ...C4G_INTRINSICS },
    width: SIZE,
    height: SIZE,
    mode: shown.mode,
  });
}

async function compare() {
  const shown = state.shown;
  const request = currentRequest();
  if (!shown || !request) return;
  // What this browser drew, taken now: the server's answer is compared with this view.
  const mine = pixelsOf(ui.canvas, SIZE, SIZE);
  ui.compare.disabled = true;
  ui.serverCaption.textContent = 'rendering on the server…';
  try {
    const theirs = await serverImage(state.clip.id, request, shown.mode, shown.depthRange);
    ui.serverCanvas.width = SIZE;
    ui.serverCanvas.height = SIZE;
    ui.serverCanvas.getContext('2d').putImageData(theirs, 0, 0);
    ui.serverFigure.hidden = false;
    const db = psnr(mine, theirs);
    state.comparison = { t: shown.t, mode: shown.mode, draw: shown.draw, psnr: db, request };
    markStaleComparison();
  } catch (error) {
    ui.serverCaption.textContent = 'the server could not render this view';
    fail(error);
  } finally {
    ui.compare.disabled = false;
  }
}

function markStaleComparison() {
  const c = state.comparison;
  if (!c) return;
  const same = state.shown && state.shown.draw === c.draw;
  const db = Number.isFinite(c.psnr) ? `${c.psnr.toFixed(1)} dB` : 'identical';
  ui.serverCaption.textContent =
    `server (${state.rasterizer} rasterizer), ${c.mode} at t = ${c.t.toFixed(3)} s: PSNR ${db} against this view` +
    (same ? '' : ' as it was (press Compare again)');
}

async function download(format) {
  const t = state.times[state.index];
  const id = state.clip.id;
  const response = await postJson(`/v1/clips/${encodeURIComponent(id)}/gaussians`, { t, format });
  const link = document.createElement('a');
  link.href = URL.createObjectURL(await response.blob());
  link.download = `${id.slice(0, 12)}-t${t.toFixed(3)}.${format}`;
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 60_000);
}

/** The whole clip at the viewer's frame rate as one 4D file (POST /v1/clips/{id}/export). */
async function downloadExport(format, button) {
  const id = state.clip.id;
  const { fps } = frameTimes(state.clip);
  button.disabled = true;
  showStatus(`exporting the clip as ${format}…`);
  try {
    const response = await postJson(`/v1/clips/${encodeURIComponent(id)}/export`, { format, fps });
    const sets = response.headers.get('X-C4G-Sets');
    const fit = response.headers.get('X-C4G-Fit-Position-Error');
    const link = document.createElement('a');
    link.href = URL.createObjectURL(await response.blob());
    link.download = `${id.slice(0, 12)}.${format.replace('_', '.')}`;
    link.click();
    setTimeout(() => URL.revokeObjectURL(link.href), 60_000);
    showStatus(`exported ${sets} frames as ${link.download}` + (fit ? ` (fit: ${fit} scene units)` : ''));
  } finally {
    button.disabled = false;
  }
}

async function uploadFiles(files) {
  ui.progress.hidden = false;
  ui.progress.removeAttribute('value');
  showStatus('uploading…');
  try {
    const clip = await upload(files, (sent, total) => {
      if (total) {
        ui.progress.value = sent / total;
        showStatus(
          sent < total
            ? `uploading: ${(sent / 1e6).toFixed(1)} of ${(total / 1e6).toFixed(1)} MB`
            : 'uploaded: the server is reading and encoding the clip…',
        );
      }
    });
    await refreshClips(clip.id);
    await openClip(clip.id, { url: 'push' });
  } finally {
    ui.progress.hidden = true;
    ui.upload.value = '';
  }
}

function wire() {
  ui.key.value = apiKey();
  ui.key.addEventListener('change', () => {
    setApiKey(ui.key.value.trim());
    state.error = null;
    start().catch(fail);
  });
  ui.clip.addEventListener('change', () => {
    if (ui.clip.value) openClip(ui.clip.value, { url: 'push' }).catch(fail);
  });
  ui.upload.addEventListener('change', () => {
    if (ui.upload.files.length) uploadFiles(ui.upload.files).catch(fail);
  });
  ui.time.addEventListener('input', () => setIndex(Number(ui.time.value)));
  ui.play.addEventListener('click', () => {
    state.playing = !state.playing;
    if (state.playing && state.index === state.times.length - 1) setIndex(0);
    state.lastStep = performance.now();
    setControls(true);
  });
  ui.mode.addEventListener('change', () => {
    state.dirty = true;
  });
  ui.home.addEventListener('click', () => {
    const first = state.source?.get(0);
    camera.home(first ? sceneDepth(first) : camera.homeDepth);
  });
  ui.compare.addEventListener('click', () => compare());
  ui.overlay.addEventListener('change', () => ui.stage.classList.toggle('overlay', ui.overlay.checked));
  ui.ply.addEventListener('click', () => download('ply').catch(fail));
  ui.splat.addEventListener('click', () => download('splat').catch(fail));
  for (const [format, button] of ui.exports) {
    button.addEventListener('click', () => downloadExport(format, button).catch(fail));
  }
  window.addEventListener('popstate', () => {
    const id = clipFromPath();
    if (id) openClip(id).catch(fail);
  });
  camera.onchange = () => {
    state.dirty = true;
  };
  camera.attach(ui.canvas, () => C4G_INTRINSICS.fx * SIZE);
}

async function start() {
  await loadModel();
  const wanted = clipFromPath();
  const clips = await refreshClips(wanted);
  const id = wanted || clips[0]?.id;
  if (id) await openClip(id, { url: wanted ? null : 'replace' });
  else showStatus('no clips on this server yet: upload a video, an archive of frames, or frames');
}

window.c4gViewer = {
  /** What the page shows: the clip, its times, the frame drawn, the last comparison, errors. */
  state: () => ({
    clip: state.clip?.id || null,
    times: state.times,
    fps: state.fps,
    index: state.index,
    loaded: state.source?.loaded || 0,
    shown: state.shown,
    // True until the current frame and camera are drawn.
    dirty: state.dirty || !state.shown || state.shown.index !== state.index,
    comparison: state.comparison,
    // The frames shown while playing, the last 32.
    played: state.played,
    error: state.error,
    target: renderer?.targetFormat || null,
    footprint: state.footprint,
    // Where the sets come from: 'stream' (C4GV) or 'c4gs', the body bytes received for them
    // and the requests made for streams.
    frames: state.source
      ? {
          kind: state.source.kind,
          bytes: state.source.bytes,
          requests: state.source.requests,
          positionError: state.source.positionError,
          precision: state.source.kind === 'c4gs' ? state.source.precision : null,
        }
      : null,
  }),
  /** The render request for the view on the canvas (colour: PNG). */
  request: () => currentRequest(),
};

try {
  ui.canvas.width = SIZE;
  ui.canvas.height = SIZE;
  renderer = new SplatRenderer(ui.canvas);
  wire();
  requestAnimationFrame(tick);
  start().catch(fail);
} catch (error) {
  fail(error);
}
