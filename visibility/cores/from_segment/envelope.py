"""Per-pixel envelopes: the lower envelope over t of the depth chords that cover a pixel's sample.

A pixel's envelope is rows (t0, t1, z0, m) of ``env[px, :cnt]``: sorted, disjoint pieces with
depth z0 + m (t - t0) on [t0, t1], and the owning primitive in ``eid[px, :cnt]``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from visibility.memmove import move_items

#: Envelope pieces shorter than this (in t) do not make a primitive visible: they are float
#: residue at seams, never seen by a sampling camera.
EPS_LEN = 1e-9
#: Envelope capacity (pieces per pixel): starting value, grown x4 in place when a tile needs
#: more, up to MAX_CAP (a memory guard: 256 pixels x MAX_CAP x 36 bytes per thread).
START_CAP = 16
MAX_CAP = 1 << 14

_JIT = dict(cache=True, nogil=True, error_model="numpy")
#: Hot callees of the pixel loop, inlined into it (numba IR inlining): the configuration the
#: published bench_segment runs measured; the arrays they take are borrowed by the caller.
_JIT_INLINE = dict(_JIT, inline="always")


@njit(**_JIT_INLINE)
def _emit(T, tid, n, a, b, za, m, pid):
    """Append piece [a, b] (depth za at a, slope m) to the scratch list, extending the previous
    piece instead when it is the same primitive's contiguous continuation on the same line."""
    if not (b > a):
        return n
    if n > 0 and tid[n - 1] == pid and T[n - 1, 1] == a and T[n - 1, 3] == m:
        T[n - 1, 1] = b
        return n
    T[n, 0] = a
    T[n, 1] = b
    T[n, 2] = za
    T[n, 3] = m
    tid[n] = pid
    return n + 1


@njit(**_JIT_INLINE)
def _shift(env, eid, px, k0, k1, by):
    """Move pixel px's rows [k0, k1) by ``by`` places: one block move each for ``env`` and
    ``eid`` (C-contiguous; the caller keeps the rows within the capacity). An element loop
    moved a row at a time with its index arithmetic, and deep envelopes shift hundreds."""
    if by == 0 or k1 <= k0:
        return
    cap = env.shape[1]
    move_items(env, (px * cap + k0 + by) * 4, (px * cap + k0) * 4, (k1 - k0) * 4)
    move_items(eid, px * cap + k0 + by, px * cap + k0, k1 - k0)


