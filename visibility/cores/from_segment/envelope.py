"""Per-pixel envelopes: the lower envelope over t of the depth chords that cover a pixel's sample.

A pixel's envelope is rows (t0, t1, z0, m) of ``env[px, :cnt]``: sorted, disjoint pieces with
depth z0 + m (t - t0) on [t0, t1], and the owning primitive in ``eid[px, :cnt]``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Envelope pieces shorter than this (in t) do not make a primitive visible: they are float
#: residue at seams, never seen by a sampling camera.
EPS_LEN = 1e-9
#: Envelope capacity (pieces per pixel): starting value, grown x4 in place when a tile needs
#: more, up to MAX_CAP (a memory guard: 256 pixels x MAX_CAP x 36 bytes per thread).
START_CAP = 16
MAX_CAP = 1 << 14

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
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


@njit(**_JIT)
def envelope_insert(env, eid, px, cnt, a, b, za, zb, pid, T, tid, zbound):
    """Depth-composite the chord [a, b] (depth za -> zb, primitive pid) into pixel ``px``'s
    envelope.

    The nearer surface wins; exact ties keep the existing piece; crossing chords are split at
    their intersection (the hinge of intersecting triangles). Only the pieces overlapping [a, b]
    are rewritten, and nothing is when the chord is hidden; they are found by bisection, so a
    chord costs the log of the envelope's length plus the rows it overlaps and the rows after
    it moved along. ``T`` (>= 2 cap + 4, 4) and ``tid`` are scratch. ``zbound`` is the least
    of the pixel's bounds (``bucket_bounds``) over the buckets [a, b] reaches. Returns (new
    count, or -1 when it would exceed the capacity; changed; whether a bucket's bound may have
    changed: a gap was
    filled or a rewritten row reached ``zbound``; otherwise every bucket's bound stands, since
    a lower envelope only comes nearer)."""
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
        for k in range(cnt - 1, hi - 1, -1):
            for r in range(4):
                env[px, k + 1, r] = env[px, k, r]
            eid[px, k + 1] = eid[px, k]
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
    shift = n - (hi - lo)
    if shift > 0:
        for k in range(cnt - 1, hi - 1, -1):
            for r in range(4):
                env[px, k + shift, r] = env[px, k, r]
            eid[px, k + shift] = eid[px, k]
    elif shift < 0:
        for k in range(hi, cnt):
            for r in range(4):
                env[px, k + shift, r] = env[px, k, r]
            eid[px, k + shift] = eid[px, k]
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


#: Buckets of t a pixel's depth bound is kept in (``bucket_bounds``): a chord or primitive is
#: behind a pixel's envelope when it is behind in every bucket it reaches, though the envelope
#: may still leave gaps elsewhere on [0, 1] or reach far deeper in other buckets.
T_BUCKETS = 8


@njit(**_JIT)
def bucket_of(t: float, nb: int) -> int:
    """The bucket (of ``nb`` equal ones on [0, 1]) holding t, clamped to [0, nb - 1]."""
    k = int(t * nb)
    return min(max(k, 0), nb - 1)


@njit(**_JIT)
def bucket_bounds(env, px, cnt, bb, k0, k1):
    """``bb[px, k]`` for k in [k0, k1]: the greatest depth of pixel ``px``'s envelope over bucket
    k of t ([k / nb, (k + 1) / nb], nb = ``bb.shape[1]``) where the envelope covers all of it
    (gaps up to EPS_LEN), else +inf. No chord at or beyond it anywhere in the bucket can change
    the envelope there."""
    nb = bb.shape[1]
    inv = 1.0 / nb
    lo = 0
    top = cnt
    s0 = k0 * inv
    while lo < top:
        mid = (lo + top) >> 1
        if env[px, mid, 1] <= s0:
            lo = mid + 1
        else:
            top = mid
    r = lo
    for k in range(k0, k1 + 1):
        s = k * inv
        e = 1.0 if k == nb - 1 else (k + 1) * inv
        while r < cnt and env[px, r, 1] <= s:
            r += 1
        prev = s
        zmax = 0.0
        j = r
        while j < cnt and env[px, j, 0] < e:
            t0 = env[px, j, 0]
            if t0 - prev > EPS_LEN:
                break
            t1 = env[px, j, 1]
            z0 = env[px, j, 2]
            m = env[px, j, 3]
            a = max(t0, s)
            b = min(t1, e)
            zmax = max(zmax, max(z0 + m * (a - t0), z0 + m * (b - t0)))
            prev = t1
            j += 1
        bb[px, k] = zmax if prev >= e - EPS_LEN else np.inf


@njit(**_JIT)
def chord_behind(bb, px, a, b, za, zb):
    """Whether the chord [a, b] (depth za -> zb, linear in t) is at or beyond pixel ``px``'s
    bucket bounds (``bucket_bounds``) in every bucket it reaches: then inserting it changes
    nothing (exact ties keep the existing piece)."""
    nb = bb.shape[1]
    inv = 1.0 / nb
    k0 = bucket_of(a, nb)
    k1 = bucket_of(b, nb)
    m = (zb - za) / (b - a) if b > a else 0.0
    for k in range(k0, k1 + 1):
        zk = bb[px, k]
        if zk == np.inf:
            return False
        s = max(a, k * inv)
        e = min(b, (k + 1) * inv)
        if min(za + m * (s - a), za + m * (e - a)) < zk:
            return False
    return True
