// Drives the viewer in Chromium for tests/e2e/viewer.rs, which starts the server, uploads the
// moving clip, runs this script and judges what it writes (PSNR against the server's renders).
//
//   node viewer.mjs --base http://127.0.0.1:PORT --clip ID --static-frame frame.png --out DIR
//                   [--size 256] [--chromium /usr/bin/chromium] [--fit 1]
//
// In DIR: moving-0.png, moving-1.png, moving-2.png (the canvas at three times, the last from an
// orbited camera, with sets from the compact stream at a fine bound, `?position_error=1e-4`),
// moving-default.png (the last time again, with the stream at its default bound, as a user's page
// fetches it), moving-exact.png (the same with exact f32 sets from the older C4GS transport,
// `?precision=f32`), static-0.png and static-1.png (a clip of one frame repeated, uploaded
// through the page's file input, at its second and last time), download.ply and download.splat
// (the download buttons' files; download.ply_zip, download.spz_zip and download.splatv the
// whole clip's), page.png (the page showing a comparison) and result.json: for
// each screenshot the render request of the view it shows (time, camera, size), the PSNR the
// page's own "Compare with server" reported in each view mode, the frames playing showed, and
// for each page where its sets came from (`frames`: kind, bytes received, sets loaded).
//
// Also: input-0.png, input-1.png, input-2.png (the input frame shown beside the canvas at each of
// the moving clip's three views, as the page has it) with what the page says of it (`input`);
// compare-view.png and difference.png (the canvas at the last colour comparison, and the page's
// "show the difference" image of it) with the gain it states (`difference`); and, when given
// `--fit 1` (a c4g-fitter worker serves the server), the page's own fits of the moving clip: a
// long one followed until it reports steps and then cancelled, a tiny one to the end, after which
// the page shows the fitted scene, then the feed-forward one, then the fitted one again, with a
// screenshot and the render request of each (fitted.png, feed-forward.png, fitted-again.png) and
// what the page said (`fit`).

import { chromium } from 'playwright-core';
import { mkdir, readFile, writeFile } from 'node:fs/promises';
import path from 'node:path';

const TIMEOUT_MS = 180_000;

function args() {
  const out = { size: '256', chromium: '/usr/bin/chromium' };
  const argv = process.argv.slice(2);
  for (let i = 0; i < argv.length; i += 2) {
    if (!argv[i].startsWith('--') || argv[i + 1] === undefined) throw new Error(`bad argument ${argv[i]}`);
    out[argv[i].slice(2).replace(/-(.)/g, (_, c) => c.toUpperCase())] = argv[i + 1];
  }
  for (const needed of ['base', 'clip', 'staticFrame', 'out']) {
    if (!out[needed]) throw new Error(`--${needed} is required`);
  }
  return out;
}

const viewerState = (page) => page.evaluate(() => window.c4gViewer?.state() ?? null);

/** Waits until the page shows frame `index` of clip `clip` with nothing left to draw. */
async function settled(page, index, clip) {
  await page.waitForFunction(
    ([i, c]) => {
      const s = window.c4gViewer?.state();
      if (!s) return false;
      if (s.error) return true;
      return (c === null || s.clip === c) && !s.dirty && s.shown.index === i;
    },
    [index, clip],
    { timeout: TIMEOUT_MS, polling: 50 },
  );
  // Two animation frames: the last draw is presented, not only issued.
  await page.evaluate(() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r))));
  const s = await viewerState(page);
  if (s.error) throw new Error(`the viewer reports: ${s.error}`);
  return s;
}

/**
 * Where the page's sets came from, once all of them have arrived: `c4gViewer`'s `frames` (kind,
 * bytes, requests, bound) and how many sets those bytes brought.
 */
async function frameSource(page) {
  await page.waitForFunction(
    () => {
      const s = window.c4gViewer.state();
      return s.error || s.loaded === s.times.length;
    },
    null,
    { timeout: TIMEOUT_MS, polling: 50 },
  );
  const s = await viewerState(page);
  if (s.error) throw new Error(`the viewer reports: ${s.error}`);
  return { ...s.frames, sets: s.loaded, count: s.shown.count };
}

