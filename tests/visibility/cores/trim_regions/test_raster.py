"""``raster_trims`` visits only the columns a row of a trim region can reach: the same entries,
in the same order, as the region test tried at every pixel of the region's box; a full
k-buffer merges trim fragments rather than give up occlusion; ``raster_surfaces`` skips a leaf
sealed all over its window and ``raster_trims`` a region sealed all over its box, and only
those."""

from __future__ import annotations

import numpy as np
import pytest

from tests.grouping import module_on_one_worker
from visibility.cores.trim_regions.kbuffer import (
    BACK,
    FRONT,
    SEALED,
    TRIM,
    K,
    KBuffer,
    joined_pieces,
    trim_holds,
)
from visibility.cores.trim_regions.raster import (
    JOIN_LAST,
    JOIN_TOL,
    Camera,
    SetUp,
    _affine_range,
    _all_sealed,
    _insert,
    _leaf_window,
    _nearest_pair,
    band_lists,
    boxes_to_camera,
    raster_surfaces,
    raster_trims,
    setup_triangles,
    to_camera,
)

pytestmark = module_on_one_worker("trim_raster")  # kernels of its own (tests/grouping.py)


def _every_pixel(trims: np.ndarray, res: int, tan: float, margin: float) -> list[list[tuple]]:
    """Per pixel, the (depth, umbra) entries the region test admits, trims in order, over each
    trim's pixel box (the edge's ends widened by the larger width and the margin)."""
    half = 0.5 * res
    out: list[list[tuple]] = [[] for _ in range(res * res)]
    for q in range(len(trims)):
        nx, ny, nz, side, u0, v0, u1, v1, iz0, iz1, w0, w1 = trims[q, :12]
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
    rows = np.full((n, 13), -1.0)
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


@pytest.mark.parametrize("n", [60, 800])
def test_trim_rows_match_the_test_at_every_pixel(n):
    # 800 trims put more than K fragments in most pixels: those merge.
    res, tan, margin = 32, 1.0, 0.75 * 2.0 / 32
    trims = _trims(np.random.default_rng(3), n, tan)
    kb = KBuffer.empty(res * res)
    vis = np.zeros(1, dtype=np.uint8)
    raster_trims(trims, res, tan, margin, kb, vis, np.zeros(1, dtype=np.uint8))
    want = _every_pixel(trims, res, tan, margin)
    assert sum(len(w) for w in want) > 10 * res  # the strips cover much of the view
    merged = 0
    joined = 0
    for p in range(res * res):
        assert kb.overflow[p] == 0  # only trims: a full buffer merges them
        held = _joined(want[p])
        joined += len(want[p]) - len(held)
        if len(held) > K:
            # Every fragment lies in the depth range of a held entry whose umbra is no deeper.
            merged += 1
            assert kb.count[p] == K
            _, lo, _, um, hi = kb.entries(p)
            for t, u in want[p]:
                e = 1e-12 * t
                assert ((lo <= t + e) & (t - e <= hi) & (um <= u * (1 + 1e-12))).any(), (t, u)
            continue
        assert kb.count[p] == len(held)
        kind, depth, _, umbra, far = kb.entries(p)
        assert (kind == TRIM).all()
        got = list(zip(depth, far, umbra, strict=True))
        assert np.allclose(got, held, rtol=1e-12) if held else not got
    assert (merged > 0) == (n > 60)
    assert joined > 0  # strips of edges sharing an end point meet at one depth there


def test_trim_regions_sealed_all_over_insert_nothing_and_open_pixels_still_get_theirs():
    # Most of the view sealed, a few scattered pixels open: every region whose box is sealed
    # is skipped, and each open pixel holds what the region test admits there.
    res, tan, margin = 32, 1.0, 0.75 * 2.0 / 32
    trims = _trims(np.random.default_rng(4), 60, tan)
    want = _every_pixel(trims, res, tan, margin)
    kb = KBuffer.empty(res * res)
    kb.stencil[:] = SEALED
    culled = raster_trims(trims, res, tan, margin, kb, np.zeros(1, dtype=np.uint8),
                          np.zeros(1, dtype=np.uint8))
    assert not kb.count.any()
    assert 0 < culled <= len(trims)
    open_px = np.random.default_rng(5).choice(res * res, 12, replace=False)
    kb.stencil[open_px] = 0
    # The regions whose box holds an open pixel are drawn, no longer counted.
    assert raster_trims(trims, res, tan, margin, kb, np.zeros(1, dtype=np.uint8),
                        np.zeros(1, dtype=np.uint8)) < culled
    assert set(np.flatnonzero(kb.count)) <= set(open_px.tolist())
    reached = 0
    for p in open_px:
        held = _joined(want[p])
        if len(held) > K:
            continue
        reached += bool(held)
        assert kb.count[p] == len(held)
        _, depth, _, umbra, far = kb.entries(p)
        got = list(zip(depth, far, umbra, strict=True))
        assert np.allclose(got, held, rtol=1e-12) if held else not got
    assert reached >= 6


