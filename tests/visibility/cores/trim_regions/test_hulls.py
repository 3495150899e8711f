"""Known answers of the gather's footprint kernels (``trim_regions.hulls``): a set-up triangle
is given directly in pixel units with 1 / depth per vertex, as ``raster.setup_triangles``
writes it, and tested against hand-made depth images and pixel states."""

from __future__ import annotations

import numpy as np

from tests.grouping import module_on_one_worker
from visibility.cores.trim_regions.hulls import (
    COPLANAR_TOL,
    small_in_front,
    touching_in_front,
    touching_samples,
)
from visibility.cores.trim_regions.kbuffer import SPANS
from visibility.cores.trim_regions.samples import open_depth

pytestmark = module_on_one_worker("trim_hulls")  # kernels of its own (tests/grouping.py)

RES = 16
S = 4


def _setup(corners: list[tuple[float, float]], depth: float):
    """One set-up triangle (poly, npoly, box) with its corners at (x, y) pixels, all at
    ``depth`` metres."""
    poly = np.zeros((1, 4, 3))
    for k, (x, y) in enumerate(corners):
        poly[0, k] = (x, y, 1.0 / depth)
    xs = [c[0] for c in corners]
    ys = [c[1] for c in corners]
    box = np.array([[max(0, int(np.floor(min(xs) - 0.5))), min(RES, int(np.ceil(max(xs) + 0.5))),
                     max(0, int(np.floor(min(ys) - 0.5))), min(RES, int(np.ceil(max(ys) + 0.5)))]],
                   dtype=np.int64)
    return poly, np.array([3], dtype=np.int64), box


# A triangle about a tenth of a sample across, between four sample centres of pixel (5, 5):
# samples sit at (u + 0.5) / S pixels, so (5.0, 5.0) +- 0.01 px meets none of them.
TINY = [(5.0, 4.99), (5.01, 5.01), (4.99, 5.01)]


def _samples(poly, npoly, box, image):
    # float32, as the supersampled render is: the kernels run with the types they were
    # compiled for by the warm-up, not a second specialization.
    image = image.astype(np.float32)
    vis = np.zeros(1, dtype=np.uint8)
    far = np.empty(RES * RES)
    open_depth(image, RES, S, 0, np.empty(RES * RES), far)
    touching_samples(poly, npoly, box, np.zeros(1, dtype=np.int64), image, far, RES, S, 8, vis)
    return int(vis[0])


def test_a_triangle_between_the_samples_in_front_of_a_wall_is_found():
    wall = np.full((RES * S, RES * S), 2.0)
    assert _samples(*_setup(TINY, 1.99), wall) == 1
    # On the wall itself (a decal, a face drawn twice): either may be what an eye sees.
    assert _samples(*_setup(TINY, 2.0 * (1 + 0.5 * COPLANAR_TOL)), wall) == 1


def test_a_triangle_behind_a_wall_is_not():
    wall = np.full((RES * S, RES * S), 2.0)
    assert _samples(*_setup(TINY, 2.1), wall) == 0


def test_a_crack_one_sample_wide_opens_only_the_samples_around_it():
    wall = np.full((RES * S, RES * S), 2.0)
    # The sample left of the tiny triangle sees through a crack to the far wall.
    wall[5 * S - 1, 5 * S - 2] = 9.0
    assert _samples(*_setup(TINY, 5.0), wall) == 1
    # Three samples away from the crack the wall hides it.
    far_tiny = [(x + 0.75, y) for x, y in TINY]
    assert _samples(*_setup(far_tiny, 5.0), wall) == 0


def _kb_state(seal: float, spans: list[tuple[float, float]]):
    n = RES * RES
    sp = np.zeros((n, SPANS, 2))
    ns = np.zeros(n, dtype=np.int64)
    for q, (a, b) in enumerate(spans):
        sp[:, q] = (a, b)
    ns[:] = len(spans)
    return np.full(n, seal), sp, ns


def _behind(poly, npoly, box, seal, spans, tol=1e-3):
    vis = np.zeros(1, dtype=np.uint8)
    small_in_front(poly, npoly, box, np.zeros(1, dtype=np.int64), *_kb_state(seal, spans), RES,
                   1.0, tol, vis)
    return int(vis[0])


def test_a_small_triangle_past_an_umbra_is_found_where_no_pixel_centre_meets_it():
    # An interval validated from 2 m with its umbra at 3 m: what lies between is hidden,
    # what lies past the umbra (and in front of the seal) is what the trims reveal.
    assert _behind(*_setup(TINY, 3.5), np.inf, [(2.0, 3.0)]) == 1
    assert _behind(*_setup(TINY, 2.5), np.inf, [(2.0, 3.0)]) == 0
    # Past the seal: hidden.
    assert _behind(*_setup(TINY, 3.5), 3.2, [(2.0, 3.0)]) == 0
    # Just behind the face that opened the span, within the depth tolerance: that face's
    # own surface, not inside it.
    assert _behind(*_setup(TINY, 2.001), np.inf, [(2.0, 3.0)]) == 1
    assert _behind(*_setup(TINY, 2.001), np.inf, [(2.0, 3.0)], tol=0.0) == 0


def test_a_sliver_counts_as_thin_a_wide_triangle_does_not():
    sliver = [(1.0, 7.0), (14.0, 7.02), (1.0, 7.04)]  # 13 px long, 0.04 px across
    assert _behind(*_setup(sliver, 3.5), np.inf, [(2.0, 3.0)]) == 1
    large = [(1.0, 1.0), (14.0, 1.0), (1.0, 14.0)]  # meets pixel centres itself
    assert _behind(*_setup(large, 3.5), np.inf, [(2.0, 3.0)]) == 0


def _in_front(poly, npoly, box, first):
    vis = np.zeros(1, dtype=np.uint8)
    touching_in_front(poly, npoly, box, np.zeros(1, dtype=np.int64), first.reshape(-1), RES,
                      vis)
    return int(vis[0])


def test_a_large_triangle_is_found_through_one_open_pixel_of_its_box_and_only_there():
    # The seals' depth pyramid spares the pixel tests of a triangle hidden over its whole
    # box; one pixel that opens past it, in a far corner of the box, or just outside the
    # triangle but within the pixel its square touches, must still find it.
    large = [(0.6, 0.6), (15.4, 0.6), (0.6, 15.4)]
    first = np.full((RES, RES), 2.0)
    assert _in_front(*_setup(large, 3.0), first) == 0
    for y, x, seen in ((14, 1, 1), (1, 14, 1), (7, 7, 1), (9, 9, 0), (15, 15, 0)):
        opened = first.copy()
        opened[y, x] = np.inf
        assert _in_front(*_setup(large, 3.0), opened) == seen, (y, x)


def test_a_pixel_square_beyond_a_slivers_tip_does_not_touch_it():
    from visibility.cores.trim_regions.hulls import _touches

    # A sliver 10 px long and 0.05 px thick: its edges grown by a square's reach pass for
    # squares up to several pixels beyond its tip at (0, 0), which it never reaches.
    a, b, c = (0.0, 0.0), (10.0, 0.05), (10.0, 0.0)
    sg = 1.0 if (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0 else -1.0
    for px in (-0.7, -1.5, -3.0):
        assert not _touches(*a, *b, *c, sg, px, 0.01), px
    for px in (-0.4, 0.3, 5.0, 10.4):
        assert _touches(*a, *b, *c, sg, px, 0.01), px
    assert not _touches(*a, *b, *c, sg, 5.0, 0.6) and _touches(*a, *b, *c, sg, 5.0, 0.5)
