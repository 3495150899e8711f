"""Brute-force references for the from-segment tests: id buffers at many points of a segment.

Triangles are drawn with ``visibility.raster.render_cubemap`` (the project's exact pixel-centre
rasterizer); spheres are ray-cast analytically at the same pixel centres (``camera.pixel_rays``)
and composited by depth, so "what a sampling camera sees" is defined the same way the core is.
"""

from __future__ import annotations

import numpy as np

from visibility.cores.from_segment.raster import sample_offset
from visibility.raster import render_cubemap
from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations, pixel_rays


def sphere_depths(centers: np.ndarray, radii: np.ndarray, eye: np.ndarray, resolution: int,
                  base_rotation: np.ndarray | None = None,
                  near: float = DEFAULT_NEAR) -> tuple[np.ndarray, np.ndarray]:
    """(6, R, R) depth (inf where none) and sphere index (-1) of the nearest sphere per pixel
    centre: the near hit when it is beyond ``near``, else the far hit (a near-clipped sphere)."""
    rays = pixel_rays(resolution, resolution).reshape(-1, 3)  # camera space, z = -1
    rots = cube_face_rotations(base_rotation)
    depth = np.full((6, resolution * resolution), np.inf)
    ids = np.full((6, resolution * resolution), -1, dtype=np.int64)
    ww = np.einsum("ij,ij->i", rays, rays)
    for f in range(6):
        o = (np.asarray(centers) - eye) @ rots[f].T  # (s, 3) camera space
        ow = rays @ o.T  # (p, s)
        oo = np.einsum("ij,ij->i", o, o)
        disc = ow * ow - ww[:, None] * (oo[None] - radii[None] ** 2)
        with np.errstate(invalid="ignore"):
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        s_near = (ow - sq) / ww[:, None]
        s_far = (ow + sq) / ww[:, None]
        s = np.where(s_near >= near, s_near, np.where(s_far >= near, s_far, np.inf))
        s = np.where(np.isfinite(s), s, np.inf)
        k = np.argmin(s, axis=1)
        best = s[np.arange(len(s)), k]
        depth[f] = best
        ids[f] = np.where(np.isfinite(best), k, -1)
    return depth.reshape(6, resolution, resolution), ids.reshape(6, resolution, resolution)


