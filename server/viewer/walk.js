// Walkthrough files (client/walkthrough.py's format) and the pose at a time:
//   {"poses": [{"t": s, "position": [x, y, z], "forward": [x, y, z]}, ...], "scene": "name"}
// +Y up, metres, seconds; other fields are ignored.

function vec3(pose, key, i) {
  const v = pose[key];
  if (!Array.isArray(v) || v.length !== 3 || !v.every((x) => typeof x === "number" && Number.isFinite(x))) {
    throw new Error(`pose ${i}: '${key}' must be a list of 3 finite numbers`);
  }
  return v.slice();
}

/** A walkthrough from the file's parsed JSON: {t: [], positions: [[3]], forwards: [[3]] unit,
 * scene}; Error naming the problem, as walkthrough_from_dict. */
export function parseWalkthrough(data) {
  if (data === null || typeof data !== "object" || !Array.isArray(data.poses) || !data.poses.length) {
    throw new Error("a walkthrough is a JSON object with a non-empty 'poses' list");
  }
  const t = [], positions = [], forwards = [];
  data.poses.forEach((pose, i) => {
    if (pose === null || typeof pose !== "object") throw new Error(`pose ${i} must be an object`);
    if (typeof pose.t !== "number" || !Number.isFinite(pose.t)) throw new Error(`pose ${i}: 't' must be a number`);
    if (i > 0 && !(pose.t > t[i - 1])) throw new Error("walkthrough times must be strictly increasing");
    t.push(pose.t);
    positions.push(vec3(pose, "position", i));
    const f = vec3(pose, "forward", i);
    const n = Math.hypot(f[0], f[1], f[2]);
    if (n < 1e-12) throw new Error(`pose ${i}: 'forward' must be non-zero`);
    forwards.push(f.map((x) => x / n));
  });
  return { t, positions, forwards, scene: typeof data.scene === "string" ? data.scene : null };
}

/** Seconds from the first to the last pose. */
export function duration(walk) { return walk.t[walk.t.length - 1] - walk.t[0]; }

/** {position, forward} at time `t` (seconds, clamped to the poses): positions interpolated
 * linearly, forwards by normalised lerp (Walkthrough.pose_at). */
export function poseAt(walk, t) {
  const n = walk.t.length;
  if (n === 1 || t <= walk.t[0]) return { position: walk.positions[0].slice(), forward: walk.forwards[0].slice() };
  if (t >= walk.t[n - 1]) return { position: walk.positions[n - 1].slice(), forward: walk.forwards[n - 1].slice() };
  let i = 0;
  while (walk.t[i + 1] <= t) i++;
  const w = (t - walk.t[i]) / (walk.t[i + 1] - walk.t[i]);
  const lerp = (a, b) => a.map((x, k) => (1 - w) * x + w * b[k]);
  const position = lerp(walk.positions[i], walk.positions[i + 1]);
  const f = lerp(walk.forwards[i], walk.forwards[i + 1]);
  const len = Math.hypot(f[0], f[1], f[2]);
  return { position, forward: len > 1e-9 ? f.map((x) => x / len) : walk.forwards[i].slice() };
}
