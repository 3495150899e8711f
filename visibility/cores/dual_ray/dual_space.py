"""Cell-to-node visibility in the dual ray space (Koltun et al. 2001, Secs. 4 and 5.2).

**The shaft and its ceiling (Sec. 4).** Cell A and node B are boxes; their XZ footprints are
separated along X or Z (the axis of the larger gap; footprints that overlap see each other).
In the shaft's frame ``u`` runs from A to B across the slab ``uA <= u <= uB`` between A's
face F_A and B's face F_B, and ``w`` is lateral. Every segment from a point of A to a point of
B crosses F_A inside ``s1`` and F_B inside ``s2``, the cross-sections of the convex hull of the
two footprints there. The ceiling ``T`` is the plane over the slab through a top edge of each
box that lies above both boxes (through A's far top edge and B's near one when B is higher,
else A's near one and B's far one): every segment between the boxes runs under it. The paper
reduces to T through Observation 1, which holds for occluders closed downwards; real walls stop
at their bottom edge (in the Lyon tile some float a centimetre above where a grazing ray
passes, with no ground under them), so here the floor ``V`` (the plane under both boxes, T
mirrored) bounds the segments from below too. The occluding segment of a wall strip
(``fences``) is the part of it, over the open slab, that spans the shaft from V to T: any
segment between the boxes whose XZ projection crosses it passes there between V and T, so it
hits the wall. For walls standing on the ground and cells above it (2.5D), that is the
paper's cross-section with T; and the test holds whatever the eye's place (inside a building,
under a floating wall): what it calls hidden is hidden.

**The dual ray space (Sec. 5.1).** ``(x, y)`` in the unit square is the segment from
``s1(x)`` to ``s2(y)``. At slab depth ``d = (u - uA) / (uB - uA)`` its lateral position is
``(1 - d) s1(x) + d s2(y)``, affine in (x, y); so for an occluding segment with end points
``(d0, l0)`` and ``(d1, l1)`` the lines ``f_i(x, y) = lateral(d_i) - l_i = 0`` bound the rays
that pass through each end point, and the rays it blocks are ``f0 * f1 <= 0``: between two
lines in the square, a trapeze or a double triangle.

**Rasterized, conservatively (Sec. 5.2).** A pixel counts as covered only when one region
covers it whole: the region's two affine functions keep their signs over the pixel, tested at
its centre with the margin ``a (|df/dx| + |df/dy|)`` (a = half the pixel side), which is
moving each bounding line inwards by the pixel's support distance: the exact form of the
paper's sqrt(2) a shrink (never more than it). An uncovered pixel means visible. Hierarchical:
a 16 x 16 pass first; a square whose centre ray no region blocks ends the test (visible); a
square neither covered nor free is split in four, with only the regions that meet it, down to
the configured resolution (a quadtree below the coarse pass). The answer is exactly that of the
full-resolution raster: a covered square's pixels are covered, and the pixels around a free
centre are not.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from visibility.cores.dual_ray.groups import PieceGrid, Pieces
from visibility.shares import run_shares, take_next

#: Side of the first, coarse raster of the hierarchical test.
COARSE = 16
#: Slack of the sign tests in the dual space, metres of lateral offset: far below anything
#: that decides visibility, above the rounding of coordinates up to 1e7 m.
EPS = 1e-7
_d16 = np.array([abs(q // COARSE - 0.5 * (COARSE - 1)) + abs(q % COARSE - 0.5 * (COARSE - 1))
                 for q in range(COARSE * COARSE)])
_SCAN16 = np.argsort(_d16, kind="mergesort").astype(np.int64)
#: Occluders within this of the slab's faces (metres) are left out: the slab is open. A wall
#: lying in B's near face is what B holds (a wall triangle's own box), not what hides it.
SLAB_TOL = 1e-6


@njit(cache=True, nogil=True)
def shaft_frame(alo, ahi, blo, bhi):  # pragma: no cover - numba
    """The shaft of boxes A and B (each (3,) [min], (3,) [max]).

    Returns
    -------
    frame : (16,) float64 ``[axis, sign, uA, uB, au0, bu1, s1lo, s1hi, s2lo, s2hi, yA, yB,
        gap, ok, yA_low, yB_low]``: the separating axis (0: x, 2: z) and its sign (+1: B on
        the + side), the
        slab's faces ``uA < uB`` and the boxes' far faces ``au0 <= uA``, ``bu1 >= uB`` in the
        frame's ``u = sign * coord[axis]``, the lateral ranges ``s1`` on F_A and ``s2`` on F_B,
        the boxes' tops, the gap, ``ok`` = 0 when the footprints overlap (no shaft), and the
        boxes' bottoms.
    """
    out = np.zeros(16)
    gaps = np.array([blo[0] - ahi[0], alo[0] - bhi[0], blo[2] - ahi[2], alo[2] - bhi[2]])
    k = int(np.argmax(gaps))
    g = gaps[k]
    if not (g > 0.0):
        return out
    axis = 0 if k < 2 else 2
    lat = 2 if axis == 0 else 0
    sgn = 1.0 if k % 2 == 0 else -1.0
    if sgn > 0:
        uA, au0, uB, bu1 = ahi[axis], alo[axis], blo[axis], bhi[axis]
    else:
        uA, au0, uB, bu1 = -alo[axis], -ahi[axis], -bhi[axis], -blo[axis]
    aw0, aw1, bw0, bw1 = alo[lat], ahi[lat], blo[lat], bhi[lat]
    lam = (uA - au0) / (uB - au0)
    kap = (bu1 - uB) / (bu1 - uA)
    out[0] = axis
    out[1] = sgn
    out[2] = uA
    out[3] = uB
    out[4] = au0
    out[5] = bu1
    out[6] = min(aw0, aw0 + lam * (bw0 - aw0))
    out[7] = max(aw1, aw1 + lam * (bw1 - aw1))
    out[8] = min(bw0, bw0 + kap * (aw0 - bw0))
    out[9] = max(bw1, bw1 + kap * (aw1 - bw1))
    out[10] = ahi[1]
    out[11] = bhi[1]
    out[12] = g
    out[13] = 1.0
    out[14] = alo[1]
    out[15] = blo[1]
    return out


@njit(cache=True, nogil=True)
def ceiling(frame, u):  # pragma: no cover - numba
    """Height of the shaft's ceiling T at frame coordinate ``u`` (metres)."""
    uA, uB, au0, bu1, yA, yB = frame[2], frame[3], frame[4], frame[5], frame[10], frame[11]
    if yB >= yA:
        return yA + (yB - yA) * (u - au0) / (uB - au0)
    return yB + (yA - yB) * (bu1 - u) / (bu1 - uA)


