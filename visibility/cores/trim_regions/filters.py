"""Per-triangle geometric filters of the pipeline's set-up and answer, as numba kernels: which
static triangles an eye of a sphere may see thinner than v* does (tested as hulls), and which
triangles of an answer no eye of the cell sees with any area (their plane holds the cell).

Both were numpy passes over every static triangle (or every triangle of the answer) with
(n, 3, 3) temporaries: a large share of a cell's time on a 1M-triangle scene.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def grazing_mask(verts, faces, ids, normals, plane, centres, delta, px, out):  # pragma: no cover
    """out[i] = True where static triangle ids[i] (rows of ``normals`` (s, 3) unit, ``plane``
    (s,) offsets) has its plane within ``delta`` of some centre (k, 3) and is thin from it:
    its plane's line within a pixel of the centre (``px`` pixels per radian), or its extent
    across that line under a pixel. ``verts`` (n, 3) world metres, ``faces`` (m, 3)."""
    for i in prange(ids.shape[0]):
        f = ids[i]
        a = verts[faces[f, 0]]
        b = verts[faces[f, 1]]
        c = verts[faces[f, 2]]
        for k in range(centres.shape[0]):
            q = centres[k]
            off = abs(normals[i, 0] * q[0] + normals[i, 1] * q[1] + normals[i, 2] * q[2]
                      - plane[i])
            if not off <= delta:
                continue
            mx = (a[0] + b[0] + c[0]) / 3.0 - q[0]
            my = (a[1] + b[1] + c[1]) / 3.0 - q[1]
            mz = (a[2] + b[2] + c[2]) / 3.0 - q[2]
            dist = max(np.sqrt(mx * mx + my * my + mz * mz), 1e-12)
            dmin = np.inf
            dmax = 0.0
            for p in (a, b, c):
                d = max(np.sqrt((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 + (p[2] - q[2]) ** 2),
                        1e-12)
                dmin = min(dmin, d)
                dmax = max(dmax, d)
            across = off * (1.0 / dmin - 1.0 / dmax)
            if off / dist * px < 1.0 or across * px < 1.0:
                out[i] = True
                break


@njit(cache=True, nogil=True, parallel=True)
def grazing_boxes(verts, faces, ids, normals, rows, centre, delta, resolution,
                  out):  # pragma: no cover - numba
    """out[i] (2, 3) = [min, max] of static triangle ids[i] (corners relative to ``centre``,
    metres) grown along its unit normal ``normals[rows[i]]`` by a slab thick enough for a few
    pixels at its distance from ``centre`` (4 / ``resolution`` of it), at most ``delta``:
    the box a grazing triangle is tested as (``pipeline._grazing``)."""
    for i in prange(ids.shape[0]):
        f = ids[i]
        r = rows[i]
        mid0 = 0.0
        mid1 = 0.0
        mid2 = 0.0
        for a in range(3):
            p = verts[faces[f, 0], a] - centre[a]
            q = verts[faces[f, 1], a] - centre[a]
            s = verts[faces[f, 2], a] - centre[a]
            out[i, 0, a] = min(min(p, q), s)
            out[i, 1, a] = max(max(p, q), s)
            m = (p + q + s) / 3.0
            if a == 0:
                mid0 = m
            elif a == 1:
                mid1 = m
            else:
                mid2 = m
        dist = np.sqrt(mid0 * mid0 + mid1 * mid1 + mid2 * mid2)
        slab = min(delta, 4.0 * dist / resolution)
        for a in range(3):
            grow = abs(normals[r, a]) * slab
            out[i, 0, a] -= grow
            out[i, 1, a] += grow


@njit(cache=True, nogil=True, parallel=True)
def plane_holds_box(verts, faces, ids, box, out):  # pragma: no cover - numba
    """out[i] = True where triangle ids[i]'s plane holds all 8 corners of ``box`` (2, 3)
    (within 1e-12 of the larger of the triangle's and the box's coordinates): no eye of the
    box sees it with any area. A triangle of no area holds nothing."""
    scale_box = 0.0
    for r in range(2):
        for k in range(3):
            scale_box = max(scale_box, abs(box[r, k]))
    for i in prange(ids.shape[0]):
        f = ids[i]
        a = verts[faces[f, 0]]
        b = verts[faces[f, 1]]
        c = verts[faces[f, 2]]
        ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        vx, vy, vz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        if not nn > 0.0:
            continue
        nx /= nn
        ny /= nn
        nz /= nn
        scale = 0.0
        for p in (a, b, c):
            for k in range(3):
                scale = max(scale, abs(p[k]))
        tol = 1e-12 * (scale + scale_box)
        holds = True
        for corner in range(8):
            dx = box[corner & 1, 0] - a[0]
            dy = box[(corner >> 1) & 1, 1] - a[1]
            dz = box[(corner >> 2) & 1, 2] - a[2]
            if not abs(nx * dx + ny * dy + nz * dz) <= tol:
                holds = False
                break
        out[i] = holds


@njit(cache=True, nogil=True, parallel=True)
def planes_near(normals, plane, q, half, radius, out):  # pragma: no cover - numba
    """out[i] = True where the plane of row i (``normals`` (s, 3) unit, ``plane`` (s,)
    offsets: n . x = plane) passes within the box of half sides ``half`` (3,) around ``q``
    (3,) grown by ``radius`` metres: |n . q - plane| <= |n| . half + radius. (No BLAS: a
    threaded matrix-vector product leaves its threads spinning beside the view workers.)"""
    for i in prange(normals.shape[0]):
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        off = abs(nx * q[0] + ny * q[1] + nz * q[2] - plane[i])
        out[i] = off <= abs(nx) * half[0] + abs(ny) * half[1] + abs(nz) * half[2] + radius
