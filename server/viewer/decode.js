// The wire protocol of protocol/ in JavaScript: binary frames (geometry, cubemap, keyframes,
// spheres) and the server's JSON messages, with the same checks as the Python decoders
// (protocol/frames.py, cubemap.py, keyframes.py, messages.py). Imports nothing: it runs in the
// browser and under node (tests/viewer/decode_golden.mjs checks it on the Python encoder's
// frames).

export const PROTOCOL_VERSION = 4;
export const FrameKind = Object.freeze({ GEOMETRY: 1, CUBEMAP: 2, KEYFRAMES: 3, SPHERES: 4 });
const MAGIC = [0x50, 0x56, 0x53, 0x47]; // "PVSG"
const UINT32_MAX = 2 ** 32 - 1;
const INT32_MAX = 2 ** 31 - 1;

export const GEOMETRY_HEADER_BYTES = 56;
export const TRIANGLE_BYTES = 43;
export const CUBEMAP_HEADER_BYTES = 80;
export const CUBEMAP_MAX_RESOLUTION = 2048;
const MAX_RANGE_RATIO = 1e7;
const RANGE_CODES = 65534;
export const KEYFRAME_HEADER_BYTES = 64;
export const MAX_KEYFRAMES = 4096;

/** Bytes that are not a valid frame (Python: protocol.frames.FrameError). */
export class FrameError extends Error {
  constructor(message) { super(message); this.name = "FrameError"; }
}

/** A text frame that is not a valid server message (Python: protocol.messages.ProtocolError);
 * `code` is the ErrorCode the Python parser gives it. */
export class ProtocolError extends Error {
  constructor(code, message) { super(message); this.name = "ProtocolError"; this.code = code; }
}

if (new Uint8Array(new Uint16Array([1]).buffer)[0] !== 1) {
  // Typed arrays read the host's byte order; the wire is little-endian.
  throw new Error("this decoder needs a little-endian host");
}

function bytesOf(data) {
  if (data instanceof ArrayBuffer) return new Uint8Array(data);
  if (ArrayBuffer.isView(data)) return new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  throw new TypeError("a frame is an ArrayBuffer or a typed array");
}

/** A copy of `bytes` starting at offset 0 of its own buffer, so typed views are aligned. */
function aligned(bytes) {
  return bytes.byteOffset % 8 === 0 ? bytes : bytes.slice();
}

/** The kind byte (offset 6) of a frame, or null when it is too short to have one. */
export function frameKind(data) {
  const b = bytesOf(data);
  return b.length > 6 ? b[6] : null;
}

function checkHeader(b, size, kind) {
  if (b.length < size) throw new FrameError(`frame too short: ${b.length} bytes < ${size}-byte header`);
  for (let i = 0; i < 4; i++) {
    if (b[i] !== MAGIC[i]) throw new FrameError("bad magic, expected PVSG");
  }
  const dv = new DataView(b.buffer, b.byteOffset, b.byteLength);
  const version = dv.getUint16(4, true);
  if (version !== PROTOCOL_VERSION) {
    throw new FrameError(`frame version ${version}, this code speaks ${PROTOCOL_VERSION}`);
  }
  if (b[6] !== kind) throw new FrameError(`frame kind ${b[6]} is not ${kind}`);
  return dv;
}

function allFinite(a) {
  for (let i = 0; i < a.length; i++) if (!Number.isFinite(a[i])) return false;
  return true;
}

function origin(dv, at) {
  const o = [dv.getFloat64(at, true), dv.getFloat64(at + 8, true), dv.getFloat64(at + 16, true)];
  if (!allFinite(o)) throw new FrameError("non-finite origin");
  return o;
}

function checkIds(ids, what) {
  for (let i = 0; i < ids.length; i++) if (ids[i] < 0) throw new FrameError(`negative ${what}`);
}

// ------------------------------------------------------------------------------ geometry
/** Size in bytes of a geometry frame of `n` triangles. */
export function geometryFrameBytes(n) { return GEOMETRY_HEADER_BYTES + TRIANGLE_BYTES * n; }

/** A geometry frame: {kind, cell, seq, index, count, origin [3], ids Int32Array(n),
 * positions Float32Array(9n) corners minus origin, colors Uint8Array(3n)}. */