@njit(cache=True, nogil=True)
def floor(frame, u):  # pragma: no cover - numba
    """Height of the shaft's floor V at frame coordinate ``u`` (metres): the lowest any segment
    between the boxes passes there (``ceiling`` mirrored)."""
    uA, uB, au0, bu1, yA, yB = frame[2], frame[3], frame[4], frame[5], frame[14], frame[15]
    if yB <= yA:
        return yA + (yB - yA) * (u - au0) / (uB - au0)
    return yA + (yB - yA) * (u - uA) / (bu1 - uA)


@njit(cache=True, nogil=True)
def _keep_nonneg(g0, g1, t0, t1):  # pragma: no cover - numba
    """[t0, t1] cut to where the linear g (g0 at t=0, g1 at t=1) is >= 0 (t0 > t1: empty)."""
    dg = g1 - g0
    if dg == 0.0:
        if g0 < 0.0:
            return 1.0, 0.0
        return t0, t1
    r = -g0 / dg
    if dg > 0.0:
        return max(t0, r), t1
    return t0, min(t1, r)


@njit(cache=True, nogil=True)
def _outside_hull(frame, u0, u1, w0, w1, uA, span):  # pragma: no cover - numba
    """Whether the segment (u0, w0) - (u1, w1) over the slab lies wholly on one side of the
    shaft's hull (then it blocks no ray from s1 to s2)."""
    d0 = min(max((u0 - uA) / span, 0.0), 1.0)
    d1 = min(max((u1 - uA) / span, 0.0), 1.0)
    lo0 = (1.0 - d0) * frame[6] + d0 * frame[8]
    lo1 = (1.0 - d1) * frame[6] + d1 * frame[8]
    hi0 = (1.0 - d0) * frame[7] + d0 * frame[9]
    hi1 = (1.0 - d1) * frame[7] + d1 * frame[9]
    return (w0 > hi0 + EPS and w1 > hi1 + EPS) or (w0 < lo0 - EPS and w1 < lo1 - EPS)


@njit(cache=True, nogil=True)
def _ray_slope(frame):  # pragma: no cover - numba
    """Largest |height change per metre of XZ length| of a segment between the shaft's boxes:
    their heights differ by at most the larger of top-to-bottom spans, over at least the gap."""
    yA, yB, yAl, yBl = frame[10], frame[11], frame[14], frame[15]
    return max(abs(yB - yAl), abs(yA - yBl)) / (frame[3] - frame[2])


@njit(cache=True, nogil=True)
def _lean_margin(frame, du, dw, lam, slope):  # pragma: no cover - numba
    """How far (XZ metres along a ray of the shaft) the real wall of a leaning piece can be
    from where the ray crosses the piece's strip, at most: ``lam / (s - slope g)``, with s the
    smallest |sine| between the piece's XZ direction (du, dw, frame coordinates) and a ray's,
    and g the rays' largest height slope (``_ray_slope``). Infinite when some ray runs along
    the piece or climbs as fast as the wall leans (no bound: the piece must not occlude).

    Why: a ray crossing the strip at height y, a distance s along it from there, has moved
    s sin(theta) off the strip's plane, and the wall is off it by o(y + g s), |o| <= lam,
    changing by ``slope`` per metre of height; they meet where s sin(theta) = o(y + g s),
    within lam / (|sin(theta)| - slope |g|)."""
    gap = frame[3] - frame[2]
    length = np.hypot(du, dw)
    if not length > 0.0:
        return np.inf
    # The rays' XZ directions are (1, m), m from (s2 - s1) / gap over the hull's sections.
    m0 = (frame[8] - frame[7]) / gap
    m1 = (frame[9] - frame[6]) / gap
    f0 = dw - du * m0
    f1 = dw - du * m1
    if f0 * f1 <= 0.0:
        return np.inf
    # |sine| is smallest at an end of the range of directions (it has no zero inside).
    s = min(abs(f0) / np.sqrt(1.0 + m0 * m0), abs(f1) / np.sqrt(1.0 + m1 * m1)) / length
    den = s - slope * _ray_slope(frame)
    if not den > 0.0:
        return np.inf
    return lam / den


