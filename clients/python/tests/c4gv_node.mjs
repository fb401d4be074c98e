// Decodes a C4GV stream with the browser viewer's reader (server/viewer/c4gv.js) under Node and
// writes its sets as C4GS f32, for tests/test_stream.py to compare with the Python decoder.
//   node c4gv_node.mjs VIEWER/c4gv.js STREAM.c4gv OUT.c4gs
import { readFileSync, writeFileSync } from 'node:fs';

const [viewer, input, output] = process.argv.slice(2);
// The viewer's files are ES modules outside any package: import the source as a data URL.
const source = readFileSync(viewer, 'utf8');
const { C4GVDecoder } = await import('data:text/javascript,' + encodeURIComponent(source));

const decoder = new C4GVDecoder();
decoder.feed(new Uint8Array(readFileSync(input)));
const frames = [];
for (let frame = await decoder.next(); frame; frame = await decoder.next()) frames.push(frame);
decoder.finish();

const n = frames.length ? frames[0].count : 0;
const header = Buffer.alloc(16);
header.write('C4GS', 0, 'latin1');
header.writeUInt16LE(1, 4);
header.writeUInt32LE(frames.length, 8);
header.writeUInt32LE(n, 12);
const parts = [header];
for (const f of frames) {
  const time = Buffer.alloc(8);
  time.writeDoubleLE(f.t, 0);
  parts.push(time);
  for (const column of [f.means, f.scales, f.rotations, f.opacities, f.colors]) {
    parts.push(Buffer.from(column.buffer, column.byteOffset, column.byteLength));
  }
}
writeFileSync(output, Buffer.concat(parts));
