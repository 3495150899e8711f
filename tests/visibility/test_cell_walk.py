"""Open floor inside a cell and the from_segment segments around it, on a built room."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cell_walk import (
    MAX_LATTICE,
    STEP,
    _hits_along,
    _near_triangles,
    body_height,
    cell_walk,
    clear_pieces,
    lattice_step,
    open_eyes,
    walk_segments,
)
from visibility.cores.base import get_core
from visibility.cores.from_segment import view_segments
from visibility.scene import Scene
from visibility.viewcells import Viewcell

BOX = np.array([[0.0, 1.5, 0.0], [4.0, 1.9, 4.0]])  # a 4 m cell, eyes 1.5-1.9 m above y = 0


def _solid(tris, lo, hi):
    """A closed axis-aligned box, counter-clockwise seen from outside (outward normals)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    c = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    for a, b, d, e in quads:
        tris.append([c[a], c[b], c[d]])
        tris.append([c[a], c[d], c[e]])


def _room():
    """Floor 20 x 20 m at y = 0; a closed 0.3 m thick wall across the cell at x 1.85-2.15
    (z -10 to 10, 3 m high) hiding a small triangle inside it; a table 1.0-1.6 x 0.4-1.4 (top
    0.75 m); the rest of the cell open. Returns the scene and the triangle ids."""
    tris = []
    tris.append([[-10, 0, -10], [-10, 0, 10], [10, 0, 10]])
    tris.append([[-10, 0, -10], [10, 0, 10], [10, 0, -10]])
    n0 = len(tris)
    _solid(tris, (1.85, 0.0, -10.0), (2.15, 3.0, 10.0))
    wall = list(range(n0, len(tris)))
    n0 = len(tris)
    _solid(tris, (1.0, 0.7, 0.4), (1.6, 0.75, 1.4))
    table = list(range(n0, len(tris)))
    # Inside the wall, facing +x: only an eye inside the wall can see it.
    tris.append([[2.0, 1.6, 1.9], [2.0, 1.6, 2.1], [2.0, 1.8, 2.0]])
    inside = [len(tris) - 1]
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    scene = Scene(v, np.arange(len(v)).reshape(-1, 3), name="walled-room")
    return scene, {"wall": wall, "table": table, "inside": inside}


def test_open_floor_excludes_wall_and_table():
    scene, _ = _room()
    w = cell_walk(scene, BOX, step=0.1)
    gx, gz = np.meshgrid(w.xs, w.zs, indexing="ij")
    in_wall = (gx > 1.85 + 1e-9) & (gx < 2.15 - 1e-9)
    under_table = (gx > 1.0 + 1e-9) & (gx < 1.6 - 1e-9) & (gz > 0.4 + 1e-9) & (gz < 1.4 - 1e-9)
    assert not w.open[in_wall].any()
    assert not w.open[under_table].any()
    e = 1e-6  # points on a solid's face may go either way
    elsewhere = ~((gx >= 1.85 - e) & (gx <= 2.15 + e)) & ~(
        (gx >= 1.0 - e) & (gx <= 1.6 + e) & (gz >= 0.4 - e) & (gz <= 1.4 + e))
    assert w.open[elsewhere].all()
    assert w.open_area == pytest.approx(w.open.sum() * 0.01)


def _crossings(seg, tris):
    buf = np.empty(64)
    n, _ = _hits_along(np.asarray(seg[0], float), np.asarray(seg[1], float), tris, buf)
    return n


def test_no_segment_passes_through_geometry():
    scene, _ = _room()
    tris = scene.triangles().astype(np.float64)
    old, how_old = view_segments(scene, BOX, 3, "rectangle")
    assert how_old == "rectangle"
    assert sum(_crossings(s, tris) for s in old) > 0  # the cell's sides cross the wall
    segs, how = view_segments(scene, BOX, 3, "open")
    assert how == "open" and len(segs) > 0
    assert all(_crossings(s, tris) == 0 for s in segs)
    # Dense check too: points along every segment lie outside the wall and the table.
    t = np.linspace(0.0, 1.0, 101)[:, None]
    pts = np.concatenate([s[0] + t * (s[1] - s[0]) for s in segs])
    assert not ((pts[:, 0] > 1.85) & (pts[:, 0] < 2.15)).any()
    # Both sides of the wall are walked, at every eye height.
    assert (pts[:, 0] < 1.85).any() and (pts[:, 0] > 2.15).any()
    assert set(np.round(segs[:, :, 1].ravel(), 6)) == {1.5, 1.7, 1.9}


