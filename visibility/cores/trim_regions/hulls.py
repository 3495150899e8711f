"""What the layers do not decide: geometry at the eye, and what moves (paper Sec. 5.1 sorts
dynamic objects in lazily; here, conservatively, they never occlude and are always tested).

- A triangle within Δ of the sphere's centre may be beside or around an eye: it is reported
  directly.
- A moving triangle or a sphere is a hull: the box holding every position it takes over the
  keyframes (positions are piecewise linear in time, so the keyframe boxes bound the sweep). A
  hull is reported when any pixel centre of its box faces, drawn from v*, lies in front of that
  pixel's seal depth (the terminator face found by the layers; unsealed pixels see to
  infinity) and outside the depth spans its validated intervals hide, or when the box meets
  the sphere.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.raster.culling import Pyramid
from visibility.raster.pyramid import PyramidLayout, build_pyramid, rect_min

#: Triangles of a box's faces, as corner indices (corner c has bit a set for max along axis a).
BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
                     dtype=np.int64)


@njit(cache=True, nogil=True, inline="always")
def _closest_on_triangle(p, a, b, c):  # pragma: no cover - numba
    """Squared distance from p to triangle abc (Ericson, Real-Time Collision Detection 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab @ ap
    d2 = ac @ ap
    if d1 <= 0 and d2 <= 0:
        q = a
    else:
        bp = p - b
        d3 = ab @ bp
        d4 = ac @ bp
        cp = p - c
        d5 = ab @ cp
        d6 = ac @ cp
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0 and d4 <= d3:
            q = b
        elif vc <= 0 and d1 >= 0 and d3 <= 0:
            q = a + ab * (d1 / (d1 - d3))
        elif d6 >= 0 and d5 <= d6:
            q = c
        elif vb <= 0 and d2 >= 0 and d6 <= 0:
            q = a + ac * (d2 / (d2 - d6))
        elif va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
            q = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
        else:
            den = 1.0 / (va + vb + vc)
            q = a + ab * (vb * den) + ac * (vc * den)
    r = p - q
    return r @ r


@njit(cache=True, nogil=True, parallel=True)
def near_sphere(verts, faces, rows, centre, radius, vis):  # pragma: no cover - numba
    """Set ``vis[f] = 1`` for each triangle f of ``rows`` within ``radius`` (metres) of
    ``centre`` (3,) (vertices (n, 3) in the same frame)."""
    r2 = radius * radius
    for i in prange(rows.shape[0]):
        f = rows[i]
        a = verts[faces[f, 0]]
        b = verts[faces[f, 1]]
        c = verts[faces[f, 2]]
        out = False
        for k in range(3):
            lo = min(a[k], min(b[k], c[k]))
            hi = max(a[k], max(b[k], c[k]))
            if lo > centre[k] + radius or hi < centre[k] - radius:
                out = True
        if out:
            continue
        if _closest_on_triangle(centre, a, b, c) <= r2:
            vis[f] = 1


@njit(cache=True, nogil=True, inline="always")
def _touches(ax, ay, bx, by, cx, cy, sg, px, py):  # pragma: no cover - numba
    """Whether the pixel square centred at (px, py) meets triangle abc (pixels; ``sg`` the
    sign of its area): the square overlaps the triangle's bounding box, and each edge
    function, oriented inwards, grown by the square's reach along the edge normal, passes.
    The grown edges alone let a sliver reach far past its tip, where the square misses it
    (a box's face seen edge-on was found beside a wall's bottom edge it lay above)."""
    if (px + 0.5 < min(ax, bx, cx) or px - 0.5 > max(ax, bx, cx)
            or py + 0.5 < min(ay, by, cy) or py - 0.5 > max(ay, by, cy)):
        return False
    e0 = sg * ((bx - ax) * (py - ay) - (by - ay) * (px - ax))
    e1 = sg * ((cx - bx) * (py - by) - (cy - by) * (px - bx))
    e2 = sg * ((ax - cx) * (py - cy) - (ay - cy) * (px - cx))
    return (e0 >= -0.5 * (abs(bx - ax) + abs(by - ay))
            and e1 >= -0.5 * (abs(cx - bx) + abs(cy - by))
            and e2 >= -0.5 * (abs(ax - cx) + abs(ay - cy)))


@njit(cache=True, nogil=True, inline="always")
def _in_span(spans, n_spans, p, z, tol):  # pragma: no cover - numba
    """Whether depth z lies in one of pixel p's hidden spans (``kbuffer.KBuffer.spans``), each
    span's front taken ``tol`` (relative) deeper."""
    for q in range(n_spans[p]):
        if spans[p, q, 0] * (1.0 + tol) < z <= spans[p, q, 1]:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _grown_box(box, i, res):  # pragma: no cover - numba
    """Pixel ranges [x0, x1), [y0, y1) of set-up triangle i's box grown by a pixel on every
    side (a pixel square it touches may lie there), clipped to the view."""
    return (max(0, box[i, 0] - 1), min(res, box[i, 1] + 1), max(0, box[i, 2] - 1),
            min(res, box[i, 3] + 1))


@njit(cache=True, nogil=True, inline="always")
def _fan(poly, i, t, scale):  # pragma: no cover - numba
    """Triangle t of set-up polygon i's fan (corners 0, t, t + 1), x and y times ``scale``:
    (ax, ay, bx, by, cx, cy) in pixels (or samples), the sign of its area (0 for none), and
    for 1 / depth, linear in the image: its value at a, its gradient (gx, gy) and its
    largest value over the triangle."""
    ax, ay, az = scale * poly[i, 0, 0], scale * poly[i, 0, 1], poly[i, 0, 2]
    bx, by, bz = scale * poly[i, t, 0], scale * poly[i, t, 1], poly[i, t, 2]
    cx, cy, cz = scale * poly[i, t + 1, 0], scale * poly[i, t + 1, 1], poly[i, t + 1, 2]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if area == 0.0:
        return ax, ay, bx, by, cx, cy, 0.0, az, 0.0, 0.0, az
    sg = 1.0 if area > 0 else -1.0
    gx = ((by - cy) * az + (cy - ay) * bz + (ay - by) * cz) / area
    gy = ((cx - bx) * az + (ax - cx) * bz + (bx - ax) * cz) / area
    return ax, ay, bx, by, cx, cy, sg, az, gx, gy, max(az, max(bz, cz))


@njit(cache=True, nogil=True, inline="always")
def _nearest_in_square(ax, ay, az, gx, gy, izmax, zmin, px, py):  # pragma: no cover - numba
    """Nearest depth (metres) of a fan triangle's plane (``_fan``) over the unit square
    centred at (px, py), clamped to the triangle's own range (``zmin`` its nearest depth)."""
    iz = az + gx * (px - ax) + gy * (py - ay) + 0.5 * (abs(gx) + abs(gy))
    return max(zmin, 1.0 / min(iz, izmax)) if iz > 0.0 else zmin


@njit(cache=True, nogil=True)
def _nearest_depth(poly, npoly, i):  # pragma: no cover - numba
    """Nearest depth (metres) of set-up polygon i, whose vertices carry 1 / depth."""
    z = 1e300
    for k in range(npoly[i]):
        z = min(z, 1.0 / poly[i, k, 2])
    return z


#: Relative depth by which a small triangle may lie behind the samples around it and still
#: count as touching their surface: a triangle coplanar with it (a decal, a face drawn twice)
#: is seen by some eyes, whichever of the two the samples show.
COPLANAR_TOL = 1e-3


@njit(cache=True, nogil=True, parallel=True)
def touching_samples(poly, npoly, box, tri_ids, depth, far, res, s, most,
                     vis):  # pragma: no cover - numba
    """Set ``vis[tri_ids[i]] = 1`` for each small set-up triangle i (``raster.setup_triangles``
    arrays; a pixel box at most ``most`` pixels wide and high) that touches a sample's square
    of v*'s supersampled render ``depth`` (res * s, res * s), conservative rasterization at the
    samples, with its nearest point over that square in front of the farthest depth among the
    sample and its eight neighbours (or within ``COPLANAR_TOL`` of it). For a surface the
    depth over a sample's square lies within its neighbours' depths, so a triangle v* sees
    between the samples (on the surface, or in a gap narrower than a sample) passes; a crack
    one sample wide lets through only what touches the samples around it. ``far``
    (res * res,): the farthest sample depth of each pixel (``samples.open_depth``), a first
    test per pixel."""
    n_s = res * s
    for i in prange(npoly.shape[0]):
        if npoly[i] < 3 or vis[tri_ids[i]]:
            continue
        if box[i, 1] - box[i, 0] > most or box[i, 3] - box[i, 2] > most:
            continue
        # The prange index is unsigned: cast, or _nearest_depth compiles twice.
        zmin = _nearest_depth(poly, npoly, np.int64(i))
        x0, x1, y0, y1 = _grown_box(box, i, res)
        near_enough = False
        for y in range(y0, y1):
            for x in range(x0, x1):
                if zmin < far[y * res + x] * (1.0 + COPLANAR_TOL):
                    near_enough = True
        if not near_enough:
            continue
        hit = False
        for t in range(1, npoly[i] - 1):
            if hit:
                break
            # In sample units: a sample's square is the unit square around (u + 0.5, v + 0.5).
            ax, ay, bx, by, cx, cy, sg, az, gx, gy, izmax = _fan(poly, i, t, float(s))
            if sg == 0.0:
                continue
            u0 = max(0, int(np.floor(min(ax, min(bx, cx)))) - 1)
            u1 = min(n_s, int(np.ceil(max(ax, max(bx, cx)))) + 1)
            v0 = max(0, int(np.floor(min(ay, min(by, cy)))) - 1)
            v1 = min(n_s, int(np.ceil(max(ay, max(by, cy)))) + 1)
            for v in range(v0, v1):
                if hit:
                    break
                for u in range(u0, u1):
                    if not _touches(ax, ay, bx, by, cx, cy, sg, u + 0.5, v + 0.5):
                        continue
                    z = _nearest_in_square(ax, ay, az, gx, gy, izmax, zmin, u + 0.5, v + 0.5)
                    deepest = 0.0
                    for dv in range(max(0, v - 1), min(n_s, v + 2)):
                        for du in range(max(0, u - 1), min(n_s, u + 2)):
                            deepest = max(deepest, np.float64(depth[dv, du]))
                    if z < deepest * (1.0 + COPLANAR_TOL):
                        hit = True
                        break
        if hit:
            vis[tri_ids[i]] = 1


@njit(cache=True, nogil=True)
def _width(poly, npoly, i):  # pragma: no cover - numba
    """Width (pixels) of set-up polygon i: twice its area over its longest edge."""
    a = 0.0
    e = 0.0
    n = npoly[i]
    for k in range(n):
        x0, y0 = poly[i, k, 0], poly[i, k, 1]
        x1, y1 = poly[i, (k + 1) % n, 0], poly[i, (k + 1) % n, 1]
        a += x0 * y1 - x1 * y0
        e = max(e, (x1 - x0) ** 2 + (y1 - y0) ** 2)
    return abs(a) / np.sqrt(e) if e > 0.0 else 0.0


def small_in_front(poly: np.ndarray, npoly: np.ndarray, box: np.ndarray, tri_ids: np.ndarray,
                   seal: np.ndarray, spans: np.ndarray, n_spans: np.ndarray, res: int,
                   thin: float, tol: float, vis: np.ndarray) -> None:
    """Set ``vis[tri_ids[i]] = 1`` for each thin set-up triangle i (at most ``thin`` pixels
    across, ``_width``: small ones and slivers alike) that touches a pixel square
    (conservative rasterization) with its nearest point over the square in front of the
    pixel's seal depth and outside the hidden spans of its validated intervals
    (``kbuffer.KBuffer.spans``), a span's front taken ``tol`` (relative) deeper (the surface
    that opened it varies in depth over the square): what the pixel's centre would have found
    visible had the triangle covered it. A triangle behind a trimmed occluder that covers no
    pixel centre (clutter under a pixel, a sliver seen edge-on from v*) is otherwise never
    tested, though the eyes of the sphere see it where the trims reveal it."""
    # The seals' depth pyramid (``visibility.raster.pyramid``, level 0 the inverse seal
    # depths, 0 where unsealed) rejects a triangle behind the seal at every pixel of its box
    # with a few reads, where a hidden wall's triangle would test each pixel it spans.
    invd = np.reciprocal(np.asarray(seal, dtype=np.float64)).reshape(1, res, res)
    lay = PyramidLayout.of(res, res)
    hz = lay.empty(1)
    build_pyramid(invd, lay.heights, lay.widths, lay.offsets, hz)
    _small_in_front(poly, npoly, box, tri_ids, seal, spans, n_spans, res, thin, tol, vis,
                    Pyramid(invd, hz, lay.heights, lay.widths, lay.offsets))


@njit(cache=True, nogil=True, parallel=True)
def _small_in_front(poly, npoly, box, tri_ids, seal, spans, n_spans, res, thin, tol, vis,
                    pyr):  # pragma: no cover - numba
    """``small_in_front`` with the seals' pyramid ``pyr`` (``culling.Pyramid``)."""
    for i in prange(npoly.shape[0]):
        if npoly[i] < 3 or vis[tri_ids[i]]:
            continue
        # (No width to work out when every triangle is tested: ``touching_in_front``.)
        # The prange index is unsigned: cast, or _width and _nearest_depth compile twice.
        if thin < np.inf and _width(poly, npoly, np.int64(i)) > thin:
            continue
        zmin = _nearest_depth(poly, npoly, np.int64(i))
        x0, x1, y0, y1 = _grown_box(box, i, res)
        if x0 >= x1 or y0 >= y1:
            continue
        # Behind the seal at every pixel of its box (rect_min never exceeds the nearest
        # seal's inverse; the margin covers the reciprocals' rounding): no square can pass.
        # View np.int64(0), not a literal 0: culling's calls pass int64 views, one compile.
        m = rect_min(pyr.invd, pyr.hz, np.int64(0), pyr.heights, pyr.widths, pyr.offsets, x0,
                     x1 - 1, y0, y1 - 1)
        if (1.0 / zmin) * (1.0 + 1e-9) <= m:
            continue
        hit = False
        for t in range(1, npoly[i] - 1):
            if hit:
                break
            ax, ay, bx, by, cx, cy, sg, az, gx, gy, izmax = _fan(poly, i, t, 1.0)
            if sg == 0.0:
                continue
            for y in range(y0, y1):
                if hit:
                    break
                for x in range(x0, x1):
                    if not _touches(ax, ay, bx, by, cx, cy, sg, x + 0.5, y + 0.5):
                        continue
                    z = _nearest_in_square(ax, ay, az, gx, gy, izmax, zmin, x + 0.5, y + 0.5)
                    p = y * res + x
                    if z >= seal[p]:
                        continue
                    if not _in_span(spans, n_spans, p, z, tol):
                        hit = True
                        break
        if hit:
            vis[tri_ids[i]] = 1


@njit(cache=True, nogil=True, parallel=True)
def hulls_in_front(poly, npoly, box, owner, open_only, seal, spans, n_spans, first, res,
                   seen):  # pragma: no cover - numba
    """Set ``seen[owner[i]] = 1`` when set-up triangle i (``raster.setup_triangles`` arrays)
    touches a pixel square (conservative) with its nearest corner in front of the pixel's seal
    depth ``seal`` (res * res,) and outside the hidden spans of its validated intervals
    (``kbuffer.KBuffer.spans``); for a hull with ``open_only[owner]``, in front of the
    pixel's first surface (``first``)."""
    for i in prange(npoly.shape[0]):
        if npoly[i] < 3 or seen[owner[i]]:
            continue
        z = _nearest_depth(poly, npoly, np.int64(i))  # int64: see _small_in_front
        hit = False
        for t in range(1, npoly[i] - 1):
            if hit:
                break
            ax, ay = poly[i, 0, 0], poly[i, 0, 1]
            bx, by = poly[i, t, 0], poly[i, t, 1]
            cx, cy = poly[i, t + 1, 0], poly[i, t + 1, 1]
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            sg = 1.0 if area >= 0 else -1.0
            x0, x1, y0, y1 = _grown_box(box, i, res)
            for y in range(y0, y1):
                if hit:
                    break
                for x in range(x0, x1):
                    if not _touches(ax, ay, bx, by, cx, cy, sg, x + 0.5, y + 0.5):
                        continue
                    p = y * res + x
                    if z >= seal[p] or (open_only[owner[i]] and z >= first[p]):
                        continue
                    if not _in_span(spans, n_spans, p, z, 0.0):
                        hit = True
                        break
        if hit:
            seen[owner[i]] = 1


def touching_in_front(poly: np.ndarray, npoly: np.ndarray, box: np.ndarray,
                      tri_ids: np.ndarray, first: np.ndarray, res: int, vis: np.ndarray) -> None:
    """Set ``vis[tri_ids[i]] = 1`` for each set-up triangle i (``raster.setup_triangles``
    arrays) that touches some pixel (its square, not only its centre: conservative
    rasterization) with its nearest point over the pixel in front of its ``first`` depth
    (res * res,): the thin and small triangles that pixel centres miss, in front of everything
    the view samples. They are occludees only here, never occluders."""
    # ``small_in_front`` with the first surface for the seal, no hidden spans and every
    # triangle, however large.
    small_in_front(poly, npoly, box, tri_ids, first, np.zeros((1, 1, 2)),
                   np.zeros(res * res, dtype=np.int64), res, np.inf, 0.0, vis)
