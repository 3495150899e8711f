"""Depth and triangle-id buffers on the CPU: a parallel numba rasterizer.

Follows ``visibility.raster.camera`` exactly: vertices go to camera space in float64 relative to
the eye (so 1e7 m coordinate offsets keep their precision), pixel centres are sampled, depth is
``-z_cam`` in metres, there is no back-face culling and no far plane.

How a pixel is decided. With the eye at the origin of camera space, each triangle edge (p, q)
spans the plane through 0, p and q; the ray ``d`` through a pixel centre hits the triangle iff it
lies on the inner side of all three planes (homogeneous rasterization, exact for triangles that
cross the eye plane). The edge value ``(p x q) . d`` is affine in the pixel coordinates and is
built from the endpoints in a canonical (lexicographic) order, so two triangles sharing an edge
evaluate bit-identical values of opposite sign at every pixel: with the top-left rule on exact
zeros, a pixel centre on a shared edge goes to exactly one of them. (Where a shared *vertex*
lies within rounding, ~1e-16 relative, of a pixel centre without being exactly on it, that one
pixel may go to none or two of its triangles; exact inputs, e.g. dyadic coordinates, are
decided exactly.) The inverse depth at a pixel is the exact ray/plane intersection, affine in
the pixel coordinates, and pixels nearer than ``near`` are rejected: the same pixels as drawing
the triangle Sutherland-Hodgman-clipped against ``z = -near``; the clipped polygon (triangle or
quad) gives the bounding box of the pixels a triangle may touch.

Pipeline for F views sharing an eye (one view, or a cubemap's six faces):
(1) per vertex (prange): the view whose frustum holds it (the dominant cube axis for a
cubemap) and its screen position there;
(2) per triangle (prange): which views it may cover a pixel centre of: a triangle whose corners
share a view lies inside that convex frustum, so only that view, from the corners' screen box
(the common case); others are clipped and projected per view;
(3) per view, per surviving triangle (prange): clip, pixel box and a raster record (three edge
functions, 1/depth plane, id and top-left flags);
(4) per view (prange over workers): worker w owns every W-th band of 8 pixel rows, streams all
records in order and rasterizes their rows in its bands (rows narrowed to the triangle's span,
branch-free inner loop). No two workers share a pixel; the depth test keeps the nearer surface
and, on exact ties, the smaller id, so the image does not depend on thread count or order.
Triangles go through in batches to bound memory; small jobs run on the calling thread only.

The entry points (``render_ids``, ``render_cubemap``) live in ``visibility.raster.render``,
which sends a draw here (every face) or through ``visibility.raster.culling`` (the
hierarchy); both use these kernels.
"""

from __future__ import annotations

import threading

import numba
import numpy as np
from numba import njit, prange

from visibility.scratch import Scratch

#: log2 of the height in pixel rows of the screen bands dealt out to the raster workers.
BAND_SHIFT = 3
#: Raster workers per numba thread (more than one evens out the load).
WORKERS_PER_THREAD = 2
#: Jobs below both sizes (triangles x views, pixels x views) run single-threaded.
PARALLEL_MIN_TRIANGLES = 50_000
PARALLEL_MIN_PIXELS = 1 << 20
#: Triangles per batch (scratch memory: about 140 bytes per triangle of a batch, kept per thread).
BATCH = 1 << 18


# --------------------------------------------------------------------------------- numba kernels
@njit(cache=True, nogil=True)
def _corner(v, eye, i, rot, k):  # pragma: no cover - numba
    """Camera coordinates (x, y, z) of vertex i under view k's rotation; the subtraction of the
    eye comes first, in float64, so large coordinate offsets cancel exactly."""
    x, y, z = v[i, 0] - eye[0], v[i, 1] - eye[1], v[i, 2] - eye[2]
    return (rot[k, 0, 0] * x + rot[k, 0, 1] * y + rot[k, 0, 2] * z,
            rot[k, 1, 0] * x + rot[k, 1, 1] * y + rot[k, 1, 2] * z,
            rot[k, 2, 0] * x + rot[k, 2, 1] * y + rot[k, 2, 2] * z)