def test_clear_pieces_split_at_a_thin_wall():
    tri = np.array([[[1.0, -5, -5], [1.0, 5, -5], [1.0, 0, 5]]], dtype=np.float64)
    pieces = clear_pieces(np.array([0.0, 0, 0]), np.array([3.0, 0, 0]), tri, 0.1, margin=0.2)
    assert len(pieces) == 2
    assert 0.75 <= pieces[0][1][0] <= 0.8 and 1.2 <= pieces[1][0][0] <= 1.25
    assert clear_pieces(np.zeros(3), np.zeros(3), tri) == []


def test_pvs_drops_what_only_the_inside_of_the_wall_sees():
    scene, ids = _room()
    core = get_core("from_segment")
    cell = Viewcell(BOX)
    old = core.compute(scene, cell, core.make_params(resolution=128, walk="rectangle"))
    new = core.compute(scene, cell, core.make_params(resolution=128))
    assert set(ids["inside"]) <= set(old.triangle_ids.tolist())
    assert not set(ids["inside"]) & set(new.triangle_ids.tolist())
    assert set(ids["table"]) & set(new.triangle_ids.tolist())
    assert new.stats["walk"] == "open"


def test_cell_with_no_open_floor_walks_its_rectangle():
    scene, _ = _room()
    inside_wall = np.array([[1.9, 1.5, 0.0], [2.1, 1.9, 4.0]])
    assert walk_segments(scene, inside_wall, [1.7]).shape == (0, 2, 3)
    segs, how = view_segments(scene, inside_wall, 1, "open")
    assert how == "rectangle (no open floor in the cell)" and len(segs) == 4
    line = np.array([[0.0, 1.7, 1.0], [1.0, 1.7, 1.0]])
    assert view_segments(scene, line, 1, "open")[1] == "rectangle (degenerate box)"
    with pytest.raises(ValueError):
        view_segments(scene, BOX, 1, "walls")
    with pytest.raises(ValueError):
        cell_walk(scene, BOX, step=0.0)


def test_clear_pieces_keep_off_a_parallel_thin_wall():
    # A wall 5 cm beside the middle metre of the segment, parallel to it: nearer than the
    # cubemap's near-plane corners, so that stretch is dropped; the ends stay.
    wall = np.array([[[1.0, -5, 0.05], [2.0, -5, 0.05], [2.0, 5, 0.05]],
                     [[1.0, -5, 0.05], [2.0, 5, 0.05], [1.0, 5, 0.05]]], dtype=np.float64)
    pieces = clear_pieces(np.array([0.0, 0, 0]), np.array([3.0, 0, 0]), wall, 0.1, 0.1)
    assert len(pieces) == 2
    assert pieces[0][1][0] < 1.0 and pieces[1][0][0] > 2.0
    far = clear_pieces(np.array([0.0, 0, 0.5]), np.array([3.0, 0, 0.5]), wall, 0.1, 0.1)
    assert len(far) == 1 and far[0][1][0] == pytest.approx(3.0)


def test_cost_estimate_uses_found_segments_without_casting():
    scene, _ = _room()
    core = get_core("from_segment")
    cell = Viewcell(BOX + np.array([0.0, 0.0, 10.0]))  # a cell no other test has walked
    params = core.make_params(resolution=64)
    before = core.estimate_cost(scene, cell, params).detail["views"]
    assert before == 12  # nothing cast yet: the rectangle's count
    segs, how = view_segments(scene, cell.box, 3, "open")
    assert core.estimate_cost(scene, cell, params).detail["views"] == len(segs)


def test_pvs_holds_what_dense_rays_from_the_segments_hit():
    # The promise, checked on the segments themselves: from points along every walked segment,
    # rays in random directions hit only triangles of the PVS, and never the one in the wall.
    from tests.visibility.segment_reference import ray_triangle_depths

    scene, ids = _room()
    core = get_core("from_segment")
    cell = Viewcell(BOX)
    pvs = set(core.compute(scene, cell, core.make_params(resolution=128)).triangle_ids.tolist())
    segs, _ = view_segments(scene, BOX, 3, "open")
    tris = scene.triangles().astype(np.float64)
    rng = np.random.default_rng(11)
    hit = set()
    for a, b in segs:
        for t in np.linspace(0.0, 1.0, 9):
            eye = a + t * (b - a)
            w = rng.normal(size=(4000, 3))
            w /= np.abs(w).max(axis=1, keepdims=True)  # depth 1 per unit along the major axis
            d = ray_triangle_depths(tris - eye, w, 0.0)
            first = d.argmin(axis=1)
            hit |= set(first[np.isfinite(d.min(axis=1))].tolist())
    assert ids["inside"][0] not in hit
    assert hit <= pvs, sorted(hit - pvs)
    assert set(ids["wall"]) & hit and set(ids["table"]) & hit


