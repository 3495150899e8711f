"""The gather of what pixel centres miss (``hulls.touching_in_front``): thin triangles in front
of the first surface, and long slivers in the gaps of a trimmed pixel."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.hulls import touching_in_front
from visibility.cores.trim_regions.kbuffer import SPANS

RES = 16


def _gather(corners, depth, *, trimmed=True, first=2.0, seal=5.0, spans=(), long_px=4.0):
    """Whether one triangle (corners in pixels, all at ``depth`` metres) is reported, every
    pixel seeing its first surface at ``first`` and sealed at ``seal``."""
    poly = np.zeros((1, 4, 3))
    poly[0, :3, :2] = corners
    poly[0, :3, 2] = 1.0 / depth
    npoly = np.array([3])
    c = np.asarray(corners, dtype=float)
    box = np.array([[int(np.floor(c[:, 0].min())), int(np.ceil(c[:, 0].max())),
                     int(np.floor(c[:, 1].min())), int(np.ceil(c[:, 1].max()))]])
    n = RES * RES
    span_arr = np.zeros((n, SPANS, 2))
    n_spans = np.zeros(n, dtype=np.int64)
    for q, (lo, hi) in enumerate(spans):
        span_arr[:, q] = (lo, hi)
        n_spans[:] = q + 1
    vis = np.zeros(1, dtype=np.uint8)
    touching_in_front(poly, npoly, box, np.array([0]), np.full(n, first),
                      np.full(n, trimmed), np.full(n, seal), span_arr, n_spans, 1e-3, long_px,
                      RES, vis)
    return bool(vis[0])


SLIVER = [(7.9, 2.0), (8.0, 2.0), (7.95, 12.0)]  # 0.1 px wide, 10 px long
SPECK = [(7.9, 7.9), (8.1, 7.9), (8.0, 8.1)]


def test_in_front_of_the_first_surface_anything_counts():
    assert _gather(SPECK, 1.5, trimmed=False)
    assert not _gather(SPECK, 2.5, trimmed=False)


def test_a_long_sliver_in_a_trimmed_pixel_counts_up_to_the_seal():
    # Behind the first surface v* samples, but a trim region reached the pixel: an eye of the
    # sphere may see past that surface's silhouette.
    assert _gather(SLIVER, 3.0)
    # A sliver on the sealing surface itself (a bevel): within the depth tolerance.
    assert _gather(SLIVER, 5.0 * (1 + 5e-4))
    assert not _gather(SLIVER, 6.0)
    assert not _gather(SLIVER, 3.0, trimmed=False)
    # Inside the umbra of a validated interval: hidden from every eye.
    assert not _gather(SLIVER, 3.0, spans=[(2.0, 4.0)])
    assert _gather(SLIVER, 3.0, spans=[(2.0, 2.5)])


def test_a_small_triangle_in_a_trimmed_pixel_needs_to_be_in_front():
    # Clutter behind small trimmed occluders would otherwise report the whole scene.
    assert not _gather(SPECK, 3.0)
    assert _gather(SPECK, 3.0, long_px=0.0)
