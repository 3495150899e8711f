"""Planar (2-D) polygon kernels that more than one core needs.

Each core keeps what only it uses in its own package; what two of them compute alike lives
here, written once (numba, float64, any units).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def convex_hull(p: np.ndarray, n: int, h: np.ndarray) -> int:
    """Convex hull of the points ``p[:n]`` (n, 2) by Andrew's monotone chain; sorts ``p[:n]``
    in place and writes the hull's vertices counter-clockwise (positive signed area) into
    ``h`` (at least 2 n rows). Returns their count (1 or 2 for a point or a segment, 0 for
    none). Collinear points are dropped: they lie on the hull's edges."""
    for a in range(1, n):
        x = p[a, 0]
        y = p[a, 1]
        b = a - 1
        while b >= 0 and (p[b, 0] > x or (p[b, 0] == x and p[b, 1] > y)):
            p[b + 1, 0] = p[b, 0]
            p[b + 1, 1] = p[b, 1]
            b -= 1
        p[b + 1, 0] = x
        p[b + 1, 1] = y
    if n <= 2:
        for a in range(n):
            h[a, 0] = p[a, 0]
            h[a, 1] = p[a, 1]
        return n
    k = 0
    for a in range(n):
        while k >= 2 and ((h[k - 1, 0] - h[k - 2, 0]) * (p[a, 1] - h[k - 2, 1])
                          - (h[k - 1, 1] - h[k - 2, 1]) * (p[a, 0] - h[k - 2, 0])) <= 0.0:
            k -= 1
        h[k, 0] = p[a, 0]
        h[k, 1] = p[a, 1]
        k += 1
    lower = k + 1
    for a in range(n - 2, -1, -1):
        while k >= lower and ((h[k - 1, 0] - h[k - 2, 0]) * (p[a, 1] - h[k - 2, 1])
                              - (h[k - 1, 1] - h[k - 2, 1]) * (p[a, 0] - h[k - 2, 0])) <= 0.0:
            k -= 1
        h[k, 0] = p[a, 0]
        h[k, 1] = p[a, 1]
        k += 1
    return k - 1