def _joined(entries: list[tuple]) -> list[tuple]:
    """(depth, far, umbra) entries a pixel holds after ``entries`` (depth, umbra) arrive in
    order, each joining one of the last ``JOIN_LAST`` held whose range it meets within
    ``JOIN_TOL`` (``raster._insert``), before any buffer is full."""
    held: list[list[float]] = []
    for t, u in entries:
        for e in reversed(held[-JOIN_LAST:]):
            if e[0] * (1.0 - JOIN_TOL) <= t <= e[1] * (1.0 + JOIN_TOL):
                e[0], e[1], e[2] = min(e[0], t), max(e[1], t), min(e[2], u)
                break
        else:
            held.append([t, t, u])
    return [tuple(e) for e in held]


def _fill(kb: KBuffer, entries: list[tuple], pieces: list[int] | None = None) -> np.ndarray:
    """Insert (kind, depth, umbra) entries into pixel 0 in order (ids 0, 1, ...; a trim's
    piece from ``pieces``, else -1); returns vis."""
    vis = np.zeros(len(entries), dtype=np.uint8)
    for i, (kind, d, um) in enumerate(entries):
        ident = i if kind != TRIM else (-1 if pieces is None else pieces[i])
        _insert(0, d, kind, ident, um, kb.depth, kb.kind, kb.ident, kb.umbra, kb.far,
                kb.count, kb.overflow, vis)
    return vis


def test_trims_keep_their_piece_and_merge_within_it_first():
    # A trim of one piece validates only intervals of its piece (``resolve``). Strips of one
    # piece crossing a pixel at one depth join and keep it; a strip of another piece joining
    # them makes the entry one of both (a piece set).
    kb = KBuffer.empty(1)
    _fill(kb, [(TRIM, 2.0, 9.0), (TRIM, 2.0, 5.0)], pieces=[1, 1])
    _, _, ident, umbra, _ = kb.entries(0)
    assert ident.tolist() == [1] and umbra.tolist() == [5.0]
    _fill(kb, [(TRIM, 2.0, 4.0)], pieces=[2])
    _, _, ident, umbra, _ = kb.entries(0)
    assert ident.tolist() == [joined_pieces(1, 2)] and umbra.tolist() == [4.0]
    assert trim_holds(ident[0], 1) and trim_holds(ident[0], 2)
    # A full buffer merges the nearest pair of one piece, farther apart than a pair of two.
    kb = KBuffer.empty(1)
    entries = [(TRIM, 1.0 + q, 10.0 + q) for q in range(K)]
    pieces = list(range(K))
    pieces[3] = pieces[9] = 77
    _fill(kb, entries + [(FRONT, 99.0, 0.0)], pieces=pieces + [-1])
    kind, depth, ident, umbra, far = kb.entries(0)
    j = int(np.flatnonzero((kind == TRIM) & (far > depth))[0])
    assert (depth[j], far[j], umbra[j], ident[j]) == (4.0, 10.0, 13.0, 77)
    # Only trims of different pieces left: they merge into a trim of both.
    kb = KBuffer.empty(1)
    _fill(kb, entries + [(FRONT, 99.0, 0.0)], pieces=list(range(K)) + [-1])
    kind, depth, ident, _, far = kb.entries(0)
    j = int(np.flatnonzero((kind == TRIM) & (far > depth))[0])
    assert ident[j] == joined_pieces(int(depth[j]) - 1, int(far[j]) - 1)
    # An incoming trim joins a held set that holds its piece before another piece's trim.
    kb = KBuffer.empty(1)
    sets = [(TRIM, 1.0 + q, 10.0 + q) for q in range(K)]
    _fill(kb, sets, pieces=[joined_pieces(3, 4)] + [100 + q for q in range(K - 1)])
    _fill(kb, [(TRIM, 40.0, 50.0)], pieces=[4])
    kind, depth, ident, _, far = kb.entries(0)
    assert (depth[0], far[0], ident[0]) == (1.0, 40.0, joined_pieces(3, 4))