export function decodeGeometry(data) {
  const b = aligned(bytesOf(data));
  const dv = checkHeader(b, GEOMETRY_HEADER_BYTES, FrameKind.GEOMETRY);
  const flags = b[7];
  const cell = dv.getInt32(8, true);
  const seq = dv.getUint32(12, true);
  const index = dv.getUint32(16, true);
  const count = dv.getUint32(20, true);
  const n = dv.getUint32(24, true);
  const reserved = dv.getUint32(28, true);
  if (flags !== 0 || reserved !== 0) {
    throw new FrameError(`reserved header fields must be 0 (flags=${flags}, reserved=${reserved})`);
  }
  if (count < 1 || index >= count) throw new FrameError(`chunk index ${index} out of range for count ${count}`);
  const expected = geometryFrameBytes(n);
  if (b.length !== expected) throw new FrameError(`frame of ${n} triangles must be ${expected} bytes, got ${b.length}`);
  const o = origin(dv, 32);
  let p = b.byteOffset + GEOMETRY_HEADER_BYTES;
  const ids = new Int32Array(b.buffer.slice(p, p + 4 * n));
  p += 4 * n;
  const positions = new Float32Array(b.buffer.slice(p, p + 36 * n));
  p += 36 * n;
  const colors = new Uint8Array(b.buffer.slice(p, p + 3 * n));
  checkIds(ids, "triangle id");
  if (!allFinite(positions)) throw new FrameError("non-finite triangle positions");
  return { kind: FrameKind.GEOMETRY, cell, seq, index, count, origin: o, ids, positions, colors };
}

// ------------------------------------------------------------------------------ cubemap
/** Worst-case relative error of decoded ranges (protocol.cubemap.range_precision). */
export function rangePrecision(lo, hi) {
  if (!(lo > 0) || hi < lo) return 0;
  return Math.expm1(Math.log(hi / lo) / (2 * RANGE_CODES)) + 2 ** -23;
}

/** Float32Array ranges (metres, +Infinity for code 0) of uint16 `codes`. */
export function decodeRanges(codes, lo, hi) {
  const out = new Float32Array(codes.length);
  const span = hi === lo ? 0 : Math.log(hi / lo);
  for (let i = 0; i < codes.length; i++) {
    const c = codes[i];
    if (c === 0) out[i] = Infinity;
    else out[i] = span === 0 ? lo : lo * Math.exp((c - 1) * (span / RANGE_CODES));
  }
  return out;
}

async function inflate(bytes, rawLength) {
  // zlib stream (RFC 1950), as Python's zlib.compress writes it. Output past rawLength is
  // refused as it arrives: a small frame cannot expand into a large allocation.
  const out = new Uint8Array(rawLength);
  let got = 0;
  const ds = new DecompressionStream("deflate");
  const writer = ds.writable.getWriter();
  const written = writer.write(bytes).then(() => writer.close()).catch(() => {});
  const reader = ds.readable.getReader();
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      if (got + value.length > rawLength) {
        throw new FrameError(`compressed payload does not hold exactly ${rawLength} bytes`);
      }
      out.set(value, got);
      got += value.length;
    }
  } catch (e) {
    reader.cancel().catch(() => {});
    if (e instanceof FrameError) throw e;
    throw new FrameError(`corrupt compressed payload: ${e.message}`);
  } finally {
    await written;
  }
  if (got !== rawLength) throw new FrameError(`compressed payload does not hold exactly ${rawLength} bytes`);
  // A zlib stream ends with the Adler-32 of its data. Some DecompressionStreams ignore bytes
  // after the end of the stream, which Python's decoder refuses: the payload's last 4 bytes
  // must be that checksum.
  const n = bytes.length;
  const tail = n >= 4 ? ((bytes[n - 4] << 24) | (bytes[n - 3] << 16) | (bytes[n - 2] << 8) | bytes[n - 1]) >>> 0 : -1;
  if (tail !== adler32(out)) throw new FrameError("compressed payload has bytes after its end");
  return out;
}

