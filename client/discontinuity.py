"""The discontinuity metric δ of near-far partitioning (Popescu et al. 2022, Eqs. 4-6 as written
in the papers' README).

For a processed frame I and the ground-truth frame I0 of the same camera: let p0 be where the 3D
surface point seen at pixel p of I projects in I0. The neighbourhood N_p holds the pixels q of I
(q != p, with a surface point) whose q0 lies within ε pixels of p0, and

    δ(p) = mean over q in N_p of ( |p - q|_I / |p0 - q0|_I0 ) - 1.

δ is 0 everywhere for I0 itself (p0 = p). A seam (neighbouring surface points shown far apart in
I) gives large δ along it; a smooth warp gives small δ.

Choices. ε defaults to 8 pixels rather than the paper's 17: our frames are 256 pixels wide (the
paper's headset frames are several times larger), so 8 pixels spans a similar share of the field
of view, and the cost grows with ε². Distances |p0 - q0| under ``min_dist`` (default 0.5 pixel)
are clamped to it: two surface points of I that project to (nearly) the same spot of I0 (one
hidden behind the other in I0, or a strong compression) would otherwise give an unbounded ratio
from a single pair. The frame's summary is the mean |δ| over the pixels that have at least one
neighbour.

Inputs are per-pixel world points (NaN where a pixel shows nothing): for a composed frame the
un-morphed point each pixel shows (``client.compose.ComposedFrame.points``), for ground truth
``points_from_depth``. Neighbour search is a grid of ε-sized buckets over the I0 positions,
scanned in parallel with numba.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from visibility.raster.camera import look_rotation, pixel_rays

#: Default neighbourhood radius ε, pixels (see the module docstring; the paper uses 17).
DEFAULT_EPS = 8.0
#: Default floor of |p0 - q0|, pixels.
DEFAULT_MIN_DIST = 0.5


@dataclass(frozen=True)
class Discontinuity:
    """δ of one frame.

    Attributes
    ----------
    delta : (H, W) float64 δ(p); NaN where p shows nothing or has no neighbour.
    mean_abs : mean |δ| over the pixels where it is defined (0.0 when there is none).
    pixels : how many pixels have δ defined.
    """

    delta: np.ndarray
    mean_abs: float
    pixels: int


def points_from_depth(
    depth: np.ndarray, eye: np.ndarray, forward: np.ndarray, tan_x: float, tan_y: float
) -> np.ndarray:
    """(H, W, 3) float64 world points of a depth image ((H, W) view depth ``-z_cam`` in metres,
    +inf where empty -> NaN) of a camera at ``eye`` (3,) looking along ``forward`` (3,)."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    if np.isnan(d).any():
        raise ValueError("depth must not contain NaN (use +inf for empty pixels)")
    e = _check_vec(eye, "eye")
    rot = look_rotation(forward)
    h, w = d.shape
    dirs = pixel_rays(w, h, tan_x, tan_y) @ rot
    out = e + np.where(np.isfinite(d), d, np.nan)[..., None] * dirs
    return out