@njit(cache=True, nogil=True)
def _clip_edge(ax, ay, aw, bx, by, bw, near, tan_x, tan_y, hw, hh, box):  # pragma: no cover
    """One Sutherland-Hodgman step against w >= near for edge a -> b: grow ``box``
    (xmin, xmax, ymin, ymax, screen pixels) by the kept start corner and the crossing point."""
    xmin, xmax, ymin, ymax = box
    if aw >= near:
        sx = (ax / (aw * tan_x) + 1.0) * hw
        sy = (1.0 - ay / (aw * tan_y)) * hh
        xmin, xmax = min(xmin, sx), max(xmax, sx)
        ymin, ymax = min(ymin, sy), max(ymax, sy)
    if (aw >= near) != (bw >= near):
        s = (near - aw) / (bw - aw)
        cx = ax + s * (bx - ax)
        cy = ay + s * (by - ay)
        sx = (cx / (near * tan_x) + 1.0) * hw
        sy = (1.0 - cy / (near * tan_y)) * hh
        xmin, xmax = min(xmin, sx), max(xmax, sx)
        ymin, ymax = min(ymin, sy), max(ymax, sy)
    return xmin, xmax, ymin, ymax


@njit(cache=True, nogil=True)
def _outside(x, y, w, near, tan_x, tan_y):  # pragma: no cover - numba
    """Bit mask of the frustum planes (near, right, left, top, bottom) a corner is outside of."""
    m = 0
    if w < near:
        m |= 1
    if x > w * tan_x:
        m |= 2
    if x < -w * tan_x:
        m |= 4
    if y > w * tan_y:
        m |= 8
    if y < -w * tan_y:
        m |= 16
    return m


@njit(cache=True, nogil=True)
def _pixel_box(x0, y0, w0, x1, y1, w1, x2, y2, w2, width, height, tan_x, tan_y,
               near):  # pragma: no cover - numba
    """Inclusive pixel-centre box (px0, px1, py0, py1) of a triangle (camera x, y and depth w
    per corner) clipped to w >= near; px0 > px1 when it cannot cover a pixel centre."""
    # All corners outside one plane of the frustum: nothing to draw.
    if (_outside(x0, y0, w0, near, tan_x, tan_y) & _outside(x1, y1, w1, near, tan_x, tan_y)
            & _outside(x2, y2, w2, near, tan_x, tan_y)) != 0:
        return 1, 0, 1, 0
    hw = 0.5 * width
    hh = 0.5 * height
    box = (np.inf, -np.inf, np.inf, -np.inf)
    box = _clip_edge(x0, y0, w0, x1, y1, w1, near, tan_x, tan_y, hw, hh, box)
    box = _clip_edge(x1, y1, w1, x2, y2, w2, near, tan_x, tan_y, hw, hh, box)
    box = _clip_edge(x2, y2, w2, x0, y0, w0, near, tan_x, tan_y, hw, hh, box)
    px0, px1 = _centre_range(box[0], box[1], width)
    py0, py1 = _centre_range(box[2], box[3], height)
    if px0 > px1 or py0 > py1:
        return 1, 0, 1, 0
    return px0, px1, py0, py1


@njit(cache=True, nogil=True)
def _fetch(faces, f, v):  # pragma: no cover - numba
    """Vertex indices of face f, and whether they are in range with finite positions."""
    n = v.shape[0]
    # int64 whatever the faces' dtype, as the other callers of _corner pass: one compile.
    i0, i1, i2 = np.int64(faces[f, 0]), np.int64(faces[f, 1]), np.int64(faces[f, 2])
    if i0 < 0 or i1 < 0 or i2 < 0 or i0 >= n or i1 >= n or i2 >= n:
        return i0, i1, i2, False
    s = 0.0
    for i in (i0, i1, i2):
        s += v[i, 0] + v[i, 1] + v[i, 2]
    return i0, i1, i2, np.isfinite(s)


