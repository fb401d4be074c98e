// The viewer page: pick or upload a clip, orbit about its scene, scrub or play its time, see the
// input frame the scene was reconstructed from beside it, compare the WebGL view with the
// server's render of the same view, fit the clip's scene to its own frames and switch between
// the feed-forward and the fitted scene. This module wires the page; frames.js fetches the
// Gaussian sets, camera.js holds the camera, splats.js draws, compare.js asks the server for the
// same view and fetches the input frames, api.js talks to the REST API and follows jobs.
//
// URL: /viewer (the newest clip) or /viewer/{clip}; `?size=N` sets the square canvas's side in
// pixels (default 512); `?position_error=E` the compact stream's position bound (default 1e-3
// scene units; the server takes 1e-5 to 1); `?precision=f32` (exact) or `f16` fetches C4GS sets
// instead of the stream.
//
// `window.c4gViewer` lets a test (tests/browser/viewer.mjs) see what the page shows.

import { apiKey, setApiKey, getJson, postJson, upload, followJob, jobEnded } from './api.js';
import { FrameSource, frameTimes } from './frames.js';
import { OrbitCamera, C4G_INTRINSICS } from './camera.js';
import { SplatRenderer, NEAR } from './splats.js';
import { renderRequest, serverImage, pixelsOf, psnr, difference, nearest, InputFrames } from './compare.js';

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
  inputFigure: $('input-figure'),
  inputView: $('input-view'),
  inputCrop: $('input-crop'),
  inputCaption: $('input-caption'),
  play: $('play'),
  time: $('time'),
  timeLabel: $('time-label'),
  mode: $('mode'),
  home: $('home'),
  compare: $('compare'),
  difference: $('difference'),
  scene: $('scene'),
  sceneShown: $('scene-shown'),
  fitPreset: $('fit-preset'),
  fit: $('fit'),
  fitCancel: $('fit-cancel'),
  fitProgress: $('fit-progress'),
  fitStatus: $('fit-status'),
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
  // How many of the times lie on the frame-rate grid (frames.js's frameTimes).
  grid: 0,
  index: 0,
  playing: false,
  lastStep: 0,
  footprint: 'ellipse',
  rasterizer: 'server',
  dirty: true,
  draws: 0,
  shown: null,
  comparison: null,
  // The two images of the last comparison and their amplified difference.
  images: null,
  // The input frame shown: {clip, index, t, loaded, width, height}, and the time it is shown for.
  input: null,
  inputFor: null,
  inputFrames: null,
  // The fit followed: {id, clip, record, stages, controller, error}.
  fit: null,
  // Fields a test adds to the Fit button's request (a tiny fit).
  fitExtra: {},
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
  state.comparison = null;
  state.images = null;
  state.inputFrames?.close();
  state.inputFrames = null;
  state.input = null;
  state.inputFor = null;
  // The fit goes on on the server; the page stops following it (and follows it again when the
  // clip is opened again).
  state.fit?.controller.abort();
  state.fit = null;
  setControls(false);
  showFitStatus('');
  ui.fitProgress.hidden = true;
  ui.fitCancel.hidden = true;
  ui.serverFigure.hidden = true;
  ui.inputFigure.hidden = true;
  ui.difference.disabled = true;
  ui.sceneShown.value = '';
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
  state.grid = grid;
  state.index = 0;
  ui.time.max = String(times.length - 1);
  ui.time.value = '0';
  state.inputFrames = new InputFrames(clip.id);
  ui.scene.value = 'auto';
  setSceneOptions(clip);
  showFitted(clip.fitted);
  const source = openSets();
  followActiveFit(clip.id).catch(() => {});
  const first = await source.want(0);
  if (opening !== state.opening) return;
  camera.home(sceneDepth(first));
  setControls(true);
  updateStatus();
}

/**
 * A frame source for the clip's sets in the scene picked, in place of the one before; the time
 * and the camera stay. The canvas keeps the old scene's image until the new one's set arrives.
 */
