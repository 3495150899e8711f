// The viewer page: reads its URL, opens the stream, walks or replays, draws every frame.
//
// URL parameters: scene (default: rooms, else the first of GET /scenes), core (a core of the
// server, or auto; default the server's), walk (URL of a walkthrough JSON file to replay),
// budget (most triangles held, declared in the hello), fov (vertical, degrees; default 70),
// size (WxH drawing size in pixels; default the window), aa=0 (no antialiasing), morph=0
// (conventional near-far compositing), ws (the WebSocket URL; default this server's /ws).
// A server with tokens: open the page as /viewer/#token=<token>, or type the token into the form
// the page shows when the server asks for one (token.js: how it is kept and sent).

import { enforceBudget } from "./budget.js";
import { CellStreams } from "./cell_streams.js";
import { Connection } from "./connection.js";
import { WalkControls } from "./controls.js";
import { FrameKind } from "./decode.js";
import { formatBytes, Overlay } from "./overlay.js";
import { ViewRenderer } from "./render.js";
import { SceneStore } from "./scene_store.js";
import {
  askForToken, authorized, currentToken, forgetToken, takeToken, wsProtocols,
} from "./token.js";
import { duration, parseWalkthrough, poseAt } from "./walk.js";

const POSE_INTERVAL_S = 0.1; // free walking: a pose every 100 ms while moving
const STALL_AFTER_S = 0.1; // a cell not complete this long after the eye entered it: a stall

const params = new URLSearchParams(window.location.search);
takeToken(); // before anything else: the fragment leaves the address bar at once
const overlay = new Overlay();

/** The server refused the request's token (HTTP 401). */
class Unauthorized extends Error {}

/** An HTTP URL of this server. */
function api(path) {
  return new URL(path, window.location.origin);
}

/** GET a JSON document; the page's token goes along to this server only. */
async function getJson(url) {
  const ours = url.origin === window.location.origin;
  const r = await fetch(url, ours ? authorized() : {});
  if (r.status === 401 && ours) throw new Unauthorized(`${url.pathname}: HTTP 401 ${await r.text()}`);
  if (!r.ok) throw new Error(`${url.pathname}: HTTP ${r.status} ${await r.text()}`);
  return r.json();
}

function wsUrl() {
  const url = new URL(params.get("ws") || "/ws", window.location.href);
  url.protocol = url.protocol === "https:" || url.protocol === "wss:" ? "wss:" : "ws:";
  return url.toString();
}

/** Say that the server wants a token (none held) or refused the one held, and ask for one. */
function refused() {
  const had = currentToken() !== null;
  forgetToken();
  const why = had ? "the server refused this token (401 unauthorized): enter another"
    : "this server needs a token: enter it, or open the page as /viewer/#token=<token>";
  overlay.setStatus({ text: why, level: "error" });
  askForToken(why);
}

/** The grid's cell of a position (visibility.viewcells.ViewcellGrid.cell_of): the column by
 * x and z, then the level whose floor is the highest at or below the eye (0.5 m slack). */
function cellLocator(listing) {
  const { cell_size: size, origin_xz: [ox, oz] } = listing.grid;
  const columns = new Map();
  for (const c of listing.cells) {
    const key = `${c.ij[0]},${c.ij[1]}`;
    if (!columns.has(key)) columns.set(key, []);
    columns.get(key).push(c);
  }
  return (p) => {
    const key = `${Math.floor((p[0] - ox) / size)},${Math.floor((p[2] - oz) / size)}`;
    let best = null, bestFloor = -Infinity;
    for (const c of columns.get(key) ?? []) {
      if (c.floor <= p[1] + 0.5 && c.floor > bestFloor && p[1] <= c.box[1][1] + 3.0) {
        best = c.id;
        bestFloor = c.floor;
      }
    }
    return best;
  };
}

/** Where a walk without a file starts: the first cell's walk point, looking towards the
 * middle of the grid (along +Z when it stands there). */
function firstPose(listing) {
  const c = listing.cells[0];
  const [lo, hi] = listing.grid.bounds;
  const d = [(lo[0] + hi[0]) / 2 - c.walk[0], 0, (lo[2] + hi[2]) / 2 - c.walk[2]];
  return { position: c.walk.slice(), forward: Math.hypot(d[0], d[2]) > 1e-6 ? d : [0, 0, 1] };
}