@njit(cache=True, nogil=True)
def _centre_range(lo, hi, size):  # pragma: no cover - numba
    """Inclusive range of pixel-centre indices j (centre j + 0.5) in [lo, hi], clamped."""
    eps = 1e-7
    lo = max(lo, -1.0)
    hi = min(hi, size + 1.0)
    if not lo <= hi:
        return 1, 0
    return max(int(np.ceil(lo - 0.5 - eps)), 0), min(int(np.floor(hi - 0.5 + eps)), size - 1)


@njit(cache=True, nogil=True, parallel=True)
def _home_views(v, eye, rots, base, cube, width, height, tan_x, tan_y, near, home,
                sxy):  # pragma: no cover - numba
    """Per vertex: a view whose frustum holds it (its ``home``; -1 if none, -2 if not finite)
    and its screen position there. For a cubemap (``cube``) the candidate is the face of the
    dominant axis in the cube frame ``base``; otherwise view 0."""
    hw = 0.5 * width
    hh = 0.5 * height
    for i in prange(v.shape[0]):
        x, y, z = v[i, 0] - eye[0], v[i, 1] - eye[1], v[i, 2] - eye[2]
        if not np.isfinite(x + y + z):
            home[i] = -2
            continue
        k = 0
        if cube:
            cx = base[0, 0] * x + base[0, 1] * y + base[0, 2] * z
            cy = base[1, 0] * x + base[1, 1] * y + base[1, 2] * z
            cz = base[2, 0] * x + base[2, 1] * y + base[2, 2] * z
            ax, ay, az = abs(cx), abs(cy), abs(cz)
            if ax >= ay and ax >= az:
                k = 0 if cx >= 0 else 1
            elif ay >= az:
                k = 2 if cy >= 0 else 3
            else:
                k = 4 if cz >= 0 else 5
        # The prange index is unsigned: cast, or _corner compiles twice.
        px, py, pz = _corner(v, eye, np.int64(i), rots, k)
        w = -pz
        if w >= near and abs(px) <= w * tan_x and abs(py) <= w * tan_y:
            home[i] = k
            sxy[i, 0] = (px / (w * tan_x) + 1.0) * hw
            sxy[i, 1] = (1.0 - py / (w * tan_y)) * hh
        else:
            home[i] = -1


@njit(cache=True, nogil=True)
def views_covered(v, eye, i0, i1, i2, rots, width, height, tan_x, tan_y,
                  near):  # pragma: no cover - numba
    """Bit k set when the triangle of vertices i0, i1, i2 may cover a pixel centre of view k
    (clipped and projected in each view: for triangles whose corners lie in different views)."""
    bits = 0
    # int64 whatever the faces' dtype, as the other callers of _corner pass: one compile.
    j0, j1, j2 = np.int64(i0), np.int64(i1), np.int64(i2)
    for k in range(rots.shape[0]):
        x0, y0, z0 = _corner(v, eye, j0, rots, k)
        x1, y1, z1 = _corner(v, eye, j1, rots, k)
        x2, y2, z2 = _corner(v, eye, j2, rots, k)
        px0, px1, py0, py1 = _pixel_box(x0, y0, -z0, x1, y1, -z1, x2, y2, -z2, width,
                                        height, tan_x, tan_y, near)
        if px0 <= px1:
            bits |= 1 << k
    return bits