function openSets() {
  state.source?.close();
  state.error = null;
  const source = new FrameSource(state.clip, state.times, {
    fps: state.fps,
    grid: state.grid,
    precision: PRECISION,
    positionError: POSITION_ERROR,
    scene: ui.scene.value,
  });
  state.source = source;
  state.dirty = true;
  ui.sceneShown.value = 'loading…';
  source.onload = (i) => {
    if (i === state.index) state.dirty = true;
    updateStatus();
  };
  source.onerror = fail;
  source.onscene = (served) => {
    if (state.source === source) ui.sceneShown.value = `showing the ${served} scene`;
  };
  return source;
}

/** The scene picker for `clip`: fitted only when it has a fitted scene. */
function setSceneOptions(clip) {
  const fitted = [...ui.scene.options].find((o) => o.value === 'fitted');
  fitted.disabled = !clip.fitted;
  fitted.textContent = clip.fitted ? 'fitted' : 'fitted (none yet)';
  if (ui.scene.value === 'fitted' && !clip.fitted) ui.scene.value = 'auto';
}

/** Shows the sets of the scene picked now. */
async function changeScene() {
  const source = openSets();
  await source.want(state.index);
}

function setControls(enabled) {
  const exports = ui.exports.map(([, button]) => button);
  const controls = [ui.play, ui.time, ui.compare, ui.ply, ui.splat, ui.scene, ...exports];
  for (const control of controls) control.disabled = !enabled;
  ui.fit.disabled = !enabled || fitRunning();
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
    // The scene the set came from (null from a server that does not say).
    scene: state.source.served,
  };
  const t = state.times[state.index];
  ui.timeLabel.value = `t = ${t.toFixed(3)} s (${state.index + 1}/${state.times.length})`;
  showInput(t);
  markStaleComparison();
  updateStatus();
}

/**
 * The clip's context frame nearest time `t` beside the canvas, within its size: what the model
 * reconstructed the scene from (a fit also trains on the source frames between them). The square
 * centre crop the model sees, which the first camera's view shows, is outlined on a frame that is
 * not square.
 */
function showInput(t) {
  const clip = state.clip;
  const k = nearest(clip.context_times, t);
  const tk = clip.context_times[k];
  const near = Math.abs(tk - t) < 1e-9 ? '' : `, the nearest to ${t.toFixed(3)} s`;
  const square = clip.source.width === clip.source.height;
  ui.inputCaption.textContent =
    `input: context frame ${k + 1} of ${clip.context_times.length}, t = ${tk.toFixed(3)} s${near}` +
    (square ? '' : '; dashed: the square the model sees');
  state.inputFor = t;
  if (state.input?.clip === clip.id && state.input.index === k) return;
  const shown = { clip: clip.id, index: k, t: tk, loaded: false, width: 0, height: 0 };
  state.input = shown;
  state.inputFrames
    .url(k)
    .then(async (url) => {
      if (state.input !== shown) return;
      ui.inputView.src = url;
      await ui.inputView.decode();
      if (state.input !== shown) return;
      const [w, h] = [ui.inputView.naturalWidth, ui.inputView.naturalHeight];
      Object.assign(shown, { loaded: true, width: w, height: h });
      // Within the canvas's square: a wide video's frame would otherwise push the comparison
      // onto another row.
      const scale = SIZE / Math.max(w, h);
      ui.inputView.style.width = `${Math.round(w * scale)}px`;
      ui.inputView.style.height = `${Math.round(h * scale)}px`;
      const side = Math.min(w, h);
      ui.inputCrop.hidden = w === h;
      Object.assign(ui.inputCrop.style, {
        left: `${(50 * (w - side)) / w}%`,
        top: `${(50 * (h - side)) / h}%`,
        width: `${(100 * side) / w}%`,
        height: `${(100 * side) / h}%`,
      });
      ui.inputFigure.hidden = false;
    })
    .catch((error) => {
      if (state.input !== shown) return;
      ui.inputCaption.textContent = `input: context frame ${k + 1} could not be fetched (${error.message || error})`;
    });
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
    // The scene the canvas shows, by name: auto could be another one by now.
    scene: shown.scene,
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
    const db = psnr(mine, theirs);
    const diff = difference(mine, theirs);
    state.images = { theirs, difference: diff.image };
    state.comparison = {
      t: shown.t,
      mode: shown.mode,
      scene: shown.scene,
      draw: shown.draw,
      psnr: db,
      request,
      difference: { gain: diff.gain, largest: diff.largest, quantile: diff.quantile },
    };
    ui.difference.disabled = false;
    paintComparison();
    ui.serverFigure.hidden = false;
  } catch (error) {
    ui.serverCaption.textContent = 'the server could not render this view';
    fail(error);
  } finally {
    ui.compare.disabled = false;
  }
}