def test_a_huge_cell_gets_a_coarser_lattice():
    # A 1 km cell would hold 25M points at 0.2 m; it holds at most MAX_LATTICE a side.
    box = np.array([[-500.0, -500.0, -500.0], [500.0, 500.0, 500.0]])
    walk = cell_walk(_room()[0], box)
    assert len(walk.xs) <= MAX_LATTICE and len(walk.zs) <= MAX_LATTICE
    assert lattice_step(box) > STEP
    assert lattice_step(np.array([[0.0, 0.0, 0.0], [4.0, 2.0, 4.0]])) == STEP


def _point_triangle_distance(p, tri):
    """Exact: to the plane where p projects inside the triangle, else to the nearest edge."""
    a, b, c = tri
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    q = p - np.dot(p - a, n) * n
    inside = all(np.dot(np.cross(v1 - v0, q - v0), n) >= 0 for v0, v1 in ((a, b), (b, c), (c, a)))
    if inside:
        return abs(float(np.dot(p - a, n)))
    best = np.inf
    for v0, v1 in ((a, b), (b, c), (c, a)):
        t = np.clip(np.dot(p - v0, v1 - v0) / np.dot(v1 - v0, v1 - v0), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(p - (v0 + t * (v1 - v0)))))
    return best


def test_open_eyes_stand_on_open_floor_clear_of_every_triangle():
    scene, _ = _room()
    rng = np.random.default_rng(4)
    eyes = open_eyes(scene, BOX, 200, rng, clearance=0.1, step=0.1)
    w = cell_walk(scene, BOX, step=0.1)
    open_xz = {(x, z) for i, x in enumerate(w.xs) for k, z in enumerate(w.zs) if w.open[i, k]}
    assert 150 <= len(eyes) <= 200
    tris = scene.triangles().astype(np.float64)
    near_wall = 0
    for e in eyes:
        assert (e[0], e[2]) in open_xz
        assert BOX[0, 1] <= e[1] <= BOX[1, 1]
        # The wall's faces are at x 1.85 and 2.15: open lattice points 0.1 m from them exist,
        # but an eye must be farther than the clearance from every triangle.
        assert min(_point_triangle_distance(e, t) for t in tris) >= 0.1
        near_wall += abs(e[0] - 1.85) < 0.15 or abs(e[0] - 2.15) < 0.15
    assert near_wall > 0  # eyes do come near the wall, just not within the clearance
    # Lattice points on the wall's faces are open (the vertical line clears it) but too near.
    on_face = [(x, z) for (x, z) in open_xz if abs(x - 1.8) < 1e-9]
    assert on_face and all(abs(e[0] - 1.8) > 1e-9 for e in eyes)
    inside_wall = np.array([[1.9, 1.5, 0.0], [2.1, 1.9, 4.0]])
    assert open_eyes(scene, inside_wall, 10, rng).shape == (0, 3)


def test_body_follows_the_scene_eye_height():
    """Eyes 1.0-1.35 m above the floor (a game level's units): a body of two thirds of the
    lowest eye height stays clear of the floor, where a fixed 1 m body touched it."""
    scene, _ = _room()
    low = np.array([[0.0, 1.0, 0.0], [1.6, 1.35, 4.0]])  # the room's floor at y = 0
    scene.meta["eye_range"] = [1.0, 1.35]
    assert body_height(scene) == pytest.approx(2.0 / 3.0)
    assert cell_walk(scene, low, step=0.2).open.any()
    assert not cell_walk(scene, low, step=0.2, body=1.0).open.any()
    # The table (top 0.75 m, 0.25 m under these eyes) still blocks a standing place.
    w = cell_walk(scene, low, step=0.1)
    gx, gz = np.meshgrid(w.xs, w.zs, indexing="ij")
    under_table = (gx > 1.0 + 1e-9) & (gx < 1.6 - 1e-9) & (gz > 0.4 + 1e-9) & (gz < 1.4 - 1e-9)
    assert under_table.any() and not w.open[under_table].any()