@njit(cache=True, nogil=True, parallel=True)
def _cull(v, eye, faces, sel, rots, home, sxy, width, height, tan_x, tan_y, near, out,
          box):  # pragma: no cover - numba
    """Bit k of ``out[t]`` set when selected face t may cover a pixel centre of view k.

    A face whose corners share a home view lies inside that (convex) frustum, so it can only
    cover centres of that view: its pixel box (``box[t]``) comes from the corners' screen
    positions. Others go through the clip-and-project test for every view (``box[t, 0] = -1``:
    the box is left to ``_setup``)."""
    n = v.shape[0]
    for t in prange(sel.shape[0]):
        out[t] = 0
        box[t, 0] = -1
        f = sel[t]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        if i0 < 0 or i1 < 0 or i2 < 0 or i0 >= n or i1 >= n or i2 >= n:
            continue
        h0, h1, h2 = home[i0], home[i1], home[i2]
        if h0 == -2 or h1 == -2 or h2 == -2:
            continue
        if h0 >= 0 and h0 == h1 and h0 == h2:
            px0, px1 = _centre_range(min(sxy[i0, 0], sxy[i1, 0], sxy[i2, 0]),
                                     max(sxy[i0, 0], sxy[i1, 0], sxy[i2, 0]), width)
            py0, py1 = _centre_range(min(sxy[i0, 1], sxy[i1, 1], sxy[i2, 1]),
                                     max(sxy[i0, 1], sxy[i1, 1], sxy[i2, 1]), height)
            if px0 <= px1 and py0 <= py1:
                out[t] = 1 << h0
                box[t, 0] = px0
                box[t, 1] = px1
                box[t, 2] = py0
                box[t, 3] = py1
            continue
        out[t] = views_covered(v, eye, i0, i1, i2, rots, width, height, tan_x, tan_y, near)


@njit(cache=True, nogil=True)
def _edge(px, py, pz, qx, qy, qz, ox, oy, oz, kx, ky, k0x, k0y):  # pragma: no cover - numba
    """Affine edge function (a, b, c) in pixel coordinates, positive on the side of the opposite
    corner o; whether exact zeros count (top-left rule); and whether the edge is usable.

    The cross product is taken with the endpoints in lexicographic order, so the triangle on
    the other side of a shared edge computes the same numbers (then negated, which is exact).
    Selects rather than branches: the orders and sides are random, so branches mispredict."""
    swap = (qx < px) | ((qx == px) & ((qy < py) | ((qy == py) & (qz < pz))))
    ax = qx if swap else px
    ay = qy if swap else py
    az = qz if swap else pz
    bx = px if swap else qx
    by = py if swap else qy
    bz = pz if swap else qz
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    side = cx * ox + cy * oy + cz * oz
    sgn = 1.0 if side > 0.0 else -1.0
    a = sgn * (cx * kx)
    b = sgn * (cy * ky)
    c = sgn * (cx * k0x + cy * k0y - cz)
    top_left = (a > 0.0) | ((a == 0.0) & (b > 0.0))
    return a, b, c, top_left, side != 0.0


@njit(cache=True, nogil=True)
def _split_views(bits, n_views):  # pragma: no cover - numba
    """CSR lists (offsets (F + 1,), indices) of the positions t with bit k of ``bits[t]`` set,
    for each view k, in increasing order."""
    offsets = np.zeros(n_views + 1, dtype=np.int64)
    for t in range(bits.shape[0]):
        b = np.int64(bits[t])
        if b == 0:
            continue
        for k in range(n_views):
            offsets[k + 1] += (b >> k) & 1
    for k in range(n_views):
        offsets[k + 1] += offsets[k]
    fill = offsets[:-1].copy()
    idx = np.empty(offsets[n_views], dtype=np.int64)
    for t in range(bits.shape[0]):
        b = np.int64(bits[t])
        if b == 0:
            continue
        for k in range(n_views):
            if (b >> k) & 1:
                idx[fill[k]] = t
                fill[k] += 1
    return offsets, idx


#: Columns of a triangle's setup record: three edges (a, b, c), 1/depth (a, b, c), id and flags.
_REC = 13


