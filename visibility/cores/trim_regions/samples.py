"""Reading v*'s supersampled renders (phase P4): per pixel, the depth its samples leave open
(the triangles any sample shows are marked by ``ground_truth.mark_seen``)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def open_depth(depth, res, s, k, out, far):  # pragma: no cover - numba
    """out[i * res + j] = the k-th smallest (0-based) of the s x s samples of pixel (i, j) in
    ``depth`` (res * s, res * s) (a render's depths, row-major: pixel (i, j) holds rows
    [i s, (i + 1) s) and columns [j s, (j + 1) s)); ``out`` (res * res,) float64. ``far``
    (res * res,) gets the largest in the same pass, unless it is empty. 0 <= k < s * s."""
    # The k-th smallest of n samples is the (n - k)-th largest: only the n - k largest are
    # kept, in descending order (three of sixteen at the pipeline's k), so most samples cost
    # one comparison.
    t = s * s - k
    for i in prange(res):
        top = np.empty(t)
        for j in range(res):
            n = 0
            for a in range(s):
                for b in range(s):
                    x = np.float64(depth[i * s + a, j * s + b])
                    if n < t:
                        m = n
                        n += 1
                    elif x > top[t - 1]:
                        m = t - 1
                    else:
                        continue
                    while m > 0 and top[m - 1] < x:
                        top[m] = top[m - 1]
                        m -= 1
                    top[m] = x
            out[i * res + j] = top[t - 1]
            if far.shape[0] > 0:
                far[i * res + j] = top[0]