/**
 * frames.js on its own, in the page, on `clip` viewed at 48 fps (29 times on the grid and the
 * span's end after them): a far scrub gives up the running stream for one at the wanted time, the
 * end comes by itself, every frame arrives; `close()` aborts the fetch; and a server that answers
 * 404 for the stream gets C4GS decodes.
 */
async function sourceChecks(page, clip) {
  const run = (fallback) =>
    page.evaluate(
      async ([id, fallback]) => {
        const { FrameSource, frameTimes } = await import('/viewer/assets/frames.js');
        const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
        const view = { id, span: [0, 0.6], source: { fps: 48 } };
        const { times, fps, grid } = frameTimes(view);
        const source = new FrameSource(view, times, { fps, grid });
        await source.want(0);
        if (fallback) {
          await source.want(2);
          source.close();
          return { kind: source.kind, loaded: source.loaded };
        }
        const far = grid - 4;
        const skipped = !source.has(far - 1);
        await source.want(far);
        await source.want(times.length - 1);
        while (source.loaded < times.length) await sleep(50);
        const ordered = times.every((t, i) => Math.abs(source.get(i).t - t) < 1e-9);
        const seek = { times: times.length, grid, skipped, ordered, requests: source.requests, bytes: source.bytes };
        // Closing as soon as the first set is in aborts the rest.
        const closing = new FrameSource(view, times, { fps, grid });
        await closing.want(0);
        closing.close();
        const [loaded, bytes] = [closing.loaded, closing.bytes];
        await sleep(1000);
        seek.closed = {
          aborted: closing.run?.controller.signal.aborted ?? null,
          loaded,
          later: closing.loaded,
          bytes,
          laterBytes: closing.bytes,
        };
        return seek;
      },
      [clip, fallback],
    );
  const seek = await run(false);
  await page.route('**/stream', (route) =>
    route.fulfill({ status: 404, contentType: 'application/json', body: '{"error": "no route", "kind": "not_found"}' }),
  );
  const fallback = await run(true);
  await page.unroute('**/stream');
  return { seek, fallback };
}

/** Moves the time slider to `index` with the keyboard, as a user would. */
async function scrub(page, index) {
  const slider = page.locator('#time');
  await slider.focus();
  await page.keyboard.press('Home');
  for (let k = 0; k < index; k++) await page.keyboard.press('ArrowRight');
}

/**
 * The canvas as PNG: its drawing buffer, as `toDataURL` gives it. (An element screenshot
 * resamples the canvas wherever the page lays it out at a fractional pixel position.)
 */
async function shoot(page, file) {
  const url = await page.evaluate(() => document.getElementById('view').toDataURL('image/png'));
  await writeFile(file, Buffer.from(url.slice(url.indexOf(',') + 1), 'base64'));
  return path.basename(file);
}

/**
 * The input frame beside the canvas once it is the one for the time shown, drawn at its own size
 * into `file` (PNG): what the page says of it (`c4gViewer.input()`), with the file's name.
 */
async function inputFrame(page, file) {
  await page.waitForFunction(
    () => {
      const [s, input] = [window.c4gViewer.state(), window.c4gViewer.input()];
      return s.error || (input.loaded && input.shown && input.clip === s.clip && input.at === s.shown.t);
    },
    null,
    { timeout: TIMEOUT_MS, polling: 50 },
  );
  const { input, url } = await page.evaluate(() => {
    const image = document.getElementById('input-view');
    const canvas = document.createElement('canvas');
    [canvas.width, canvas.height] = [image.naturalWidth, image.naturalHeight];
    canvas.getContext('2d').drawImage(image, 0, 0);
    return { input: window.c4gViewer.input(), url: canvas.toDataURL('image/png') };
  });
  await writeFile(file, Buffer.from(url.slice(url.indexOf(',') + 1), 'base64'));
  return { ...input, file: path.basename(file) };
}

/**
 * After a colour comparison: the canvas as compared (compare-view.png), then "show the
 * difference" ticked and the image it shows (difference.png) with its caption and the gain the
 * page chose; unticked again.
 */