@njit(cache=True, nogil=True, parallel=True)
def _setup(v, eye, faces, sel, idx, box, ids_of, rots, k, width, height, tan_x, tan_y, near,
           bounds, rec):  # pragma: no cover - numba
    """For faces ``sel[idx]`` in view k: the pixel-centre box [x0, x1, y0, y1] (inclusive;
    x0 > x1 when it covers no pixel centre) of the near-clipped projection (``box[idx]`` when
    ``_cull`` found it), and the raster record."""
    # Pixel (x, y) -> ray (kx x + k0x, ky y + k0y, -1).
    kx = 2.0 * tan_x / width
    ky = -2.0 * tan_y / height
    k0x = -tan_x
    k0y = tan_y
    for t in prange(idx.shape[0]):
        bounds[t, 0] = 1
        bounds[t, 1] = 0
        bounds[t, 2] = 1
        bounds[t, 3] = 0
        j = idx[t]
        f = sel[j]
        i0, i1, i2, ok = _fetch(faces, f, v)
        if not ok:
            continue
        x0, y0, z0 = _corner(v, eye, i0, rots, k)
        x1, y1, z1 = _corner(v, eye, i1, rots, k)
        x2, y2, z2 = _corner(v, eye, i2, rots, k)
        if box[j, 0] >= 0:
            px0, px1, py0, py1 = box[j, 0], box[j, 1], box[j, 2], box[j, 3]
        else:
            px0, px1, py0, py1 = _pixel_box(x0, y0, -z0, x1, y1, -z1, x2, y2, -z2, width,
                                            height, tan_x, tan_y, near)
            if px0 > px1:
                continue
        ea, eb, ec, etl, ok0 = _edge(x0, y0, z0, x1, y1, z1, x2, y2, z2, kx, ky, k0x, k0y)
        fa, fb, fc, ftl, ok1 = _edge(x1, y1, z1, x2, y2, z2, x0, y0, z0, kx, ky, k0x, k0y)
        ga, gb, gc, gtl, ok2 = _edge(x2, y2, z2, x0, y0, z0, x1, y1, z1, kx, ky, k0x, k0y)
        if not (ok0 and ok1 and ok2):
            continue
        # Plane n . p = dd; along the ray d (d_z = -1) 1/depth = (n . d) / dd.
        ux, uy, uz = x1 - x0, y1 - y0, z1 - z0
        vx, vy, vz = x2 - x0, y2 - y0, z2 - z0
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        dd = nx * x0 + ny * y0 + nz * z0
        if not (dd != 0.0 and np.isfinite(dd)):
            continue
        rec[t, 0] = ea
        rec[t, 1] = eb
        rec[t, 2] = ec
        rec[t, 3] = fa
        rec[t, 4] = fb
        rec[t, 5] = fc
        rec[t, 6] = ga
        rec[t, 7] = gb
        rec[t, 8] = gc
        rec[t, 9] = nx * kx / dd
        rec[t, 10] = ny * ky / dd
        rec[t, 11] = (nx * k0x + ny * k0y - nz) / dd
        # id and the three top-left flags packed exactly into one float64.
        fid = f if ids_of.shape[0] == 0 else ids_of[f]  # no ids given: the row index
        rec[t, 12] = fid * 8.0 + (int(etl) + 2 * int(ftl) + 4 * int(gtl))
        bounds[t, 0] = px0
        bounds[t, 1] = px1
        bounds[t, 2] = py0
        bounds[t, 3] = py1


@njit(cache=True, nogil=True, inline="always")
def _inside(w, top_left):  # pragma: no cover - numba
    return (w > 0.0) | ((w == 0.0) & top_left)


@njit(cache=True, nogil=True, inline="always")
def _row_span(a, rc, lo, hi):  # pragma: no cover - numba
    """Narrow the column range [lo, hi] to where ``a (j + 0.5) + rc >= 0`` can hold, with a
    pixel of slack (the exact test is still made per pixel)."""
    if a > 0.0:
        lo = max(lo, -rc / a - 1.5)
    elif a < 0.0:
        hi = min(hi, -rc / a + 0.5)
    elif rc < 0.0:
        hi = -1.0
    return lo, hi


#: Boxes at least this many pixels wide get their rows narrowed to the triangle's span.
_SPAN_MIN = 8


