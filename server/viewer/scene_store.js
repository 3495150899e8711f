// The viewer's geometry store (client/store.py in the browser): the triangles received so far
// by id, in a pool of GPU-ready slots, plus keyframes of moving triangles and spheres.
//
// Each held triangle owns one slot of `positions` (9 float32, metres from the store's origin)
// and `colors` (9 uint8, its shaded colour per corner); a dropped triangle's slot is zeroed (a
// degenerate triangle draws nothing) and reused. Slots written since the renderer last looked
// are listed by takeDirty(), so each geometry frame is uploaded as it arrives, only its slots.
// Memory is bounded by the scene: ids outside [0, scene triangles) are refused, one slot per id.
// Moving triangles (those with keyframes) keep a zeroed slot and are drawn at scene time t from
// movingAt(t); spheres from spheresAt(t). Imports nothing but the shading.

import { shadeInto, unitIcosphere } from "./shading.js";

const FIRST_CAPACITY = 1 << 14;
const MAX_DIRTY_RANGES = 64;

/** Items at shared keyframe times (client/store.py's _Tracks): times Float64Array(k), per id
 * the positions at every keyframe (float64, metres from the store origin). */
class Tracks {
  constructor(perKey) { this.perKey = perKey; this.times = null; this.byId = new Map(); }

  add(ids, times, valuesOf) {
    if (this.times === null || !sameTimes(this.times, times)) {
      if (this.byId.size) throw new Error("keyframe times differ from the held ones");
      this.times = Float64Array.from(times);
    }
    for (let i = 0; i < ids.length; i++) this.byId.set(ids[i], valuesOf(i));
  }

  /** (i, j, w): the value at t is (1 - w) key[i] + w key[j], clamped (keyframe_weights). */
  weights(t) {
    const k = this.times.length;
    if (k === 1 || t === null) return [0, 0, 0];
    const tc = Math.min(Math.max(t, this.times[0]), this.times[k - 1]);
    let i = 0;
    while (i < k - 2 && this.times[i + 1] <= tc) i++;
    return [i, i + 1, (tc - this.times[i]) / (this.times[i + 1] - this.times[i])];
  }

  at(values, t, out) {
    const [i, j, w] = this.weights(t);
    const n = this.perKey;
    for (let c = 0; c < n; c++) out[c] = w === 0 ? values[i * n + c] : (1 - w) * values[i * n + c] + w * values[j * n + c];
    return out;
  }
}