async function differenceShown(page, out) {
  const view = await shoot(page, path.join(out, 'compare-view.png'));
  await page.check('#difference');
  const url = await page.evaluate(() => document.getElementById('server-view').toDataURL('image/png'));
  await writeFile(path.join(out, 'difference.png'), Buffer.from(url.slice(url.indexOf(',') + 1), 'base64'));
  const s = await viewerState(page);
  const caption = await page.locator('#server-caption').textContent();
  await page.uncheck('#difference');
  const plain = await page.locator('#server-caption').textContent();
  return { view, file: 'difference.png', request: s.comparison.request, ...s.comparison.difference, caption, plain };
}

/** Waits until the page shows the `scene` scene's set at frame `index`, drawn. */
async function sceneShown(page, index, scene) {
  await page.waitForFunction(
    ([i, scene]) => {
      const s = window.c4gViewer.state();
      return s.error || (!s.dirty && s.shown.index === i && s.shown.scene === scene);
    },
    [index, scene],
    { timeout: TIMEOUT_MS, polling: 50 },
  );
  return settled(page, index, null);
}

/**
 * Waits until the page's fit is at `stage` ('fitting': reporting steps, or an end state:
 * 'cancelled', 'done'); what the page says of it.
 */
async function fitReached(page, stage) {
  await page.waitForFunction(
    (stage) => {
      const fit = window.c4gViewer.fit();
      if (window.c4gViewer.state().error || fit?.error) return true;
      return fit && (fit.state === stage || (fit.state === 'running' && fit.progress?.stage === stage));
    },
    stage,
    { timeout: TIMEOUT_MS, polling: 50 },
  );
  const [s, fit] = await page.evaluate(() => [window.c4gViewer.state(), window.c4gViewer.fit()]);
  if (s.error) throw new Error(`the viewer reports: ${s.error}`);
  if (fit.error) throw new Error(`the page lost the fit: ${fit.error}`);
  return fit;
}

/**
 * frames.js on its own on `clip`, which has a fitted scene now, asked for `auto` and made to start
 * further streams (a far scrub, the span's end): the scene its first answer named, and the
 * `scene` of every stream request's body (none in the first: auto is the server's default).
 */
async function pinnedScene(page, clip) {
  const scenes = [];
  const fps = 48;
  await page.route('**/stream', (route) => {
    // This source's requests only, by their step: the page's own (at the clip's 10 fps) may
    // still be loading the fitted scene it switched to.
    const body = route.request().postDataJSON();
    if (Math.abs(body.step - 1 / fps) < 1e-9) scenes.push(body.scene ?? null);
    return route.continue();
  });
  const pinned = await page.evaluate(
    async ([id, fps]) => {
      const { FrameSource, frameTimes } = await import('/viewer/assets/frames.js');
      const view = { id, span: [0, 0.6], source: { fps } };
      const { times, grid } = frameTimes(view);
      const source = new FrameSource(view, times, { fps, grid });
      await source.want(0);
      await source.want(grid - 4);
      await source.want(times.length - 1);
      source.close();
      return { served: source.served, requests: source.requests };
    },
    [clip, fps],
  );
  await page.unroute('**/stream');
  return { ...pinned, scenes };
}

/**
 * The page's own fits of `clip` with its Fit button: a long one, followed until its status
 * reports steps, then cancelled with its Cancel button (the clip still has no fitted scene); then
 * a tiny one, to the end, after which the page shows the fitted scene; then the scene picker to
 * feed-forward and back to fitted, a screenshot and render request of each.
 */
