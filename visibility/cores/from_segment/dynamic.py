"""From-segment coverage of moving triangles (Popescu et al. 2024, Sec. 3.2) and root solvers.

Everything is in camera space relative to the eye at t = 0 (float64). While the camera moves by
``t * d`` (t in [0, 1]) a vertex moves from ``P`` to ``P + dP``; relative to the moving eye it is at
``P + t u`` with ``u = dP - d``. The edge event of Eq. 4 for edge (P, Q) and the pixel ray ``w``,
``w . ((P + t uP) x (Q + t uQ))``, is quadratic in t; the eye-to-plane determinant
``det[A(t), B(t), C(t)]`` is cubic. A pixel centre is covered at t when the three edge values share
a sign (the ray's line crosses the triangle) and the hit depth ``det / (w . N(t))`` is at least the
near distance. Coverage is solved exactly from the roots of these polynomials (up to four
intervals); depth along an interval is a rational function, handed to the envelope as chords
with exact depth at their ends, halved until the midpoint error is below CHORD_TOL (relative)
or the chord is 1 / knots long.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.borrow import NO_REFCOUNT
from visibility.cores.from_segment.static import edge_order

#: Depth returned where a surface is seen exactly edge-on (the true depth diverges there).
FAR_DEPTH = 1e30
#: Relative depth error at a chord's midpoint below which it is not split further.
CHORD_TOL = 1e-4
#: Bisection steps for cubic roots (2^-60 of the unit interval: below float64 resolution).
_BISECT_STEPS = 60

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Helpers called per primitive, tile or row that allocate nothing: no reference counting.
_JIT_NO_NRT = dict(_JIT, **NO_REFCOUNT)


@njit(**_JIT)
def quadratic_roots(a: float, b: float, c: float) -> tuple[int, float, float]:
    """Real roots of ``a t^2 + b t + c`` without cancellation (citardauq form).

    Returns ``(n, r0, r1)`` with ``r0 <= r1`` (n = 0, 1 or 2). ``a`` = 0 falls back to the linear
    root; a vanishing ``a`` is handled by the same formula (the lost root goes to +-inf).
    Non-finite coefficients give no roots.
    """
    scale = max(abs(a), max(abs(b), abs(c)))
    if not (scale > 0.0 and scale < np.inf):
        return 0, 0.0, 0.0
    a /= scale
    b /= scale
    c /= scale
    if a == 0.0:
        if b == 0.0:
            return 0, 0.0, 0.0
        r = -c / b
        return 1, r, r
    disc = b * b - 4.0 * a * c
    if disc < 0.0:
        return 0, 0.0, 0.0
    sq = np.sqrt(disc)
    q = -0.5 * (b + sq) if b >= 0.0 else -0.5 * (b - sq)
    if q == 0.0:
        # b = 0 and c = 0: double root at 0.
        return 2, 0.0, 0.0
    r0 = q / a
    r1 = c / q
    if r0 > r1:
        r0, r1 = r1, r0
    return 2, r0, r1


@njit(**_JIT)
def _cubic(c0: float, c1: float, c2: float, c3: float, t: float) -> float:
    return ((c3 * t + c2) * t + c1) * t + c0


@njit(**_JIT)
def cubic_roots01(c0: float, c1: float, c2: float, c3: float, out: np.ndarray) -> int:
    """Roots in the open interval (0, 1) of ``c0 + c1 t + c2 t^2 + c3 t^3`` where it changes
    sign, written to ``out`` (length >= 3) in increasing order; returns their count.

    The interval is split at the derivative's roots into monotone pieces, each bisected.
    """
    n, d0, d1 = quadratic_roots(3.0 * c3, 2.0 * c2, c1)
    # Monotone pieces between 0, the derivative's roots in (0, 1) and 1.
    p1 = d0 if n >= 1 and 0.0 < d0 < 1.0 else -1.0
    p2 = d1 if n == 2 and 0.0 < d1 < 1.0 and d1 > d0 else -1.0
    cnt = 0
    lo_prev = 0.0
    for k in range(3):
        nxt = p1 if k == 0 else (p2 if k == 1 else 1.0)
        if nxt < 0.0:
            continue
        lo = lo_prev
        hi = nxt
        lo_prev = nxt
        flo = _cubic(c0, c1, c2, c3, lo)
        fhi = _cubic(c0, c1, c2, c3, hi)
        if flo == 0.0 and lo > 0.0 and (cnt == 0 or out[cnt - 1] != lo):
            # An exact root at a critical point (an inflection through zero).
            out[cnt] = lo
            cnt += 1
            continue
        if not ((flo < 0.0 and fhi > 0.0) or (flo > 0.0 and fhi < 0.0)):
            continue
        for _ in range(_BISECT_STEPS):
            mid = 0.5 * (lo + hi)
            if mid <= lo or mid >= hi:
                break
            fm = _cubic(c0, c1, c2, c3, mid)
            if (fm < 0.0) == (flo < 0.0) and fm != 0.0:
                lo = mid
                flo = fm
            else:
                hi = mid
        out[cnt] = 0.5 * (lo + hi)
        cnt += 1
    return cnt


@njit(**_JIT)
def add_roots01(a: float, b: float, c: float, buf: np.ndarray, k: int) -> int:
    """Append the roots in (0, 1) of ``a t^2 + b t + c`` to ``buf[k:]``; returns the new k."""
    m, r0, r1 = quadratic_roots(a, b, c)
    if m >= 1 and r0 > 0.0 and r0 < 1.0:
        buf[k] = r0
        k += 1
    if m == 2 and r1 > 0.0 and r1 < 1.0 and r1 != r0:
        buf[k] = r1
        k += 1
    return k


@njit(**_JIT)
def sort_small(buf: np.ndarray, n: int) -> None:
    """Insertion sort of ``buf[:n]`` in place (n is at most a dozen here)."""
    for i in range(1, n):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v


@njit(**_JIT)
def emit_chords(ta: float, tb: float, knots: int, kind: int, pc: np.ndarray, t0: np.ndarray,
                t1: np.ndarray, z0: np.ndarray, z1: np.ndarray, n: int,
                stack: np.ndarray) -> int:
    """Append chords approximating the depth over [ta, tb] to the piece buffers from index n;
    ``kind`` and the per-pixel coefficients ``pc`` select the depth function (``depth_at``).
    A chord is halved while its midpoint depth is off by more than CHORD_TOL (relative) and it
    is longer than 1 / knots; chord ends carry exact depths. ``stack`` is (>= 64, 4) scratch.
    Returns the new n (the buffers need room for 2 knots + 2 more)."""
    # Pending intervals (a, b, za, zb), left-most on top, so chords come out in t order.
    stack[0, 0] = ta
    stack[0, 1] = tb
    stack[0, 2] = depth_at(kind, pc, ta)
    stack[0, 3] = depth_at(kind, pc, tb)
    top = 1
    min_len = 1.0 / knots
    limit = stack.shape[0] - 2
    while top > 0:
        top -= 1
        a = stack[top, 0]
        b = stack[top, 1]
        za = stack[top, 2]
        zb = stack[top, 3]
        if b - a > min_len and top < limit:
            m = 0.5 * (a + b)
            zm = depth_at(kind, pc, m)
            if abs(zm - 0.5 * (za + zb)) > CHORD_TOL * (abs(zm) + 1e-9):
                stack[top, 0] = m
                stack[top, 2] = zm
                stack[top + 1, 0] = a
                stack[top + 1, 1] = m
                stack[top + 1, 2] = za
                stack[top + 1, 3] = zm
                top += 2
                continue
        if n < t0.shape[0]:
            t0[n] = a
            t1[n] = b
            z0[n] = za
            z1[n] = zb
            n += 1
    return n


@njit(**_JIT)
def depth_at(kind: int, pc: np.ndarray, t: float) -> float:
    """Depth (metres along the view axis) at time t, clamped to [0, FAR_DEPTH], from per-pixel
    coefficients ``pc``: kind 0, a moving triangle: det(t) / (w . N(t)) with ``pc[0:3]`` the
    quadratic w . N and ``pc[3:7]`` the cubic det; kind 1 / 2, a sphere's near / far hit:
    (o(t) . w -+ sqrt(-G(t))) / |w|^2 with o . w = pc[0] + pc[1] t, -G = pc[2] + pc[3] t + pc[4] t^2
    and |w|^2 = pc[5]."""
    if kind == 0:
        wn = (pc[2] * t + pc[1]) * t + pc[0]
        if wn == 0.0:
            return FAR_DEPTH
        s = (((pc[6] * t + pc[5]) * t + pc[4]) * t + pc[3]) / wn
    else:
        disc = (pc[4] * t + pc[3]) * t + pc[2]
        sq = np.sqrt(disc) if disc > 0.0 else 0.0
        ow = pc[0] + pc[1] * t
        s = (ow - sq) / pc[5] if kind == 1 else (ow + sq) / pc[5]
    if not (s >= 0.0):
        return 0.0
    if s > FAR_DEPTH:
        return FAR_DEPTH
    return s


@njit(**_JIT)
def quad_range01(c0: float, c1: float, c2: float) -> tuple[float, float]:
    """(min, max) of c0 + c1 t + c2 t^2 over t in [0, 1] (no square roots)."""
    f1 = c0 + c1 + c2
    lo = min(c0, f1)
    hi = max(c0, f1)
    if c2 != 0.0:
        tv = -c1 / (2.0 * c2)
        if 0.0 < tv < 1.0:
            fv = c0 + tv * (c1 + c2 * tv)
            lo = min(lo, fv)
            hi = max(hi, fv)
    return lo, hi


@njit(**_JIT)
def _cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@njit(**_JIT)
def _det(ax, ay, az, bx, by, bz, cx, cy, cz):
    x, y, z = _cross(bx, by, bz, cx, cy, cz)
    return ax * x + ay * y + az * z


@njit(**_JIT_NO_NRT)
def moving_setup(P: np.ndarray, U: np.ndarray, W: np.ndarray, coef: np.ndarray) -> None:
    """Coefficients of a moving triangle for ``moving_cover``.

    P : (3, 3) camera-space corners at t = 0 relative to the eye; U : (3, 3) their velocities
    relative to the moving eye; W : (3, 3) world corners (only to order each edge canonically, so
    that triangles sharing an edge get bit-identical event times). ``coef`` (>= 31) receives, per
    edge, the vectors whose dot with (x, y, -1) give the t^0, t^1, t^2 coefficients of its edge
    value (9 per edge), then the cubic of det[A(t), B(t), C(t)].
    """
    for e in range(3):
        i, j, sgn = edge_order(W, e)
        px, py, pz = P[i, 0], P[i, 1], P[i, 2]
        qx, qy, qz = P[j, 0], P[j, 1], P[j, 2]
        upx, upy, upz = U[i, 0], U[i, 1], U[i, 2]
        uqx, uqy, uqz = U[j, 0], U[j, 1], U[j, 2]
        c0 = _cross(px, py, pz, qx, qy, qz)
        c1a = _cross(px, py, pz, uqx, uqy, uqz)
        c1b = _cross(upx, upy, upz, qx, qy, qz)
        c2 = _cross(upx, upy, upz, uqx, uqy, uqz)
        o = 9 * e
        coef[o] = sgn * c0[0]
        coef[o + 1] = sgn * c0[1]
        coef[o + 2] = sgn * c0[2]
        coef[o + 3] = sgn * (c1a[0] + c1b[0])
        coef[o + 4] = sgn * (c1a[1] + c1b[1])
        coef[o + 5] = sgn * (c1a[2] + c1b[2])
        coef[o + 6] = sgn * c2[0]
        coef[o + 7] = sgn * c2[1]
        coef[o + 8] = sgn * c2[2]
    a = P[0]
    b = P[1]
    c = P[2]
    ua = U[0]
    ub = U[1]
    uc = U[2]
    coef[27] = _det(a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2])
    coef[28] = (_det(ua[0], ua[1], ua[2], b[0], b[1], b[2], c[0], c[1], c[2])
                + _det(a[0], a[1], a[2], ub[0], ub[1], ub[2], c[0], c[1], c[2])
                + _det(a[0], a[1], a[2], b[0], b[1], b[2], uc[0], uc[1], uc[2]))
    coef[29] = (_det(ua[0], ua[1], ua[2], ub[0], ub[1], ub[2], c[0], c[1], c[2])
                + _det(ua[0], ua[1], ua[2], b[0], b[1], b[2], uc[0], uc[1], uc[2])
                + _det(a[0], a[1], a[2], ub[0], ub[1], ub[2], uc[0], uc[1], uc[2]))
    coef[30] = _det(ua[0], ua[1], ua[2], ub[0], ub[1], ub[2], uc[0], uc[1], uc[2])


@njit(**_JIT)
def _moving_state(e, t, near, slow, pc):
    """Whether the pixel ray sees the moving triangle at time t (edge quadratics ``e`` (3, 3),
    depth coefficients ``pc``)."""
    pos = True
    neg = True
    for k in range(3):
        v = (e[k, 2] * t + e[k, 1]) * t + e[k, 0]
        if v < 0.0:
            pos = False
        if v > 0.0:
            neg = False
    if not (pos or neg):
        return False
    wn = (pc[2] * t + pc[1]) * t + pc[0]
    if wn == 0.0:
        return False
    if slow:
        return (((pc[6] * t + pc[5]) * t + pc[4]) * t + pc[3]) / wn >= near
    return True


@njit(**_JIT)
def moving_cover(coef: np.ndarray, x: float, y: float, near: float, slow: bool, knots: int,
                 t0: np.ndarray, t1: np.ndarray, z0: np.ndarray, z1: np.ndarray,
                 brk: np.ndarray, stack: np.ndarray) -> int:
    """Depth pieces of a moving triangle at the pixel ray (x, y, -1) over t in [0, 1].

    Coverage intervals are exact (bounded by roots of the edge quadratics and, when the triangle
    may cross the near plane (``slow``), of the near-plane cubic); each is emitted as chords
    split adaptively (``emit_chords``). ``brk`` (>= 48) and ``stack`` (>= 64, 4) are scratch.
    Returns the number of pieces.
    """
    e = brk[16:25].reshape((3, 3))
    pc = brk[32:40]
    # Edge quadratics and their ranges: a cheap rejection (or full acceptance) before roots.
    pos_ok = True
    neg_ok = True
    all_pos = True
    all_neg = True
    for k in range(3):
        o = 9 * k
        c0 = coef[o] * x + coef[o + 1] * y - coef[o + 2]
        c1 = coef[o + 3] * x + coef[o + 4] * y - coef[o + 5]
        c2 = coef[o + 6] * x + coef[o + 7] * y - coef[o + 8]
        e[k, 0] = c0
        e[k, 1] = c1
        e[k, 2] = c2
        lo, hi = quad_range01(c0, c1, c2)
        if hi < 0.0:
            pos_ok = False
        if lo > 0.0:
            neg_ok = False
        if lo < 0.0:
            all_pos = False
        if hi > 0.0:
            all_neg = False
    if not (pos_ok or neg_ok):
        return 0
    pc[0] = e[0, 0] + e[1, 0] + e[2, 0]
    pc[1] = e[0, 1] + e[1, 1] + e[2, 1]
    pc[2] = e[0, 2] + e[1, 2] + e[2, 2]
    pc[3] = coef[27]
    pc[4] = coef[28]
    pc[5] = coef[29]
    pc[6] = coef[30]
    # depth_at's kind (a moving triangle) and the piece count, typed int64 from the start (not
    # literal 0s, as sphere_cover's): emit_chords and depth_at compile once.
    tri = np.int64(0)
    n = np.int64(0)
    if (all_pos or all_neg) and not slow:
        # Inside all three edges for the whole segment (w . N cannot vanish then).
        if all_pos and all_neg:
            return 0
        return emit_chords(0.0, 1.0, knots, tri, pc, t0, t1, z0, z1, n, stack)
    k = 0
    brk[k] = 0.0
    k += 1
    for q in range(3):
        k = add_roots01(e[q, 2], e[q, 1], e[q, 0], brk, k)
    if slow:
        # det - near * (w . N): cubic.
        k += cubic_roots01(pc[3] - near * pc[0], pc[4] - near * pc[1], pc[5] - near * pc[2],
                           pc[6], brk[k:])
    brk[k] = 1.0
    k += 1
    sort_small(brk, k)
    start = -1.0
    for q in range(k - 1):
        a = brk[q]
        b = brk[q + 1]
        if not (b > a):
            continue
        inside = _moving_state(e, 0.5 * (a + b), near, slow, pc)
        if inside and start < 0.0:
            start = a
        elif not inside and start >= 0.0:
            n = emit_chords(start, a, knots, tri, pc, t0, t1, z0, z1, n, stack)
            start = -1.0
    if start >= 0.0:
        n = emit_chords(start, 1.0, knots, tri, pc, t0, t1, z0, z1, n, stack)
    return n