def sampled_visible(vertices0: np.ndarray, vertices1: np.ndarray, faces: np.ndarray,
                    v0: np.ndarray, v1: np.ndarray, resolution: int, samples: int,
                    base_rotation: np.ndarray | None = None, centers0=None, centers1=None,
                    radii=None, near: float = DEFAULT_NEAR,
                    face_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Union over ``samples`` evenly spaced t in [0, 1] of the ids seen from v0 + t (v1 - v0),
    with vertices (and sphere centres) at (1 - t) x0 + t x1.

    Returns (visible triangle mask (m,), visible sphere mask (s,))."""
    m = len(faces)
    s = 0 if radii is None else len(radii)
    tri = np.zeros(m, dtype=bool)
    sph = np.zeros(s, dtype=bool)
    v0 = np.asarray(v0, dtype=np.float64)
    v1 = np.asarray(v1, dtype=np.float64)
    for t in np.linspace(0.0, 1.0, samples):
        eye = v0 + t * (v1 - v0)
        verts = vertices0 if vertices1 is vertices0 else (1 - t) * vertices0 + t * vertices1
        if m:
            depth, ids = render_cubemap(verts, faces, eye, resolution, base_rotation, near,
                                        face_mask=face_mask)
            depth = depth.astype(np.float64)
        else:
            depth = np.full((6, resolution, resolution), np.inf)
            ids = np.full((6, resolution, resolution), -1)
        if s:
            c = (1 - t) * centers0 + t * centers1
            sd, si = sphere_depths(c, radii, eye, resolution, base_rotation, near)
            front = sd < depth
            sph[np.unique(si[front & (si >= 0)])] = True
            ids = np.where(front, -1, ids)
        u = np.unique(ids)
        tri[u[u >= 0]] = True
    return tri, sph


def ray_triangle_depths(tri: np.ndarray, w: np.ndarray, near: float) -> np.ndarray:
    """(p, m) depth at which ray p (direction ``w[p]``, depth 1 per unit, from the origin) hits
    triangle m (``tri`` (m, 3, 3), relative to the eye), inf where it misses or the hit is
    nearer than ``near``."""
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.einsum("ij,ij->i", tri[:, 0], n)[None] / (w @ n.T)
        q = s[..., None] * w[:, None] - tri[None, :, 0]  # (p, m, 3)
        # Barycentrics of the hit point q (relative to corner 0).
        d00 = np.einsum("ij,ij->i", e1, e1)
        d01 = np.einsum("ij,ij->i", e1, e2)
        d11 = np.einsum("ij,ij->i", e2, e2)
        d20 = np.einsum("pmk,mk->pm", q, e1)
        d21 = np.einsum("pmk,mk->pm", q, e2)
        den = d00 * d11 - d01 * d01
        bv = (d11 * d20 - d01 * d21) / den
        bw = (d00 * d21 - d01 * d20) / den
        ok = (s >= near) & (bv >= 0) & (bw >= 0) & (bv + bw <= 1) & np.isfinite(s)
    return np.where(ok, s, np.inf)


def prepare(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                np.ndarray]:
    """(m, 3, 3) float64 corners of the ``faces`` and their boxes' (m, 3) lows and highs."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    return tri, tri.min(axis=1), tri.max(axis=1)


def _box_candidates(lo: np.ndarray, hi: np.ndarray, eye: np.ndarray, w: np.ndarray,
                    near: float) -> np.ndarray:
    """Indices of the boxes (``lo``, ``hi`` (m, 3)) that the ray ``eye + s w``, s >= ``near``,
    may meet: every triangle ``ray_triangle_depths`` can hit, since its hit point lies in the
    triangle's box, padded here for the rounding of both computations. A slab test only
    prunes: the exact cast still decides."""
    pad = 1e-9 * (np.abs(lo).max(axis=1) + np.abs(hi).max(axis=1) + np.abs(eye).max()
                  + 1.0)
    s0 = np.full(len(lo), -np.inf)
    s1 = np.full(len(lo), np.inf)
    ok = np.ones(len(lo), dtype=bool)
    for a in range(3):
        lo_a = lo[:, a] - pad - eye[a]
        hi_a = hi[:, a] + pad - eye[a]
        if w[a] == 0.0:
            ok &= (lo_a <= 0.0) & (hi_a >= 0.0)
            continue
        t0, t1 = lo_a / w[a], hi_a / w[a]
        s0 = np.maximum(s0, np.minimum(t0, t1))
        s1 = np.minimum(s1, np.maximum(t0, t1))
    # Depths a hair short of ``near`` still count: the exact cast applies ``near`` itself.
    ok &= s1 >= np.maximum(s0, near * (1.0 - 1e-9) - 1e-12)
    return np.flatnonzero(ok)


def nearest_at_pixel(vertices: np.ndarray, faces: np.ndarray, eye: np.ndarray,
                     rotation: np.ndarray, resolution: int, row: int, col: int,
                     centers: np.ndarray | None = None, radii: np.ndarray | None = None,
                     near: float = DEFAULT_NEAR,
                     offset: tuple[float, float] = (0.0, 0.0),
                     prepared: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                     ) -> tuple[int, float]:
    """Brute-force ray cast of one pixel's sample of a 90-degree face (its centre moved by
    ``offset`` pixels, x right and y up): (id of the nearest primitive (triangles first, spheres
    after them; -1 for none), its depth). ``prepared``: ``prepare(vertices, faces)``, for many
    casts into one static scene."""
    x = (col + 0.5 + offset[0]) * (2.0 / resolution) - 1.0
    y = 1.0 - (row + 0.5 - offset[1]) * (2.0 / resolution)
    w = np.asarray(rotation).T @ np.array([x, y, -1.0])  # world direction, depth 1 per unit
    tri, lo, hi = prepared if prepared is not None else prepare(vertices, faces)
    best, best_id = np.inf, -1
    if len(tri):
        cand = _box_candidates(lo, hi, eye, w, near)
        if len(cand):
            depth = ray_triangle_depths(tri[cand] - eye, w[None], near)[0]
            k = int(np.argmin(depth))
            if np.isfinite(depth[k]):
                best, best_id = float(depth[k]), int(cand[k])
    if radii is not None and len(radii):
        o = np.asarray(centers) - eye
        ww = w @ w
        ow = o @ w
        disc = ow * ow - ww * (np.einsum("ij,ij->i", o, o) - radii ** 2)
        with np.errstate(invalid="ignore"):
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        sn, sf = (ow - sq) / ww, (ow + sq) / ww
        s = np.where(sn >= near, sn, np.where(sf >= near, sf, np.inf))
        s = np.where(np.isfinite(s), s, np.inf)
        k = int(np.argmin(s))
        if s[k] < best:
            best, best_id = float(s[k]), len(faces) + k
    return best_id, best


def unwitnessed(witness: np.ndarray, visible: np.ndarray, vertices0: np.ndarray,
                vertices1: np.ndarray, faces: np.ndarray, v0: np.ndarray, v1: np.ndarray,
                resolution: int, base_rotation: np.ndarray | None = None, centers0=None,
                centers1=None, radii=None, near: float = DEFAULT_NEAR, jitter: float = 0.0,
                seed: int = 0) -> list[int]:
    """Ids reported visible whose witness (t, face, pixel) a brute-force ray cast does not
    confirm as the nearest primitive there: should be empty for an exact algorithm. With
    ``jitter``, the pixel's sample is where ``segment_visible`` put it (``sample_offset``)."""
    rots = cube_face_rotations(base_rotation)
    bad = []
    static = prepare(vertices0, faces) if vertices0 is vertices1 else None
    for pid in np.flatnonzero(visible):
        _, t, f, row, col = witness[pid]
        eye = v0 + t * (v1 - v0)
        verts = vertices0 if static is not None else (1 - t) * vertices0 + t * vertices1
        c = None if radii is None else (1 - t) * centers0 + t * centers1
        off = sample_offset(int(f), int(row), int(col), resolution, jitter, seed)
        got, _ = nearest_at_pixel(verts, faces, eye, rots[int(f)], resolution, int(row),
                                  int(col), c, radii, near, off, static)
        if got != pid:
            bad.append(int(pid))
    return bad


def jittered_visible(vertices: np.ndarray, faces: np.ndarray, v0: np.ndarray, v1: np.ndarray,
                     resolution: int, samples: int, jitter: float, seed: int,
                     base_rotation: np.ndarray | None = None,
                     near: float = DEFAULT_NEAR) -> np.ndarray:
    """(m,) bool: static triangles first hit, at ``samples`` evenly spaced points of v0 -> v1,
    by the ray of some pixel's jittered sample (``sample_offset``) of the cubemap: a brute-force
    ray cast of every sample against every triangle (small scenes only)."""
    res = int(resolution)
    rows, cols = np.divmod(np.arange(res * res), res)
    rots = cube_face_rotations(base_rotation)
    dirs = []
    for f in range(6):
        off = np.array([sample_offset(f, int(i), int(j), res, jitter, seed)
                        for i, j in zip(rows, cols, strict=True)])
        x = (cols + 0.5 + off[:, 0]) * (2.0 / res) - 1.0
        y = 1.0 - (rows + 0.5 - off[:, 1]) * (2.0 / res)
        cam = np.stack([x, y, -np.ones_like(x)], axis=1)
        dirs.append(cam @ rots[f])  # world directions, depth 1 per unit along the face axis
    w = np.concatenate(dirs)  # (p, 3)
    seen = np.zeros(len(faces), dtype=bool)
    v0 = np.asarray(v0, dtype=np.float64)
    v1 = np.asarray(v1, dtype=np.float64)
    for t in np.linspace(0.0, 1.0, samples):
        tri = np.asarray(vertices)[np.asarray(faces)] - (v0 + t * (v1 - v0))  # (m, 3, 3)
        depth = ray_triangle_depths(tri, w, near)
        k = np.argmin(depth, axis=1)
        hit = np.isfinite(depth[np.arange(len(w)), k])
        seen[k[hit]] = True
    return seen