def test_a_full_buffer_merges_the_two_trims_nearest_in_depth_for_a_surface():
    kb = KBuffer.empty(1)
    trims = [(TRIM, 1.0 + q, 10.0 + q) for q in range(K - 2)] + [(TRIM, 50.0, 60.0),
                                                                  (TRIM, 50.5, 55.0)]
    vis = _fill(kb, trims + [(FRONT, 7.25, 0.0)])
    assert kb.overflow[0] == 0 and kb.count[0] == K and not vis.any()
    kind, depth, ident, umbra, far = kb.entries(0)
    k = int(np.flatnonzero(kind == FRONT)[0])
    assert depth[k] == 7.25 and ident[k] == K
    # 50 and 50.5 were the nearest pair: one entry spans them with the nearer umbra.
    j = int(np.flatnonzero((kind == TRIM) & (far > depth))[0])
    assert (depth[j], far[j], umbra[j]) == (50.0, 50.5, 55.0)


def test_a_trim_at_the_depth_of_a_recent_one_joins_it():
    # Strips of one silhouette chain cross a pixel at one depth: one entry holds them, its
    # range both depths and its umbra the nearer (what a full buffer's merge keeps).
    kb = KBuffer.empty(1)
    _fill(kb, [(TRIM, 2.0, 9.0), (TRIM, 2.0 * (1 + 0.5 * JOIN_TOL), 4.0), (TRIM, 2.5, 8.0)])
    assert kb.count[0] == 2
    _, depth, _, umbra, far = kb.entries(0)
    assert (depth[0], far[0], umbra[0]) == (2.0, 2.0 * (1 + 0.5 * JOIN_TOL), 4.0)
    # Only the last JOIN_LAST entries are looked at: an older one at that depth is not joined.
    kb = KBuffer.empty(1)
    _fill(kb, [(TRIM, 2.0, 9.0)] + [(TRIM, 3.0 + q, 9.0) for q in range(JOIN_LAST)]
          + [(TRIM, 2.0, 5.0)])
    assert kb.count[0] == JOIN_LAST + 2
    # A surface never joins, nor does a trim join a surface.
    kb = KBuffer.empty(1)
    _fill(kb, [(FRONT, 2.0, 0.0), (TRIM, 2.0, 5.0), (BACK, 2.0, 0.0)])
    assert kb.count[0] == 3


def test_a_trim_joins_the_held_trim_nearest_in_depth_when_the_buffer_is_full():
    kb = KBuffer.empty(1)
    _fill(kb, [(TRIM, 1.0 + q, 10.0 + q) for q in range(K)] + [(TRIM, 5.4, 7.0)])
    assert kb.overflow[0] == 0 and kb.count[0] == K
    _, depth, _, umbra, far = kb.entries(0)
    j = int(np.flatnonzero(depth == 5.0)[0])
    assert (far[j], umbra[j]) == (5.4, 7.0)


def test_a_full_buffer_without_two_trims_overflows_and_reports_its_surfaces():
    kb = KBuffer.empty(1)
    entries = [(FRONT if q % 2 == 0 else BACK, 1.0 + q, 0.0) for q in range(K)]
    vis = _fill(kb, entries + [(TRIM, 3.5, 9.0), (FRONT, 99.0, 0.0)])
    assert kb.overflow[0] == 1 and kb.count[0] == 0
    assert vis[:K].all() and vis[K + 1]  # every surface held, and the one after, is reported


def test_band_lists_hold_each_item_in_every_band_its_rows_meet_in_order():
    rng = np.random.default_rng(3)
    n_bands = 9
    ylo = rng.integers(-3, 72, 400)
    yhi = ylo + rng.integers(-2, 30, 400)
    ylo, yhi = np.clip(ylo, 0, 72), np.clip(yhi, 0, 72)
    start, items = band_lists(ylo, yhi, n_bands)
    for b in range(n_bands):
        want = [q for q in range(400) if yhi[q] > ylo[q] and ylo[q] < 8 * b + 8
                and yhi[q] > 8 * b]
        assert items[start[b]:start[b + 1]].tolist() == want
    assert start[-1] == len(items)