function sameTimes(a, b) {
  if (a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

export class SceneStore {
  /** `triangles`, `spheres`: the scene's counts as the welcome gives them (ids beyond are
   * refused); `budget`: the most triangles the viewer means to hold (null: no limit). */
  constructor({ triangles, spheres = 0, budget = null }) {
    this.sceneTriangles = triangles;
    this.sceneSpheres = spheres;
    this.budget = budget;
    this.origin = null; // float64 [3], the first frame's origin (frames share the scene's)
    this.slotOf = new Int32Array(triangles).fill(-1);
    this.capacity = 0;
    this.positions = new Float32Array(0);
    this.colors = new Uint8Array(0);
    this.rawColors = new Uint8Array(0); // unshaded RGB per slot (moving triangles reshade)
    this.idOf = new Int32Array(0);
    this.used = 0; // slots ever used (the draw range)
    this.free = [];
    this.count = 0;
    /** Bumps when the arrays are replaced (grown): the renderer then uploads them whole. */
    this.layout = 0;
    this.version = 0;
    this.dirty = [];
    this.keys = new Tracks(9);
    this.spheres = new Tracks(3);
    this.sphereInfo = new Map(); // id -> {radius, rgb}
  }

  setOrigin(o) { if (this.origin === null) this.origin = [o[0], o[1], o[2]]; }

  // ------------------------------------------------------------------------------ writing
  /** Add a decoded geometry frame (decode.js); throws (adding nothing) for ids outside the
   * scene. Shades each face from its float64 corners, as the Python client does. */
  addGeometry(chunk) {
    const { ids, positions, colors } = chunk;
    this.checkIds(ids, this.sceneTriangles, "triangle");
    this.setOrigin(chunk.origin);
    const d = [chunk.origin[0] - this.origin[0], chunk.origin[1] - this.origin[1], chunk.origin[2] - this.origin[2]];
    const abs = new Float64Array(9);
    let lo = Infinity, hi = -1;
    for (let t = 0; t < ids.length; t++) {
      const id = ids[t];
      let slot = this.slotOf[id];
      if (slot < 0) {
        slot = this.allocate();
        this.slotOf[id] = slot;
        this.idOf[slot] = id;
        this.count += 1;
      }
      for (let c = 0; c < 9; c++) abs[c] = positions[9 * t + c] + chunk.origin[c % 3];
      this.rawColors.set(colors.subarray(3 * t, 3 * t + 3), 3 * slot);
      if (this.keys.byId.has(id)) this.clearSlot(slot);
      else {
        for (let c = 0; c < 9; c++) this.positions[9 * slot + c] = positions[9 * t + c] + d[c % 3];
        shadeInto(abs, colors[3 * t], colors[3 * t + 1], colors[3 * t + 2], this.colors, 9 * slot);
        this.colors.copyWithin(9 * slot + 3, 9 * slot, 9 * slot + 3);
        this.colors.copyWithin(9 * slot + 6, 9 * slot, 9 * slot + 3);
      }
      lo = Math.min(lo, slot);
      hi = Math.max(hi, slot);
    }
    if (hi >= 0) this.markDirty(lo, hi + 1);
  }

  /** Add a complete keyframe chunk: each triangle's corners at every keyframe. */
  addKeyframes(chunk) {
    const { ids, times, positions } = chunk;
    this.checkIds(ids, this.sceneTriangles, "triangle");
    this.setOrigin(chunk.origin);
    const n = ids.length, k = times.length;
    this.keys.add(ids, times, (i) => {
      const out = new Float64Array(9 * k);
      for (let j = 0; j < k; j++) {
        for (let c = 0; c < 9; c++) out[9 * j + c] = positions[(j * n + i) * 9 + c] + chunk.origin[c % 3] - this.origin[c % 3];
      }
      return out;
    });
    for (const id of ids) {
      const slot = this.slotOf[id];
      if (slot >= 0) { this.clearSlot(slot); this.markDirty(slot, slot + 1); }
    }
    this.version += 1;
  }

  /** Add a complete sphere chunk: centre per keyframe, radius, colour. */
  addSpheres(chunk) {
    const { ids, times, centers, radii, colors } = chunk;
    this.checkIds(ids, this.sceneSpheres, "sphere");
    this.setOrigin(chunk.origin);
    const n = ids.length, k = times.length;
    this.spheres.add(ids, times, (i) => {
      const out = new Float64Array(3 * k);
      for (let j = 0; j < k; j++) {
        for (let c = 0; c < 3; c++) out[3 * j + c] = centers[(j * n + i) * 3 + c] + chunk.origin[c] - this.origin[c];
      }
      return out;
    });
    ids.forEach((id, i) => this.sphereInfo.set(id, { radius: radii[i], rgb: colors.subarray(3 * i, 3 * i + 3) }));
    this.version += 1;
  }

  /** Remove these triangle ids and their keyframes (absent ones are ignored); how many
   * triangles were removed. */
  drop(ids) {
    let removed = 0;
    for (const id of ids) {
      if (id < 0 || id >= this.sceneTriangles) continue;
      this.keys.byId.delete(id);
      const slot = this.slotOf[id];
      if (slot < 0) continue;
      this.slotOf[id] = -1;
      this.idOf[slot] = -1;
      this.clearSlot(slot);
      this.markDirty(slot, slot + 1);
      this.free.push(slot);
      this.count -= 1;
      removed += 1;
    }
    return removed;
  }

  clear() {
    this.drop(this.heldIds());
    this.keys = new Tracks(9);
    this.spheres = new Tracks(3);
    this.sphereInfo.clear();
  }

  // ------------------------------------------------------------------------------ reading
  has(id) { return id >= 0 && id < this.sceneTriangles && this.slotOf[id] >= 0; }

  get overBudget() { return this.budget !== null && this.count > this.budget; }

  /** Int32Array of the held ids, sorted. */
  heldIds() {
    const out = new Int32Array(this.count);
    let k = 0;
    for (let s = 0; s < this.used; s++) if (this.idOf[s] >= 0) out[k++] = this.idOf[s];
    return out.sort();
  }

  /** The dirty slot ranges [start, end) since the last call. */
  takeDirty() { const d = this.dirty; this.dirty = []; return d; }

  /** The moving triangles held, at scene time t (seconds; null: at rest): {positions
   * Float32Array(9m) from the store origin, colors Uint8Array(9m) shaded at t}. */
  movingAt(t) {
    const ids = [...this.keys.byId.keys()].filter((id) => this.slotOf[id] >= 0);
    const positions = new Float32Array(9 * ids.length);
    const colors = new Uint8Array(9 * ids.length);
    const rel = new Float64Array(9), abs = new Float64Array(9);
    ids.forEach((id, i) => {
      this.keys.at(this.keys.byId.get(id), t, rel);
      for (let c = 0; c < 9; c++) { positions[9 * i + c] = rel[c]; abs[c] = rel[c] + this.origin[c % 3]; }
      const s = 3 * this.slotOf[id];
      shadeInto(abs, this.rawColors[s], this.rawColors[s + 1], this.rawColors[s + 2], colors, 9 * i);
      colors.copyWithin(9 * i + 3, 9 * i, 9 * i + 3);
      colors.copyWithin(9 * i + 6, 9 * i, 9 * i + 3);
    });
    return { positions, colors };
  }

  /** The spheres held at scene time t, as icosphere triangles like the moving ones. */
  spheresAt(t) {
    if (!this.sphereInfo.size) return { positions: new Float32Array(0), colors: new Uint8Array(0) };
    this.unit ??= unitIcosphere(2);
    const f = this.unit.length / 9;
    const positions = new Float32Array(9 * f * this.sphereInfo.size);
    const colors = new Uint8Array(9 * f * this.sphereInfo.size);
    const centre = new Float64Array(3), abs = new Float64Array(9);
    let k = 0;
    for (const [id, { radius, rgb }] of this.sphereInfo) {
      this.spheres.at(this.spheres.byId.get(id), t, centre);
      for (let i = 0; i < f; i++, k++) {
        for (let c = 0; c < 9; c++) {
          const v = this.unit[9 * i + c] * radius + centre[c % 3];
          positions[9 * k + c] = v;
          abs[c] = v + this.origin[c % 3];
        }
        shadeInto(abs, rgb[0], rgb[1], rgb[2], colors, 9 * k);
        colors.copyWithin(9 * k + 3, 9 * k, 9 * k + 3);
        colors.copyWithin(9 * k + 6, 9 * k, 9 * k + 3);
      }
    }
    return { positions, colors };
  }

  /** Centroid (metres from the store origin) of held triangle `id`, into `out`. */
  centroid(id, out) {
    const s = 9 * this.slotOf[id];
    const track = this.keys.byId.get(id);
    const p = track ? track : this.positions;
    const at = track ? 0 : s;
    for (let c = 0; c < 3; c++) out[c] = (p[at + c] + p[at + 3 + c] + p[at + 6 + c]) / 3;
    return out;
  }

  // ------------------------------------------------------------------------------ internals
  checkIds(ids, bound, what) {
    for (let i = 0; i < ids.length; i++) {
      if (ids[i] < 0 || ids[i] >= bound) {
        throw new Error(`${what} id ${ids[i]} outside [0, ${bound}), the scene's ${what}s per the welcome`);
      }
    }
  }

  allocate() {
    if (this.free.length) return this.free.pop();
    if (this.used === this.capacity) this.grow();
    return this.used++;
  }

  grow() {
    const cap = Math.min(Math.max(FIRST_CAPACITY, 2 * this.capacity), Math.max(this.sceneTriangles, 1));
    const grown = (Type, old, per) => { const a = new Type(cap * per); a.set(old); return a; };
    this.positions = grown(Float32Array, this.positions, 9);
    this.colors = grown(Uint8Array, this.colors, 9);
    this.rawColors = grown(Uint8Array, this.rawColors, 3);
    const idOf = new Int32Array(cap).fill(-1);
    idOf.set(this.idOf);
    this.idOf = idOf;
    this.capacity = cap;
    this.layout += 1;
  }

  clearSlot(slot) {
    this.positions.fill(0, 9 * slot, 9 * slot + 9);
  }

  markDirty(start, end) {
    this.version += 1;
    const last = this.dirty[this.dirty.length - 1];
    if (last && start <= last[1] && end >= last[0]) {
      last[0] = Math.min(last[0], start);
      last[1] = Math.max(last[1], end);
    } else this.dirty.push([start, end]);
    if (this.dirty.length > MAX_DIRTY_RANGES) {
      // Many scattered slots (reused after drops): one range over them all uploads faster.
      const lo = Math.min(...this.dirty.map((r) => r[0]));
      const hi = Math.max(...this.dirty.map((r) => r[1]));
      this.dirty = [[lo, hi]];
    }
  }
}