def _check_vec(v: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite 3-vector, got {v!r}")
    return a


def project_points(
    points: np.ndarray, eye: np.ndarray, forward: np.ndarray, width: int, height: int,
    tan_x: float, tan_y: float,
) -> np.ndarray:
    """(…, 2) float64 image positions (x = column, y = row; pixel (i, j)'s centre is (j, i)) of
    world points (…, 3) in the camera at ``eye`` looking along ``forward``; NaN for NaN points
    and points not in front of the camera."""
    p = np.asarray(points, dtype=np.float64)
    rot = look_rotation(forward)
    c = (p - _check_vec(eye, "eye")) @ rot.T
    z = -c[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = z > 0
        x = (c[..., 0] / (z * tan_x) + 1.0) * (0.5 * width) - 0.5
        y = (1.0 - c[..., 1] / (z * tan_y)) * (0.5 * height) - 0.5
    out = np.stack([x, y], axis=-1)
    out[~ok] = np.nan
    return out


@njit(cache=True, nogil=True, parallel=True)
def _delta_kernel(pix, pos, order, starts, cell_of, ncx, ncy, eps, min_dist,
                  out):  # pragma: no cover - numba
    """out[k] = δ of valid pixel k (NaN: no neighbour). ``pix`` (n, 2) its (x, y) in I, ``pos``
    (n, 2) its position in I0, ``order`` pixels sorted by bucket, ``starts`` CSR offsets of
    the ncx * ncy buckets, ``cell_of`` (n, 2) each pixel's bucket."""
    eps2 = eps * eps
    for k in prange(pix.shape[0]):
        cx, cy = cell_of[k, 0], cell_of[k, 1]
        s = 0.0
        m = 0
        for gx in range(max(cx - 1, 0), min(cx + 2, ncx)):
            for gy in range(max(cy - 1, 0), min(cy + 2, ncy)):
                b = gx * ncy + gy
                for t in range(starts[b], starts[b + 1]):
                    q = order[t]
                    if q == k:
                        continue
                    dx0 = pos[q, 0] - pos[k, 0]
                    dy0 = pos[q, 1] - pos[k, 1]
                    d02 = dx0 * dx0 + dy0 * dy0
                    if d02 > eps2:
                        continue
                    d0 = max(np.sqrt(d02), min_dist)
                    dx = pix[q, 0] - pix[k, 0]
                    dy = pix[q, 1] - pix[k, 1]
                    s += np.sqrt(dx * dx + dy * dy) / d0
                    m += 1
        out[k] = s / m - 1.0 if m > 0 else np.nan


def discontinuity(
    points: np.ndarray,
    eye: np.ndarray,
    forward: np.ndarray,
    tan_x: float,
    tan_y: float,
    eps: float = DEFAULT_EPS,
    min_dist: float = DEFAULT_MIN_DIST,
) -> Discontinuity:
    """δ of a frame whose pixels show world ``points`` (H, W, 3) (NaN: nothing), against the
    ground-truth camera at ``eye`` (3,) looking along ``forward`` (3,) with half-angle tangents
    ``tan_x, tan_y`` (the frame's own camera). ``eps`` and ``min_dist`` in pixels."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"points must be (H, W, 3), got {pts.shape}")
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be a positive number of pixels, got {eps}")
    if not (np.isfinite(min_dist) and 0 < min_dist <= eps):
        raise ValueError(f"min_dist must be in (0, eps], got {min_dist}")
    h, w = pts.shape[:2]
    pos_all = project_points(pts, eye, forward, w, h, tan_x, tan_y)
    valid = np.all(np.isfinite(pos_all), axis=2)
    delta = np.full((h, w), np.nan)
    rows, cols = np.nonzero(valid)
    n = len(rows)
    if n == 0:
        return Discontinuity(delta, 0.0, 0)
    pix = np.stack([cols, rows], axis=1).astype(np.float64)
    pos = pos_all[valid]
    # Buckets cover the image plus one image size of margin on each side; projections beyond
    # (points just in front of the eye) share the edge buckets: buckets only get coarser, the
    # distance test stays exact.
    lo = -np.array([w, h], dtype=np.float64)
    span = np.ceil(3.0 * np.array([w, h]) / eps).astype(np.int64)
    cell = np.clip(np.floor((pos - lo) / eps), 0, span).astype(np.int64)
    ncx, ncy = int(cell[:, 0].max()) + 1, int(cell[:, 1].max()) + 1
    key = cell[:, 0] * ncy + cell[:, 1]
    order = np.argsort(key, kind="stable")
    starts = np.searchsorted(key[order], np.arange(ncx * ncy + 1)).astype(np.int64)
    out = np.empty(n)
    _delta_kernel(pix, pos, order.astype(np.int64), starts, cell, ncx, ncy, float(eps),
                  float(min_dist), out)
    delta[rows, cols] = out
    ok = np.isfinite(out)
    mean_abs = float(np.mean(np.abs(out[ok]))) if np.any(ok) else 0.0
    return Discontinuity(delta, mean_abs, int(np.count_nonzero(ok)))