@njit(cache=True, nogil=True, parallel=True)
def _raster(rec, bounds, width, near, shift, n_workers, invd, idbuf, counts):  # pragma: no cover
    """Rasterize every set-up triangle into ``invd`` (1/depth, 0 = empty) and ``idbuf`` (both
    (H, W), C order).

    Worker ``w`` owns the pixel rows of every ``n_workers``-th band of ``2**shift`` rows (a power
    of two of workers), so no two workers write the same pixel, busy screen regions are shared
    out evenly, and each worker streams through the triangle records in order. ``counts[w]``
    accumulates (pixel tests, triangle-band pairs)."""
    k = bounds.shape[0]
    inv_near = 1.0 / near
    mask = n_workers - 1
    # Flat buffers and unsigned pixel indices: no negative-index wraparound in the inner loop,
    # which lets it vectorize.
    invf = invd.reshape(-1)
    idf = idbuf.reshape(-1)
    # Pixel centres' x read from a table: converting the (unsigned) column index to a float
    # in the loop kept it from vectorizing well; the values are the same.
    xs = np.arange(width) + 0.5
    for w in prange(n_workers):
        tests = 0
        pairs = 0
        for t in range(k):
            x0 = bounds[t, 0]
            x1 = bounds[t, 1]
            if x0 > x1:
                continue
            y0 = bounds[t, 2]
            y1 = bounds[t, 3]
            # The first band at or below row y0 that this worker owns.
            b0 = y0 >> shift
            b = (b0 & ~mask) | w
            if b < b0:
                b += n_workers
            if (b << shift) > y1:
                continue
            ea, eb, ec = rec[t, 0], rec[t, 1], rec[t, 2]
            fa, fb, fc = rec[t, 3], rec[t, 4], rec[t, 5]
            ga, gb, gc = rec[t, 6], rec[t, 7], rec[t, 8]
            za, zb, zc = rec[t, 9], rec[t, 10], rec[t, 11]
            packed = np.int64(rec[t, 12])
            fid = np.int32(packed >> 3)
            etl = (packed & 1) != 0
            ftl = (packed & 2) != 0
            gtl = (packed & 4) != 0
            wide = x1 - x0 + 1 >= _SPAN_MIN
            while (b << shift) <= y1:
                r0 = max(y0, b << shift)
                r1 = min(y1, ((b + 1) << shift) - 1)
                b += n_workers
                pairs += 1
                for i in range(r0, r1 + 1):
                    sy = i + 0.5
                    # Per-row parts of the edge and depth functions; any fixed evaluation order
                    # keeps a shared edge's values identical (and opposite) in both triangles.
                    rc0 = eb * sy + ec
                    rc1 = fb * sy + fc
                    rc2 = gb * sy + gc
                    rz = zb * sy + zc
                    j0 = x0
                    j1 = x1
                    if wide:
                        lo, hi = _row_span(ea, rc0, float(x0), float(x1))
                        lo, hi = _row_span(fa, rc1, lo, hi)
                        lo, hi = _row_span(ga, rc2, lo, hi)
                        if not lo <= hi:
                            continue
                        j0 = max(x0, int(np.floor(lo)))
                        j1 = min(x1, int(np.ceil(hi)))
                    tests += j1 - j0 + 1
                    row = np.uint64(i * width)
                    for j in range(np.uint64(j0), np.uint64(j1 + 1)):
                        sx = xs[j]
                        iz = za * sx + rz
                        ok = (_inside(ea * sx + rc0, etl) & _inside(fa * sx + rc1, ftl)
                              & _inside(ga * sx + rc2, gtl) & (iz > 0.0) & (iz <= inv_near))
                        p = row + j
                        cur = invf[p]
                        cid = idf[p]
                        win = ok & ((iz > cur) | ((iz == cur) & (fid < cid)))
                        invf[p] = iz if win else cur
                        idf[p] = fid if win else cid
        counts[w, 0] += tests
        counts[w, 1] += pairs


@njit(cache=True, nogil=True, parallel=True)
def _finish(invd, idbuf, depth):  # pragma: no cover - numba
    for k in range(invd.shape[0]):
        for i in prange(invd.shape[1]):
            for j in range(invd.shape[2]):
                if idbuf[k, i, j] >= 0:
                    depth[k, i, j] = np.float32(1.0 / invd[k, i, j])
                else:
                    depth[k, i, j] = np.float32(np.inf)


# --------------------------------------------------------------------------------- Python API
_SCRATCH = threading.local()
#: Largest scratch buffer (bytes) kept between calls, per thread and use.
_SCRATCH_KEEP = 32 << 20


