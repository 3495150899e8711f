"""Pixel-centre boxes on a square cube face (shared by the from-segment kernels).

A face of ``res`` x ``res`` pixels spans NDC [-1, 1]^2; pixel (row i, column j) has its centre at
x = (j + 0.5) 2 / res - 1, y = 1 - (i + 0.5) 2 / res (``visibility.raster.camera`` conventions).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def pixel_range(umin: float, umax: float, vmin: float, vmax: float, res: int,
                box: np.ndarray, pad: float = 0.0) -> bool:
    """Write into ``box`` (4,) int the pixel-centre box [row0, row1, col0, col1] (inclusive) of
    the NDC rectangle [umin, umax] x [vmin, vmax], widened by ``pad`` pixels (the reach of a
    sample jittered off its pixel centre, 0 to 0.5) and by 1e-6 pixel against rounding;
    False (box untouched) when the widened rectangle holds no pixel centre of the face."""
    h = 0.5 * res
    eps = 1e-6 + pad
    col0 = max(-1.0, (umin + 1.0) * h - 0.5)
    col1 = min(res + 1.0, (umax + 1.0) * h - 0.5)
    row0 = max(-1.0, (1.0 - vmax) * h - 0.5)
    row1 = min(res + 1.0, (1.0 - vmin) * h - 0.5)
    j0 = max(int(np.ceil(col0 - eps)), 0)
    j1 = min(int(np.floor(col1 + eps)), res - 1)
    i0 = max(int(np.ceil(row0 - eps)), 0)
    i1 = min(int(np.floor(row1 + eps)), res - 1)
    if j0 > j1 or i0 > i1:
        return False
    box[0] = i0
    box[1] = i1
    box[2] = j0
    box[3] = j1
    return True
