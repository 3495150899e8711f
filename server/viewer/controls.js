// Walking with the keyboard and the mouse: W/S forward and back, A/D sideways along the ground
// (the eye keeps its height; Q/E move it down and up), Shift to run, the mouse to look once the
// canvas has the pointer (click it; Esc gives the pointer back). Angles follow shading.forwardOf.

import { forwardOf, yawPitchOf } from "./shading.js";

const WALK_SPEED = 1.4; // m/s, the headless client's generated walks
const RUN_FACTOR = 4;
const MOUSE_RADIANS_PER_PIXEL = 0.0025;
const MAX_PITCH = 1.45;

export class WalkControls {
  constructor(canvas, position, forward) {
    this.canvas = canvas;
    this.position = position.slice();
    ({ yaw: this.yaw, pitch: this.pitch } = yawPitchOf(forward));
    this.keys = new Set();
    /** Bumps on every input, so a replay can hand over to the person. */
    this.touched = 0;
    canvas.addEventListener("click", () => canvas.requestPointerLock?.());
    document.addEventListener("mousemove", (e) => {
      if (document.pointerLockElement !== canvas) return;
      this.yaw -= e.movementX * MOUSE_RADIANS_PER_PIXEL;
      this.pitch = Math.max(-MAX_PITCH, Math.min(MAX_PITCH, this.pitch - e.movementY * MOUSE_RADIANS_PER_PIXEL));
      this.touched += 1;
    });
    const code = (e) => e.code.replace(/^Key/, "").replace(/^Shift(Left|Right)$/, "Shift");
    window.addEventListener("keydown", (e) => {
      if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
      this.keys.add(code(e));
      if ("WASDQE".includes(code(e))) this.touched += 1;
    });
    window.addEventListener("keyup", (e) => this.keys.delete(code(e)));
    window.addEventListener("blur", () => this.keys.clear());
  }

  get forward() { return forwardOf(this.yaw, this.pitch); }

  /** Place the eye (a replay's pose) without counting it as input. */
  set(position, forward) {
    this.position = position.slice();
    ({ yaw: this.yaw, pitch: this.pitch } = yawPitchOf(forward));
  }

  /** Move by the keys held over `dt` seconds; the velocity (m/s) it walked at. */
  step(dt) {
    const k = this.keys;
    const ahead = (k.has("W") ? 1 : 0) - (k.has("S") ? 1 : 0);
    const side = (k.has("D") ? 1 : 0) - (k.has("A") ? 1 : 0);
    const up = (k.has("E") ? 1 : 0) - (k.has("Q") ? 1 : 0);
    const speed = WALK_SPEED * (k.has("Shift") ? RUN_FACTOR : 1);
    // Along the ground: forward without its pitch, and right of it (+Y up, right-handed).
    const fx = Math.sin(this.yaw), fz = Math.cos(this.yaw);
    let vx = ahead * fx - side * fz, vz = ahead * fz + side * fx;
    const n = Math.hypot(vx, vz);
    if (n > 0) { vx = (vx / n) * speed; vz = (vz / n) * speed; }
    const v = [vx, up * WALK_SPEED, vz];
    for (let i = 0; i < 3; i++) this.position[i] += v[i] * dt;
    return v;
  }
}