/** The server's image of the last comparison, or its difference from this browser's. */
function paintComparison() {
  if (!state.images) return;
  ui.serverCanvas.width = SIZE;
  ui.serverCanvas.height = SIZE;
  const image = ui.difference.checked ? state.images.difference : state.images.theirs;
  ui.serverCanvas.getContext('2d').putImageData(image, 0, 0);
  markStaleComparison();
}

/**
 * The comparison's caption. Both images are renders of the same Gaussians, so their PSNR says
 * how alike the two renderers draw (about 60 dB: a few levels apart at most), not how well the
 * scene reconstructs the clip; the caption says so, since a newcomer reads a PSNR as quality.
 */
function markStaleComparison() {
  const c = state.comparison;
  if (!c) return;
  const same = state.shown && state.shown.draw === c.draw;
  const mode = { color: 'colour', depth: 'depth', alpha: 'alpha' }[c.mode];
  const what = `${mode} at t = ${c.t.toFixed(3)} s` + (c.scene ? `, ${c.scene} scene` : '');
  const { gain, largest } = c.difference;
  let caption;
  if (ui.difference.checked) {
    caption =
      largest === 0
        ? `|this browser − server|, ${what}: none, the two renders are identical`
        : `|this browser − server| × ${gain}, ${what}: black where they agree; ` +
          `the largest difference is ${largest} of 255 levels`;
  } else {
    const db = Number.isFinite(c.psnr) ? `PSNR ${c.psnr.toFixed(1)} dB` : 'identical images';
    caption =
      `server (${state.rasterizer} rasterizer), ${what}. This browser's renderer against the server's, ` +
      `same Gaussians: ${db} (how alike the renderers draw, not reconstruction quality)`;
  }
  ui.serverCaption.textContent = caption + (same ? '' : ' (of the view as it was: press Compare again)');
}

/** The request field that asks for the scene the canvas shows (none before one is known). */
function sceneShown() {
  const scene = state.source?.served;
  return scene ? { scene } : {};
}

