"""Tests of client.metrics on synthetic images with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from client.metrics import (
    PSNR_CAP_DB,
    capped_psnr,
    epsilon,
    epsilon_mask,
    frame_metrics,
    psnr,
    psnr_summary,
    ssim,
    ssim_uniform7,
)
from client.render import Frame


def _images(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    color = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    depth = rng.uniform(1.0, 200.0, size=(h, w)).astype(np.float32)
    return color, depth


def test_identical_frames():
    color, depth = _images()
    m = frame_metrics(Frame(color, depth), Frame(color.copy(), depth.copy()))
    assert m["epsilon"] == 0.0
    assert m["psnr"] == math.inf
    assert m["ssim"] == 1.0


def test_hole_gives_its_share_of_pixels():
    color, depth = _images()
    holed = depth.copy()
    holed[10:20, 5:35] = np.inf  # nothing drawn where the ground truth has surfaces
    assert epsilon(holed, depth) == pytest.approx(100.0 * 300 / depth.size)
    mask = epsilon_mask(holed, depth)
    assert mask.sum() == 300 and mask[10:20, 5:35].all()


def test_farther_nearer_and_tolerance():
    gt = np.full((10, 10), 100.0)
    d = gt.copy()
    d[0, :5] = 100.0 + 0.5 * (1e-3 + 1e-3 * 100.0)  # farther, but within tolerance
    d[1, :4] = 100.0 + 2.0 * (1e-3 + 1e-3 * 100.0)  # farther beyond tolerance: 4 pixels
    d[2, :] = 50.0  # nearer: never an error
    assert epsilon(d, gt) == pytest.approx(4.0)
    assert epsilon(d, gt, rel_tol=0.0, abs_tol=0.0) == pytest.approx(9.0)
    # Empty in the ground truth: whatever the frame shows is not an error.
    gt2 = np.full((4, 4), np.inf)
    assert epsilon(np.full((4, 4), 3.0), gt2) == 0.0
    assert epsilon(np.full((4, 4), np.inf), gt2) == 0.0


def test_psnr_known_value_and_ssim_drops():
    a = np.full((32, 32, 3), 100, np.uint8)
    b = np.full((32, 32, 3), 110, np.uint8)  # MSE 100
    assert psnr(b, a) == pytest.approx(10 * math.log10(255**2 / 100), rel=1e-9)
    # A smooth image: added noise lowers its structural similarity clearly.
    yy, xx = np.mgrid[0:48, 0:64]
    color = np.stack([xx * 3, yy * 4, (xx + yy) * 2], axis=-1).astype(np.uint8)
    rng = np.random.default_rng(5)
    noisy = np.clip(color.astype(int) + rng.integers(-40, 41, color.shape), 0, 255).astype(np.uint8)
    s = ssim(noisy, color)
    assert 0.0 < s < 0.7
    assert ssim(color, color) == 1.0
    # Tiny images still work (uniform window that fits), images below 3x3 are refused.
    assert ssim(noisy[:5, :5], color[:5, :5]) < 1.0
    with pytest.raises(ValueError):
        ssim(noisy[:2, :2], color[:2, :2])


def test_capped_psnr():
    np.testing.assert_array_equal(
        capped_psnr([30.0, math.inf, PSNR_CAP_DB + 20.0]), [30.0, PSNR_CAP_DB, PSNR_CAP_DB]
    )


def test_bad_input_raises():
    color, depth = _images()
    with pytest.raises(ValueError):
        epsilon(depth, depth[:-1])
    bad = depth.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError):
        epsilon(bad, depth)
    with pytest.raises(ValueError):
        psnr(color, color[:, :-1])
    with pytest.raises(ValueError):
        psnr(color.astype(np.float32), color)
    with pytest.raises(ValueError):
        epsilon(depth, depth, rel_tol=-1.0)


def test_ssim_constant_images_known_value():
    # Flat images: variances and covariance vanish, so SSIM is the luminance term alone,
    # (2 mu_x mu_y + C1) / (mu_x^2 + mu_y^2 + C1) with C1 = (0.01 * 255)^2, for every window.
    a = np.full((40, 40, 3), 100, np.uint8)
    b = np.full((40, 40, 3), 110, np.uint8)
    c1 = (0.01 * 255) ** 2
    want = (2 * 100 * 110 + c1) / (100**2 + 110**2 + c1)
    assert ssim(b, a) == pytest.approx(want, rel=1e-12)


def _wang_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Independent SSIM: Wang et al. 2004 eq. 13 with an 11x11 Gaussian (sigma 1.5) window
    normalised to 1, population statistics, means over the valid (fully inside) windows."""
    from scipy.signal import fftconvolve

    r = np.arange(-5, 6)
    g1 = np.exp(-(r**2) / (2 * 1.5**2))
    w = np.outer(g1, g1)
    w /= w.sum()
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    out = []
    for ch in range(3):
        a = x[..., ch].astype(np.float64)
        b = y[..., ch].astype(np.float64)

        def f(img):
            return fftconvolve(img, w, mode="valid")

        mx, my = f(a), f(b)
        sxx, syy, sxy = f(a * a) - mx**2, f(b * b) - my**2, f(a * b) - mx * my
        s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
        out.append(s.mean())
    return float(np.mean(out))


def test_ssim_is_wang_gaussian_window():
    yy, xx = np.mgrid[0:48, 0:64]
    color = np.stack([xx * 3, yy * 4, (xx + yy) * 2], axis=-1).astype(np.uint8)
    rng = np.random.default_rng(7)
    noisy = np.clip(color.astype(int) + rng.integers(-30, 31, color.shape), 0, 255)
    noisy = noisy.astype(np.uint8)
    got = ssim(noisy, color)
    assert got == pytest.approx(_wang_ssim(color, noisy), rel=1e-6)
    # The 7x7 uniform-window SSIM is a different number on the same images.
    assert abs(ssim_uniform7(noisy, color) - got) > 1e-3
    assert ssim_uniform7(color, color) == 1.0


def test_psnr_summary_counts_identical_frames():
    s = psnr_summary([30.0, math.inf, 40.0, math.inf])
    assert s["mean"] == pytest.approx((30.0 + 40.0 + 2 * PSNR_CAP_DB) / 4)
    assert s["min"] == 30.0
    assert s["mean_differing"] == pytest.approx(35.0)
    assert s["identical"] == 2 and s["frames"] == 4
    flawless = psnr_summary([math.inf] * 3)
    assert flawless["mean"] == PSNR_CAP_DB == flawless["min"]
    assert math.isnan(flawless["mean_differing"])
    with pytest.raises(ValueError):
        psnr_summary([])
    with pytest.raises(ValueError):
        psnr_summary([30.0, math.nan])


def test_ssim_small_images_fall_back_to_uniform_window():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, (9, 9, 3), dtype=np.uint8)
    b = rng.integers(0, 256, (9, 9, 3), dtype=np.uint8)
    assert ssim(a, b) == ssim_uniform7(a, b)