@njit(cache=True, nogil=True)
def cut_piece(frame, px, pz, qx, qz, tp, tq, bp, bq, out, lam=0.0,
              slope=0.0):  # pragma: no cover - numba
    """The occluding segment of one fence piece in the shaft: the part of it over the open
    slab whose strip spans the shaft from floor to ceiling (bottom <= V, top >= T), as
    ``out = [d0, l0, d1, l1, kept0, kept1]`` (slab depth 0..1, lateral metres; kept: the end is
    the piece's own, not cut). Every segment between the
    boxes whose XZ projection crosses that part passes it between V and T: it hits the wall.
    Returns False when none of it occludes inside the shaft's hull.

    A leaning piece (``lam`` > 0: its wall strays up to ``lam`` metres from the strip,
    ``slope`` metres per metre of height, ``fences.Fences.lean``) is first shrunk by
    ``_lean_margin``: a ray of the shaft that crosses the shrunk strip meets the real wall
    within that distance, inside the strip's uncut part and the slab."""
    axis, sgn, uA, uB = int(frame[0]), frame[1], frame[2], frame[3]
    if axis == 0:
        pu, pw, qu, qw = sgn * px, pz, sgn * qx, qz
    else:
        pu, pw, qu, qw = sgn * pz, px, sgn * qz, qx
    t0, t1 = 0.0, 1.0
    du = qu - pu
    margin = 0.0
    if lam > 0.0 and frame[10] > -1e299:  # (a heightless frame keeps every piece)
        margin = _lean_margin(frame, qu - pu, qw - pw, lam, slope)
        if not margin < np.inf:
            return False
        length = np.hypot(qu - pu, qw - pw)
        t0 = margin / length
        t1 = 1.0 - margin / length
        if t0 > t1:
            return False
        # Heights: the real crossing is up to margin away along the strip (its top and bottom
        # change by their slopes) and along the ray (its height by the ray's slope).
        g = _ray_slope(frame)
        dt = (abs(tq - tp) / length + g) * margin
        db = (abs(bq - bp) / length + g) * margin
        tp, tq, bp, bq = tp - dt, tq - dt, bp + db, bq + db
    # Inside the open slab.
    ua = uA + SLAB_TOL + margin
    ub = uB - SLAB_TOL - margin
    if ua >= ub:
        return False
    if du == 0.0:
        if pu < ua or pu > ub:
            return False
    else:
        a = (ua - pu) / du
        b = (ub - pu) / du
        if a > b:
            a, b = b, a
        t0 = max(t0, a)
        t1 = min(t1, b)
        if t0 > t1:
            return False
    span = uB - uA
    # Outside the shaft's hull on one side (checked again once the heights cut it).
    if _outside_hull(frame, pu + t0 * du, pu + t1 * du, pw + t0 * (qw - pw),
                     pw + t1 * (qw - pw), uA, span):
        return False
    # Top at or above the ceiling, bottom at or below the floor (both linear in t).
    t0, t1 = _keep_nonneg(tp - ceiling(frame, pu), tq - ceiling(frame, qu), t0, t1)
    if t0 > t1:
        return False
    t0, t1 = _keep_nonneg(floor(frame, pu) - bp, floor(frame, qu) - bq, t0, t1)
    if t0 > t1:
        return False
    u0 = pu + t0 * du
    u1 = pu + t1 * du
    w0 = pw + t0 * (qw - pw)
    w1 = pw + t1 * (qw - pw)
    # Outside the hull of the shaft on one side: blocks no ray from s1 to s2.
    if _outside_hull(frame, u0, u1, w0, w1, uA, span):
        return False
    d0 = min(max((u0 - uA) / span, 0.0), 1.0)
    d1 = min(max((u1 - uA) / span, 0.0), 1.0)
    out[0] = d0
    out[1] = w0
    out[2] = d1
    out[3] = w1
    # Whether each end is the piece's own end (it joins the pieces that share it there).
    out[4] = 1.0 if t0 == 0.0 else 0.0
    out[5] = 1.0 if t1 == 1.0 else 0.0
    return True


@njit(cache=True, nogil=True)
def region(frame, d0, l0, d1, l1, out):  # pragma: no cover - numba
    """The dual region of the occluding segment (d0, l0) - (d1, l1): ``out`` = the affine
    functions ``f_i = c_i + a_i x + b_i y`` (i = 0, 1) as ``[c0, a0, b0, c1, a1, b1]``; the
    rays it blocks are ``f0 * f1 <= 0``."""
    s1lo, s1hi, s2lo, s2hi = frame[6], frame[7], frame[8], frame[9]
    L1 = s1hi - s1lo
    L2 = s2hi - s2lo
    out[0] = (1.0 - d0) * s1lo + d0 * s2lo - l0
    out[1] = (1.0 - d0) * L1
    out[2] = d0 * L2
    out[3] = (1.0 - d1) * s1lo + d1 * s2lo - l1
    out[4] = (1.0 - d1) * L1
    out[5] = d1 * L2