class Viewer {
  constructor(scene, listing, start, walk) {
    this.scene = scene;
    this.cellOf = cellLocator(listing);
    this.walk = walk;
    const [w, h] = (params.get("size") || "").split("x").map(Number);
    const canvas = document.getElementById("view");
    if (w > 0 && h > 0) { canvas.style.width = `${w}px`; canvas.style.height = `${h}px`; }
    this.renderer = new ViewRenderer(canvas, {
      fov: Number(params.get("fov") || 70), antialias: params.get("aa") !== "0",
      width: w > 0 ? w : null, height: h > 0 ? h : null,
    });
    window.addEventListener("resize", () => this.renderer.resize());
    this.morph = params.get("morph") !== "0";
    this.controls = new WalkControls(canvas, start.position, start.forward);
    this.framesDrawn = 0;
    this.framesNonEmpty = 0;
    this.frozen = false;
    this.stalls = 0;
    this.stallSeconds = 0;
    this.budget = params.get("budget") ? Number(params.get("budget")) : null;
    // Seconds into the walkthrough where its clock (re)starts: a replay cut by a dropped
    // connection resumes where it was, not from its first pose.
    this.replayOffset = 0;
    this.replayStart = null;
    this.reset();
    this.connection = new Connection(wsUrl(), {
      scene, core: params.get("core") || null, budget: this.budget,
    }, {
      onWelcome: (w) => this.onWelcome(w),
      onMessage: (m) => this.onMessage(m),
      onFrame: (f) => this.onFrame(f),
      onStatus: (s) => overlay.setStatus(s),
      onReset: () => this.reset(),
      onRefused: (m) => { if (m.code === "unauthorized") refused(); },
    }, wsProtocols(wsUrl()));
  }

  /** A new session: nothing held, nothing streamed; a replay keeps its place. */
  reset() {
    if (this.walk && this.replayStart !== null) this.replayOffset = this.replayElapsed(performance.now());
    this.store = null;
    this.streams = null;
    this.welcome = null;
    this.seq = 0;
    this.cell = null;
    this.cellSince = 0;
    this.stalledCell = null;
    this.lastPoseAt = -Infinity;
    this.replayStart = null; // performance.now() when the replay's clock started
    this.nextWalkPose = 0;
    this.evicted = 0;
    this.renderer.layout = -1;
    this.renderer.dynamicKey = null;
    this.renderer.setCubemap(null, [0, 0, 0]);
  }

  /** Seconds of the walkthrough played at `now` (its clock runs once its first cell is held). */
  replayElapsed(now) {
    const run = this.replayStart === null ? 0 : (now - this.replayStart) / 1000;
    return Math.min(duration(this.walk), this.replayOffset + run);
  }

  start() {
    this.connection.connect();
    this.last = performance.now();
    const loop = (now) => {
      requestAnimationFrame(loop);
      if (!this.frozen) this.frame(now);
    };
    requestAnimationFrame(loop);
  }

  onWelcome(w) {
    this.welcome = w;
    this.renderer.setNear(w.near_plane);
    this.store = new SceneStore({ triangles: w.scene.triangles, spheres: w.scene.spheres, budget: w.budget ?? this.budget });
    this.streams = new CellStreams(w, this.store);
    overlay.setCores(w.features.cores || [], params.get("core") || w.core);
    // The first pose at once: the server streams its cell while the page waits for it.
    const t0 = this.walk ? this.walk.t[0] + this.replayOffset : 0;
    const p = this.walk ? poseAt(this.walk, t0) : { position: this.controls.position, forward: this.controls.forward };
    if (this.walk) {
      this.controls.set(p.position, p.forward);
      this.nextWalkPose = this.walk.t.findIndex((t) => t > t0);
      if (this.nextWalkPose < 0) this.nextWalkPose = this.walk.t.length;
    }
    this.sendPose(t0, p.position, p.forward, null);
  }

  onMessage(msg) {
    if (!this.streams) return;
    this.streams.onMessage(msg);
    if (msg.type === "error") overlay.showError(`${msg.code}: ${msg.message}`);
  }

  onFrame(f) {
    if (!this.streams) return;
    if (f.kind === FrameKind.GEOMETRY) this.streams.onGeometry(f);
    else if (f.kind === FrameKind.CUBEMAP) this.streams.onCubemap(f);
    else this.streams.onKeyframes(f);
  }

  sendPose(t, position, forward, velocity) {
    const seq = this.seq++;
    if (this.connection.sendPose(seq, t, position, forward, velocity)) {
      this.streams.poseSentAt.set(seq, performance.now());
      if (this.streams.poseSentAt.size > 1000) this.streams.poseSentAt.delete(this.streams.poseSentAt.keys().next().value);
    }
    this.lastPoseAt = performance.now();
  }