async function fits(page, base, clip, size, out) {
  await page.goto(`${base}/viewer/${clip}?size=${size}`);
  let s = await settled(page, 0, clip);
  const last = s.times.length - 1;
  await scrub(page, last);
  await settled(page, last, clip);
  const result = { before: await page.evaluate(() => window.c4gViewer.scene()) };

  // Every 4th frame held out: the synthetic clip's 7 frames are under the presets' 8.
  const tiny = { resolution: 32, max_frames: 8, holdout_every: 4 };
  await page.evaluate((o) => window.c4gViewer.fitOptions(o), { ...tiny, steps: 100000 });
  await page.click('#fit');
  const running = await fitReached(page, 'fitting');
  result.running = { ...running, cancelVisible: await page.locator('#fit-cancel').isVisible() };
  await page.click('#fit-cancel');
  result.cancelled = await fitReached(page, 'cancelled');
  result.afterCancel = await page.evaluate(() => window.c4gViewer.scene());

  await page.evaluate((o) => window.c4gViewer.fitOptions(o), { ...tiny, steps: 6 });
  await page.click('#fit');
  result.done = await fitReached(page, 'done');
  result.pinned = await pinnedScene(page, clip);
  result.views = [];
  for (const [name, scene] of [
    ['fitted', 'fitted'],
    ['feed-forward', 'feed-forward'],
    ['fitted-again', 'fitted'],
  ]) {
    if (name !== 'fitted') await page.selectOption('#scene', scene);
    s = await sceneShown(page, last, scene);
    result.views.push({
      name,
      t: s.times[last],
      scene: await page.evaluate(() => window.c4gViewer.scene()),
      screenshot: await shoot(page, path.join(out, `${name}.png`)),
      request: await page.evaluate(() => window.c4gViewer.request()),
    });
  }
  return result;
}

/** Clicks "Compare with server" in `mode`; the PSNR the page reports. */
async function compareIn(page, mode) {
  await page.selectOption('#mode', mode);
  const s = await viewerState(page);
  await settled(page, s.index, s.clip);
  const drawn = (await viewerState(page)).shown.draw;
  await page.click('#compare');
  await page.waitForFunction(
    (d) => {
      const s = window.c4gViewer.state();
      return s.error || (s.comparison && s.comparison.draw === d);
    },
    drawn,
    { timeout: TIMEOUT_MS, polling: 50 },
  );
  const after = await viewerState(page);
  if (after.error) throw new Error(`the viewer reports: ${after.error}`);
  return after.comparison.psnr;
}

/** Clicks a download button; the saved file's name and size. */
async function download(page, format, out) {
  const [file] = await Promise.all([page.waitForEvent('download'), page.click(`#download-${format}`)]);
  const saved = path.join(out, `download.${format}`);
  await file.saveAs(saved);
  return { name: file.suggestedFilename(), file: path.basename(saved) };
}

/** Plays until three frames have been shown, then pauses; the frames shown while playing. */
async function play(page) {
  await page.click('#play');
  await page.waitForFunction(() => window.c4gViewer.state().played.length >= 3, null, {
    timeout: TIMEOUT_MS,
    polling: 20,
  });
  await page.click('#play');
  return (await viewerState(page)).played;
}

