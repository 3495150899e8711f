// What the viewer knows of the server's cell streams (the bookkeeping of client/session.py):
// cell_begin, geometry frames, cubemap and keyframe frames, cell_end, drops. Each decoded
// message goes in here; the geometry lands in the SceneStore. Anything that does not fit the
// welcome (ids past the scene, cells past the grid, more triangles than a cell_begin announced)
// is refused and kept in `localErrors`, as the Python client does.

import { FrameKind, KeyframeAssembler } from "./decode.js";

export class CellStreams {
  constructor(welcome, store) {
    this.welcome = welcome;
    this.store = store;
    this.cells = new Map(); // cell -> {cell, begin, end, chunks, triangles, ids: [], answer, latency}
    this.complete = new Set();
    this.current = null;
    this.cubemaps = new Map(); // anchor cell -> decoded cubemap
    this.localErrors = [];
    this.errors = []; // the server's error messages
    this.dropped = 0;
    this.triangles = 0;
    this.assemble = { [FrameKind.KEYFRAMES]: new KeyframeAssembler(), [FrameKind.SPHERES]: new KeyframeAssembler() };
    this.poseSentAt = new Map(); // seq -> performance.now() when sent, for latency
    this.lastLatency = null; // {cell, seconds}: pose to cell_end of the latest walker's stream
  }

  refuse(why) {
    this.localErrors.push(why);
    if (this.localErrors.length > 100) this.localErrors.shift();
  }

  /** A decoded server message (decode.parseServerMessage). */
  onMessage(msg) {
    switch (msg.type) {
      case "cell_begin": return this.onBegin(msg);
      case "cell_end": return this.onEnd(msg);
      case "drop": return this.onDrop(msg);
      case "error": this.errors.push(msg); return undefined;
      case "welcome": return this.refuse("second welcome");
      default: return undefined;
    }
  }

  onBegin(msg) {
    const { cells } = this.welcome.grid;
    const n = this.welcome.scene.triangles;
    if (msg.cell >= cells || msg.triangles > n || msg.new > msg.triangles) {
      this.refuse(`cell_begin for cell ${msg.cell} with ${msg.new} new of ${msg.triangles} triangles does not fit the welcome (${cells} cells, ${n} triangles): refused`);
      this.current = null;
      return;
    }
    const before = this.cells.get(msg.cell);
    const stream = { cell: msg.cell, begin: msg, end: null, chunks: 0, triangles: 0, ids: [], answer: null, latency: null };
    if (msg.answer === "refined" && before) {
      // A refinement adds to the first answer: the cell stays complete with it until the end.
      stream.ids = [...before.ids];
      stream.answer = before.answer;
    }
    this.current = stream;
    this.cells.set(msg.cell, stream);
  }

  onEnd(msg) {
    let cs = this.current;
    if (!cs || cs.cell !== msg.cell) {
      this.refuse(`cell_end for ${msg.cell} without its cell_begin`);
      if (msg.cell >= this.welcome.grid.cells) return;
      cs = this.cells.get(msg.cell) ?? { cell: msg.cell, begin: null, chunks: 0, triangles: 0, ids: [], answer: null };
      this.cells.set(msg.cell, cs);
    } else if (!msg.partial && (cs.chunks !== cs.begin.chunks || cs.triangles !== cs.begin.new)) {
      this.refuse(`cell ${msg.cell}: got ${cs.chunks} chunks / ${cs.triangles} triangles, announced ${cs.begin.chunks} / ${cs.begin.new}`);
    }
    cs.end = msg;
    const sent = this.poseSentAt.get(msg.seq);
    if (!msg.prefetch && sent !== undefined) {
      cs.latency = (performance.now() - sent) / 1000;
      this.lastLatency = { cell: msg.cell, seconds: cs.latency };
    }
    if (!msg.partial) {
      cs.answer = msg.answer;
      this.complete.add(msg.cell);
    }
    this.current = null;
  }

  onDrop(msg) {
    this.dropped += this.store.drop(msg.ids);
    for (const c of msg.cells) this.complete.delete(c);
  }

  /** A decoded geometry frame; false when refused. */
  onGeometry(chunk) {
    const cs = this.current;
    const inStream = cs !== null && cs.cell === chunk.cell;
    if (inStream && cs.begin && cs.triangles + chunk.ids.length > cs.begin.new) {
      this.refuse(`cell ${cs.cell}: a geometry frame past the ${cs.begin.new} triangles its cell_begin announced: refused`);
      return false;
    }
    try {
      this.store.addGeometry(chunk);
    } catch (e) {
      this.refuse(`geometry frame refused: ${e.message}`);
      return false;
    }
    this.triangles += chunk.ids.length;
    if (!inStream) {
      this.refuse(`chunk of cell ${chunk.cell} outside its cell stream`);
      return true;
    }
    cs.chunks += 1;
    cs.triangles += chunk.ids.length;
    cs.ids.push(chunk.ids);
    return true;
  }

  /** A decoded keyframe or sphere frame: joined with its windows, then into the store. */
  onKeyframes(chunk) {
    const whole = this.assemble[chunk.kind].add(chunk);
    if (whole === null) return;
    try {
      if (whole.kind === FrameKind.KEYFRAMES) this.store.addKeyframes(whole);
      else this.store.addSpheres(whole);
    } catch (e) {
      this.refuse(`keyframe frame refused: ${e.message}`);
    }
  }

  onCubemap(cube) {
    if (!(cube.cell >= 0 && cube.cell < this.welcome.grid.cells)) {
      this.refuse(`cubemap of cell ${cube.cell}, not a cell of the grid: refused`);
      return;
    }
    this.cubemaps.set(cube.cell, cube);
  }

  /** The far cubemap `cell` composes with: the one its cell_begin.near_far names. */
  cubemapFor(cell) {
    const s = this.cells.get(cell);
    const nf = s && s.begin ? s.begin.near_far : null;
    const key = nf && Number.isInteger(nf.cubemap_cell) ? nf.cubemap_cell : cell;
    return this.cubemaps.get(key) ?? null;
  }

  /** The near-far radii and centre of `cell`'s stream, or null. */
  nearFarOf(cell) {
    const s = this.cells.get(cell);
    return s && s.begin && s.begin.near_far ? s.begin.near_far : null;
  }

  isComplete(cell) { return this.complete.has(cell); }

  /** The ids `cell`'s latest stream brought (its PVS as far as the viewer knows it). */
  idsOf(cell) {
    const s = this.cells.get(cell);
    const out = new Set();
    if (s) for (const a of s.ids) for (const id of a) out.add(id);
    return out;
  }
}