def test_a_leaf_window_holds_the_pixels_whose_rays_meet_the_leaf():
    # Random boxes, most in front of v*: every pixel whose square a point of the box projects
    # into lies inside its window; a box reaching v*'s plane gets the whole face.
    rng = np.random.default_rng(5)
    res, tan = 64, 1.2
    half = 0.5 * res
    a = rng.normal(size=(3, 3))
    rot = np.linalg.qr(a)[0]
    vstar = rng.normal(size=3)
    win = np.empty(4, dtype=np.int64)
    checked = 0
    for _ in range(200):
        c = rng.uniform(-1.0, 1.0, size=3) * np.array([2.0, 2.0, 1.0]) + np.array([0, 0, -3.0])
        size = rng.uniform(0.05, 1.5, size=3)
        lo_c, hi_c = c - size, c + size  # a box in camera space, mostly in front
        # The world box holding it (the window is conservative for any box holding the leaf).
        corners = np.array([[x, y, z] for x in (lo_c[0], hi_c[0]) for y in (lo_c[1], hi_c[1])
                            for z in (lo_c[2], hi_c[2])]) @ rot + vstar
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        _leaf_window(lo, hi, vstar, rot, tan, res, win)
        pts = rng.uniform(lo, hi, size=(400, 3))
        cam = (pts - vstar) @ rot.T
        z = -cam[:, 2]
        front = z > 1e-9
        px = (cam[front, 0] / z[front] / tan + 1.0) * half
        py = (1.0 - cam[front, 1] / z[front] / tan) * half
        on = (px >= 0) & (px < res) & (py >= 0) & (py < res)
        x, y = np.floor(px[on]).astype(int), np.floor(py[on]).astype(int)
        assert ((win[0] <= x) & (x < win[1]) & (win[2] <= y) & (y < win[3])).all()
        checked += int(on.sum())
    assert checked > 10_000
    # A box around v* itself: no window.
    _leaf_window(vstar - 1.0, vstar + 1.0, vstar, rot, tan, res, win)
    assert list(win) == [0, res, 0, res]


def test_picked_boxes_corners_in_camera_space_follow_box_faces_order():
    """``boxes_to_camera``: corner c of box b is (hi if bit a of c else lo) along axis a, in
    camera space, as ``to_camera`` of that corner gives it, for the picked boxes only (the
    corner order ``hulls.BOX_FACES`` indexes)."""
    rng = np.random.default_rng(3)
    lo = rng.normal(size=(50, 3)) * 20.0
    hi = lo + rng.random((50, 3)) + 0.1
    sel = np.array([3, 17, 41], dtype=np.int64)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    vstar = rng.normal(size=3)
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1 == 1
    corners = np.where(bits, hi[sel][:, None, :], lo[sel][:, None, :]).reshape(-1, 3)
    cam = boxes_to_camera(lo, hi, sel, vstar, rot)
    assert cam.shape == (24, 3)
    assert np.array_equal(cam, to_camera(corners, vstar, rot))


def _pair_by_every_pair(kb: KBuffer, c: int, same_only: bool) -> tuple[int, int, bool]:
    """``_nearest_pair`` as its docstring says, over every pair in slot order."""
    trims = [q for q in range(c) if kb.kind[q >> 3, 0, q & 7] == TRIM]

    def entry(q):
        i, j = q >> 3, q & 7
        return kb.ident[i, 0, j], kb.depth[i, 0, j], kb.far[i, 0, j]

    pairs = [(q, r) for n, q in enumerate(trims) for r in trims[n + 1:]]
    same = [(q, r) for q, r in pairs if entry(q)[0] == entry(r)[0]]
    pool = same or ([] if same_only else pairs)
    if not pool:
        return -1, -1, False

    def gap(q, r):
        _, a0, a1 = entry(q)
        _, b0, b1 = entry(r)
        return max(0.0, b0 - a1, a0 - b1)

    a, b = min(pool, key=lambda qr: (gap(*qr), qr))
    return a, b, bool(same)