function adler32(data) {
  let a = 1, b = 0;
  for (let i = 0; i < data.length; i += 4096) {
    const end = Math.min(data.length, i + 4096);
    for (let j = i; j < end; j++) { a += data[j]; b += a; }
    a %= 65521;
    b %= 65521;
  }
  return ((b << 16) | a) >>> 0;
}

/** A cubemap frame (async: its payload may be zlib-compressed): {kind, cell, resolution,
 * center [3], r1, r2, rangeLo, rangeHi, colors Uint8Array(6 R R 3), ranges Float32Array(6 R R)
 * metres from the centre, +Infinity where empty}. Faces +X, -X, +Y, -Y, +Z, -Z, row 0 on top. */
export async function decodeCubemap(data) {
  const b = aligned(bytesOf(data));
  const dv = checkHeader(b, CUBEMAP_HEADER_BYTES, FrameKind.CUBEMAP);
  const flags = b[7];
  const cell = dv.getInt32(8, true);
  const res = dv.getUint32(12, true);
  const f64 = (at) => dv.getFloat64(at, true);
  const [r1, r2, lo, hi] = [f64(40), f64(48), f64(56), f64(64)];
  const plen = dv.getUint32(72, true);
  const reserved = dv.getUint32(76, true);
  if ((flags & ~1) !== 0 || reserved !== 0) {
    throw new FrameError(`unknown flags ${flags} or non-zero reserved field ${reserved}`);
  }
  if (!(res >= 1 && res <= CUBEMAP_MAX_RESOLUTION)) {
    throw new FrameError(`resolution ${res} out of range [1, ${CUBEMAP_MAX_RESOLUTION}]`);
  }
  const center = [f64(16), f64(24), f64(32)];
  if (!allFinite(center)) throw new FrameError("non-finite cubemap centre");
  if (!(Number.isFinite(r1) && Number.isFinite(r2) && r1 > 0 && r1 < r2)) {
    throw new FrameError(`need finite radii 0 < r1 < r2, got r1=${r1}, r2=${r2}`);
  }
  if (!(Number.isFinite(lo) && Number.isFinite(hi) && lo >= 0 && lo <= hi)
      || ((lo === 0) !== (hi === 0)) || (lo > 0 && hi / lo > MAX_RANGE_RATIO * (1 + 1e-9))) {
    throw new FrameError(`bad range bounds [${lo}, ${hi}]`);
  }
  if (b.length !== CUBEMAP_HEADER_BYTES + plen) {
    throw new FrameError(`frame must be ${CUBEMAP_HEADER_BYTES + plen} bytes, got ${b.length}`);
  }
  const rawLength = 6 * res * res * 5;
  const payload = b.subarray(CUBEMAP_HEADER_BYTES);
  let raw;
  if (flags & 1) raw = await inflate(payload, rawLength);
  else {
    if (payload.length !== rawLength) throw new FrameError(`payload must be ${rawLength} bytes, got ${payload.length}`);
    raw = payload.slice();
  }
  const n = 6 * res * res;
  const colors = raw.slice(0, 3 * n);
  const codes = new Uint16Array(raw.buffer.slice(raw.byteOffset + 3 * n, raw.byteOffset + 5 * n));
  if (hi === 0 && codes.some((c) => c !== 0)) {
    throw new FrameError("range codes present but the range bounds are empty");
  }
  return {
    kind: FrameKind.CUBEMAP, cell, resolution: res, center, r1, r2, rangeLo: lo, rangeHi: hi,
    colors, ranges: decodeRanges(codes, lo, hi),
  };
}

// ------------------------------------------------------------------------------ keyframes
/** Size in bytes of a keyframe (kind 3) or sphere (kind 4) frame of n items, m keyframes. */
export function keyframeFrameBytes(kind, n, m) {
  const [fixed, perKey] = kind === FrameKind.KEYFRAMES ? [4, 36] : [11, 12];
  return KEYFRAME_HEADER_BYTES + 8 * m + n * (fixed + perKey * m);
}