async function main() {
  const a = args();
  await mkdir(a.out, { recursive: true });
  const browser = await chromium.launch({
    executablePath: a.chromium,
    headless: true,
    // No GPU here: WebGL2 runs on SwiftShader, Chromium's CPU implementation.
    args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-background-networking'],
  });
  const result = { browser: browser.version(), moving: [], static: [], compare: {} };
  try {
    const context = await browser.newContext({ viewport: { width: 1000, height: 800 }, deviceScaleFactor: 1 });
    const page = await context.newPage();
    page.on('console', (m) => {
      if (m.type() === 'error' || m.type() === 'warning') console.error(`[page ${m.type()}] ${m.text()}`);
    });
    page.on('pageerror', (e) => console.error(`[page error] ${e.message}`));
    page.setDefaultTimeout(TIMEOUT_MS);

    // The stream at a fine bound first: the images then differ by the renderers (and sets
    // within 1e-4 of position, 4.9e-4 of the rest) alone. Not the finest, 1e-5: its range is
    // ±10 scene units, and c4g-tiny v2 puts far walls beyond that.
    await page.goto(`${a.base}/viewer/${a.clip}?size=${a.size}&position_error=1e-4`);
    let s = await settled(page, 0, a.clip);
    result.target = s.target;
    result.footprint = s.footprint;
    result.times = s.times;
    const last = s.times.length - 1;
    // The second time and the last from the first camera (frames apart: the scene moves), then
    // the middle one from an orbited camera.
    const picks = [1, last, Math.floor(last / 2)];
    for (const [k, index] of picks.entries()) {
      await scrub(page, index);
      if (k === 2) {
        const box = await page.locator('#view').boundingBox();
        const [x, y] = [box.x + box.width / 2, box.y + box.height / 2];
        await page.mouse.move(x, y);
        await page.mouse.down();
        await page.mouse.move(x + 40, y + 16, { steps: 4 });
        await page.mouse.up();
      }
      s = await settled(page, index, a.clip);
      const request = await page.evaluate(() => window.c4gViewer.request());
      const file = await shoot(page, path.join(a.out, `moving-${k}.png`));
      const input = await inputFrame(page, path.join(a.out, `input-${k}.png`));
      result.moving.push({ index, t: s.times[index], screenshot: file, request, input });
    }
    for (const mode of ['color', 'depth', 'alpha']) result.compare[mode] = await compareIn(page, mode);
    result.compare.color = await compareIn(page, 'color');
    result.difference = await differenceShown(page, a.out);
    // The page as it looks then (for docs/viewer/): the WebGL view beside the server's.
    const bottom = await page.locator('#status').evaluate((e) => e.getBoundingClientRect().bottom);
    const right = await page.evaluate(() =>
      Math.max(...[...document.querySelectorAll('#stage > figure:not([hidden])')].map((f) => f.getBoundingClientRect().right)),
    );
    const clip = { x: 0, y: 0, width: Math.max(800, Math.ceil(right) + 14), height: Math.ceil(bottom) + 8 };
    await page.screenshot({ path: path.join(a.out, 'page.png'), clip });
    result.downloads = {};
    for (const format of ['ply', 'splat', 'ply_zip', 'spz_zip', 'splatv']) {
      result.downloads[format] = await download(page, format, a.out);
    }
    result.played = await play(page);
    result.finest = { frames: await frameSource(page) };
    Object.assign(result, await sourceChecks(page, a.clip));

    // The last time with exact sets from the older transport (C4GS f32), then as a user opens the
    // page (the stream at its default bound).
    for (const [name, query] of [['exact', '&precision=f32'], ['default', '']]) {
      await page.goto(`${a.base}/viewer/${a.clip}?size=${a.size}${query}`);
      await settled(page, 0, a.clip);
      await scrub(page, last);
      s = await settled(page, last, a.clip);
      result[name] = {
        index: last,
        t: s.times[last],
        screenshot: await shoot(page, path.join(a.out, `moving-${name}.png`)),
        request: await page.evaluate(() => window.c4gViewer.request()),
        frames: await frameSource(page),
      };
    }

    // The static clip, through the page's upload: one frame four times (fps 10: 0 to 0.3 s).
    const frame = await readFile(a.staticFrame);
    const files = [0, 1, 2, 3].map((i) => ({ name: `frame-${i}.png`, mimeType: 'image/png', buffer: frame }));
    await page.setInputFiles('#upload', files);
    await page.waitForFunction(
      (moving) => {
        const s = window.c4gViewer.state();
        return s.error || (s.clip && s.clip !== moving && !s.dirty);
      },
      a.clip,
      { timeout: TIMEOUT_MS, polling: 100 },
    );
    s = await settled(page, 0, null);
    result.staticClip = s.clip;
    result.staticUrl = new URL(page.url()).pathname;
    for (const [k, index] of [1, s.times.length - 1].entries()) {
      await scrub(page, index);
      s = await settled(page, index, result.staticClip);
      const file = await shoot(page, path.join(a.out, `static-${k}.png`));
      result.static.push({ index, t: s.times[index], screenshot: file });
    }
    if (a.fit === '1') result.fit = await fits(page, a.base, a.clip, a.size, a.out);
  } finally {
    await browser.close();
  }
  await writeFile(path.join(a.out, 'result.json'), JSON.stringify(result, null, 1));
}

main().catch((e) => {
  console.error(e.stack || String(e));
  process.exit(1);
});
