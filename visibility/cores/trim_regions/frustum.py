"""Viewcells, adapted frusta and octree layers (paper Secs. 3.4 and 5.2).

A server cell is a box; the method's viewcell is a sphere of radius Δ around v0. The box is
covered by spheres (``cover_box``): split into the fewest equal sub-boxes whose circumscribed
sphere has a radius of at most ``max_delta``; every eye of the box lies in one of those
spheres, so the union of their PVS is a PVS of the box (the sphere only adds eye positions,
which can only add to a PVS).

Every direction is covered by the six cube faces, each widened by a margin of pixels so their
seams overlap. For face f the viewpoint moves back to v* = v0 - R f with R = Δ sqrt(1 + 1/T²),
T the tangent of the face's half angle: then the whole sphere lies in the cone of half angle
atan(T) around f at v*, so the frustum at v* holds every frustum of direction f from an eye in
the sphere (the paper's double cone is the special case of a sphere of radius R/√2 at T = 1).
Points nearer to v* than R - Δ lie in no such frustum: that is the near plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from visibility.raster.camera import cube_face_rotations

#: Pixels each cube face is widened by on every side (seams between faces overlap).
FACE_MARGIN_PX = 2.0
#: Most spheres a box is covered by; a box needing more gets larger spheres.
MAX_SPHERES = 27


@dataclass
class View:
    """One adapted frustum: a cube face seen from v* of one sphere.

    Attributes
    ----------
    v0 : (3,) sphere centre, metres relative to the computation's centre.
    delta : sphere radius Δ, metres.
    vstar : (3,) the moved-back viewpoint v*, metres relative to the centre.
    rot : (3, 3) world-to-camera rotation (rows right, up, back; looking along -z).
    tan : tangent of the half field of view of the widened face.
    back : R, how far v* lies behind v0, metres.
    near : near-plane depth from v*, metres.
    res : pixels across the face.
    face : cube face index (+X, -X, +Y, -Y, +Z, -Z).
    """

    v0: np.ndarray
    delta: float
    vstar: np.ndarray
    rot: np.ndarray
    tan: float
    back: float
    near: float
    res: int
    face: int


def cover_box(box: np.ndarray, max_delta: float) -> tuple[np.ndarray, float]:
    """Spheres covering a box cell: the fewest equal sub-boxes (n_x x n_y x n_z) whose
    circumscribed sphere has a radius of at most ``max_delta``, the smallest radius among
    those (``sphere_counts``).

    Parameters
    ----------
    box : (2, 3) float64 [min, max], metres.
    max_delta : largest sphere radius wanted, metres (> 0).

    Returns
    -------
    centres : (k, 3) float64 sphere centres, metres, k <= ``MAX_SPHERES``.
    delta : the common radius: the half diagonal of the sub-boxes (at least a micrometre).
    """
    lo, hi = np.asarray(box[0], float), np.asarray(box[1], float)
    size = np.maximum(hi - lo, 0.0)
    n = sphere_counts(size, float(max_delta))
    if int(np.prod(n.astype(float))) > MAX_SPHERES:
        # Too many: larger sub-boxes, at most cbrt(MAX_SPHERES) along every axis.
        per_axis = int(round(MAX_SPHERES ** (1.0 / 3.0)))
        side = float(np.max(size)) / per_axis
        n = np.clip(np.ceil(size / side - 1e-9), 1, per_axis).astype(np.int64)
    sub = size / n
    delta = max(0.5 * float(np.linalg.norm(sub)), 1e-6)
    grids = [lo[a] + (np.arange(n[a]) + 0.5) * sub[a] for a in range(3)]
    cx, cy, cz = np.meshgrid(*grids, indexing="ij")
    return np.stack([cx.ravel(), cy.ravel(), cz.ravel()], axis=1), delta


def sphere_counts(size: np.ndarray, max_delta: float) -> np.ndarray:
    """Sub-boxes per axis (3,) int64 splitting a box of ``size`` (3,) metres into the fewest
    equal sub-boxes of half diagonal at most ``max_delta`` metres; among as few, the smallest
    half diagonal. A server cell is flat (its height is the eye range, 0.4 m by default): a
    lattice of cubes would split that height too (1 x 0.4 x 1 m at Δ 0.3: 3 x 2 x 3 = 18
    spheres) where 4 x 1 x 3 = 12 sub-boxes already have a half diagonal under Δ."""
    size = np.maximum(np.asarray(size, float), 0.0)
    # A lattice of cubes of side 2Δ/√3 (circumscribed radius Δ) always fits: it bounds the
    # count, and so every axis' share of it.
    side = 2.0 * max_delta / np.sqrt(3.0)
    best = np.maximum(1, np.ceil(size / side - 1e-9)).astype(np.int64)
    best_key = (float(np.prod(best.astype(float))), float(np.sum((size / best) ** 2)))
    reach = (2.0 * max_delta) ** 2 * (1.0 + 1e-12)
    # Only splits up to MAX_SPHERES are searched: a box needing more gets larger spheres
    # (``cover_box``) whatever the split.
    most = int(min(best_key[0], MAX_SPHERES))
    for nx in range(1, most + 1):
        rx = (size[0] / nx) ** 2
        if rx > reach:
            continue
        for ny in range(1, most // nx + 1):
            rest = reach - rx - (size[1] / ny) ** 2
            if rest < 0.0:
                continue
            nz = max(1, int(np.ceil(size[2] / np.sqrt(rest) - 1e-9))) if size[2] > 0 else 1
            key = (float(nx * ny * nz), rx + (size[1] / ny) ** 2 + (size[2] / nz) ** 2)
            if key < best_key:
                best, best_key = np.array([nx, ny, nz], dtype=np.int64), key
    return best


def sphere_views(v0: np.ndarray, delta: float, res: int) -> list[View]:
    """The six adapted frusta of the sphere (``v0`` (3,), ``delta``) at ``res`` pixels."""
    tan = 1.0 + 2.0 * FACE_MARGIN_PX / res
    back = delta * np.sqrt(1.0 + 1.0 / tan**2)
    near = max(back - delta, 1e-6)
    out = []
    for f, rot in enumerate(cube_face_rotations()):
        fwd = -rot[2]
        out.append(View(np.asarray(v0, float), float(delta), np.asarray(v0, float) - back * fwd,
                        np.ascontiguousarray(rot), float(tan), float(back), float(near),
                        int(res), f))
    return out


@njit(cache=True, nogil=True)
def layers(leaf_lo, leaf_hi, nbr_start, nbr_items, nbr_face, vstar):  # pragma: no cover
    """Layer of every leaf as seen from ``vstar`` (paper Sec. 5.2).

    A leaf depends on a face neighbour that lies on v*'s side of their shared face; a leaf is
    queued once all its dependencies are processed (no re-visits), and its layer is one more
    than its latest dependency. The relation is acyclic for an octree; leaves left over (none
    expected) go to one last layer, which only costs early termination, not correctness.

    Returns (L,) int64 layers, 0 first.
    """
    n = leaf_lo.shape[0]
    indeg = np.zeros(n, dtype=np.int64)
    for k in range(n):
        for q in range(nbr_start[k], nbr_start[k + 1]):
            face = nbr_face[q]
            axis = face // 2
            if face % 2 == 1:
                ahead = vstar[axis] > leaf_hi[k, axis]
            else:
                ahead = vstar[axis] < leaf_lo[k, axis]
            if ahead:
                indeg[k] += 1
    layer = np.zeros(n, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    head = 0
    tail = 0
    for k in range(n):
        if indeg[k] == 0:
            queue[tail] = k
            tail += 1
    while head < tail:
        a = queue[head]
        head += 1
        for q in range(nbr_start[a], nbr_start[a + 1]):
            b = nbr_items[q]
            # a is a dependency of b when a lies on v*'s side of b's face towards a.
            face = nbr_face[q]
            axis = face // 2
            # The face of b that touches a is the opposite of a's face towards b.
            if face % 2 == 1:
                ahead = vstar[axis] < leaf_lo[b, axis]
            else:
                ahead = vstar[axis] > leaf_hi[b, axis]
            if not ahead:
                continue
            if layer[a] + 1 > layer[b]:
                layer[b] = layer[a] + 1
            indeg[b] -= 1
            if indeg[b] == 0:
                queue[tail] = b
                tail += 1
    if tail < n:
        top = 0
        for k in range(n):
            top = max(top, layer[k])
        for k in range(n):
            if indeg[k] > 0:
                layer[k] = top + 1
    return layer


@njit(cache=True, nogil=True)
def in_frustum(lo, hi, vstar, rot, tan, near):  # pragma: no cover - numba
    """True when the box [lo, hi] (metres) may meet the frustum (v*, rot, tan, near): no side
    plane or the near plane has all eight corners outside."""
    # Corners outside each plane: near, right, left, top, bottom (no array: this runs per
    # octree leaf and per hull, for every view).
    o0 = o1 = o2 = o3 = o4 = 0
    for c in range(8):
        p0 = (hi[0] if c & 1 else lo[0]) - vstar[0]
        p1 = (hi[1] if c & 2 else lo[1]) - vstar[1]
        p2 = (hi[2] if c & 4 else lo[2]) - vstar[2]
        x = rot[0, 0] * p0 + rot[0, 1] * p1 + rot[0, 2] * p2
        y = rot[1, 0] * p0 + rot[1, 1] * p1 + rot[1, 2] * p2
        z = -(rot[2, 0] * p0 + rot[2, 1] * p1 + rot[2, 2] * p2)
        if z < near:
            o0 += 1
        if x > tan * z:
            o1 += 1
        if x < -tan * z:
            o2 += 1
        if y > tan * z:
            o3 += 1
        if y < -tan * z:
            o4 += 1
    return not (o0 == 8 or o1 == 8 or o2 == 8 or o3 == 8 or o4 == 8)