def test_near_triangles_are_the_same_with_and_without_the_hierarchy():
    """The hierarchy only narrows the scan: the triangles near a cell, in face order, are
    those of the full scan (a fresh scene object has no hierarchy until one is built)."""
    from visibility.generators import make_scene
    from visibility.raster.hierarchy import scene_hierarchy

    a = make_scene("city", 6000, seed=3)
    b = make_scene("city", 6000, seed=3)
    scene_hierarchy(b)
    box = np.array([[10.0, 1.5, 10.0], [14.0, 1.9, 14.0]])
    full = _near_triangles(a, box, 0.3, 0.5)
    tree = _near_triangles(b, box, 0.3, 0.5)
    assert len(full) > 0 and np.array_equal(full, tree)
    far = np.array([[1e4, 1.5, 1e4], [1e4 + 4.0, 1.9, 1e4 + 4.0]])
    assert _near_triangles(b, far, 0.3, 0.5).shape == (0, 3, 3)


def _clutter(rng, n=600):
    """A floor, closed boxes and random triangles of 1 cm to 2 m (some vertical, some lying
    on lattice lines) over a 6 m square: a soup on which the binned queries must agree with
    testing every triangle."""
    tris = [[[-1, 0, -1], [-1, 0, 7], [7, 0, 7]], [[-1, 0, -1], [7, 0, 7], [7, 0, -1]]]
    for _ in range(12):
        lo = rng.uniform([0, 0, 0], [5, 1.5, 5])
        _solid(tris, lo, lo + rng.uniform([0.05, 0.05, 0.05], [1.5, 2.0, 1.5]))
    for _ in range(n):
        c = rng.uniform([0, 0, 0], [6, 3, 6])
        tri = c + rng.normal(size=(3, 3)) * rng.choice([0.01, 0.2, 1.0])
        if rng.random() < 0.2:
            tri[:, 0] = c[0]  # a vertical triangle in the plane x = const
        if rng.random() < 0.1:
            tri[:, 2] = np.round(c[2] / STEP) * STEP  # in the plane of a lattice line
        tris.append(tri)
    return np.asarray(tris, dtype=np.float64)


def _open_brute(px, pz, y_lo, y_hi, y_top, tris, sign):
    """``cell_walk``'s per-point test against every triangle (the reference for the grid)."""
    out = np.zeros(len(px), dtype=bool)
    buf = np.empty(1)
    for s, (x, z) in enumerate(zip(px, pz, strict=True)):
        if _hits_along(np.array([x, y_lo, z]), np.array([x, y_hi, z]), tris, buf)[0]:
            continue
        c, ny = _hits_along(np.array([x, y_hi, z]), np.array([x, y_top, z]), tris, buf)
        out[s] = not (c and sign * ny > 0.0)
    return out


@pytest.mark.parametrize("seed", range(3))
def test_binned_open_points_and_clear_pieces_match_testing_every_triangle(seed):
    """The XZ grid only skips triangles a query cannot meet: the open lattice and the clear
    pieces are those a scan of every triangle gives."""
    from visibility.cell_walk import XZGrid, _open_points

    rng = np.random.default_rng(seed)
    tris = _clutter(rng)
    box = np.array([[0.0, 1.5, 0.0], [6.0, 1.9, 6.0]])
    xs = np.linspace(0.0, 6.0, 31)
    gx, gz = (a.ravel() for a in np.meshgrid(xs, xs, indexing="ij"))
    grid = XZGrid(tris, box, STEP)
    got = _open_points(gx, gz, 0.5, 1.9, 4.0, tris, 1.0, *grid.args())
    want = _open_brute(gx, gz, 0.5, 1.9, 4.0, tris, 1.0)
    assert 0 < want.sum() < len(want)  # both open and closed points are tried
    np.testing.assert_array_equal(got, want)
    for _ in range(20):
        p, q = (np.r_[rng.uniform(0, 6), 1.7, rng.uniform(0, 6)] for _ in range(2))
        binned = clear_pieces(p, q, tris, grid=grid)
        alone = clear_pieces(p, q, tris)  # its own grid over the segment
        # Every sample's cross line against every triangle: the pieces' ends are kept samples.
        for a, b in binned:
            for end in (a, b):
                side = np.array([-(q - p)[2], 0.0, (q - p)[0]])
                side = side / np.linalg.norm(side) * 0.1
                assert _hits_along(end - side, end + side, tris, np.empty(1))[0] == 0
        assert len(binned) == len(alone)
        for (a, b), (c, d) in zip(binned, alone, strict=True):
            np.testing.assert_array_equal(a, c)
            np.testing.assert_array_equal(b, d)