@pytest.mark.parametrize("seed", range(40))
def test_the_nearest_pair_of_held_trims_is_the_first_of_the_nearest(seed):
    # A full buffer's merge partners (the costliest search of the kitchen's clutter): pieces
    # repeated or not, ranges touching or apart, surfaces between them.
    rng = np.random.default_rng(seed)
    kb = KBuffer.empty(1)
    c = int(rng.integers(2, K + 1))
    pieces = rng.integers(0, [3, 40, 10 ** 6][seed % 3], size=c)
    for q in range(c):
        d = float(rng.choice([rng.random(), round(rng.random(), 1)]))
        kind = TRIM if rng.random() < 0.8 else FRONT
        kb.put(0, q, kind, d, int(pieces[q]), 1.0, d + float(rng.random()) * 0.1 * (seed % 2))
    for same_only in (True, False):
        got = _nearest_pair(0, kb.depth, kb.kind, kb.ident, kb.far, c, np.bool_(same_only))
        assert tuple(got) == _pair_by_every_pair(kb, c, same_only), (same_only, got)


def test_all_sealed_reads_every_pixel_of_the_window():
    res = 8
    stencil = np.full(res * res, SEALED, dtype=np.int8)
    win = np.array([2, 6, 1, 5], dtype=np.int64)
    assert _all_sealed(stencil, res, win)
    stencil[4 * res + 5] = 0  # the window's last pixel
    assert not _all_sealed(stencil, res, win)
    stencil[:] = 0
    assert _all_sealed(stencil, res, np.array([3, 3, 0, res], dtype=np.int64))  # empty


def _one_leaf_view(res: int = 32):
    """One front-facing triangle 2 m ahead of v* (at the origin, looking along -z), its
    set-up, its leaf's box and the view."""
    verts = np.array([[-0.5, -0.5, -2.0], [0.5, -0.5, -2.0], [0.0, 0.5, -2.0]])
    faces = np.array([[0, 1, 2]], dtype=np.int64)
    tan = 1.0
    rows = np.array([0], dtype=np.int64)
    facing = np.empty(1, dtype=np.int8)
    poly = np.empty((1, 4, 3))
    npoly = np.empty(1, dtype=np.int64)
    box = np.empty((1, 4), dtype=np.int64)
    setup_triangles(verts, faces, rows, np.ones(1, dtype=np.bool_), 0.01, tan, res, facing,
                    poly, npoly, box)
    tris = SetUp(rows, facing, poly, npoly, box)
    cam = Camera(np.zeros(3), np.eye(3), tan, res)
    lo = np.array([[-0.6, -0.6, -2.1]])
    hi = np.array([[0.6, 0.6, -1.9]])
    return tris, cam, lo, hi


def test_a_leaf_sealed_all_over_its_window_is_not_drawn_and_one_open_pixel_draws_it():
    res = 32
    tris, cam, lo, hi = _one_leaf_view(res)
    inst = np.zeros(1, dtype=np.int64)
    stop = np.zeros(1, dtype=np.uint8)
    win = np.empty(4, dtype=np.int64)
    _leaf_window(lo[0], hi[0], cam.vstar, cam.rot, cam.tan, res, win)
    # Open: the triangle's pixels get one front entry each.
    kb = KBuffer.empty(res * res)
    assert raster_surfaces(inst, inst, tris, lo, hi, cam, kb, np.zeros(1, dtype=np.uint8),
                           stop) == 0
    drawn = np.flatnonzero(kb.count)
    assert len(drawn) > 20 and (kb.count[drawn] == 1).all()
    # Sealed over the leaf's window: nothing is drawn.
    kb = KBuffer.empty(res * res)
    st = kb.stencil.reshape(res, res)
    st[win[2]:win[3], win[0]:win[1]] = SEALED
    assert raster_surfaces(inst, inst, tris, lo, hi, cam, kb, np.zeros(1, dtype=np.uint8),
                           stop) == 1  # the one instance, counted as culled
    assert not kb.count.any() and not kb.active.any()
    # One pixel under the triangle open again: drawn there only, as without the cull.
    p = int(drawn[len(drawn) // 2])
    kb.stencil[p] = 0
    assert raster_surfaces(inst, inst, tris, lo, hi, cam, kb, np.zeros(1, dtype=np.uint8),
                           stop) == 0
    assert list(np.flatnonzero(kb.count)) == [p]
