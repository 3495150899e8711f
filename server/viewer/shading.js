// The headless client's look, in JavaScript: the fixed face shading of
// visibility/raster/shading.py, the camera basis of visibility/raster/camera.py (look_rotation)
// and the icospheres client/render.py draws spheres with. Imports nothing.

/** Background (sky blue) RGB, what a pixel that sees nothing shows. */
export const BACKGROUND = [135, 206, 235];
/** Fixed light direction of the baked two-sided lambert term (towards the light). */
export const LIGHT_DIR = (() => {
  const v = [0.35, 0.85, 0.4];
  const n = Math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  return v.map((x) => x / n);
})();
/** Share of the face colour a face lit edge-on gets. */
export const AMBIENT = 0.45;
/** Near plane until the welcome states the one the answers assume (`near_plane`;
 * visibility.raster.camera.DEFAULT_NEAR), and the headless renderer's far plane. */
export const NEAR = 0.05;
export const FAR = 5000.0;

/** numpy's rint: round half to even, so colours round as the Python shading rounds them. */
export function rint(x) {
  const r = Math.round(x);
  return Math.abs(x - Math.trunc(x)) === 0.5 && r % 2 !== 0 ? r - 1 : r;
}

/** Shade the face with corners `c` (9 float64, metres, absolute) and RGB `rgb` (3 ints) into
 * `out` at `at` (3 uint8), as shade_colors does: colour * (AMBIENT + (1 - AMBIENT) |n.l| / |n|). */
export function shadeInto(c, r, g, b, out, at) {
  const ax = c[3] - c[0], ay = c[4] - c[1], az = c[5] - c[2];
  const bx = c[6] - c[0], by = c[7] - c[1], bz = c[8] - c[2];
  const nx = ay * bz - az * by, ny = az * bx - ax * bz, nz = ax * by - ay * bx;
  const len = Math.sqrt(nx * nx + ny * ny + nz * nz);
  let cos = Math.abs(nx * LIGHT_DIR[0] + ny * LIGHT_DIR[1] + nz * LIGHT_DIR[2]) / len;
  if (!Number.isFinite(cos)) cos = 0; // a degenerate face: ambient only
  const s = AMBIENT + (1 - AMBIENT) * cos;
  out[at] = Math.min(255, Math.max(0, rint(r * s)));
  out[at + 1] = Math.min(255, Math.max(0, rint(g * s)));
  out[at + 2] = Math.min(255, Math.max(0, rint(b * s)));
}

/** The camera's right, up and back axes (world) for a view along `forward` with +Y up,
 * look_rotation's rows; a forward along +-Y takes its other up, as the Python one does. */
export function lookRotation(forward) {
  const n = Math.hypot(forward[0], forward[1], forward[2]);
  if (!Number.isFinite(n) || n === 0) throw new Error("forward must be a finite non-zero vector");
  const f = forward.map((x) => x / n);
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  let up = [0, 1, 0];
  let r = cross(f, up);
  if (Math.hypot(r[0], r[1], r[2]) < 1e-9) {
    up = f[1] > 0 ? [0, 0, -1] : [0, 0, 1];
    r = cross(f, up);
  }
  const rn = Math.hypot(r[0], r[1], r[2]);
  r = r.map((x) => x / rn);
  const u = cross(r, f);
  return { right: r, up: u, back: f.map((x) => -x) };
}

/** The forward direction of a yaw (about +Y, 0 looking along +Z) and pitch, radians; the
 * convention of client/walkthrough.py's generated walks. */
export function forwardOf(yaw, pitch) {
  return [Math.cos(pitch) * Math.sin(yaw), Math.sin(pitch), Math.cos(pitch) * Math.cos(yaw)];
}

/** Yaw and pitch (radians) of a direction. */
export function yawPitchOf(f) {
  const n = Math.hypot(f[0], f[1], f[2]) || 1;
  return { yaw: Math.atan2(f[0], f[2]), pitch: Math.asin(Math.max(-1, Math.min(1, f[1] / n))) };
}

/** Unit icosphere triangles (Float64Array, 9 per face) with trimesh's icosahedron and
 * `subdivisions` midpoint subdivisions, as trimesh.creation.icosphere makes them (320 faces
 * for 2, client/render.py's SPHERE_SUBDIVISIONS). */
export function unitIcosphere(subdivisions = 2) {
  const a = 0.5257311121191336, b = 0.85065080835204;
  const v = [[-a, b, 0], [a, b, 0], [-a, -b, 0], [a, -b, 0], [0, -a, b], [0, a, b], [0, -a, -b],
    [0, a, -b], [b, 0, -a], [b, 0, a], [-b, 0, -a], [-b, 0, a]];
  const f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
    [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
    [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]];
  let tris = f.map(([i, j, k]) => [v[i], v[j], v[k]]);
  const unit = (p) => { const n = Math.hypot(p[0], p[1], p[2]); return p.map((x) => x / n); };
  const mid = (p, q) => [(p[0] + q[0]) / 2, (p[1] + q[1]) / 2, (p[2] + q[2]) / 2];
  for (let s = 0; s < subdivisions; s++) {
    // Midpoints, then every vertex pushed onto the unit sphere (trimesh does both per level).
    tris = tris.flatMap(([p, q, r]) => {
      const pq = mid(p, q), qr = mid(q, r), rp = mid(r, p);
      return [[p, pq, rp], [pq, q, qr], [rp, qr, r], [pq, qr, rp]];
    }).map((t) => t.map(unit));
  }
  return Float64Array.from(tris.flat(2));
}
