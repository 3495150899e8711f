// Decodes the golden samples (tests/protocol/golden, written by the Python encoders) with the
// viewer's decoder and prints, per manifest entry, what it made of them in the manifest's
// normalised form; tests/viewer/test_decode_js.py compares that with the Python decoders'.
//   node tests/viewer/decode_golden.mjs tests/protocol/golden
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { decodeFrame, FrameError, KeyframeAssembler, parseServerMessage, ProtocolError } from "../../server/viewer/decode.js";

const folder = process.argv[2];
const flat = (a) => Array.from(a, (v) => (v === Infinity ? "inf" : v === -Infinity ? "-inf" : v));

function normalise(d) {
  const head = () => ({ cell: d.cell, seq: d.seq, index: d.index, count: d.count, origin: flat(d.origin), ids: flat(d.ids) });
  switch (d.kind) {
    case 1: return { kind: 1, ...head(), positions: flat(d.positions), colors: flat(d.colors) };
    case 2: return { kind: 2, cell: d.cell, resolution: d.resolution, center: flat(d.center), r1: d.r1, r2: d.r2,
      range_lo: d.rangeLo, range_hi: d.rangeHi, colors: flat(d.colors), ranges: flat(d.ranges) };
    case 3: return { kind: 3, ...head(), keyframes: d.keyframes, key_start: d.keyStart, times: flat(d.times), positions: flat(d.positions) };
    case 4: return { kind: 4, ...head(), keyframes: d.keyframes, key_start: d.keyStart, times: flat(d.times),
      radii: flat(d.radii), centers: flat(d.centers), colors: flat(d.colors) };
    default: return d; // a message: already plain JSON
  }
}

async function run(entry) {
  const bytes = entry.files.map((f) => readFileSync(join(folder, f)));
  if (entry.what === "message") return parseServerMessage(bytes[0].toString("utf8"));
  if (entry.what === "frame") return decodeFrame(bytes[0]);
  const asm = new KeyframeAssembler();
  let out = null;
  for (const b of bytes) out = asm.add(await decodeFrame(b));
  if (out === null) throw new FrameError("incomplete keyframe set");
  return out;
}

const manifest = JSON.parse(readFileSync(join(folder, "manifest.json"), "utf8"));
const results = [];
for (const entry of manifest) {
  try {
    results.push({ name: entry.name, ok: true, value: normalise(await run(entry)) });
  } catch (e) {
    if (e instanceof FrameError) results.push({ name: entry.name, ok: false, error: "FrameError", message: e.message });
    else if (e instanceof ProtocolError) results.push({ name: entry.name, ok: false, error: e.code, message: e.message });
    else results.push({ name: entry.name, ok: false, error: `unexpected ${e.name}`, message: e.message });
  }
}
process.stdout.write(JSON.stringify(results));