function keyframeHeader(data, kind) {
  const b = aligned(bytesOf(data));
  const dv = checkHeader(b, KEYFRAME_HEADER_BYTES, kind);
  const u32 = (at) => dv.getUint32(at, true);
  const flags = b[7];
  const cell = dv.getInt32(8, true);
  const [seq, index, count, n, k, j0, m] = [12, 16, 20, 24, 28, 32, 36].map(u32);
  if (flags !== 0) throw new FrameError(`reserved flags must be 0, got ${flags}`);
  if (count < 1 || index >= count) throw new FrameError(`chunk index ${index} out of range for count ${count}`);
  if (!(k >= 1 && k <= MAX_KEYFRAMES)) throw new FrameError(`keyframe count ${k} out of range [1, ${MAX_KEYFRAMES}]`);
  if (m < 1 || j0 + m > k) throw new FrameError(`keyframes ${j0}..${j0 + m - 1} out of range for ${k}`);
  const expected = keyframeFrameBytes(kind, n, m);
  if (b.length !== expected) {
    throw new FrameError(`frame of ${n} items and ${m} keyframes must be ${expected} bytes, got ${b.length}`);
  }
  const o = origin(dv, 40);
  let p = b.byteOffset + KEYFRAME_HEADER_BYTES;
  const times = new Float64Array(b.buffer.slice(p, p + 8 * m));
  for (let i = 0; i < m; i++) {
    if (!Number.isFinite(times[i]) || (i > 0 && !(times[i] > times[i - 1]))) {
      throw new FrameError("keyframe times must be finite and strictly increasing");
    }
  }
  p += 8 * m;
  const ids = new Int32Array(b.buffer.slice(p, p + 4 * n));
  checkIds(ids, "id");
  p += 4 * n;
  return { b, p, head: { cell, seq, index, count, origin: o, ids, keyframes: k, keyStart: j0, times } };
}

/** A triangle keyframe frame: header fields plus positions Float32Array(m n 9), corners minus
 * origin, keyframe-major (as protocol.keyframes: positions[m, n, 3, 3]). */
export function decodeKeyframes(data) {
  const { b, p, head } = keyframeHeader(data, FrameKind.KEYFRAMES);
  const m = head.times.length;
  const n = head.ids.length;
  const positions = new Float32Array(b.buffer.slice(p, p + 36 * m * n));
  if (!allFinite(positions)) throw new FrameError("non-finite keyframe positions");
  return { kind: FrameKind.KEYFRAMES, ...head, positions };
}

/** A sphere frame: header fields plus radii Float32Array(n), centers Float32Array(m n 3) minus
 * origin, colors Uint8Array(3n). */
export function decodeSpheres(data) {
  const { b, p, head } = keyframeHeader(data, FrameKind.SPHERES);
  const m = head.times.length;
  const n = head.ids.length;
  const radii = new Float32Array(b.buffer.slice(p, p + 4 * n));
  const centers = new Float32Array(b.buffer.slice(p + 4 * n, p + 4 * n + 12 * m * n));
  const colors = new Uint8Array(b.buffer.slice(p + 4 * n + 12 * m * n, p + 4 * n + 12 * m * n + 3 * n));
  for (let i = 0; i < n; i++) {
    if (!(Number.isFinite(radii[i]) && radii[i] > 0)) throw new FrameError("sphere radii must be finite and positive");
  }
  if (!allFinite(centers)) throw new FrameError("non-finite sphere centres");
  return { kind: FrameKind.SPHERES, ...head, radii, centers, colors };
}

/** Whether a keyframe or sphere chunk holds every keyframe of its items. */
export function isComplete(chunk) {
  return chunk.keyStart === 0 && chunk.times.length === chunk.keyframes;
}