@njit(**_JIT_INLINE)
def envelope_insert(env, eid, px, cnt, a, b, za, zb, pid, T, tid, zbound):
    """Depth-composite the chord [a, b] (depth za -> zb, primitive pid) into pixel ``px``'s
    envelope.

    The nearer surface wins; exact ties keep the existing piece; crossing chords are split at
    their intersection (the hinge of intersecting triangles). Only the pieces overlapping [a, b]
    are rewritten, and nothing is when the chord is hidden; they are found by bisection, so a
    chord costs the log of the envelope's length plus the rows it overlaps, and the rows after
    it move in one block (``_shift``). ``T`` (>= 2 cap + 4, 4) and ``tid`` are scratch.
    ``zbound`` is the pixel's current ``pixel_bound`` (inf while the envelope leaves gaps).
    Returns (new count, or -1 when it would exceed the capacity; changed; whether the bound may
    have changed: a gap was filled or a rewritten row reached ``zbound``; otherwise it stands,
    since a lower envelope only comes nearer)."""
    if not (b > a):
        return cnt, False, False
    mn = (zb - za) / (b - a)
    # Rows are sorted and disjoint, so their ends ascend: the first row ending after a.
    lo = 0
    top = cnt
    while lo < top:
        mid = (lo + top) >> 1
        if env[px, mid, 1] <= a:
            lo = mid + 1
        else:
            top = mid
    hi = lo
    while hi < cnt and env[px, hi, 0] < b:
        hi += 1
    cap = env.shape[1]
    if lo == hi:
        # Falls in a gap: insert as is.
        if cnt + 1 > cap:
            return -1, False, False
        _shift(env, eid, px, hi, cnt, 1)
        env[px, lo, 0] = a
        env[px, lo, 1] = b
        env[px, lo, 2] = za
        env[px, lo, 3] = mn
        eid[px, lo] = pid
        return cnt + 1, True, True
    # Hidden everywhere (no gap, behind at both ends of every overlap): nothing to do.
    cur = a
    hidden = True
    for k in range(lo, hi):
        p0 = env[px, k, 0]
        if p0 > cur:
            hidden = False
            break
        o1 = min(env[px, k, 1], b)
        q0 = env[px, k, 2]
        mp = env[px, k, 3]
        if za + mn * (cur - a) < q0 + mp * (cur - p0) or za + mn * (o1 - a) < q0 + mp * (o1 - p0):
            hidden = False
            break
        cur = o1
    if hidden and cur >= b:
        return cnt, False, False
    n = 0
    cur = a
    won = False
    rebound = False
    for k in range(lo, hi):
        p0 = env[px, k, 0]
        p1 = env[px, k, 1]
        q0 = env[px, k, 2]
        mp = env[px, k, 3]
        qi = eid[px, k]
        if max(q0, q0 + mp * (p1 - p0)) >= zbound:
            rebound = True
        if p0 > cur:
            n = _emit(T, tid, n, cur, p0, za + mn * (cur - a), mn, pid)
            won = True
            rebound = True
            cur = p0
        elif p0 < cur:
            n = _emit(T, tid, n, p0, cur, q0, mp, qi)
        o0 = cur
        o1 = min(p1, b)
        n0 = za + mn * (o0 - a)
        e0 = q0 + mp * (o0 - p0)
        d0 = n0 - e0
        d1 = (za + mn * (o1 - a)) - (q0 + mp * (o1 - p0))
        if d0 >= 0.0 and d1 >= 0.0:
            n = _emit(T, tid, n, o0, o1, e0, mp, qi)
        elif d0 <= 0.0 and d1 <= 0.0:
            n = _emit(T, tid, n, o0, o1, n0, mn, pid)
            won = True
        else:
            tc = o0 + (o1 - o0) * (d0 / (d0 - d1))
            tc = min(max(tc, o0), o1)
            if d0 < 0.0:
                won = won or tc > o0
                n = _emit(T, tid, n, o0, tc, n0, mn, pid)
                n = _emit(T, tid, n, tc, o1, q0 + mp * (tc - p0), mp, qi)
            else:
                won = won or o1 > tc
                n = _emit(T, tid, n, o0, tc, e0, mp, qi)
                n = _emit(T, tid, n, tc, o1, za + mn * (tc - a), mn, pid)
        cur = o1
        if p1 > b:
            n = _emit(T, tid, n, b, p1, q0 + mp * (b - p0), mp, qi)
    if cur < b:
        n = _emit(T, tid, n, cur, b, za + mn * (cur - a), mn, pid)
        won = True
        rebound = True
    if not won:
        return cnt, False, False
    new_cnt = cnt - (hi - lo) + n
    if new_cnt > cap:
        return -1, False, False
    _shift(env, eid, px, hi, cnt, n - (hi - lo))
    for k in range(n):
        for r in range(4):
            env[px, lo + k, r] = T[k, r]
        eid[px, lo + k] = tid[k]
    return new_cnt, True, rebound


@njit(**_JIT)
def _grow(env, eid, cnt, npx, cap):
    """Envelope storage with room for ``cap`` pieces per pixel, holding the current pieces of the
    first ``npx`` pixels; fresh insertion scratch to match."""
    env2 = np.empty((env.shape[0], cap, 4))
    eid2 = np.empty((env.shape[0], cap), dtype=np.int32)
    for p in range(npx):
        for k in range(cnt[p]):
            for r in range(4):
                env2[p, k, r] = env[p, k, r]
            eid2[p, k] = eid[p, k]
    return env2, eid2, np.empty((2 * cap + 8, 4)), np.empty(2 * cap + 8, dtype=np.int32)


@njit(**_JIT)
def pixel_bound(env, px, cnt):
    """Greatest depth of a pixel's envelope when it covers all of [0, 1] (gaps up to EPS_LEN),
    else +inf: no chord at or beyond it can change the envelope."""
    if cnt == 0 or env[px, 0, 0] > EPS_LEN or env[px, cnt - 1, 1] < 1.0 - EPS_LEN:
        return np.inf
    prev = 0.0
    zmax = 0.0
    for k in range(cnt):
        t0 = env[px, k, 0]
        if t0 - prev > EPS_LEN:
            return np.inf
        prev = env[px, k, 1]
        z0 = env[px, k, 2]
        zmax = max(zmax, max(z0, z0 + env[px, k, 3] * (prev - t0)))
    if prev < 1.0 - EPS_LEN:
        return np.inf
    return zmax


@njit(**_JIT)
def hides_over(env, px, cnt, lo, hi, z0, slope):  # pragma: no cover - numba
    """Whether pixel px's envelope covers all of [lo, hi] (gaps up to EPS_LEN) nearer than
    the depth z0 + slope t."""
    cur = lo
    for k in range(cnt[px]):
        t0 = env[px, k, 0]
        t1 = env[px, k, 1]
        if t1 <= lo:
            continue
        if t0 >= hi:
            break
        if t0 > cur + EPS_LEN:
            return False
        a = max(t0, lo)
        b = min(t1, hi)
        za = env[px, k, 2]
        m = env[px, k, 3]
        if z0 + slope * a < za + m * (a - t0) or z0 + slope * b < za + m * (b - t0):
            return False
        cur = t1
    return cur >= hi - EPS_LEN