def _inward(tris, lo, hi):
    """A sealed room: ``_solid``'s box wound the other way, its faces towards the inside (a game
    level's walls face into its rooms)."""
    part = []
    _solid(part, lo, hi)
    tris += [[a, c, b] for a, b, c in part]


def test_a_level_s_void_is_no_open_floor_though_nothing_stands_above_or_below():
    """A sealed room (walls facing in) whose wall at x = 2 crosses the cell: inside it the floor
    is open; beside it, in the void, the vertical lines meet nothing above or below, as in a
    street of a city without terrain, but level rays meet the room's walls from behind (or
    nothing), and no one stands there."""
    tris = []
    _inward(tris, (-6.0, 0.0, -6.0), (2.0, 3.0, 6.0))
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    scene = Scene(v, np.arange(len(v)).reshape(-1, 3), name="sealed-room")
    walk = cell_walk(scene, BOX)
    inside = walk.xs[:, None] < 2.0 - 1e-9
    outside = walk.xs[:, None] > 2.0 + 1e-9
    assert walk.open[np.broadcast_to(inside, walk.open.shape)].all()
    assert not walk.open[np.broadcast_to(outside, walk.open.shape)].any()
    # From_segment's segments follow: none reaches into the void.
    segs = walk_segments(scene, BOX, [1.7])
    assert len(segs) and segs[:, :, 0].max() < 2.0


def test_a_street_between_solids_without_terrain_stays_open_floor():
    """Two closed buildings (faces out) with a 2 m street between them and no ground at all
    (the city scenes): the street's level rays meet facades from the front, so it stays open
    floor; the buildings' insides do not."""
    tris = []
    _solid(tris, (-6.0, 0.0, -6.0), (1.0, 10.0, 10.0))
    _solid(tris, (3.0, 0.0, -6.0), (10.0, 10.0, 10.0))
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    scene = Scene(v, np.arange(len(v)).reshape(-1, 3), name="street")
    walk = cell_walk(scene, BOX)
    street = (walk.xs > 1.0 + 1e-9) & (walk.xs < 3.0 - 1e-9)
    assert walk.open[street].all()
    # (Lattice points on a facade's plane may go either way.)
    assert not walk.open[(walk.xs < 1.0 - 1e-9) | (walk.xs > 3.0 + 1e-9)].any()


def test_walls_closed_around_a_point_with_no_roof_straight_above_are_no_open_floor():
    """A house's lower storey: four walls (faces out) with no ceiling over the lattice point,
    the storey above set back off it (a village's overhang seen from inside: the first surface
    above faces down). The vertical tests pass; the level rays meet only the walls' backs."""
    tris = []
    part = []
    _solid(part, (0.5, 0.0, 0.5), (3.5, 2.5, 3.5))
    # The walls only: no floor, no top (the sides of the box).
    tris += [t for t in part if not (np.ptp(np.array(t)[:, 1]) == 0.0)]
    # An upper storey's bottom face (facing down) above the middle, 2.7 m up.
    tris += [[[1.0, 2.7, 1.0], [3.0, 2.7, 1.0], [3.0, 2.7, 3.0]],
             [[1.0, 2.7, 1.0], [3.0, 2.7, 3.0], [1.0, 2.7, 3.0]]]
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    scene = Scene(v, np.arange(len(v)).reshape(-1, 3), name="storey")
    walk = cell_walk(scene, BOX)
    inner = ((walk.xs[:, None] > 0.5 + 1e-9) & (walk.xs[:, None] < 3.5 - 1e-9)
             & (walk.zs[None, :] > 0.5 + 1e-9) & (walk.zs[None, :] < 3.5 - 1e-9))
    assert not walk.open[inner].any()
    # Around the house (outside its walls) the floor stays open.
    assert walk.open[(walk.xs[:, None] < 0.5 - 1e-9) | (walk.zs[None, :] < 0.5 - 1e-9)].all()