function sameIds(a, b) {
  if (a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

/** Joins the keyframe windows of one id set into one complete chunk
 * (protocol.keyframes.KeyframeAssembler): add() returns it once its last window is in. */
export class KeyframeAssembler {
  constructor() { this.parts = []; this.next = 0; this.abandoned = 0; }

  get pending() { return this.parts.length > 0; }

  add(chunk) {
    if (chunk.keyStart === 0) {
      if (this.parts.length) { this.abandoned += 1; this.reset(); }
      if (isComplete(chunk)) return chunk;
    } else {
      const first = this.parts[0];
      const last = this.parts[this.parts.length - 1];
      if (!first || chunk.keyStart !== this.next || chunk.kind !== first.kind
          || chunk.keyframes !== first.keyframes || !sameIds(chunk.ids, first.ids)
          || !(chunk.times[0] > last.times[last.times.length - 1])) {
        this.reset();
        throw new FrameError(`keyframe window starting at ${chunk.keyStart} does not continue the pending set`);
      }
    }
    this.parts.push(chunk);
    this.next = chunk.keyStart + chunk.times.length;
    if (this.next < chunk.keyframes) return null;
    const parts = this.parts;
    this.reset();
    return joinWindows(parts);
  }

  reset() { this.parts = []; this.next = 0; }
}

function joinWindows(parts) {
  const first = parts[0];
  const o = first.origin;
  const times = Float64Array.from(parts.flatMap((p) => Array.from(p.times)));
  const key = first.kind === FrameKind.KEYFRAMES ? "positions" : "centers";
  const total = parts.reduce((s, p) => s + p[key].length, 0);
  const joined = new Float32Array(total);
  let at = 0;
  for (const p of parts) {
    const d = [p.origin[0] - o[0], p.origin[1] - o[1], p.origin[2] - o[2]];
    const a = p[key];
    for (let i = 0; i < a.length; i++) joined[at + i] = a[i] + d[i % 3];
    at += a.length;
  }
  return { ...first, keyStart: 0, times, [key]: joined };
}

/** Decode any binary frame (async for cubemaps); FrameError when it is none of the kinds. */
export async function decodeFrame(data) {
  switch (frameKind(data)) {
    case FrameKind.GEOMETRY: return decodeGeometry(data);
    case FrameKind.CUBEMAP: return decodeCubemap(data);
    case FrameKind.KEYFRAMES: return decodeKeyframes(data);
    case FrameKind.SPHERES: return decodeSpheres(data);
    default: {
      const b = bytesOf(data);
      // The same message the Python geometry decoder gives a frame of another kind or none.
      if (b.length < GEOMETRY_HEADER_BYTES) throw new FrameError(`frame too short: ${b.length} bytes`);
      return decodeGeometry(data);
    }
  }
}

// ------------------------------------------------------------------------------ messages
// Checkers of JSON values, strict as pydantic's strict fields: no strings for numbers, no
// floats for integers, no booleans for either.
const isInt = (v) => typeof v === "number" && Number.isInteger(v);
const int = (lo, hi) => (v) => isInt(v) && v >= lo && v <= (hi ?? Number.MAX_SAFE_INTEGER);
const num = (v) => typeof v === "number" && Number.isFinite(v);
const str = (v) => typeof v === "string";
const bool = (v) => typeof v === "boolean";
const obj = (v) => v !== null && typeof v === "object" && !Array.isArray(v);
const vec = (n) => (v) => Array.isArray(v) && v.length === n && v.every(num);
const nullable = (check) => (v) => v === null || check(v);
const literal = (...values) => (v) => values.includes(v);
const any = () => true;
const u16 = int(0, 2 ** 16 - 1);
const u32 = int(0, UINT32_MAX);
const id32 = int(0, INT32_MAX);
const count32 = int(0, INT32_MAX + 1);
const nonneg = int(0);
const ANSWER = literal("full", "known", "first", "refined");
const paramValue = (v) => v === null || bool(v) || num(v) || str(v)
  || (Array.isArray(v) && v.every((x) => x === null || bool(x) || num(x) || str(x)));
const params = (v) => obj(v) && Object.values(v).every(paramValue);

// {field: [check, required]}; unknown fields are refused, as the Python schemas do.
function schema(fields) {
  return (v) => {
    if (!obj(v)) return "not an object";
    for (const k of Object.keys(v)) if (!(k in fields)) return `${k}: extra inputs are not permitted`;
    for (const [k, [check, required]] of Object.entries(fields)) {
      if (!(k in v)) { if (required) return `${k}: field required`; continue; }
      const bad = check(v[k]);
      if (bad === false) return `${k}: invalid value`;
      if (typeof bad === "string") return `${k}.${bad}`;
    }
    return true;
  };
}

const SCENE_INFO = schema({
  name: [str, true], kind: [literal("file", "generated", "memory"), true],
  triangles: [count32, true], valid_triangles: [count32, true], vertices: [nonneg, true],
  objects: [count32, true], spheres: [count32], dynamic: [bool], states: [nonneg],
  bounds: [(v) => Array.isArray(v) && v.length === 2 && v.every(vec(3)), true],
  degenerate: [(v) => obj(v) && Object.values(v).every(nonneg)],
  source: [(v) => obj(v) && Object.values(v).every((x) => str(x) || num(x))],
});
const GRID_INFO = schema({
  cell_size: [num, true], origin_xz: [vec(2), true], cells: [count32, true],
  levels: [nonneg, true], eye_range: [vec(2), true],
  bounds: [(v) => Array.isArray(v) && v.length === 2 && v.every(vec(3)), true],
});
const LIMITS = schema({ max_frame_bytes: [nonneg, true], max_message_bytes: [nonneg, true] });

const SERVER_SCHEMAS = {
  welcome: schema({
    type: [any, true], version: [u16], session: [str, true], scene: [SCENE_INFO, true],
    grid: [GRID_INFO, true], core: [str, true], params: [params, true],
    budget: [nullable(int(1, UINT32_MAX))], limits: [LIMITS, true], prefetch: [bool],
    features: [obj], near_plane: [(v) => num(v) && v > 0, true],
  }),
  cell_begin: schema({
    type: [any, true], cell: [id32, true], seq: [u32, true], triangles: [count32, true],
    new: [count32, true], chunks: [u32, true], prefetch: [bool], near_far: [nullable(obj)],
    answer: [ANSWER],
  }),
  cell_end: schema({
    type: [any, true], cell: [id32, true], seq: [u32, true], seconds: [num, true],
    compute_seconds: [num], cached: [bool], prefetch: [bool], partial: [bool], answer: [ANSWER],
  }),
  drop: schema({
    type: [any, true], ids: [(v) => Array.isArray(v) && v.every(id32), true],
    cells: [(v) => Array.isArray(v) && v.every(id32)], reason: [str],
  }),
  error: schema({
    type: [any, true], code: [str, true], message: [str, true], fatal: [bool],
    seq: [nullable(u32)],
  }),
};

const DEFAULTS = {
  welcome: { version: PROTOCOL_VERSION, budget: null, prefetch: false, features: {} },
  cell_begin: { prefetch: false, near_far: null, answer: "full" },
  cell_end: { compute_seconds: 0, cached: false, prefetch: false, partial: false, answer: "full" },
  drop: { cells: [], reason: "budget" },
  error: { fatal: false, seq: null },
};

/** The server message in a text frame, its defaults filled in; ProtocolError (with the code
 * protocol.messages.parse_server_message gives) otherwise. */
export function parseServerMessage(text) {
  let v;
  try {
    v = JSON.parse(text);
  } catch (e) {
    throw new ProtocolError("bad_json", `not valid JSON: ${e.message}`);
  }
  if (!obj(v)) throw new ProtocolError("bad_json", "a message is a JSON object");
  if (typeof v.type !== "string") throw new ProtocolError("invalid_message", "a message needs a string 'type' field");
  const check = SERVER_SCHEMAS[v.type];
  if (!check) throw new ProtocolError("unknown_type", `unknown server message type ${JSON.stringify(v.type.slice(0, 64))}`);
  const ok = check(v);
  if (ok !== true) throw new ProtocolError("invalid_message", `invalid ${v.type}: ${ok}`);
  return { ...DEFAULTS[v.type], ...v };
}

/** The JSON text of a hello (protocol.messages.Hello); null fields are left out. */
export function helloMessage({ scene, core = null, params = {}, budget = null, prefetch = null,
  progressive = null }) {
  const m = { type: "hello", version: PROTOCOL_VERSION, scene, params };
  if (core !== null) m.core = core;
  if (budget !== null) m.budget = budget;
  if (prefetch !== null) m.prefetch = prefetch;
  if (progressive !== null) m.progressive = progressive;
  return JSON.stringify(m);
}

/** The JSON text of a pose: seq (uint32), t seconds, position and forward [x, y, z] metres,
 * optional velocity m/s. */
export function poseMessage(seq, t, position, forward, velocity = null) {
  const m = { type: "pose", seq, t, position: Array.from(position), forward: Array.from(forward) };
  if (velocity) m.velocity = Array.from(velocity);
  return JSON.stringify(m);
}