  /** Where the eye is now: the replay's pose, or the person's. */
  move(now, dt) {
    const walk = this.walk;
    if (walk && this.replayStart === null) {
      // Like the headless client: wait behind the loading screen for the first cell.
      const c = this.cellOf(poseAt(walk, walk.t[0] + this.replayOffset).position);
      if (c === null || this.streams.isComplete(c)) this.replayStart = now;
    }
    if (walk && this.replayStart !== null && this.controls.touched === 0) {
      const t = walk.t[0] + this.replayElapsed(now);
      const p = poseAt(walk, t);
      this.controls.set(p.position, p.forward);
      // Every pose of the walk goes out at its time, as client/replay.py sends them.
      while (this.nextWalkPose < walk.t.length && walk.t[this.nextWalkPose] <= t) {
        const i = this.nextWalkPose++;
        const next = i + 1 < walk.t.length ? i + 1 : null;
        const vel = next === null ? null : walk.positions[i].map((x, k) => (walk.positions[next][k] - x) / (walk.t[next] - walk.t[i]));
        this.sendPose(walk.t[i], walk.positions[i], walk.forwards[i], vel);
      }
      return;
    }
    if (walk && this.replayStart === null) return;
    const v = this.controls.step(dt);
    const moving = v.some((x) => x !== 0);
    const cell = this.cellOf(this.controls.position);
    if ((moving && now - this.lastPoseAt >= POSE_INTERVAL_S * 1000) || cell !== this.cell) {
      this.sendPose(now / 1000, this.controls.position, this.controls.forward, moving ? v : null);
    }
  }

  frame(now) {
    const dt = Math.min(0.1, (now - this.last) / 1000);
    this.last = now;
    // Between sessions the last frame stays on screen, under the status line.
    if (!this.welcome || !this.connection.open) { this.updateOverlay(now); return; }
    this.move(now, dt);
    const pos = this.controls.position;
    const cell = this.cellOf(pos);
    if (cell !== this.cell) { this.cell = cell; this.cellSince = now; }
    if (cell !== null && !this.streams.isComplete(cell) && now - this.cellSince > STALL_AFTER_S * 1000) {
      if (this.stalledCell !== cell) { this.stalls += 1; this.stalledCell = cell; }
      this.stallSeconds += dt;
    }
    this.draw(pos, this.controls.forward, this.sceneTime(now));
    this.updateOverlay(now);
  }

  /** Scene time of a dynamic scene's keyframes: the replay's clock, else seconds walked. */
  sceneTime(now) {
    if (!this.welcome.scene.dynamic) return null;
    if (this.walk && this.replayStart !== null) return this.walk.t[0] + this.replayElapsed(now);
    return now / 1000;
  }

  /** Draw the held geometry (and the cell's far cubemap) from `pos` along `fwd`. */
  draw(pos, fwd, t) {
    const store = this.store;
    const o = store.origin ?? [0, 0, 0];
    const eye = [pos[0] - o[0], pos[1] - o[1], pos[2] - o[2]];
    if (store.overBudget) {
      const protect = this.cell !== null ? this.streams.idsOf(this.cell) : new Set();
      this.evicted += enforceBudget(store, protect, eye);
    }
    this.renderer.sync(store, t);
    const cube = this.cell !== null ? this.streams.cubemapFor(this.cell) : null;
    this.renderer.setCubemap(cube, o, this.morph);
    this.renderer.render(eye, fwd);
    this.framesDrawn += 1;
    if (this.renderer.drawn > 0 || cube) this.framesNonEmpty += 1;
  }

  updateOverlay(now) {
    if (now - (this.overlayAt ?? 0) < 250) return;
    this.overlayAt = now;
    const w = this.welcome;
    const s = this.streams;
    const stream = s && this.cell !== null ? s.cells.get(this.cell) : null;
    const latency = s ? s.lastLatency : null;
    const p = this.controls.position;
    overlay.setStats([
      ["scene", this.scene + (w ? ` (${w.scene.triangles.toLocaleString()} triangles)` : "")],
      ["core", w ? `${w.core}` : "-"],
      ["cell", this.cell === null ? "outside the grid" : `${this.cell}${stream && stream.answer ? ` (${stream.answer})` : ""}${s && this.cell !== null && !s.isComplete(this.cell) ? " streaming" : ""}`],
      ["eye", p.map((x) => x.toFixed(1)).join(", ")],
      ["triangles held", this.store ? this.store.count.toLocaleString() : "0"],
      ["bytes received", formatBytes(this.connection.bytes)],
      ["PVS latency", latency ? `${(latency.seconds * 1000).toFixed(0)} ms (cell ${latency.cell})` : "-"],
      ["stalls", `${this.stalls} (${this.stallSeconds.toFixed(1)} s)`],
      ["mode", this.walk ? (this.controls.touched ? "walking (replay left)" : "replay") : "walking: WASD, mouse (click), Q/E, Shift"],
    ]);
  }

