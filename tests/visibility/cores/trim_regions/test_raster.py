"""``raster_trims`` visits only the columns a row of a trim region can reach: the same entries,
in the same order, as the region test tried at every pixel of the region's box."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.kbuffer import TRIM, K, KBuffer
from visibility.cores.trim_regions.raster import _affine_range, raster_trims


def _every_pixel(trims: np.ndarray, res: int, tan: float, margin: float) -> list[list[tuple]]:
    """Per pixel, the (depth, umbra) entries the region test admits, trims in order, over each
    trim's pixel box (the edge's ends widened by the larger width and the margin)."""
    half = 0.5 * res
    out: list[list[tuple]] = [[] for _ in range(res * res)]
    for q in range(len(trims)):
        nx, ny, nz, side, u0, v0, u1, v1, iz0, iz1, w0, w1 = trims[q]
        nl = np.hypot(nx, ny)
        if nl == 0.0:
            continue
        ex, ey = u1 - u0, v1 - v0
        el2 = ex * ex + ey * ey
        lm = margin / np.sqrt(el2) if el2 > 0 else 1e300
        grow = max(w0, w1) + margin
        ya = max(0, int(np.floor((1.0 - (max(v0, v1) + grow) / tan) * half)))
        yb = min(res, int(np.ceil((1.0 - (min(v0, v1) - grow) / tan) * half)) + 1)
        xa = max(0, int(np.floor(((min(u0, u1) - grow) / tan + 1.0) * half)))
        xb = min(res, int(np.ceil(((max(u0, u1) + grow) / tan + 1.0) * half)) + 1)
        for y in range(ya, yb):
            v = (1.0 - (y + 0.5) / half) * tan
            for x in range(xa, xb):
                u = ((x + 0.5) / half - 1.0) * tan
                d = side * (nx * u + ny * v - nz) / nl
                lam = ((u - u0) * ex + (v - v0) * ey) / el2 if el2 > 0 else 0.0
                if d < -margin or lam < -lm or lam > 1.0 + lm:
                    continue
                lc = min(1.0, max(0.0, lam))
                wid = (1.0 - lc) * w0 + lc * w1
                if d > wid:
                    continue
                t = 1.0 / ((1.0 - lc) * iz0 + lc * iz1)
                frac = d / wid if wid > 0 else 0.0
                um = t / (1.0 - frac) if frac < 1.0 - 1e-12 else np.inf
                out[y * res + x].append((t, max(um, t)))
    return out


def _trims(gen: np.random.Generator, n: int, tan: float) -> np.ndarray:
    """Random trim rows: edges anywhere near the view (some short, some long, one pointing at
    v*: a point in the image, its plane's normal only rounding residue), widths from a sliver
    to four times the view (a silhouette beside an eye)."""
    rows = np.empty((n, 12))
    for q in range(n):
        a = gen.uniform(-1.5 * tan, 1.5 * tan, 2)
        b = a + gen.normal(0.0, [0.02, 0.5, 1.5][q % 3] * tan, 2) if q else a.copy()
        za, zb = gen.uniform(0.3, 20.0, 2)
        pa, pb = np.array([a[0] * za, a[1] * za, -za]), np.array([b[0] * zb, b[1] * zb, -zb])
        rows[q, :3] = np.cross(pa, pb)
        rows[q, 3] = gen.choice([-1.0, 1.0])
        rows[q, 4:8] = [a[0], a[1], b[0], b[1]]
        rows[q, 8:10] = [1.0 / za, 1.0 / zb]
        rows[q, 10:12] = gen.choice([0.01, 0.2, 4.0], 2) * tan
    return rows


def test_affine_range_solves_the_row_inequalities():
    assert _affine_range(2.0, 1.0, -1.0, 3.0) == (-1.0, 1.0)
    assert _affine_range(-2.0, 1.0, -1.0, 3.0) == (-1.0, 1.0)
    assert _affine_range(0.0, 1.0, -1.0, 3.0) == (-1e300, 1e300)
    lo, hi = _affine_range(0.0, 5.0, -1.0, 3.0)
    assert lo > hi


def test_trim_rows_match_the_test_at_every_pixel():
    res, tan, margin = 32, 1.0, 0.75 * 2.0 / 32
    trims = _trims(np.random.default_rng(3), 60, tan)
    kb = KBuffer.empty(res * res)
    vis = np.zeros(1, dtype=np.uint8)
    raster_trims(trims, res, tan, margin, kb, vis, np.zeros(1, dtype=np.uint8))
    want = _every_pixel(trims, res, tan, margin)
    assert sum(len(w) for w in want) > 10 * res  # the strips cover much of the view
    for p in range(res * res):
        if len(want[p]) > K:
            assert kb.overflow[p] == 1
            continue
        assert kb.count[p] == len(want[p])
        assert (kb.kind[p, :kb.count[p]] == TRIM).all()
        got = list(zip(kb.depth[p, :kb.count[p]], kb.umbra[p, :kb.count[p]], strict=True))
        assert np.allclose(got, want[p], rtol=1e-12) if want[p] else not got
