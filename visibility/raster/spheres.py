"""From-point depth and id buffers of spheres: analytic ray-sphere hits at pixel centres.

The sampled ground truth and the from-point peers draw spheres with this kernel on top of the
triangle buffers of ``visibility.raster`` (same conventions: ``visibility.raster.camera``; depth is
``-z_cam``; a pixel centre's ray is ``(ndc_x, ndc_y, -1)`` in camera space). A sphere is what a
near-clipped sphere rasterizer without back-face culling shows: the near hit where it lies beyond
the near plane, else the far hit. Spheres win depth ties against triangles only when strictly
nearer, so a triangle buffer stays untouched where no sphere is in front.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations
from visibility.raster.face_pixels import pixel_range


@njit(cache=True, nogil=True, error_model="numpy")
def _sphere_box(c, r, near, res, box):  # pragma: no cover - numba
    """Pixel-centre box of a sphere (camera-space centre c, radius r) on a 90-degree face:
    the box of its bounding cube's projected corners, or the whole face when the cube reaches
    the near plane. False when no pixel centre can be covered."""
    if -c[2] + r < near:
        return False  # entirely in front of the near plane (behind the eye side)
    if -c[2] - r < near:
        box[0] = 0
        box[1] = res - 1
        box[2] = 0
        box[3] = res - 1
        return True
    umin = np.inf
    umax = -np.inf
    vmin = np.inf
    vmax = -np.inf
    for k in range(8):
        x = c[0] + (r if k & 1 else -r)
        y = c[1] + (r if k & 2 else -r)
        d = -(c[2] + (r if k & 4 else -r))
        umin = min(umin, x / d)
        umax = max(umax, x / d)
        vmin = min(vmin, y / d)
        vmax = max(vmax, y / d)
    # pad given (0.0): the same signature as the other callers', one compile.
    return pixel_range(umin, umax, vmin, vmax, res, box, 0.0)


@njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _draw_spheres(centers, radii, sel, eye, rots, res, near, depth, ids, base_id):
    # pragma: no cover - numba
    """Depth-composite the spheres ``sel`` into ``depth``/``ids`` (6, R, R), one face per
    thread (faces never share pixels, so the result does not depend on scheduling)."""
    h = 2.0 / res
    for f in prange(6):
        c = np.empty(3)
        box = np.empty(4, dtype=np.int64)
        for q in range(len(sel)):
            s = sel[q]
            r = radii[s]
            for a in range(3):
                c[a] = (rots[f, a, 0] * (centers[s, 0] - eye[0])
                        + rots[f, a, 1] * (centers[s, 1] - eye[1])
                        + rots[f, a, 2] * (centers[s, 2] - eye[2]))
            if not _sphere_box(c, r, near, res, box):
                continue
            cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2] - r * r
            for i in range(box[0], box[1] + 1):
                y = 1.0 - (i + 0.5) * h
                for j in range(box[2], box[3] + 1):
                    x = (j + 0.5) * h - 1.0
                    ww = x * x + y * y + 1.0
                    cw = c[0] * x + c[1] * y - c[2]
                    disc = cw * cw - ww * cc
                    if disc < 0.0:
                        continue
                    sq = np.sqrt(disc)
                    # Near root without cancellation: (cw - sq) = cc / (cw + sq) when cw > 0.
                    s_near = cc / (cw + sq) if cw > 0.0 else (cw - sq) / ww
                    z = s_near
                    if z < near:
                        z = (cw + sq) / ww
                        if z < near:
                            continue
                    if z < depth[f, i, j]:
                        depth[f, i, j] = z
                        ids[f, i, j] = base_id + s


def draw_spheres_cubemap(
    centers: np.ndarray,
    radii: np.ndarray,
    eye: np.ndarray,
    depth: np.ndarray,
    ids: np.ndarray,
    base_rotation: np.ndarray | None = None,
    near: float = DEFAULT_NEAR,
    base_id: int = 0,
) -> None:
    """Depth-composite spheres into six cube-face buffers, in place.

    Parameters
    ----------
    centers : (s, 3) float64 sphere centres, metres (world).
    radii : (s,) float64 radii, metres; spheres with non-finite data or radius <= 0 are skipped.
    eye : (3,) camera position, metres.
    depth : (6, R, R) float (``visibility.raster.render_cubemap``'s depth, or +inf), updated.
    ids : (6, R, R) int32 or int64 ids, updated: sphere k writes ``base_id + k``.
    base_rotation : (3, 3) world-to-cube rotation, None = axis-aligned (as ``render_cubemap``).
    near : near-plane distance, metres.
    base_id : offset of sphere ids (e.g. the scene's triangle count, to keep the two apart).
    """
    c = np.ascontiguousarray(centers, dtype=np.float64).reshape(-1, 3)
    r = np.ascontiguousarray(radii, dtype=np.float64).reshape(-1)
    if len(c) != len(r):
        raise ValueError(f"centers ({len(c)}) and radii ({len(r)}) differ in length")
    if depth.ndim != 3 or depth.shape[0] != 6 or depth.shape[1] != depth.shape[2]:
        raise ValueError(f"depth must be (6, R, R), got {depth.shape}")
    if ids.shape != depth.shape:
        raise ValueError(f"ids {ids.shape} must match depth {depth.shape}")
    e = np.asarray(eye, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(e)):
        raise ValueError("eye must be finite")
    sel = np.flatnonzero(np.all(np.isfinite(c), axis=1) & np.isfinite(r) & (r > 0))
    if len(sel) == 0:
        return
    rots = np.ascontiguousarray(cube_face_rotations(base_rotation))
    _draw_spheres(c, r, sel.astype(np.int64), e, rots, int(depth.shape[1]), float(near), depth,
                  ids, int(base_id))
