"""Occlusion interval resolve per pixel (paper Sec. 4.3, Fig. 9), phase P3, and the gather of
what each pixel found visible (P4).

Per active pixel the trim sequence (its k-buffer) is sorted by depth. Surface entries hidden by
the umbra of an interval validated earlier (``cover``) are skipped. The first open surface
starts an occlusion interval: the run of entries of its facing, closed by the next entry of
the other facing (front faces closed by a back face; a soup wound the other way gives back
faces then front faces, handled alike). An interval is validated when a trim
fragment lies inside it (depth tolerance ``DEPTH_TOL``): its first face goes to the PVS and the
umbra replaces its back face, i.e. everything up to the (smallest) umbra depth of those trim
fragments is hidden, and the walk goes on behind. An interval that is not validated is a
terminator: its first face goes to the PVS and the pixel is sealed. A run with nothing after it
yet is carried to the next layer (its closing faces may lie in a later octree node).

After the last layer (``final``), a carried run is read as single-sided surfaces: each front
face in turn is seen; it is trimmed (validated) when a trim fragment lies between it and the
next one, else it terminates the pixel.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from visibility.cancel import flag_set
from visibility.cores.trim_regions.kbuffer import SEALED, TRIM

#: Relative depth tolerance when testing a trim fragment against an interval (erring towards
#: validation: trimming more only adds false positives).
DEPTH_TOL = 1e-3


@njit(cache=True)
def _sort(depth, kinds, idents, umbra, n, order):  # pragma: no cover - numba
    """Insertion sort of the first n entries by (depth, kind) into ``order``."""
    for i in range(n):
        order[i] = i
    for i in range(1, n):
        j = i
        while j > 0:
            a = order[j - 1]
            b = order[j]
            if depth[a] > depth[b] or (depth[a] == depth[b] and kinds[a] > kinds[b]):
                order[j - 1] = b
                order[j] = a
                j -= 1
            else:
                break


@njit(cache=True)
def _umbra_in(sd, sk, su, n, lo, hi):  # pragma: no cover - numba
    """Smallest umbra depth of the trim entries with depth in [lo, hi]; -1 if none."""
    best = -1.0
    for q in range(n):
        if sk[q] == TRIM and sd[q] >= lo and sd[q] <= hi:
            if best < 0 or su[q] < best:
                best = su[q]
    return best


@njit(cache=True)
def resolve_pixel(depth, kinds, idents, umbra, count, cover, seal, p, final, vis,
                  stats):  # pragma: no cover - numba
    """Resolve pixel p's trim sequence (see the module docstring); compacts the residual
    sequence back into the k-buffer. Returns True when the pixel got sealed.
    ``stats`` (4,): validated intervals, terminators, entries resolved, single-sided trims.
    """
    n = count[p]
    order = np.empty(n, dtype=np.int64)
    _sort(depth[p], kinds[p], idents[p], umbra[p], n, order)
    sd = np.empty(n)
    sk = np.empty(n, dtype=np.int8)
    si = np.empty(n, dtype=np.int32)
    su = np.empty(n)
    for q in range(n):
        sd[q] = depth[p, order[q]]
        sk[q] = kinds[p, order[q]]
        si[q] = idents[p, order[q]]
        su[q] = umbra[p, order[q]]
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
        if end_second < 0:
            if not final:
                keep_from = i
                break
            # Single-sided reading: this face, up to the next surface of the run.
            nxt = 1e300
            for q in range(i + 1, n):
                if sk[q] != TRIM:
                    nxt = sd[q]
                    break
            vis[si[i]] = 1
            u = _umbra_in(sd, sk, su, n, d - tol, nxt + DEPTH_TOL * min(nxt, 1e290))
            last = d
            if u >= 0:
                stats[3] += 1
                if u > cov:
                    cov = u
                i += 1
                continue
            stats[1] += 1
            seal[p] = d
            sealed = True
            break
        b = sd[end_second]
        vis[si[i]] = 1
        u = _umbra_in(sd, sk, su, n, d - tol, b + DEPTH_TOL * b)
        last = b
        if u >= 0:
            stats[0] += 1
            if u > cov:
                cov = u
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
        lim = sd[keep_from] * (1.0 - DEPTH_TOL)
    elif last >= 0:
        lim = last * (1.0 - DEPTH_TOL)
    else:
        lim = -1.0
    for q in range(n):
        if (sk[q] == TRIM and sd[q] >= lim) or (sk[q] != TRIM and q >= keep_from):
            depth[p, w] = sd[q]
            kinds[p, w] = sk[q]
            idents[p, w] = si[q]
            umbra[p, w] = su[q]
            w += 1
    count[p] = w
    return False


@njit(cache=True, parallel=True)
def resolve_layer(depth, kinds, idents, umbra, count, cover, seal, stencil, active, overflow,
                  res, final, vis, stats, stop):  # pragma: no cover - numba
    """Resolve every active pixel (all held pixels when ``final``) of one view, parallel over
    bands of rows; ``stats`` (n_bands, 4) accumulates ``resolve_pixel``'s counters per band."""
    n_bands = (res + 7) // 8
    for band in prange(n_bands):
        if flag_set(stop):
            continue
        for p in range(band * 8 * res, min(res, band * 8 + 8) * res):
            if overflow[p] or stencil[p] == SEALED or count[p] == 0:
                active[p] = 0
                continue
            if not (active[p] or final):
                continue
            active[p] = 0
            if resolve_pixel(depth, kinds, idents, umbra, count, cover, seal, p, final, vis,
                             stats[band]):
                stencil[p] = SEALED
