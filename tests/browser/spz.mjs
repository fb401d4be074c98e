// Reads .spz files with the SPZ format's own reference library and prints what it finds as JSON,
// so that tests/e2e can check the service's SPZ exports against the reference rather than
// against our own decoder. `@adobe/spz` is the npm WebAssembly build of nianticlabs/spz, the
// format's reference C++ library.
//
//   node tests/browser/spz.mjs FILE.spz [FILE.spz ...]
//
// prints one object to stdout:
//   {"library": "@adobe/spz 0.2.3",
//    "files": [{"file", "numPoints", "shDegree",
//               "positions": [[x, y, z]], "scales": [[sx, sy, sz]], "rotations": [[w, x, y, z]],
//               "opacities": [o], "colors": [[r, g, b]]}]}
// and exits non-zero, with the reason on stderr, when a file cannot be read or loaded.
//
// Every file is loaded with `to: RDF`, the service's OpenCV axes (x right, y down, z forward):
// the library converts from the RUB axes SPZ stores. Its GaussianCloud holds the values as a
// trainer keeps them, so this script converts them to the service's activated ones:
// - scales: the library returns ln(scale); printed linear, exp(·);
// - alphas: the library returns the logit of opacity (±Infinity for the bytes 255 and 0);
//   printed activated, 1 / (1 + exp(−·)), which maps ±Infinity to 1 and 0;
// - colors: the library returns the degree-0 SH coefficient f_dc; printed 0.5 + C0 · f_dc;
// - rotations: the library returns x, y, z, w; printed w, x, y, z.
// Positions are printed as returned. SH coefficients beyond degree 0 are not printed.
//
// The library logs to stdout through Emscripten's `print`; that goes to stderr here, so that
// stdout holds the JSON alone.

import { readFileSync } from 'node:fs';
import createSpzModule from '@adobe/spz';

const LIBRARY = '@adobe/spz 0.2.3';
// The degree-0 spherical-harmonic constant, 1 / (2 √π).
const SH_C0 = 0.28209479177387814;

function fail(message) {
  process.stderr.write(`spz.mjs: ${message}\n`);
  process.exit(1);
}

const files = process.argv.slice(2);
if (files.length === 0) {
  fail('usage: node tests/browser/spz.mjs FILE.spz [FILE.spz ...]');
}

const spz = await createSpzModule({
  print: (line) => process.stderr.write(`${line}\n`),
  printErr: (line) => process.stderr.write(`${line}\n`),
});

const triples = (a) => Array.from({ length: a.length / 3 }, (_, i) => [a[3 * i], a[3 * i + 1], a[3 * i + 2]]);
const sigmoid = (v) => 1 / (1 + Math.exp(-v));

const out = { library: LIBRARY, files: [] };
for (const file of files) {
  let bytes;
  try {
    bytes = new Uint8Array(readFileSync(file));
  } catch (e) {
    fail(`${file}: cannot read: ${e.message}`);
  }
  let cloud;
  try {
    cloud = spz.loadSpzFromBuffer(bytes, { to: spz.CoordinateSystem.RDF });
  } catch (e) {
    fail(`${file}: the library threw: ${e?.message ?? e}`);
  }
  // The library reports a failed load as a cloud of no points (its reason goes to stderr); it
  // also refuses to load a file of no points, so 0 is never a success.
  if (!cloud || cloud.numPoints === 0) {
    fail(`${file}: the library loaded no points (a failed load; its log above says why)`);
  }
  const n = cloud.numPoints;
  const lengths = { positions: 3, scales: 3, rotations: 4, alphas: 1, colors: 3 };
  for (const [name, width] of Object.entries(lengths)) {
    if (cloud[name].length !== n * width) {
      fail(`${file}: ${name} holds ${cloud[name].length} values for ${n} points`);
    }
  }
  const r = cloud.rotations;
  out.files.push({
    file,
    numPoints: n,
    shDegree: cloud.shDegree,
    positions: triples(cloud.positions),
    scales: triples(cloud.scales.map(Math.exp)),
    rotations: Array.from({ length: n }, (_, i) => [r[4 * i + 3], r[4 * i], r[4 * i + 1], r[4 * i + 2]]),
    opacities: Array.from(cloud.alphas, sigmoid),
    colors: triples(cloud.colors.map((dc) => 0.5 + SH_C0 * dc)),
  });
}
process.stdout.write(`${JSON.stringify(out)}\n`);