async function download(format) {
  const t = state.times[state.index];
  const id = state.clip.id;
  const response = await postJson(`/v1/clips/${encodeURIComponent(id)}/gaussians`, { t, format, ...sceneShown() });
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
    const response = await postJson(`/v1/clips/${encodeURIComponent(id)}/export`, { format, fps, ...sceneShown() });
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

// ------------------------------------------------------------------------------------------
// Fitting: `POST /v1/clips/{id}/fit` queues a job that a c4g-fitter worker runs; the page follows
// its events and, when it is done, shows the fitted scene and what the fit reports.

function fitRunning() {
  return Boolean(state.fit && !state.fit.error && !jobEnded(state.fit.record));
}

function showFitStatus(text, isError = false) {
  ui.fitStatus.textContent = text;
  ui.fitStatus.classList.toggle('error', isError);
}

/** Seconds as the fit's status says them. */
function duration(seconds) {
  if (seconds < 60) return `${seconds.toFixed(1)} s`;
  return `${Math.floor(seconds / 60)} min ${Math.round(seconds % 60)} s`;
}

/**
 * What the clip's fitted scene is and how it scores ('' when it has none), then the fit's notes
 * (a camera that probably moved). The held-out frames' PSNR is the reconstruction's quality on
 * frames the fit never trained on, beside the feed-forward scene's on the same frames.
 */
function fittedSummary(fitted) {
  if (!fitted) return '';
  const dB = (v) => `${v.toFixed(1)} dB`;
  const held = fitted.holdout_frames.length;
  let score;
  if (fitted.holdout_psnr !== null && held > 0) {
    const against =
      fitted.holdout_psnr_feed_forward !== null ? ` against ${dB(fitted.holdout_psnr_feed_forward)} feed-forward` : '';
    score =
      `held-out PSNR ${dB(fitted.holdout_psnr)} fitted${against}, ` +
      `on ${held} source frame${held === 1 ? '' : 's'} the fit never trained on`;
  } else {
    const trained = fitted.train_psnr !== null ? ` (PSNR ${dB(fitted.train_psnr)} on its training frames)` : '';
    score = `no frames held out${trained}`;
  }
  return (
    `Fitted scene (${fitted.preset}): ${fitted.steps} steps on ${fitted.frames} source frames in ` +
    `${duration(fitted.seconds)}; ${fitted.gaussians.toLocaleString('en')} Gaussians ` +
    `(${fitted.static_gaussians.toLocaleString('en')} static) at ${fitted.keyframes.length} keyframes; ${score}.` +
    (fitted.notes || []).map((note) => ` Note: ${note}.`).join('')
  );
}

function showFitted(fitted) {
  showFitStatus(fittedSummary(fitted));
}

/** A fit job's record as the progress bar and a line of text. */
function showFitJob(job) {
  const p = job.progress || {};
  const ended = jobEnded(job);
  ui.fitProgress.hidden = ended;
  ui.fitCancel.hidden = ended;
  ui.fitCancel.disabled = job.cancel_requested;
  ui.fit.disabled = !ended || !state.source;
  if (p.steps) ui.fitProgress.value = p.step / p.steps;
  else ui.fitProgress.removeAttribute('value');
  // An earlier fit's scene stays the clip's when this one fails or is cancelled: say which.
  const earlier = fittedSummary(state.clip?.fitted);
  if (job.state === 'failed') {
    showFitStatus([`The fit failed: ${job.error || 'no reason given'}.`, earlier].join(' ').trim(), true);
    return;
  }
  if (job.state === 'cancelled') {
    showFitStatus(["The fit was cancelled: the clip's scenes are as they were.", earlier].join(' ').trim());
    return;
  }
  if (job.state === 'done') return;
  const parts = [];
  if (job.state === 'queued') {
    parts.push('Fit queued: waiting for a c4g-fitter worker');
    if (job.attempt > 1) parts.push(`attempt ${job.attempt} of ${job.max_attempts}`);
  } else if (p.stage === 'fitting') {
    parts.push(`Fitting: step ${p.step} of ${p.steps}`);
    if (p.loss !== undefined) parts.push(`loss ${p.loss.toFixed(4)}`);
    if (p.holdout_psnr !== undefined) parts.push(`held-out PSNR ${p.holdout_psnr.toFixed(1)} dB`);
    if (p.gaussians !== undefined) parts.push(`${p.gaussians.toLocaleString('en')} Gaussians`);
  } else if (p.stage === 'storing') {
    parts.push('Fit: storing the fitted scene');
  } else {
    parts.push("Fit: preparing (reading the clip's frames)");
  }
  if (p.elapsed_s !== undefined) parts.push(duration(p.elapsed_s));
  if (job.cancel_requested) parts.push('cancelling…');
  showFitStatus(parts.join(' · '));
}

/** Follows fit job `job` until it ends; a done fit's scene is then shown. */
function followFit(job) {
  state.fit?.controller.abort();
  const fit = {
    id: job.id,
    clip: job.clip_id,
    record: job,
    stages: [],
    controller: new AbortController(),
    error: null,
  };
  state.fit = fit;
  const seen = (record) => {
    if (state.fit !== fit) return;
    fit.record = record;
    const stage = record.state === 'running' ? record.progress?.stage || 'running' : record.state;
    if (fit.stages.at(-1) !== stage) fit.stages.push(stage);
    showFitJob(record);
  };
  seen(job);
  followJob(job.id, seen, fit.controller.signal)
    .then((record) => {
      // A failure from here on is the page's (reading the clip, loading the sets), not the fit's.
      if (record.state === 'done' && state.fit === fit) fitDone(fit).catch(fail);
    })
    .catch((error) => {
      if (state.fit !== fit || fit.controller.signal.aborted) return;
      fit.error = error.message || String(error);
      ui.fit.disabled = false;
      ui.fitCancel.hidden = true;
      ui.fitProgress.hidden = true;
      showFitStatus(`Lost the fit's progress: ${fit.error}`, true);
    });
}

/** The fit is done: the clip's record now lists its fitted scene, which the canvas switches to. */
async function fitDone(fit) {
  const clip = await getJson(`/v1/clips/${encodeURIComponent(fit.clip)}`);
  if (state.fit !== fit || state.clip?.id !== fit.clip) return;
  state.clip = clip;
  setSceneOptions(clip);
  showFitted(clip.fitted);
  ui.scene.value = 'fitted';
  await changeScene();
}

async function startFit() {
  if (!state.clip || fitRunning()) return;
  ui.fit.disabled = true;
  showFitStatus('Fit: asking the server…');
  try {
    const id = state.clip.id;
    const body = { preset: ui.fitPreset.value, ...state.fitExtra };
    const job = await (await postJson(`/v1/clips/${encodeURIComponent(id)}/fit`, body)).json();
    if (state.clip?.id === id) followFit(job);
  } catch (error) {
    ui.fit.disabled = false;
    showFitStatus(`The server did not take the fit: ${error.message || error}`, true);
  }
}

async function cancelFit() {
  const fit = state.fit;
  if (!fit) return;
  ui.fitCancel.disabled = true;
  try {
    // The events then say when it stopped.
    await postJson(`/v1/jobs/${encodeURIComponent(fit.id)}/cancel`, {});
  } catch (error) {
    ui.fitCancel.disabled = false;
    showFitStatus(`The fit could not be cancelled: ${error.message || error}`, true);
  }
}

/** Follows the clip's fit that is queued or running (started earlier, or by someone else). */
async function followActiveFit(clipId) {
  const { jobs } = await getJson('/v1/jobs');
  const active = jobs.filter((j) => j.kind === 'fit' && j.clip_id === clipId && !jobEnded(j)).at(-1);
  if (active && state.clip?.id === clipId && !state.fit) followFit(active);
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
  ui.difference.addEventListener('change', () => paintComparison());
  ui.scene.addEventListener('change', () => changeScene().catch(fail));
  ui.fit.addEventListener('click', () => startFit());
  ui.fitCancel.addEventListener('click', () => cancelFit());
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
  /** The scene picked, the one the canvas's sets came from, and whether the clip has a fitted one. */
  scene: () => ({
    picked: ui.scene.value,
    served: state.source?.served || null,
    fitted: Boolean(state.clip?.fitted),
    fittedEnabled: !ui.scene.querySelector('option[value="fitted"]').disabled,
    text: ui.sceneShown.value,
  }),
  /** The fit the page follows: its job, state, progress, the stages seen, its status line. */
  fit: () =>
    state.fit && {
      id: state.fit.id,
      state: state.fit.record.state,
      progress: state.fit.record.progress,
      stages: state.fit.stages,
      error: state.fit.error,
      text: ui.fitStatus.textContent,
    },
  /** The input frame beside the canvas, and the time it is shown for. */
  input: () => ({
    ...state.input,
    at: state.inputFor,
    shown: !ui.inputFigure.hidden,
    caption: ui.inputCaption.textContent,
  }),
  /** Fields the Fit button adds to its request (a test's tiny fit). */
  fitOptions: (extra) => {
    state.fitExtra = { ...extra };
  },
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