def release_scratch() -> None:
    """Drop this thread's kept scratch buffers (``_scratch``): their memory goes back, and the
    next render allocates afresh."""
    _SCRATCH.pool = Scratch(_SCRATCH_KEEP)


def _scratch(name, shape, dtype):
    """An uninitialised array of ``shape`` from this thread's buffer ``name``, kept between
    calls (``visibility.scratch``: first-touch page faults of fresh buffers cost as much as
    the rasterizing itself)."""
    pool = getattr(_SCRATCH, "pool", None)
    if pool is None:
        pool = _SCRATCH.pool = Scratch(_SCRATCH_KEEP)
    return pool.array(name, shape, dtype)


def out_ids(out: tuple | None, n_views: int, height: int, width: int) -> np.ndarray:
    """(n_views, height, width) int32 id buffers set to -1: the caller's ``out[1]`` when
    given (a caller rendering view after view keeps one: fresh pages cost their first-touch
    faults), else new."""
    if out is None:
        return np.full((n_views, height, width), -1, dtype=np.int32)
    ids = out[1]
    ids.fill(-1)
    return ids


def out_depth(out: tuple | None, n_views: int, height: int, width: int) -> np.ndarray:
    """(n_views, height, width) float32 depth buffers to write every element of: the
    caller's ``out[0]`` when given, else new."""
    if out is None or out[0] is None:
        return np.empty((n_views, height, width), dtype=np.float32)
    return out[0]


def raster_workers(height: int) -> int:
    """Raster workers for an image ``height`` rows high: a power of two, at least two per numba
    thread, no more than there are bands of rows."""
    n_workers = 1
    while n_workers < WORKERS_PER_THREAD * numba.get_num_threads() and \
            n_workers * (1 << BAND_SHIFT) < height:
        n_workers *= 2
    return n_workers


def _render_views_on(v, eye, faces, sel, ids, rots, base, width, height, tan_x, tan_y, near,
                     stats, want_depth, out=None):
    rots = np.ascontiguousarray(rots, dtype=np.float64)
    cube = base is not None
    home = _scratch("home", len(v), np.int8)
    sxy = _scratch("sxy", (len(v), 2), np.float64)
    _home_views(v, eye, rots, np.eye(3) if base is None else base, cube, width, height,
                float(tan_x), float(tan_y), float(near), home, sxy)
    n_views = len(rots)
    invd = _scratch("invd", (n_views, height, width), np.float64)
    invd.fill(0.0)
    idbuf = out_ids(out, n_views, height, width)
    n_workers = raster_workers(height)
    counts = np.zeros((n_workers, 2), dtype=np.int64)
    tan_x, tan_y, near = float(tan_x), float(tan_y), float(near)
    for s in range(0, len(sel), BATCH):
        part = sel[s : s + BATCH]
        bits = _scratch("bits", len(part), np.uint8)
        box = _scratch("box", (len(part), 4), np.int32)
        _cull(v, eye, faces, part, rots, home, sxy, width, height, tan_x, tan_y, near, bits, box)
        offsets, order = _split_views(bits, n_views)
        for k in range(n_views):
            idx = order[offsets[k] : offsets[k + 1]]
            bounds = _scratch("bounds", (len(idx), 4), np.int32)
            rec = _scratch("rec", (len(idx), _REC), np.float64)
            _setup(v, eye, faces, part, idx, box, ids, rots, k, width, height, tan_x, tan_y, near,
                   bounds, rec)
            _raster(rec, bounds, width, near, BAND_SHIFT, n_workers, invd[k], idbuf[k], counts)
    depth = None
    if want_depth:
        depth = out_depth(out, n_views, height, width)
        _finish(invd, idbuf, depth)
    if stats is not None:
        stats["triangles"] = stats.get("triangles", 0) + n_views * int(len(sel))
        stats["pixels"] = stats.get("pixels", 0) + n_views * int(width * height)
        stats["pixel_tests"] = stats.get("pixel_tests", 0) + int(counts[:, 0].sum())
        stats["band_pairs"] = stats.get("band_pairs", 0) + int(counts[:, 1].sum())
    return depth, idbuf