  /** What the tests and the README's screenshot read (window.pvsViewer.state()). */
  state() {
    const s = this.streams;
    return {
      status: overlay.status.textContent,
      history: overlay.history.map((h) => `${h.level}: ${h.text}`),
      connected: this.connection.open,
      connections: this.connection.connections,
      scene: this.scene,
      core: this.welcome ? this.welcome.core : null,
      cell: this.cell,
      eye: this.controls.position.slice(),
      forward: this.controls.forward,
      complete: s ? [...s.complete] : [],
      begun: s ? [...s.cells.keys()] : [],
      held: this.store ? this.store.count : 0,
      bytes: this.connection.bytes,
      framesDrawn: this.framesDrawn,
      framesNonEmpty: this.framesNonEmpty,
      stalls: this.stalls,
      latency: s && s.lastLatency ? s.lastLatency.seconds : null,
      evicted: this.evicted,
      dropped: s ? s.dropped : 0,
      // Geometry triangles received over the session (a re-sent one counts again).
      received: s ? s.triangles : 0,
      serverErrors: s ? s.errors.map((e) => `${e.code}: ${e.message}`) : [],
      localErrors: s ? s.localErrors.slice() : [],
      replayDone: !!(this.walk && this.replayStart !== null && this.replayElapsed(performance.now()) >= duration(this.walk)),
      replayAt: this.walk ? this.replayElapsed(performance.now()) : null,
    };
  }

  /** Stop the loop and draw one frame at a pose (and scene time `t`, seconds, for a dynamic
   * scene; default the page's clock); the frame as a PNG data URL, the triangle and sphere ids
   * held (what the headless client would draw there) and the cell. */
  snapshot(position, forward, t = undefined) {
    this.frozen = true;
    this.controls.set(position, forward);
    this.cell = this.cellOf(position);
    this.draw(position, forward, t === undefined ? this.sceneTime(performance.now()) : t);
    const png = this.renderer.canvas.toDataURL("image/png");
    return { png, ids: Array.from(this.store.heldIds()), spheres: [...this.store.sphereInfo.keys()], cell: this.cell };
  }
}

async function main() {
  overlay.setStatus({ text: "loading", level: "info" });
  let names = [];
  try {
    names = (await getJson(api("/scenes"))).scenes.map((s) => s.name);
  } catch (e) {
    if (e instanceof Unauthorized) { refused(); return; }
    overlay.setStatus({ text: `cannot list the scenes: ${e.message}`, level: "error" });
  }
  const scene = params.get("scene") || (names.includes("rooms") ? "rooms" : names[0]);
  overlay.setScenes(names, scene);
  overlay.setCores([], params.get("core") || "");
  if (!scene) { overlay.setStatus({ text: "the server serves no scene", level: "error" }); return; }
  let walk = null;
  if (params.get("walk")) {
    try {
      walk = parseWalkthrough(await getJson(new URL(params.get("walk"), window.location.href)));
    } catch (e) {
      overlay.setStatus({ text: `walkthrough ${params.get("walk")}: ${e.message}`, level: "error" });
      return;
    }
  }
  let listing;
  try {
    listing = await getJson(api(`/scenes/${encodeURIComponent(scene)}/cells`));
  } catch (e) {
    if (e instanceof Unauthorized) { refused(); return; }
    overlay.setStatus({ text: `scene ${scene}: ${e.message}`, level: "error" });
    return;
  }
  if (!listing.cells.length) { overlay.setStatus({ text: `scene ${scene} has no walkable cell`, level: "error" }); return; }
  const start = walk ? poseAt(walk, walk.t[0]) : firstPose(listing);
  const viewer = new Viewer(scene, listing, start, walk);
  window.pvsViewer = viewer;
  viewer.start();
}

main().catch((e) => overlay.setStatus({ text: `the viewer failed: ${e.message}`, level: "error" }));