@njit(cache=True, nogil=True)
def shaft_regions(frame, seg, top, bot, lean, glo, step, gn, cell_start,
                  cell_items):  # pragma: no cover - numba
    """Dual regions (n, 6) of every fence piece occluding inside the shaft ``frame`` (one per
    segment, for the exact test), the occluding segments (n, 6) and their pieces (n,)."""
    segs, ids = _gather(frame, seg, top, bot, lean, glo, step, gn, cell_start, cell_items)
    regs = np.empty((segs.shape[0], 6))
    for i in range(segs.shape[0]):
        region(frame, segs[i, 0], segs[i, 1], segs[i, 2], segs[i, 3], regs[i])
    return regs, segs, ids


@njit(cache=True, nogil=True)
def _classify(vf, vstart, cand, n_cand, cx, cy, a, out, final):  # pragma: no cover - numba
    """One square of the raster (centre (cx, cy), half side a) against the candidate
    occluders ``cand[:n_cand]`` (``occluders``): 1 when one occluder covers it whole, 2 when
    no occluder blocks its centre ray (a free ray: visible), else 0, with the occluders that
    may meet it written to ``out`` (their count returned second). At the final level only
    coverage is asked."""
    m = 0
    free = True
    for t in range(n_cand):
        g = cand[t]
        neg_all = False
        pos_all = False
        any_nonpos = False
        any_nonneg = False
        cmin = np.inf
        cmax = -np.inf
        for v in range(vstart[g], vstart[g + 1]):
            f = vf[v, 0] + vf[v, 1] * cx + vf[v, 2] * cy
            sp = a * (abs(vf[v, 1]) + abs(vf[v, 2]))
            if f + sp <= -EPS:
                neg_all = True
            if f - sp >= EPS:
                pos_all = True
            if f - sp <= EPS:
                any_nonpos = True
            if f + sp >= -EPS:
                any_nonneg = True
            cmin = min(cmin, f)
            cmax = max(cmax, f)
        if neg_all and pos_all:
            # Found first next time: neighbouring squares are often covered by the same one.
            if t > 0:
                c0 = cand[0]
                cand[0] = cand[t]
                cand[t] = c0
            return 1, 0
        if final:
            continue
        if free and cmin <= EPS and cmax >= -EPS:
            free = False
        if any_nonpos and any_nonneg:
            out[m] = g
            m += 1
    if final:
        return 0, 0
    if free:
        return 2, 0
    return 0, m


