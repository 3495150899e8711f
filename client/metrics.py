"""Per-frame image metrics of a client frame against the ground-truth frame of the same view.

ε (the from-segment paper's error, Sec. 4.3) counts pixels where the client sees something
*farther* than the ground truth: a surface that should hide it is missing from the client's PVS.
Pixels where the client sees something nearer cannot come from a missing PVS triangle and are
not errors.

Tolerance: a pixel is an ε pixel when ``depth > depth_gt + abs_tol + rel_tol * depth_gt``. Both
frames come from the same renderer, so the same surface normally gets bit-identical depth; the
tolerance absorbs what is left: the 24-bit depth buffer with near plane 0.05 m quantises view
depth in steps of about ``z^2 / (0.05 * 2^24)`` (1.2e-4 relative at 100 m, 1.2e-3 at 1 km),
float32 vertex positions (about 1e-7 relative), and z-fighting between coplanar surfaces when the
two frames hold different triangle sets. With the defaults a missing occluder less than 1 mm (plus
0.1 %) in front of the surface behind it is not counted, which no visibility error can hide in
practice.

PSNR of identical images is +inf. The paper's Table 2 reports a flawless sequence as 255 dB
(average and minimum), i.e. an identical frame counts as 255 dB in its averages; summaries here do
the same: +inf is capped at ``PSNR_CAP_DB`` (255) before averaging, and ``psnr_summary`` also
gives the mean over the frames that differ and how many frames were identical, so that a mean
pulled up by identical frames can be read apart.

SSIM is Wang et al. 2004: an 11x11 Gaussian window (sigma 1.5), population covariances, K1 0.01,
K2 0.03, per colour channel, mean over the image (scikit-image is the implementation). The
project's earlier 7x7 uniform-window SSIM stays available as ``ssim_uniform7``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: PSNR (dB) used in place of +inf (identical images) when PSNR values are averaged: the value
#: the from-segment paper's Table 2 gives flawless sequences.
PSNR_CAP_DB = 255.0

#: Wang et al. 2004: Gaussian window of standard deviation 1.5 px, truncated to 11x11.
SSIM_SIGMA = 1.5
SSIM_WINDOW = 11


def _check_depths(depth: np.ndarray, depth_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(depth, dtype=np.float64)
    g = np.asarray(depth_gt, dtype=np.float64)
    if d.ndim != 2 or d.shape != g.shape:
        raise ValueError(f"depths must be equal (H, W) arrays, got {d.shape} and {g.shape}")
    if np.isnan(d).any() or np.isnan(g).any():
        raise ValueError("depth images must not contain NaN (use +inf for empty pixels)")
    return d, g


def epsilon_mask(
    depth: np.ndarray, depth_gt: np.ndarray, rel_tol: float = 1e-3, abs_tol: float = 1e-3
) -> np.ndarray:
    """(H, W) bool: pixels whose depth is farther than the ground truth's beyond the tolerance.

    ``depth`` and ``depth_gt`` are (H, W) view depths in metres with +inf for empty pixels; a
    pixel empty in the frame but covered in the ground truth counts, one empty in the ground
    truth never does.
    """
    d, g = _check_depths(depth, depth_gt)
    if rel_tol < 0 or abs_tol < 0:
        raise ValueError("tolerances must be non-negative")
    with np.errstate(invalid="ignore"):  # inf - inf style comparisons are simply False
        return d > g + (abs_tol + rel_tol * g)


def epsilon(
    depth: np.ndarray, depth_gt: np.ndarray, rel_tol: float = 1e-3, abs_tol: float = 1e-3
) -> float:
    """Percentage (0-100) of all pixels that are ε pixels (see ``epsilon_mask``)."""
    m = epsilon_mask(depth, depth_gt, rel_tol, abs_tol)
    return 100.0 * float(np.count_nonzero(m)) / m.size if m.size else 0.0


def _check_colors(color: np.ndarray, color_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(color)
    g = np.asarray(color_gt)
    if c.shape != g.shape or c.ndim != 3 or c.shape[2] != 3:
        raise ValueError(f"colours must be equal (H, W, 3) arrays, got {c.shape} and {g.shape}")
    if c.dtype != np.uint8 or g.dtype != np.uint8:
        raise ValueError(f"colours must be uint8, got {c.dtype} and {g.dtype}")
    return c, g


def psnr(color: np.ndarray, color_gt: np.ndarray) -> float:
    """PSNR in dB of an (H, W, 3) uint8 frame against the ground truth; +inf when identical."""
    c, g = _check_colors(color, color_gt)
    if np.array_equal(c, g):
        return math.inf
    # Imported here: scikit-image pulls in scipy (seconds), which report writers do not need.
    from skimage.metrics import peak_signal_noise_ratio

    return float(peak_signal_noise_ratio(g, c, data_range=255))


def ssim(color: np.ndarray, color_gt: np.ndarray) -> float:
    """Mean SSIM of (H, W, 3) uint8 images as Wang et al. 2004 define it; 1 when identical.

    11x11 Gaussian window with sigma 1.5, population (not sample) covariances, data range 255,
    each colour channel separately, averaged over pixels and channels. Images smaller than
    11x11 cannot hold that window; they get ``ssim_uniform7`` (smaller uniform window) instead.
    """
    c, g = _check_colors(color, color_gt)
    if np.array_equal(c, g):
        return 1.0
    if min(c.shape[0], c.shape[1]) < SSIM_WINDOW:
        return ssim_uniform7(c, g)
    from skimage.metrics import structural_similarity

    # skimage fixes the Gaussian at 11 taps for sigma 1.5 (truncate 3.5), Wang et al.'s window.
    return float(structural_similarity(
        g, c, channel_axis=-1, data_range=255, gaussian_weights=True, sigma=SSIM_SIGMA,
        use_sample_covariance=False))


def ssim_uniform7(color: np.ndarray, color_gt: np.ndarray) -> float:
    """Mean SSIM with scikit-image's defaults (7x7 uniform window, sample covariances), per
    channel, data range 255, of (H, W, 3) uint8 images; 1 when identical. The project's SSIM
    before the Wang et al. window; kept so that older figures can be compared. Images smaller
    than 7 pixels use the largest odd window that fits."""
    c, g = _check_colors(color, color_gt)
    if np.array_equal(c, g):
        return 1.0
    side = min(c.shape[0], c.shape[1])
    win = min(7, side if side % 2 else side - 1)
    if win < 3:
        raise ValueError(f"images of {c.shape[:2]} are too small for SSIM (need 3x3)")
    from skimage.metrics import structural_similarity

    return float(structural_similarity(g, c, channel_axis=-1, data_range=255, win_size=win))


def frame_metrics(
    frame: Any, frame_gt: Any, rel_tol: float = 1e-3, abs_tol: float = 1e-3
) -> dict[str, float]:
    """``{"epsilon": %, "psnr": dB, "ssim": ...}`` of a frame against its ground truth.

    Frames are anything with ``color`` (H, W, 3) uint8 and ``depth`` (H, W) attributes, such as
    ``client.render.Frame``.
    """
    return {
        "epsilon": epsilon(frame.depth, frame_gt.depth, rel_tol, abs_tol),
        "psnr": psnr(frame.color, frame_gt.color),
        "ssim": ssim(frame.color, frame_gt.color),
    }


def capped_psnr(values: np.ndarray) -> np.ndarray:
    """PSNR values (dB) with +inf (and anything above) replaced by ``PSNR_CAP_DB``."""
    return np.minimum(np.asarray(values, dtype=np.float64), PSNR_CAP_DB)


def psnr_summary(values: np.ndarray) -> dict[str, float]:
    """Summary of per-frame PSNR values (dB, +inf for identical frames), shape (N,).

    ``mean``: mean with +inf counted as ``PSNR_CAP_DB`` (how the paper's Table 2 averages);
    ``min``: minimum, capped likewise; ``mean_differing``: mean over the frames that differ from
    the ground truth (NaN when none do); ``identical``: how many frames were identical;
    ``frames``: N. NaN values (frames not measured) are refused.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if np.isnan(v).any():
        raise ValueError("PSNR values must not contain NaN")
    if v.size == 0:
        raise ValueError("no PSNR values to summarise")
    same = np.isposinf(v)
    capped = capped_psnr(v)
    return {
        "mean": float(capped.mean()),
        "min": float(capped.min()),
        "mean_differing": float(v[~same].mean()) if (~same).any() else math.nan,
        "identical": float(same.sum()),
        "frames": float(v.size),
    }
