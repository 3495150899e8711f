"""Occlusion interval resolve per pixel (paper Sec. 4.3, Fig. 9), phase P3, and the gather of
what each pixel found visible (P4).

Per active pixel the trim sequence (its k-buffer) is sorted by depth. Surface entries hidden by
the umbra of an interval validated earlier (``cover``) are skipped. An open front face directly
followed by a back face is a simple occlusion interval [f, b]. It is validated when a trim
fragment of it lies inside it (depth tolerance ``DEPTH_TOL``): its face goes to the PVS and the
umbra replaces its back face, i.e. everything up to the (smallest) umbra depth of those trim
fragments is hidden, and the walk goes on behind. An interval that is not validated is a
terminator: its face goes to the PVS and the pixel is sealed. A run with nothing after it yet
is carried to the next layer (its closing face may lie in a later octree node).

A trim fragment is *of* an interval when its silhouette edge lies on the same connected piece
(``topology.connected_pieces``: triangles joined through corners at one position) as one of the
interval's faces; fragments of different pieces merged into one entry count for each of them
(a piece set: ``kbuffer.piece_bits``). The paper validates by depth alone: a trim region is
part of its occluder, and the rim trims of small clutter, wider than the clutter itself, then
opened whatever lay in front of it at that depth range (the wall of the 1M kitchen's room,
seen from a cell outside it).

Several front faces before the closing one (soups, intersecting or nested objects) are not one
interval extended at the front as in the paper: each but the last is read as a single-sided
surface; and a front face and the back face after it that cannot bound one solid (one of them
on a closed part the other is not on, ``topology.closed_components``) read so too.

A back face met first, those faces, and after the last layer a carried run read as
single-sided surfaces: each face in turn is seen, and trimmed (validated) when a trim fragment
of its piece lies between it and the next surface, that surface's depth included (a trim at
the next surface's depth may be the face's own: the edge an inward-wound face shares with the
face the ray leaves by, as in the Quake level lavaducts), else it terminates the pixel. A front
face read so takes only trims as deep as an eye of the sphere can pass its rim
(``_front_reach``): a room's wall is one connected piece with the rims inside the room behind
it, which no eye outside sees past the wall. A back face read so also takes the trims in front
of it back to the last surface, no nearer than its own nearest corner (``_rim_from``): the ray
was inside what it closes since then, and its rim may lie in front of it (a sloped wall seen
from behind recedes from the edge that eyes of the sphere on the wall's other side see past;
a carried back face keeps those trims in its residual sequence).

A simple interval's front face takes the trims from its nearest corner on, when that lies
in front of it along the ray (``_front_rim``): a wall receding from a corner the ray passes
has its rim there, and eyes of the sphere that pass the rim see into the interval from its
side (in lavaducts, at Δ 0.4 m, the back of a wall 5 m away past a corner 1.4 m away).

A validated interval's hidden span (``KBuffer.spans``, what the footprint tests of small
triangles take as hidden) starts where its face lies deepest over the pixel's square
(``_deepest_over_pixel``), not at the pixel's centre: a sliver just behind an oblique face at
the centre lies in front of it elsewhere in the pixel.

A back face is not reported when a front face of the same closed, consistently wound part
(``topology.closed_components``) hid in an umbra before it: it is that part's back, never seen
from outside it. Any other back face may be seen (single-sided or inward-wound geometry seen
from behind, as in lavaducts, where the whole level is one open part).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from visibility.borrow import NO_REFCOUNT
from visibility.cancel import flag_set
from visibility.cores.trim_regions.kbuffer import (
    BACK,
    LANE_BITS,
    LANE_MASK,
    SEALED,
    TRIM,
    K,
    band_stride,
    trim_holds,
)
from visibility.cores.trim_regions.silhouettes import AMBIGUOUS

#: Relative depth tolerance when testing a trim fragment against an interval (erring towards
#: validation: trimming more only adds false positives).
DEPTH_TOL = 1e-3


class Reach(NamedTuple):
    """The view as the resolve needs it of a face: how deep a single-sided front face's trims
    may lie (``_front_reach``) and where a hidden span starts over a pixel
    (``_deepest_over_pixel``). A named group the kernels take whole (``resolve_into``).

    Attributes
    ----------
    normal : (m, 3) float64 unit normal of each triangle id (world frame; zero for none).
    rot : (3, 3) the view's world-to-camera rotation (looking along -z).
    tan : tangent of the view's half field of view.
    res : pixels across the view.
    lateral : how far from v* an eye of the sphere may lie, Δ + R, metres (inf: no bound).
    cam : (n, 3) float64 the scene's vertices in the view's camera frame (v* at the origin),
        metres; (0, 3): no face's own umbra (``_self_umbra``) is used.
    faces : (m, 3) int64 each triangle id's vertex rows of ``cam``.
    back : R, how far v* lies behind the sphere's centre (along the view axis), metres.
    delta : Δ, the sphere's radius, metres.
    facing_of : (m,) int8 each triangle id's facing in the view (``view_masks.drawn_edges``),
        ``silhouettes.AMBIGUOUS`` where its plane passes through the sphere (some of its eyes
        see the face's front whichever side v* sees); (0,): none is.
    """

    normal: np.ndarray
    rot: np.ndarray
    tan: float
    res: int
    lateral: float
    cam: np.ndarray = np.zeros((0, 3))
    faces: np.ndarray = np.zeros((0, 3), dtype=np.int64)
    back: float = 0.0
    delta: float = 0.0
    facing_of: np.ndarray = np.zeros(0, dtype=np.int8)


@njit(cache=True, nogil=True, inline="always")
def _pixel_ray(reach, p):  # pragma: no cover - numba
    """Pixel p's centre ray (rx, ry, -1) in camera space: (rx, ry)."""
    half = 0.5 * reach.res
    rx = ((p % reach.res + 0.5) / half - 1.0) * reach.tan
    ry = (1.0 - (p // reach.res + 0.5) / half) * reach.tan
    return rx, ry


@njit(cache=True, nogil=True, inline="always")
def _ray_and_normal(reach, ident, p):  # pragma: no cover - numba
    """Pixel p's ray (rx, ry, -1) and face ``ident``'s normal (nx, ny, nz), in camera space."""
    rx, ry = _pixel_ray(reach, p)
    n = reach.normal[ident]
    rot = reach.rot
    nx = n[0] * rot[0, 0] + n[1] * rot[0, 1] + n[2] * rot[0, 2]
    ny = n[0] * rot[1, 0] + n[1] * rot[1, 1] + n[2] * rot[1, 2]
    nz = n[0] * rot[2, 0] + n[1] * rot[2, 1] + n[2] * rot[2, 2]
    return rx, ry, nx, ny, nz


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _front_reach(reach, ident, p, d):  # pragma: no cover - numba
    """The deepest a trim fragment of the rim that lets an eye of the sphere see past
    single-sided front face ``ident``, met at depth d in pixel p, can lie (inf: no bound).

    An eye at most ``lateral`` from v* that sees past the face along pixel p's ray crosses
    the face's plane beside the face within ``lateral`` of the ray, so past a rim point of the
    plane no deeper than d + lateral * tan(angle between the normal and the ray); the trim
    fragment lies at the depth of the rim point nearest the pixel in the image, so twice that
    reach is allowed. A trim deeper than that belongs to what lies behind the face (the rims
    inside a room seen from outside its wall, one connected piece with it)."""
    if not reach.lateral < np.inf:
        return np.inf
    rx, ry, nx, ny, nz = _ray_and_normal(reach, ident, p)
    c = abs(nx * rx + ny * ry - nz) / np.sqrt(rx * rx + ry * ry + 1.0)
    if c < 1e-6:
        return np.inf
    return d + 2.0 * reach.lateral * np.sqrt(max(0.0, 1.0 - c * c)) / c


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _deepest_over_pixel(reach, ident, p, d):  # pragma: no cover - numba
    """The farthest depth of face ``ident``'s plane over pixel p's square, given its depth d
    at the pixel's centre (d itself for a face of no normal; inf where the plane turns
    edge-on within the square). A hidden span starts there: what lies in front of the face
    somewhere in the square is not hidden by it (a sliver just behind an oblique face at the
    centre lies in front of it elsewhere in the pixel, where v* sees it)."""
    rx, ry, nx, ny, nz = _ray_and_normal(reach, ident, p)
    if nx == 0.0 and ny == 0.0 and nz == 0.0:
        return d
    return _square_on_plane(rx, ry, nx, ny, nz, reach.tan / reach.res, d)[0]


@njit(cache=True, nogil=True, inline="always")
def _square_on_plane(rx, ry, nx, ny, nz, h, d):  # pragma: no cover - numba
    """Where the corner rays of the pixel square (rx, ry) +- h (tan units) meet the plane of
    normal n (unit for the last value) through the centre ray's point at depth d: (deepest
    depth, nearest depth, farthest distance from the centre's point, least |n . r| over the
    corner rays r = (x, y, -1)); (inf, d, inf, 0) where the plane turns edge-on within the
    square. The square's image on the plane is the convex hull of the corners' points."""
    k = d * (nx * rx + ny * ry - nz)
    deepest = d
    nearest = d
    spread = 0.0
    c = np.inf
    for su in (-1.0, 1.0):
        for sv in (-1.0, 1.0):
            cx = rx + su * h
            cy = ry + sv * h
            den = nx * cx + ny * cy - nz
            t = k / den if den != 0.0 else np.inf
            if not (t > 0.0 and t < np.inf):
                return np.inf, d, np.inf, 0.0
            deepest = max(deepest, t)
            nearest = min(nearest, t)
            spread = max(spread, np.sqrt((t * cx - d * rx) ** 2 + (t * cy - d * ry) ** 2
                                         + (d - t) ** 2))
            c = min(c, abs(den))
    return deepest, nearest, spread, c


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _self_umbra(reach, ident, p, d):  # pragma: no cover - numba
    """How deep triangle ``ident``, met at depth d on pixel p's centre ray, hides on its own
    the points behind it on any ray through the pixel's square from every eye of the sphere
    (d: no further than itself; inf: all of them).

    A triangle is an occluder whether or not its edges are silhouettes: a trim fragment of
    another edge (the back edge of a thick wall, a neighbour's rim) validates the interval
    with the umbra of that edge, but an eye that sees past that edge must still see past
    this triangle. An eye e = v* + w (|w x r| <= R |(rx, ry)| + Δ |r| over the sphere, r the
    ray (rx, ry, -1)) sees the ray's point X at depth z > d only through the triangle's
    plane, which the segment e-X crosses at most (z - d) K / ((z - d) c + D) from the ray's
    hit H, with c = |n . r| and D the sphere's distance to the plane; the triangle holds
    that crossing while it stays within s of H, s the distance from H to the triangle's
    edges in its plane less the spread of the pixel's square over the plane. So X is hidden
    for z up to d + s D / (K - s c) (every z where K <= s c), d taken where the plane lies
    nearest over the square. Not for a plane through the
    sphere or with v* on its other side."""
    if reach.cam.shape[0] == 0 or ident < 0:
        return d
    rx, ry, nx, ny, nz = _ray_and_normal(reach, ident, p)
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    if nn == 0.0:
        return d
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    hx, hy, hz = d * rx, d * ry, -d
    # v* (the origin) and the sphere's centre (0, 0, -R) on one side, the sphere clear of it.
    sv = -(nx * hx + ny * hy + nz * hz)
    sc = sv - nz * reach.back
    if sv * sc <= 0.0:
        return d
    dist = abs(sc) - reach.delta
    if not dist > 0.0:
        return d
    f = reach.faces[ident]
    cam = reach.cam
    s = np.inf
    for k in range(3):
        a = f[k]
        b = f[(k + 1) % 3]
        o = f[(k + 2) % 3]
        ex = cam[b, 0] - cam[a, 0]
        ey = cam[b, 1] - cam[a, 1]
        ez = cam[b, 2] - cam[a, 2]
        # In-plane normal of the edge, n x e, turned towards the opposite corner.
        mx = ny * ez - nz * ey
        my = nz * ex - nx * ez
        mz = nx * ey - ny * ex
        ml = np.sqrt(mx * mx + my * my + mz * mz)
        if ml == 0.0:
            return d
        side = mx * (cam[o, 0] - cam[a, 0]) + my * (cam[o, 1] - cam[a, 1]) \
            + mz * (cam[o, 2] - cam[a, 2])
        if side == 0.0:
            return d
        g = (mx * (hx - cam[a, 0]) + my * (hy - cam[a, 1]) + mz * (hz - cam[a, 2])) / ml
        if side < 0.0:
            g = -g
        s = min(s, g)
    # The pixel's square: its corner rays meet the plane within ``spread`` of H, and their
    # slant bounds K and c over the square.
    h = reach.tan / reach.res
    deepest, nearest, spread, c = _square_on_plane(rx, ry, nx, ny, nz, h, d)
    if deepest == np.inf:
        return d
    s -= spread
    if not s > 0.0:
        return d
    ax = abs(rx) + h
    ay = abs(ry) + h
    lat = np.sqrt(ax * ax + ay * ay)
    kk = reach.back * lat + reach.delta * np.sqrt(lat * lat + 1.0)
    if kk <= s * c:
        return np.inf
    # From the plane's nearest point over the square: the bound grows as the hit comes nearer.
    return max(d, nearest + s * dist / (kk - s * c))


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _covers_square(reach, ident, p):  # pragma: no cover - numba
    """Whether triangle ``ident`` lies across all of pixel p's square (each corner ray
    crosses it): only then does an interval it opens hide depths over the whole square, as
    the footprint tests of small triangles take a hidden span. A strip of a bevelled edge
    3 mm tall opened one over a 5 cm pixel 7 m off, and hid the table top behind it that
    the eyes see above the strip. True without the view's vertices (``Reach.cam``)."""
    if reach.cam.shape[0] == 0 or ident < 0:
        return True
    f = reach.faces[ident]
    cam = reach.cam
    h = reach.tan / reach.res
    rx, ry = _pixel_ray(reach, p)
    sign = 0.0
    for k in range(3):
        a = f[k]
        b = f[(k + 1) % 3]
        # The plane through v* (the origin) and the edge ab: its normal a x b.
        nx = cam[a, 1] * cam[b, 2] - cam[a, 2] * cam[b, 1]
        ny = cam[a, 2] * cam[b, 0] - cam[a, 0] * cam[b, 2]
        nz = cam[a, 0] * cam[b, 1] - cam[a, 1] * cam[b, 0]
        for su in (-1.0, 1.0):
            for sv in (-1.0, 1.0):
                v = nx * (rx + su * h) + ny * (ry + sv * h) - nz
                if v == 0.0 or (sign != 0.0 and v * sign < 0.0):
                    return False
                sign = v
    return True


@njit(cache=True, nogil=True, inline="always")
def _push_face_span(spans, n_spans, reach, ident, p, d, hi):  # pragma: no cover - numba
    """Record the span face ``ident`` (met at depth d in pixel p) hides up to ``hi``, from
    where it lies deepest over the pixel, when it lies across the whole pixel
    (``_covers_square``)."""
    if _covers_square(reach, ident, p):
        _push_span(spans, n_spans, p, _deepest_over_pixel(reach, ident, p, d), hi)


@njit(cache=True, nogil=True, inline="always")
def _push_span(spans, n_spans, p, lo, hi):  # pragma: no cover - numba
    """Record the hidden span [lo, hi] of pixel p when its list has room (a span left out
    only hides less)."""
    if n_spans[p] < spans.shape[1]:
        spans[p, n_spans[p], 0] = lo
        spans[p, n_spans[p], 1] = hi
        n_spans[p] += 1


class SortScratch(NamedTuple):
    """One thread's scratch for a pixel's sorted sequence of K entries: the depths ``sd``
    (K,), kinds ``sk`` (K,) int8, ids ``si`` (K,) int64, umbrae ``su`` (K,) and far ends of
    the trims' depth ranges ``sr`` (K,)."""

    sd: np.ndarray
    sk: np.ndarray
    si: np.ndarray
    su: np.ndarray
    sr: np.ndarray


@njit(cache=True, nogil=True)
def _scratch(k):  # pragma: no cover - numba
    """A ``SortScratch`` for k entries."""
    return SortScratch(np.empty(k), np.empty(k, dtype=np.int8), np.empty(k, dtype=np.int64),
                       np.empty(k), np.empty(k))


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _sort(sd, sk, si, su, sr, n):  # pragma: no cover - numba
    """Stable insertion sort of the first n entries of the five arrays by (depth, kind)."""
    for i in range(1, n):
        d, kd, ident, um, fr = sd[i], sk[i], si[i], su[i], sr[i]
        j = i
        while j > 0 and (sd[j - 1] > d or (sd[j - 1] == d and sk[j - 1] > kd)):
            sd[j], sk[j], si[j], su[j], sr[j] = sd[j - 1], sk[j - 1], si[j - 1], su[j - 1], \
                sr[j - 1]
            j -= 1
        sd[j], sk[j], si[j], su[j], sr[j] = d, kd, ident, um, fr


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _umbra_in(sd, sk, si, su, sr, n, lo, hi, pa, pb):  # pragma: no cover - numba
    """Smallest umbra depth of the trim entries of piece ``pa`` or ``pb`` (or of a merged
    piece set that may hold one, ``kbuffer.trim_holds``) whose depth range [sd, sr] meets
    [lo, hi]; -1 if none."""
    best = -1.0
    for q in range(n):
        if (sk[q] == TRIM and sr[q] >= lo and sd[q] <= hi
                and (trim_holds(si[q], pa) or trim_holds(si[q], pb))):
            if best < 0 or su[q] < best:
                best = su[q]
    return best


@njit(cache=True, nogil=True, inline="always")
def _next_surface(sk, start, n):  # pragma: no cover - numba
    """Index of the first surface (not trim) entry of the sorted sequence ``sk[:n]`` at or
    after ``start``; n if none."""
    q = start
    while q < n and sk[q] == TRIM:
        q += 1
    return q


@njit(cache=True, nogil=True, inline="always")
def _rim_from(reach, ident, last):  # pragma: no cover - numba
    """Depth from which trim fragments may be the rim of back face ``ident`` met after a
    surface at depth ``last`` (-1: none): behind that surface (a trim at its depth is its
    own) and no nearer than the face's nearest corner (a nearer trim is another edge's: in
    a level of one connected piece the piece says nothing). -1: every trim in front of it."""
    lo = last * (1.0 + DEPTH_TOL) if last >= 0 else -1.0
    z = _nearest_corner(reach, ident)
    if z < np.inf:
        lo = max(lo, z * (1.0 - DEPTH_TOL))
    return lo


@njit(cache=True, nogil=True, inline="always")
def _nearest_corner(reach, ident):  # pragma: no cover - numba
    """Depth from v* of face ``ident``'s nearest corner; inf without the view's vertices
    (``Reach.cam`` empty) or a face."""
    if reach.cam.shape[0] == 0 or ident < 0:
        return np.inf
    f = reach.faces[ident]
    return min(-reach.cam[f[0], 2], -reach.cam[f[1], 2], -reach.cam[f[2], 2])


@njit(cache=True, nogil=True, inline="always")
def _front_rim(reach, ident, d):  # pragma: no cover - numba
    """Depth from which trim fragments may be the rim of front face ``ident`` met at depth d,
    the face of a simple interval: its nearest corner, when nearer. A face receding from its
    rim (a wall running away from the corner of another the ray passes through, in a level
    of single-sided walls) has that rim in front of it along the ray, at the corner wall's
    depth, and eyes of the sphere that pass the rim look into the interval from its side.
    Without the view's vertices (``Reach.cam`` empty): d, less the tolerance."""
    return min(d, _nearest_corner(reach, ident)) * (1.0 - DEPTH_TOL)


@njit(cache=True, nogil=True, inline="always")
def _back_of_hidden(h, closed, reach, ident):  # pragma: no cover - numba
    """Whether back face ``ident`` belongs to the closed part h - 1 whose front face hid,
    and no eye of the sphere sees its front (``_two_sided``)."""
    return h > 0 and closed[ident] + 1 == h and not _two_sided(reach, ident)


@njit(cache=True, nogil=True, inline="always")
def _two_sided(reach, ident):  # pragma: no cover - numba
    """Whether face ``ident``'s plane passes through the sphere: met from behind by v*'s
    ray, it is still seen face on by the eyes on its other side (a post's side face whose
    plane cuts the sphere, behind its top from v*), so it is never a part's unseen back."""
    t = reach.facing_of
    return ident < t.shape[0] and t[ident] == AMBIGUOUS


@njit(cache=True, nogil=True, inline="always")
def _apart(closed, front, back):  # pragma: no cover - numba
    """Whether faces ``front`` and ``back`` cannot bound one solid: one of them belongs to a
    closed part (``topology.closed_components``) the other does not belong to."""
    a, b = closed[front], closed[back]
    return a != b and (a >= 0 or b >= 0)


@njit(cache=True, nogil=True)
def resolve_pixel(kb, closed, piece, reach, p, final, vis, stats):  # pragma: no cover
    """Resolve pixel p's trim sequence in the k-buffers ``kb`` (``kbuffer.KBuffer``; see the
    module docstring); compacts the residual sequence back into the k-buffer and records the
    hidden span of each validated interval in ``spans`` / ``n_spans`` and the depth of its
    first surface in ``first``. Returns True when the pixel got sealed. ``hid`` (n,) int64
    remembers, across layers, the closed part (1 + ``closed[id]``, 0 none) of the front face
    that hid in an umbra since the last front face seen. ``closed`` (m,) and ``piece`` (m,)
    int64: each triangle id's closed part (``topology.closed_components``) and connected
    piece (``topology.connected_pieces``); ``reach`` (``Reach``): the view, for how deep a
    single-sided front face's trims may lie.
    ``stats`` (4,): validated intervals, terminators, entries resolved, single-sided trims.
    """
    return resolve_into(kb, closed, piece, reach, p, final, vis, stats, _scratch(K))


@njit(cache=True, nogil=True, inline="always", **NO_REFCOUNT)
def resolve_into(kb, closed, piece, reach, p, final, vis, stats, scratch):  # pragma: no cover
    """``resolve_pixel`` with its scratch passed in (``SortScratch``, one per thread: an
    allocation per pixel resolve cost as much as a short sequence)."""
    depth, kinds, idents, umbra, count = kb.depth, kb.kind, kb.ident, kb.umbra, kb.count
    far = kb.far
    cover, seal, spans, n_spans, first, hid = (kb.cover, kb.seal, kb.spans, kb.n_spans,
                                               kb.first, kb.hid)
    sd, sk, si, su, sr = scratch
    n = count[p]
    trims = 0
    for q in range(n):
        i, j = q >> LANE_BITS, q & LANE_MASK
        sd[q] = depth[i, p, j]
        sk[q] = kinds[i, p, j]
        si[q] = idents[i, p, j]
        # A surface's umbra and far end are never read (nor written: ``raster._insert``):
        # two cache lines a pixel spared.
        if sk[q] == TRIM:
            trims += 1
            su[q] = umbra[i, p, j]
            sr[q] = far[i, p, j]
    _sort(sd, sk, si, su, sr, n)
    cov = cover[p]
    i = 0
    keep_from = n  # first surface entry of the carried run (n: none)
    last = -1.0  # depth of the last resolved surface entry
    sealed = False
    while i < n:
        if sk[i] == TRIM:
            i += 1
            continue
        d = sd[i]
        tol = DEPTH_TOL * d
        if d <= cov:
            if sk[i] != BACK:
                hid[p] = closed[si[i]] + 1
            # Hidden, it still stands in the way of what lies behind it: all of it (the pixel
            # is sealed there) or up to its own umbra (a hidden span).
            uf = _self_umbra(reach, si[i], p, d)
            if uf > cov:
                if uf == np.inf:
                    seal[p] = _deepest_over_pixel(reach, si[i], p, d)
                    sealed = True
                    break
                _push_span(spans, n_spans, p, _deepest_over_pixel(reach, si[i], p, d), uf)
                cov = uf
            # A hidden front face closed by the back face right after it, with no trim
            # fragment of theirs in between, ends the ray as a terminator does: no eye sees
            # past that solid here, whether or not any eye sees the solid (not reported).
            # Two faces of open geometry (a level's walls, one open part) need not bound a
            # solid: then the back face's trims up to the next surface count too, as when it
            # is read on its own (which they would validate).
            if sk[i] != BACK:
                j = _next_surface(sk, i + 1, n)
                if j < n and sk[j] == BACK and not _apart(closed, si[i], si[j]):
                    hi = sd[j] * (1.0 + DEPTH_TOL)
                    if closed[si[i]] < 0:
                        q = _next_surface(sk, j + 1, n)
                        # Nothing after it yet: what validates it may come in a later layer.
                        hi = sd[q] * (1.0 + DEPTH_TOL) if q < n else (np.inf if final
                                                                      else -1.0)
                    if hi >= 0 and (trims == 0 or _umbra_in(
                            sd, sk, si, su, sr, n, d - tol, hi, piece[si[i]],
                            piece[si[j]]) < 0):
                        # The solid's back face, seen face on from its other side where
                        # its plane cuts the sphere, unless an umbra holds it too.
                        if sd[j] > cov and _two_sided(reach, si[j]):
                            vis[si[j]] = 1
                        seal[p] = d
                        sealed = True
                        break
            last = d
            i += 1
            continue
        # The run of this facing, then the run of the other facing (trim entries between
        # them do not break a run).
        k0 = sk[i]
        j = i
        end_first = i
        while j < n and (sk[j] == k0 or sk[j] == TRIM):
            if sk[j] == k0:
                end_first = j
            j += 1
        # The interval closes at the first face of the other facing (the paper's simple
        # interval [f, b], extended over the preceding run of front faces); further faces of
        # that facing are walked on their own: uncovered, they terminate (conservative).
        end_second = -1
        while j < n:
            if sk[j] != TRIM:
                if sk[j] != k0:
                    end_second = j
                break
            j += 1
        if first[p] == np.inf:
            first[p] = d
        if end_second < 0 or k0 == BACK or end_first > i or _apart(closed, si[i],
                                                                      si[end_second]):
            if end_second < 0 and not final:
                keep_from = i
                break
            # Single-sided reading: this face, up to the next surface. A back face always reads
            # so (nothing closes it: single-sided geometry seen from behind, or the back of
            # something whose front lies in an umbra), and so do each front face but the last
            # of a run and a front face apart from its back face (module docstring).
            q = _next_surface(sk, i + 1, n)
            nxt = sd[q] if q < n else 1e300
            if k0 != BACK or not _back_of_hidden(hid[p], closed, reach, si[i]):
                vis[si[i]] = 1
            if k0 != BACK:
                hid[p] = 0
            # Up to the next surface, trims at its depth included (see the module docstring).
            u = -1.0
            if trims:  # with no trim held, no umbra can be found (the pixel's last entry)
                hi = nxt + DEPTH_TOL * min(nxt, 1e290)
                if k0 != BACK:
                    hi = min(hi, _front_reach(reach, si[i], p, d) + tol)
                own = piece[si[i]]
                # A back face read so closes what the ray was inside since the last surface
                # (from v* if none): its piece's rim may lie in front of it along the ray (a
                # sloped wall seen from behind, receding from the edge an eye of the sphere
                # sees past), so its trims count from just behind that surface (a trim at the
                # surface's own depth is that surface's).
                lo = d - tol
                if k0 == BACK:
                    lo = _rim_from(reach, si[i], last)
                u = _umbra_in(sd, sk, si, su, sr, n, lo, hi, own, own)
            last = d
            if u >= 0:
                u = max(u, _self_umbra(reach, si[i], p, d))
                stats[3] += 1
                if u == np.inf:
                    # The face alone hides everything behind it: the pixel ends here.
                    seal[p] = _deepest_over_pixel(reach, si[i], p, d)
                    sealed = True
                    break
                if u > d:
                    _push_face_span(spans, n_spans, reach, si[i], p, d, u)
                if u > cov:
                    cov = u
                i += 1
                continue
            stats[1] += 1
            seal[p] = d
            sealed = True
            break
        b = sd[end_second]
        if k0 != BACK or not _back_of_hidden(hid[p], closed, reach, si[i]):
            vis[si[i]] = 1
        if k0 != BACK:
            # A front face seen opens a new stretch of the ray.
            hid[p] = 0
        # Its trims count as deep as an eye can pass the front face's rim: a thin board
        # crossed nearly edge-on is left within millimetres of its front, and the far rim
        # eyes see past lies behind its back face on the ray, behind the next board too.
        # (No bound on the eyes, or a ray along the face: the paper's interval alone.)
        u = -1.0
        if trims:
            hi = b * (1.0 + DEPTH_TOL)
            deep = _front_reach(reach, si[i], p, d)
            if deep < np.inf:
                hi = max(hi, deep + tol)
            u = _umbra_in(sd, sk, si, su, sr, n, _front_rim(reach, si[i], d), hi,
                          piece[si[i]], piece[si[end_second]])
        last = b
        if u >= 0:
            # The interval's front face hides on its own too (``_self_umbra``).
            u = max(u, _self_umbra(reach, si[i], p, d))
            stats[0] += 1
            # The closing back face is the occluder's own back, never seen, only when it and
            # the face before it (the simple interval's front) belong to one closed part; any
            # other back face beyond the umbra (a single-sided wall seen from behind, as in
            # lavaducts) may be seen past the occluder's silhouette: reported, and the walk
            # goes on behind it as before. Inside the umbra, it hides on its own what lies
            # behind it (a cover is one depth: a back face seen leaves what lies between the
            # umbra and it to later layers).
            ub = u
            if u >= b * (1.0 - DEPTH_TOL):
                ub = max(u, _self_umbra(reach, si[end_second], p, b))
            upto = max(ub, b)
            part = closed[si[end_second]]
            own = part >= 0 and part == closed[si[end_first]]
            if u < b * (1.0 - DEPTH_TOL) and (not own or _two_sided(reach, si[end_second])):
                vis[si[end_second]] = 1
                upto = u
            _push_face_span(spans, n_spans, reach, si[i], p, sd[i], upto)
            cov = max(cov, ub)
            if cov == np.inf:
                seal[p] = _deepest_over_pixel(reach, si[i], p, sd[i])
                sealed = True
                break
            i = end_second + 1
            continue
        stats[1] += 1
        seal[p] = d
        sealed = True
        break
    stats[2] += n
    cover[p] = cov
    if sealed:
        count[p] = 0
        return True
    # The residual sequence: the carried run and every trim fragment that may still validate
    # an interval that starts at or behind it.
    w = 0
    if keep_from < n:
        # A carried back face keeps the trims since the last surface (see above), a carried
        # front face those from its rim (``_front_rim``).
        lim = (_front_rim(reach, si[keep_from], sd[keep_from]) if sk[keep_from] != BACK
               else _rim_from(reach, si[keep_from], last))
    elif last >= 0:
        lim = last * (1.0 - DEPTH_TOL)
    else:
        lim = -1.0
    for q in range(n):
        if (sk[q] == TRIM and sr[q] >= lim) or (sk[q] != TRIM and q >= keep_from):
            i, j = w >> LANE_BITS, w & LANE_MASK
            depth[i, p, j] = sd[q]
            kinds[i, p, j] = sk[q]
            idents[i, p, j] = si[q]
            if sk[q] == TRIM:
                umbra[i, p, j] = su[q]
                far[i, p, j] = sr[q]
            w += 1
    count[p] = w
    return False


@njit(cache=True, nogil=True, parallel=True)
def resolve_layer(kb, closed, piece, reach, res, final, vis, stats, stop, held,
                  tally):  # pragma: no cover
    """Resolve the pixels marked active in this layer (each band's list in ``kb.queue``,
    filled by ``raster.raster_surfaces``), or every pixel holding entries when ``final``, of
    one view's k-buffers ``kb`` (``kbuffer.KBuffer``), parallel over bands of rows; ``stats``
    (n_bands, 4) accumulates ``resolve_pixel``'s counters per band.
    On the way: ``held`` (res * res,) gets 1 where a resolved pixel holds entries, ``tally``
    (n_bands, 2) gets per band the entries held before resolving (``kb.held_entries``, kept
    by the rasterizers) and adds the pixels resolved (the view's statistics, without a
    full-frame pass per layer)."""
    n_bands = (res + 7) // 8
    stride = band_stride(n_bands)
    # The body is a function of its own: numba's parallel passes drop stores made in a
    # prange body through a named group's arrays (``kb.seal[p] = ...``).
    for j in prange(n_bands):
        if flag_set(stop):
            continue
        band = np.int64((j * stride) % n_bands)
        _resolve_band(kb, closed, piece, reach, res, final, vis, stats[band], held, tally,
                      band, _scratch(K))


@njit(cache=True, nogil=True, **NO_REFCOUNT)
def _resolve_band(kb, closed, piece, reach, res, final, vis, stats, held, tally, band,
                  scratch):  # pragma: no cover - numba
    """``resolve_layer``'s band of 8 rows (its arguments; ``stats`` the band's row).
    ``resolve_into`` is inlined here: a call per pixel passes some 250 words of array
    descriptors (``kb``, ``reach``), which cost more than resolving a pixel of one entry, and
    compiled without numba's runtime it counts no references to them either."""
    count, stencil, active, overflow = kb.count, kb.stencil, kb.active, kb.overflow
    queue, queued, held_entries = kb.queue, kb.queued, kb.held_entries
    tally[band, 0] = held_entries[band]
    base = band * 8 * res
    n = min(res, band * 8 + 8) * res - base if final else queued[band]
    for i in range(n):
        p = base + i if final else queue[base + i]
        if count[p] > 0:
            held[p] = 1
        if active[p]:
            tally[band, 1] += 1
        if overflow[p] or stencil[p] == SEALED or count[p] == 0:
            active[p] = 0
            continue
        active[p] = 0
        c0 = count[p]
        if resolve_into(kb, closed, piece, reach, p, final, vis, stats, scratch):
            stencil[p] = SEALED
        held_entries[band] += count[p] - c0
    queued[band] = 0