@njit(cache=True, nogil=True)
def _centre_out(c):  # pragma: no cover - numba
    """Indices of a c x c grid, centre first, outwards (the coarse pass's order)."""
    if c == COARSE:
        return _SCAN16
    dist = np.empty(c * c)
    for q in range(c * c):
        dist[q] = abs(q // c - 0.5 * (c - 1)) + abs(q % c - 0.5 * (c - 1))
    return np.argsort(dist, kind="mergesort")


@njit(cache=True, nogil=True)
def raster_visible(vf, vstart, resolution, coarse_side):  # pragma: no cover - numba
    """Hierarchical conservative raster test (module docstring): the ``coarse_side`` square
    grid first; each square neither covered whole by one region nor free at its centre is
    split in four, with the regions that meet it, down to pixels of 1 / ``resolution``
    (rounded up to ``coarse_side`` times a power of two).

    Returns
    -------
    visible : True when some pixel at the final resolution is not wholly covered by one region.
    refined : coarse squares that had to be split.
    """
    n = len(vstart) - 1
    if n <= 0:
        return True, 0
    c = min(coarse_side, resolution)
    depth = 0
    while c * (1 << depth) < resolution:
        depth += 1
    lists = np.empty((depth + 2, n), dtype=np.int64)
    counts = np.zeros(depth + 2, dtype=np.int64)
    for r in range(n):
        lists[0, r] = r
    counts[0] = n
    hc = 1.0 / c
    refined = 0
    # Centre first, outwards: a visible node usually has free rays near the middle ray (from
    # the middle of s1 to the middle of s2), and its test ends at the first one found.
    scan = _centre_out(c)
    stack_l = np.empty(4 * (depth + 1) + 4, dtype=np.int64)
    stack_i = np.empty(4 * (depth + 1) + 4, dtype=np.int64)
    stack_j = np.empty(4 * (depth + 1) + 4, dtype=np.int64)
    for q0 in range(c * c):
        i = scan[q0] // c
        j = scan[q0] % c
        if True:
            kind, m = _classify(vf, vstart, lists[0], counts[0], (i + 0.5) * hc,
                                (j + 0.5) * hc,
                                0.5 * hc, lists[1], depth == 0)
            if kind == 1:
                continue
            if kind == 2 or depth == 0:
                return True, refined
            refined += 1
            counts[1] = m
            # Depth first over the quadtree below square (i, j); a square at level l (side
            # hc / 2^l) reads its parent's list lists[l] and writes its own to lists[l + 1].
            top = 0
            for q in range(4):
                stack_l[top] = 1
                stack_i[top] = 2 * i + q // 2
                stack_j[top] = 2 * j + q % 2
                top += 1
            while top > 0:
                top -= 1
                lv, si, sj = stack_l[top], stack_i[top], stack_j[top]
                h = hc / (1 << lv)
                kind, m = _classify(vf, vstart, lists[lv], counts[lv], (si + 0.5) * h,
                                    (sj + 0.5) * h, 0.5 * h, lists[lv + 1], lv == depth)
                if kind == 1:
                    continue
                if kind == 2 or lv == depth:
                    return True, refined
                counts[lv + 1] = m
                for q in range(4):
                    stack_l[top] = lv + 1
                    stack_i[top] = 2 * si + q // 2
                    stack_j[top] = 2 * sj + q % 2
                    top += 1
    return False, refined


#: Rays probed before the raster (dual ray space coordinates): the middle ray first. A probe
#: that no segment blocks is a free ray: the node is visible, and the raster would say so too
#: (no region holds that point, so the pixels around it are not covered).
_PROBES = np.array([[0.5, 0.5], [0.25, 0.25], [0.75, 0.75], [0.25, 0.75], [0.75, 0.25],
                    [0.5, 0.0], [0.5, 1.0], [0.0, 0.5], [1.0, 0.5]])


@njit(cache=True, nogil=True)
def probe_free(frame, segs):  # pragma: no cover - numba
    """Whether one of ``_PROBES`` is a ray that no occluding segment (n, 6) blocks."""
    s1lo, s1hi, s2lo, s2hi = frame[6], frame[7], frame[8], frame[9]
    L1 = s1hi - s1lo
    L2 = s2hi - s2lo
    for q in range(_PROBES.shape[0]):
        x, y = _PROBES[q, 0], _PROBES[q, 1]
        a = s1lo + x * L1
        b = s2lo + y * L2
        free = True
        for i in range(segs.shape[0]):
            d0, d1 = segs[i, 0], segs[i, 2]
            f0 = (1.0 - d0) * a + d0 * b - segs[i, 1]
            f1 = (1.0 - d1) * a + d1 * b - segs[i, 3]
            if f0 * f1 <= 0.0 or abs(f0) <= EPS or abs(f1) <= EPS:
                free = False
                break
        if free:
            return True
    return False


@njit(cache=True, nogil=True)
def node_visible(alo, ahi, blo, bhi, pieces, grid, resolution, coarse_side, mark,
                 stamp):  # pragma: no cover - numba
    """Whether box B may be seen from box A among the fence ``pieces`` (``groups.Pieces``,
    found through ``grid``, ``groups.PieceGrid``), and how it was decided: 0 hidden, 1
    visible by the raster, 2 visible by a probe ray no occluder blocks (``probe_free``), 3
    visible since the footprints overlap; the number of occluding segments in the shaft and
    the coarse pixels refined. ``mark``, ``stamp``: ``_gather_marked``."""
    seg, top, bot, lean, vid = pieces
    glo, step, gn, cell_start, cell_items = grid
    frame = shaft_frame(alo, ahi, blo, bhi)
    if frame[13] == 0.0:
        return 3, 0, 0
    segs, ids = _gather_marked(frame, seg, top, bot, lean, glo, step, gn, cell_start,
                               cell_items, mark, stamp)
    if probe_free(frame, segs):
        return 2, segs.shape[0], 0
    vf, vstart = occluders(frame, segs, ids, vid)
    vis, refined = raster_visible(vf, vstart, resolution, coarse_side)
    return (1 if vis else 0), segs.shape[0], refined


def nodes_visible(alo: np.ndarray, ahi: np.ndarray, blo: np.ndarray, bhi: np.ndarray,
                  pieces: Pieces, grid: PieceGrid, resolution: int,
                  coarse_side: int) -> np.ndarray:
    """``node_visible`` for every box of ``blo, bhi`` (n, 3) against A, in parallel.

    Returns (n, 3) int64: how it was decided (0: hidden, 1-3: visible, ``node_visible``),
    occluding segments, coarse pixels refined."""
    n = blo.shape[0]
    out = np.zeros((n, 3), dtype=np.int64)
    # Runs of boxes, many more than threads so uneven boxes even out, each thread taking the
    # next run as it finishes one. Threads, not a prange loop: compiled into a parallel loop,
    # ``node_visible`` was compiled twice (``visibility.shares``).
    runs = min(n, 64)
    nxt = np.zeros(1, dtype=np.int64)
    run_shares(_nodes_share, max(1, min(numba.get_num_threads(), runs)), alo, ahi, blo, bhi,
               pieces, grid, np.int64(resolution), np.int64(coarse_side), out, runs, nxt)
    return out


@njit(cache=True, nogil=True)
def _nodes_share(alo, ahi, blo, bhi, pieces, grid, resolution, coarse_side, out, runs, nxt,
                 share, k):  # pragma: no cover - numba
    """Share ``share`` of ``nodes_visible``'s ``k`` (its arguments): the next run of boxes of
    ``nxt`` (shared by the shares) until none is left."""
    n = blo.shape[0]
    # One ``mark`` array (``_gather_marked``) for all the share's boxes: it stamps each with
    # the box's index.
    mark = np.full(pieces.seg.shape[0], -1, dtype=np.int64)
    while True:
        t = take_next(nxt)
        if t >= runs:
            break
        for i in range(t * n // runs, (t + 1) * n // runs):
            v, s, r = node_visible(alo, ahi, blo[i], bhi[i], pieces, grid, resolution,
                                   coarse_side, mark, i)
            out[i, 0] = v
            out[i, 1] = s
            out[i, 2] = r


@njit(cache=True, nogil=True)
def _heightless(frame):  # pragma: no cover - numba
    """``frame`` with its ceiling far below and its floor far above every strip: cut_piece then
    keeps every piece over the slab and inside the hull, whatever its heights."""
    f = frame.copy()
    f[10] = -1e300
    f[11] = -1e300
    f[14] = 1e300
    f[15] = 1e300
    return f


@njit(cache=True, nogil=True)
def _box_piece_ids(blo, bhi, seg, glo, step, gn, cell_start, cell_items):  # pragma: no cover
    """Ids of the pieces whose XZ bounds meet box B's footprint."""
    nx, nz = gn[0], gn[1]
    i0 = min(max(int(np.floor((blo[0] - glo[0]) / step)), 0), nx - 1)
    i1 = min(max(int(np.floor((bhi[0] - glo[0]) / step)), 0), nx - 1)
    j0 = min(max(int(np.floor((blo[2] - glo[1]) / step)), 0), nz - 1)
    j1 = min(max(int(np.floor((bhi[2] - glo[1]) / step)), 0), nz - 1)
    total = 0
    for a in range(i0, i1 + 1):
        for b in range(j0, j1 + 1):
            total += cell_start[a * nz + b + 1] - cell_start[a * nz + b]
    ids = np.empty(total, dtype=np.int64)
    n = 0
    for a in range(i0, i1 + 1):
        for b in range(j0, j1 + 1):
            c = a * nz + b
            for e in range(cell_start[c], cell_start[c + 1]):
                p = cell_items[e]
                pa = min(max(int(np.floor((min(seg[p, 0], seg[p, 2]) - glo[0]) / step)), 0),
                         nx - 1)
                pb = min(max(int(np.floor((min(seg[p, 1], seg[p, 3]) - glo[1]) / step)), 0),
                         nz - 1)
                if max(pa, i0) != a or max(pb, j0) != b:
                    continue
                if max(seg[p, 0], seg[p, 2]) < blo[0] or min(seg[p, 0], seg[p, 2]) > bhi[0] \
                        or max(seg[p, 1], seg[p, 3]) < blo[2] \
                        or min(seg[p, 1], seg[p, 3]) > bhi[2]:
                    continue
                ids[n] = p
                n += 1
    return ids[:n]


@njit(cache=True, nogil=True)
def shaft_piece_ids(frame, blo, bhi, seg, top, bot, lean, glo, step, gn, cell_start,
                    cell_items, mark, stamp):  # pragma: no cover - numba
    """Ids of the fence pieces over the slab of ``frame`` inside its hull, heights aside,
    and of those within box B's footprint: the occluders of the shaft of any box inside B
    that shares B's axis. ``mark``, ``stamp``: ``_gather_marked``."""
    _, ids1 = _gather_marked(_heightless(frame), seg, top, bot, lean, glo, step, gn, cell_start,
                             cell_items, mark, stamp)
    ids2 = _box_piece_ids(blo, bhi, seg, glo, step, gn, cell_start, cell_items)
    out = np.empty(len(ids1) + len(ids2), dtype=np.int64)
    out[:len(ids1)] = ids1
    out[len(ids1):] = ids2
    return out


@njit(cache=True, nogil=True)
def _gather(frame, seg, top, bot, lean, glo, step, gn, cell_start,
            cell_items):  # pragma: no cover - numba
    """The fence pieces occluding inside the shaft ``frame``: the occluding segments (n, 6)
    ``[d0, l0, d1, l1, kept0, kept1]`` (``cut_piece``) and the pieces' ids (n,)."""
    mark = np.full(seg.shape[0], -1, dtype=np.int64)
    # An int64 stamp, as its other callers pass (a literal 0 compiles another specialization).
    return _gather_marked(frame, seg, top, bot, lean, glo, step, gn, cell_start, cell_items,
                          mark, np.int64(0))


@njit(cache=True, nogil=True)
def _gather_marked(frame, seg, top, bot, lean, glo, step, gn, cell_start, cell_items, mark,
                   stamp):  # pragma: no cover - numba
    """``_gather`` with the caller's ``mark`` (k,) int64 array: a piece listed in several cells
    of the shaft is taken once, where ``mark[p]`` is not yet ``stamp`` (then set to it). One
    array serves a thread's queries in turn, each with its own stamp, so no query sorts its
    candidates to drop the repeats."""
    axis, sgn, uA, uB = int(frame[0]), frame[1], frame[2], frame[3]
    wlo = min(frame[6], frame[8])
    whi = max(frame[7], frame[9])
    if axis == 0:
        x0, x1 = min(sgn * uA, sgn * uB), max(sgn * uA, sgn * uB)
        z0, z1 = wlo, whi
    else:
        z0, z1 = min(sgn * uA, sgn * uB), max(sgn * uA, sgn * uB)
        x0, x1 = wlo, whi
    nx, nz = gn[0], gn[1]
    i0 = min(max(int(np.floor((x0 - glo[0]) / step)), 0), nx - 1)
    i1 = min(max(int(np.floor((x1 - glo[0]) / step)), 0), nx - 1)
    j0 = min(max(int(np.floor((z0 - glo[1]) / step)), 0), nz - 1)
    j1 = min(max(int(np.floor((z1 - glo[1]) / step)), 0), nz - 1)
    # Columns of cells along the separation axis, nearest to A first; in each, only the cells
    # the shaft's hull reaches (its lateral bounds are linear in the depth), so a long
    # diagonal shaft visits a thin band of cells, not its bounding box.
    lo_u, hi_u = (i0, i1) if axis == 0 else (j0, j1)
    lo_w, hi_w = (j0, j1) if axis == 0 else (i0, i1)
    g_u = glo[0] if axis == 0 else glo[1]
    g_w = glo[1] if axis == 0 else glo[0]
    n_cols = hi_u - lo_u + 1
    span = uB - uA
    band = np.empty((n_cols, 2), dtype=np.int64)
    t_col = np.empty(n_cols)
    total = 0
    for k in range(n_cols):
        col = lo_u + k if sgn > 0 else hi_u - k
        # The column's u range in the frame (u = sgn * coordinate), as slab depths.
        c0 = sgn * (g_u + col * step)
        c1 = sgn * (g_u + (col + 1) * step)
        da = min(max((min(c0, c1) - uA) / span, 0.0), 1.0)
        db = min(max((max(c0, c1) - uA) / span, 0.0), 1.0)
        wl = min((1.0 - da) * frame[6] + da * frame[8], (1.0 - db) * frame[6] + db * frame[8])
        wh = max((1.0 - da) * frame[7] + da * frame[9], (1.0 - db) * frame[7] + db * frame[9])
        w0 = max(int(np.floor((wl - g_w) / step)), lo_w)
        w1 = min(int(np.floor((wh - g_w) / step)), hi_w)
        band[k, 0] = w0
        band[k, 1] = w1
        # The ceiling's lowest point over the column's part of the slab (it is linear in u).
        t_col[k] = min(ceiling(frame, min(max(min(c0, c1), uA), uB)),
                       ceiling(frame, min(max(max(c0, c1), uA), uB)))
        for w in range(w0, w1 + 1):
            a = col if axis == 0 else w
            b = w if axis == 0 else col
            total += cell_start[a * nz + b + 1] - cell_start[a * nz + b]
    cand = np.empty(total, dtype=np.int64)
    n = 0
    for k in range(n_cols):
        col = lo_u + k if sgn > 0 else hi_u - k
        for w in range(band[k, 0], band[k, 1] + 1):
            a = col if axis == 0 else w
            b = w if axis == 0 else col
            c = a * nz + b
            # A cell's pieces come highest top first: the scan stops at the first one under
            # the ceiling's lowest point over the column. Its part in this column cannot
            # reach the ceiling, nor can any later piece's; a part in another column is
            # found there (a piece is listed in every cell it crosses).
            for e in range(cell_start[c], cell_start[c + 1]):
                p = cell_items[e]
                if max(top[p, 0], top[p, 1]) < t_col[k]:
                    break
                # A piece is listed in every cell it crosses: each is cut once.
                if mark[p] != stamp:
                    mark[p] = stamp
                    cand[n] = p
                    n += 1
    # np.bool_, not a literal False: boxes_visible_among passes np.bool_(True), so
    # segments_from compiles once for both.
    return segments_from(frame, cand[:n], seg, top, bot, lean, np.bool_(False))


@njit(cache=True, nogil=True)
def segments_from(frame, ids, seg, top, bot, lean, by_top):  # pragma: no cover - numba
    """The occluding segments (n, 6) of the pieces ``ids`` inside the shaft ``frame``, and
    the ids of those that occlude. With ``by_top`` the ``ids`` come sorted by their highest
    top, highest first (``leaf_piece_ids``): the scan stops at the first piece lower than the
    ceiling's lowest point over the slab, which no later piece can reach either."""
    segs = np.empty((len(ids), 6))
    out_ids = np.empty(len(ids), dtype=np.int64)
    t_min = min(ceiling(frame, frame[2]), ceiling(frame, frame[3])) if by_top else -np.inf
    n = 0
    for e in range(len(ids)):
        p = ids[e]
        if max(top[p, 0], top[p, 1]) < t_min:
            break
        if cut_piece(frame, seg[p, 0], seg[p, 1], seg[p, 2], seg[p, 3], top[p, 0], top[p, 1],
                     bot[p, 0], bot[p, 1], segs[n], lean[p, 0], lean[p, 1]):
            out_ids[n] = p
            n += 1
    return segs[:n], out_ids[:n]


@njit(cache=True, nogil=True)
def _find(parent, i):  # pragma: no cover - numba
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(cache=True, nogil=True)
def occluders(frame, segs, ids, vid):  # pragma: no cover - numba
    """The occluding segments joined where they share an end (a building's walls around a
    corner): connected occluders for the raster.

    A ray (x, y) meets a connected union of segments iff their end points are not all strictly
    on one side of it: ``min_v f_v <= 0 <= max_v f_v`` over its end points v, with ``f_v``
    the affine function of ``region``. So a pixel is covered whole by one connected occluder
    when some end point's function is <= 0 over the whole pixel and some other's >= 0: two
    walls meeting at a corner cover the rays through the corner, which neither covers alone.

    Parameters
    ----------
    segs : (n, 6) occluding segments (``cut_piece``); ids : (n,) their pieces;
    vid : (k, 2) int64 the pieces' end point ids (equal ids: the same XZ point).

    Returns
    -------
    vf : (m, 3) float64 ``[c, a, b]`` of each distinct end point, grouped by occluder.
    start : (g + 1,) int64 CSR offsets of the occluders into ``vf``.
    """
    n = segs.shape[0]
    key = np.empty(2 * n, dtype=np.int64)
    for i in range(n):
        for e in range(2):
            if segs[i, 4 + e] != 0.0:
                key[2 * i + e] = vid[ids[i], e]
            else:
                key[2 * i + e] = -(2 * i + e) - 1
    order = np.argsort(key, kind="mergesort")
    node = np.empty(2 * n, dtype=np.int64)
    m = 0
    for q in range(2 * n):
        if q > 0 and key[order[q]] == key[order[q - 1]]:
            node[order[q]] = m - 1
        else:
            node[order[q]] = m
            m += 1
    parent = np.arange(m)
    for i in range(n):
        ra = _find(parent, node[2 * i])
        rb = _find(parent, node[2 * i + 1])
        if ra != rb:
            parent[ra] = rb
    # Each node's function (from any of its segment ends: they are the same point).
    f = np.empty((m, 3))
    s1lo, s1hi, s2lo, s2hi = frame[6], frame[7], frame[8], frame[9]
    L1 = s1hi - s1lo
    L2 = s2hi - s2lo
    for i in range(n):
        for e in range(2):
            d = segs[i, 2 * e]
            lat = segs[i, 2 * e + 1]
            k = node[2 * i + e]
            f[k, 0] = (1.0 - d) * s1lo + d * s2lo - lat
            f[k, 1] = (1.0 - d) * L1
            f[k, 2] = d * L2
    root = np.empty(m, dtype=np.int64)
    for k in range(m):
        root[k] = _find(parent, k)
    by = np.argsort(root, kind="mergesort")
    vf = np.empty((m, 3))
    start = np.empty(m + 1, dtype=np.int64)
    g = 0
    for q in range(m):
        k = by[q]
        vf[q] = f[k]
        if q == 0 or root[k] != root[by[q - 1]]:
            start[g] = q
            g += 1
    start[g] = m
    return vf, start[:g + 1]


@njit(cache=True, nogil=True, parallel=True)
def leaf_piece_ids(alo, ahi, leaf_lo, leaf_hi, seg, top, bot, lean, glo, step, gn, cell_start,
                   cell_items):  # pragma: no cover - numba
    """Per leaf box (n, 3), the pieces of ``shaft_piece_ids`` for its shaft, as CSR
    (start (n + 1,), ids; each leaf's sorted by the pieces' highest top, highest first), and
    whether the leaf has a shaft at all (``ok``; a leaf over the cell's footprint has none):
    what its triangles' tests draw their occluders from."""
    n = leaf_lo.shape[0]
    counts = np.zeros(n + 1, dtype=np.int64)
    ok = np.zeros(n, dtype=np.bool_)
    runs = min(n, 64)
    for t in prange(runs):
        mark = np.full(seg.shape[0], -1, dtype=np.int64)
        for i in range(t * n // runs, (t + 1) * n // runs):
            frame = shaft_frame(alo, ahi, leaf_lo[i], leaf_hi[i])
            if frame[13] != 0.0:
                ok[i] = True
                counts[i + 1] = len(shaft_piece_ids(frame, leaf_lo[i], leaf_hi[i], seg, top,
                                                    bot, lean, glo, step, gn, cell_start,
                                                    cell_items, mark, 2 * i))
    start = np.cumsum(counts)
    ids = np.empty(start[-1], dtype=np.int64)
    for t in prange(runs):
        mark = np.full(seg.shape[0], -1, dtype=np.int64)
        for i in range(t * n // runs, (t + 1) * n // runs):
            if ok[i]:
                frame = shaft_frame(alo, ahi, leaf_lo[i], leaf_hi[i])
                got = shaft_piece_ids(frame, leaf_lo[i], leaf_hi[i], seg, top, bot, lean, glo,
                                      step, gn, cell_start, cell_items, mark, 2 * i + 1)
                # Highest top first: a test stops at the first piece under its ceiling.
                key = np.empty(len(got))
                for k in range(len(got)):
                    key[k] = -max(top[got[k], 0], top[got[k], 1])
                got = got[np.argsort(key, kind="mergesort")]
                ids[start[i]:start[i] + len(got)] = got
    return start, ids, ok


@njit(cache=True, nogil=True, parallel=True)
def boxes_visible_among(alo, ahi, blo, bhi, lists, pieces, grid, resolution,
                        coarse_side):  # pragma: no cover - numba
    """Like ``nodes_visible``, each box (n, 3) drawing its occluders from its group's pieces
    (``lists``, ``groups.GroupLists``: ``ids[start[g]:start[g + 1]]``, a subset of its shaft's
    at most: still conservative), or from the whole grid when its group has no list
    (``ok[g]`` False)."""
    group, start, ids, ok = lists
    seg, top, bot, lean, vid = pieces
    glo, step, gn, cell_start, cell_items = grid
    n = blo.shape[0]
    out = np.zeros((n, 3), dtype=np.int64)
    for i in prange(n):
        frame = shaft_frame(alo, ahi, blo[i], bhi[i])
        if frame[13] == 0.0:
            out[i, 0] = 1
            continue
        g = group[i]
        if ok[g]:
            segs, sids = segments_from(frame, ids[start[g]:start[g + 1]], seg, top, bot, lean,
                                       np.bool_(True))
        else:
            segs, sids = _gather(frame, seg, top, bot, lean, glo, step, gn, cell_start,
                                 cell_items)
        out[i, 1] = segs.shape[0]
        if probe_free(frame, segs):
            out[i, 0] = 1
            continue
        vf, vstart = occluders(frame, segs, sids, vid)
        vis, refined = raster_visible(vf, vstart, resolution, coarse_side)
        out[i, 0] = 1 if vis else 0
        out[i, 1] = segs.shape[0]
        out[i, 2] = refined
    return out
