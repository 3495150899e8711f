"""The ``from_segment`` core: cell PVS, designed scenes with known answers, stiff inputs."""

from __future__ import annotations

import numpy as np
import pytest

from tests.visibility.segment_reference import sampled_visible, unwitnessed
from visibility.cores import designed_scenes as ds
from visibility.cores.base import available_cores, get_core
from visibility.cores.from_segment import (
    SUBPIXEL_CANDIDATES,
    FromSegmentCore,
    FromSegmentParams,
    cell_segments,
    cube_rotations,
)
from visibility.cores.from_segment.geometry import scene_geometries
from visibility.cores.from_segment.segment import segment_visible
from visibility.generators import make_scene
from visibility.ground_truth import fn_fp_rates, sample_pvs
from visibility.scene import Scene
from visibility.viewcells import Viewcell, ViewcellGrid

CORE = get_core("from_segment")


def test_registered_with_its_parameters():
    assert "from_segment" in available_cores()
    p = CORE.make_params()
    assert isinstance(p, FromSegmentParams)
    assert (p.resolution, p.runs, p.eye_levels, p.small) == (256, 1, 3, "corners")
    for bad in ({"small": "centres"}, {"runs": 0}, {"runs": 1.5}, {"near": 0.0},
                {"near": np.nan}, {"eye_levels": 4}, {"depth_knots": 0},
                {"batch_triangles": 10}, {"resolution": 4}, {"subpixel_runs": -1}):
        with pytest.raises(ValueError):
            CORE.make_params(**bad)


def test_cell_segments_walk_the_rectangle_at_each_eye_level():
    box = np.array([[0.0, 1.5, 0.0], [4.0, 1.9, 2.0]])
    segs = cell_segments(box, 3)
    assert segs.shape == (12, 2, 3)
    np.testing.assert_allclose(np.unique(segs[:, :, 1]), [1.5, 1.7, 1.9])
    # Each level is a closed loop around the rectangle.
    loop = segs[:4]
    np.testing.assert_array_equal(loop[:, 1], np.roll(loop[:, 0], -1, axis=0))
    assert cell_segments(box, 1).shape == (4, 2, 3)
    assert cell_segments(box, 2).shape == (8, 2, 3)
    flat = np.array([[0.0, 1.7, 0.0], [4.0, 1.7, 2.0]])
    assert cell_segments(flat, 3).shape == (4, 2, 3)
    line = np.array([[0.0, 1.7, 0.0], [4.0, 1.7, 0.0]])
    assert cell_segments(line, 1).shape == (1, 2, 3)
    point = np.array([[1.0, 1.7, 1.0], [1.0, 1.7, 1.0]])
    segs = cell_segments(point, 3)
    assert segs.shape == (1, 2, 3) and np.all(segs[0, 0] == segs[0, 1])
    with pytest.raises(ValueError):
        cell_segments(np.array([[1.0, 0, 0], [0.0, 0, 0]]))


def test_first_cube_is_oblique_by_default_and_axis_on_request():
    from visibility.cores.from_segment import oblique_rotation

    assert CORE.make_params().first_orientation == "oblique"
    r = oblique_rotation()
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    # No cube axis lies along a world axis (what keeps axis-aligned slivers off pixel rows).
    assert np.abs(r).max() < 0.95
    np.testing.assert_array_equal(cube_rotations(3, seed=2, first="oblique")[0], r)
    np.testing.assert_array_equal(cube_rotations(3, seed=2, first="oblique")[1:],
                                  cube_rotations(3, seed=2, first="axis")[1:])
    with pytest.raises(ValueError):
        CORE.make_params(first_orientation="diagonal")
    with pytest.raises(ValueError):
        cube_rotations(1, first="diagonal")


def test_oblique_first_cube_finds_more_of_an_axis_aligned_city():
    """The reason for the default: on an axis-aligned scene one oblique run misses less of the
    sampled ground truth than one axis-aligned run (long ledges parallel to the sides)."""
    scene = make_scene("city", triangles=20_000, seed=1)
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(len(grid) // 2)
    gt = sample_pvs(scene, cell, n_points=48, resolution=128, seed=5).triangle_ids
    fn = {}
    for first in ("axis", "oblique"):
        pvs = CORE.compute(scene, cell, CORE.make_params(resolution=64, eye_levels=1,
                                                         first_orientation=first))
        fn[first], _ = fn_fp_rates(pvs.triangle_ids, gt)
    assert fn["oblique"] < fn["axis"], fn


def test_cube_rotations_are_deterministic_rotations():
    a = cube_rotations(4, seed=9)
    np.testing.assert_array_equal(a, cube_rotations(4, seed=9))
    np.testing.assert_array_equal(a[0], np.eye(3))
    for r in a:
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
    assert not np.allclose(a[1], cube_rotations(4, seed=10)[1])


# ----------------------------------------------------------------------------- designed scenes
def _slit_scene():
    """A wall at z = -2 with a 4 cm vertical slit at x in [0.30, 0.34]; behind it at z = -6:
    ``part`` (seen through the slit from x ~ -0.5 only), ``between`` (seen only for x in about
    [-0.15, -0.05], between the samples of an 11-point sweep of x in [-1, 1]) and ``hidden``
    (never in line with the slit)."""
    tris = []

    def quad(x0, x1, y0, y1, z):
        tris.append([[x0, y0, z], [x1, y0, z], [x1, y1, z]])
        tris.append([[x0, y0, z], [x1, y1, z], [x0, y1, z]])

    quad(-30.0, 0.30, -30.0, 30.0, -2.0)
    quad(0.34, 30.0, -30.0, 30.0, -2.0)
    wall = [0, 1, 2, 3]

    def target(xc, z=-6.0, s=0.1, y=1.7):
        tris.append([[xc - s / 2, y - s / 2, z], [xc + s / 2, y - s / 2, z], [xc, y + s / 2, z]])
        return [len(tris) - 1]

    part = target(2.0)
    between = target(1.16)
    hidden = target(-5.0)
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    scene = Scene(v, np.arange(len(v)).reshape(-1, 3), name="slit")
    return scene, {"wall": wall, "part": part, "between": between, "hidden": hidden}


def test_wall_with_a_slit():
    scene, ids = _slit_scene()
    cell = Viewcell(np.array([[-1.0, 1.7, 0.0], [1.0, 1.7, 0.0]]))  # one segment, x -1 -> 1
    pvs = CORE.compute(scene, cell, CORE.make_params(resolution=128))
    found = set(pvs.triangle_ids.tolist())
    assert set(ids["wall"]) <= found
    assert set(ids["part"]) <= found and set(ids["between"]) <= found
    assert not set(ids["hidden"]) & found
    # "part" is visible for part of the segment only: not from either end.
    v, f = scene.vertices, scene.faces
    a, b = cell.box[0], cell.box[1]
    for end in (a, b):
        seen, _ = sampled_visible(v, v, f, end, end, 128, 1)
        assert not seen[ids["part"][0]]


def test_a_triangle_seen_only_between_two_sample_points():
    scene, ids = _slit_scene()
    a, b = np.array([-1.0, 1.7, 0.0]), np.array([1.0, 1.7, 0.0])
    v, f = scene.vertices, scene.faces
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, resolution=128, witness=wit)
    k = ids["between"][0]
    assert vis[k]
    # Eleven evenly spaced id buffers miss it; the witness proves it is seen in between.
    coarse, _ = sampled_visible(v, v, f, a, b, 128, 11)
    assert not coarse[k]
    assert 0.4 < wit[k, 1] < 0.5  # x = -1 + 2 t in (-0.2, 0.0)
    assert unwitnessed(wit, vis, v, v, f, a, b, 128) == []


def test_two_rooms_and_a_door():
    scene, cell, known = ds.two_rooms_and_a_door()
    pvs = CORE.compute(scene, cell, CORE.make_params(resolution=128))
    found = set(pvs.triangle_ids.tolist())
    assert known["visible"][0] in found  # the far wall of room B, through the door
    assert not set(known["hidden"]) & found


def test_open_scene_everything_visible_and_runs_only_add():
    scene, cell, known = ds.open_ring()
    one = CORE.compute(scene, cell, CORE.make_params(resolution=64))
    assert set(known["visible"]) <= set(one.triangle_ids.tolist())
    scene, cell, _ = ds.two_rooms_and_a_door()
    p1 = CORE.make_params(resolution=64, runs=1, seed=4)
    p3 = CORE.make_params(resolution=64, runs=3, seed=4)
    r1 = CORE.compute(scene, cell, p1)
    r3 = CORE.compute(scene, cell, p3)
    assert set(r1.triangle_ids.tolist()) <= set(r3.triangle_ids.tolist())
    np.testing.assert_array_equal(r3.triangle_ids, CORE.compute(scene, cell, p3).triangle_ids)


def _dust_behind_slits(n: int = 4000, slats: int = 200, gap: float = 0.01,
                       seed: int = 3) -> Scene:
    """Triangles of a few millimetres scattered 40-80 m around the origin (a pixel of 256 is
    0.3-0.6 m there), seen through a ring of ``slats`` tall slats 15 m out with ``gap`` m slits
    between them (no slats: in the open)."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:, 1] = np.abs(d[:, 1]) * 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centres = d * rng.uniform(40.0, 80.0, size=(n, 1)) + [0.0, 1.7, 0.0]
    tris = [(centres[:, None, :] + rng.uniform(-0.003, 0.003, size=(n, 3, 3))).reshape(-1, 3)]
    if slats:
        half = (2.0 * np.pi / slats - gap / 15.0) / 2.0
        for a in np.linspace(0.0, 2.0 * np.pi, slats, endpoint=False):
            p0 = 15.0 * np.array([np.cos(a - half), 0.0, np.sin(a - half)])
            p1 = 15.0 * np.array([np.cos(a + half), 0.0, np.sin(a + half)])
            lo, hi = np.array([0.0, -30.0, 0.0]), np.array([0.0, 40.0, 0.0])
            tris.append(np.array([p0 + lo, p1 + lo, p1 + hi, p0 + lo, p1 + hi, p0 + hi]))
    v = np.concatenate(tris)
    return Scene(v, np.arange(len(v)).reshape(-1, 3), name="dust")


def test_subpixel_runs_follow_only_where_the_answer_is_sub_pixel():
    """Dust seen through slits: the footprint rule tests its triangles along every segment
    and finds few, so the extra run is taken (the same turned cube as an explicit second run)
    and finds more. In the open the rule finds the dust at once (a candidate or less per
    triangle found), and rooms of pixel-sized triangles need no rule: one run each."""
    cell = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]))
    dust = _dust_behind_slits()
    auto = CORE.compute(dust, cell, CORE.make_params(walk="rectangle"))
    one = CORE.compute(dust, cell, CORE.make_params(walk="rectangle", subpixel_runs=0))
    two = CORE.compute(dust, cell, CORE.make_params(walk="rectangle", runs=2, subpixel_runs=0))
    assert auto.stats["subpixel_ratio"] > SUBPIXEL_CANDIDATES
    assert (auto.stats["runs"], one.stats["runs"], two.stats["runs"]) == (2, 1, 2)
    np.testing.assert_array_equal(auto.triangle_ids, two.triangle_ids)
    assert set(one.triangle_ids.tolist()) < set(auto.triangle_ids.tolist())
    for scene, c in ((_dust_behind_slits(slats=0), cell), ds.two_rooms_and_a_door()[:2]):
        plain = CORE.compute(scene, c, CORE.make_params(resolution=64))
        assert plain.stats["subpixel_ratio"] <= SUBPIXEL_CANDIDATES
        assert plain.stats["runs"] == 1


# ----------------------------------------------------------------------------- stiff inputs
@pytest.fixture(scope="module")
def stress():
    return make_scene("stress", triangles=10_000, seed=0)


def _check_pvs(pvs, scene):
    ids = pvs.triangle_ids
    assert ids.dtype == np.int32 and np.all(np.diff(ids) > 0)
    assert len(ids) == 0 or (ids[0] >= 0 and ids[-1] < scene.n_triangles)
    assert scene.valid_faces[ids].all()
    for val in pvs.stats.values():
        if isinstance(val, float):
            assert np.isfinite(val)


def test_stress_scene_cases(stress):
    grid = ViewcellGrid.for_scene(stress)
    cases = stress.meta["cases"]
    found = set()
    for cid in range(len(grid)):
        pvs = CORE.compute(stress, grid.cell(cid), CORE.make_params(resolution=128))
        _check_pvs(pvs, stress)
        found |= set(pvs.triangle_ids.tolist())
        assert not set(cases["hidden"]) & set(pvs.triangle_ids.tolist())
        assert set(cases["visible"]) <= set(pvs.triangle_ids.tolist())
    for name in ("zero_area", "repeated_index", "non_finite"):
        assert not set(cases[name]) & found
    # Slivers, eye-plane, coplanar, intersecting and huge triangles in view are found.
    for name in ("slivers", "coplanar", "intersecting", "huge"):
        assert set(cases[name]) & found, name


def test_large_offsets_do_not_change_the_answer(stress):
    near = make_scene("stress", triangles=10_000, seed=0, offset=0.0)
    far_grid = ViewcellGrid.for_scene(stress)
    near_grid = ViewcellGrid.for_scene(near)
    p = CORE.make_params(resolution=96, eye_levels=1)
    a = set(CORE.compute(near, near_grid.cell(0), p).triangle_ids.tolist())
    b = set(CORE.compute(stress, far_grid.cell(0), p).triangle_ids.tolist())
    assert len(a ^ b) <= 0.005 * len(a | b)


def test_edge_on_and_eye_plane_triangles():
    """A triangle containing the segment (eye in its plane all along), one in the plane of the
    segment but beside it (segment parallel to its plane), and one the eye crosses."""
    tris = np.array([
        [[-5.0, 1.7, -1.0], [5.0, 1.7, -1.0], [0.0, 1.7, 1.0]],   # contains the segment
        [[-5.0, 1.7, 3.0], [5.0, 1.7, 3.0], [0.0, 1.7, 6.0]],    # same plane, beside it
        [[-0.5, 0.0, -3.0], [0.5, 0.0, -3.0], [0.0, 4.0, -3.0]],  # in plain view
        [[0.3, 1.0, -1.0], [0.3, 1.0, 1.0], [0.3, 3.0, 0.0]],    # the eye passes through it
    ])
    scene = Scene(tris.reshape(-1, 3), np.arange(12).reshape(-1, 3))
    cell = Viewcell(np.array([[-1.0, 1.7, 0.0], [1.0, 1.7, 0.0]]))
    pvs = CORE.compute(scene, cell, CORE.make_params(resolution=64))
    _check_pvs(pvs, scene)
    got = set(pvs.triangle_ids.tolist())
    assert 2 in got and 3 in got
    assert 0 not in got and 1 not in got  # always edge-on: never covers a pixel centre


# ----------------------------------------------------------------------------- other scenes
def test_spheres_come_back_as_sphere_ids():
    scene = make_scene("spheres", spheres=150, states=3, seed=1)
    grid = ViewcellGrid.for_scene(scene)
    pvs = CORE.compute(scene, grid.cell(len(grid) // 2), CORE.make_params(resolution=48,
                                                                            eye_levels=1))
    _check_pvs(pvs, scene)
    assert pvs.sphere_ids is not None and len(pvs.sphere_ids) > 0
    assert pvs.sphere_ids.min() >= 0 and pvs.sphere_ids.max() < scene.n_spheres
    assert pvs.stats["state_intervals"] == 2


def test_dynamic_scene_against_sampled_ground_truth():

    scene = make_scene("swaying_grass", triangles=3000, seed=2, states=3)
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(0)
    pvs = CORE.compute(scene, cell, CORE.make_params(resolution=64, runs=1))
    _check_pvs(pvs, scene)
    assert pvs.stats["state_intervals"] == 2
    gt = sample_pvs(scene, cell, n_points=24, resolution=96, seed=3)
    fn, _ = fn_fp_rates(pvs.triangle_ids, gt.triangle_ids)
    assert fn == 0.0  # nothing the sampled eyes see is missing (fixed seeds: deterministic)


def test_compute_segment_is_exact_on_a_diagonal_segment():
    """The PVS of a diagonal segment (no box describes it) holds everything id buffers see from
    points on it with the same cube and resolution, and is not the PVS of its bounding box."""
    scene = make_scene("village", triangles=4000, seed=3)
    grid = ViewcellGrid.for_scene(scene)
    box = grid.cell(len(grid) // 2).box
    p, q = box[0].copy(), box[1].copy()
    p[1] = q[1] = 0.5 * (box[0, 1] + box[1, 1])
    res = 48
    # The reference renders axis-aligned cubes: the core must use the same one.
    pvs = CORE.compute_segment(scene, p, q, CORE.make_params(resolution=res, runs=1, jitter=0.0,
                                                             first_orientation="axis"))
    assert pvs.stats["segments"] == 1
    tri, _ = sampled_visible(scene.vertices, scene.vertices, scene.faces, p, q, res, 64,
                             face_mask=scene.valid_faces)
    seen = np.flatnonzero(tri)
    missing = np.setdiff1d(seen, pvs.triangle_ids)
    assert len(missing) <= max(1, len(seen) // 200), missing
    # The bounding box's perimeter sees more than the diagonal does.
    boxed = CORE.compute(scene, Viewcell(np.stack([np.minimum(p, q), np.maximum(p, q)])),
                         CORE.make_params(resolution=res, eye_levels=1,
                                          first_orientation="axis"))
    assert len(boxed) > len(pvs)
    with pytest.raises(ValueError):
        CORE.compute_segment(scene, p, np.array([np.nan, 0, 0]))


def test_lone_sliver_is_reported_exactly_when_a_pixel_centre_crosses_it():
    """Exact at pixel centres (``jitter=0``, the paper's samples): the 1e6-aspect sliver of
    ``checks.check_lone_sliver`` is reported exactly when a row centre of the axis-aligned -Z
    face crosses it for some eye of the perimeter (a crossing lasts a tiny stretch of a side, so
    point samples along the sides miss it: the reason for a continuous method). The eyes are at
    y in {1.5, 1.7, 1.9}, 7 to 9 m from the sliver's plane, so it spans the vertical tangents
    [(1.7 - y) / d, (1.7 + 4e-6 - y) / d] for d in [7, 9]; row centres are at tangents (2k + 1)
    / R - 1."""
    from visibility.cores.checks import check_valid

    core = FromSegmentCore()
    tri = np.array([[(-2, 1.7, -8), (2, 1.7, -8), (0, 1.7 + 4e-6, -8)]], dtype=np.float64)
    scene = Scene(tri.reshape(-1, 3), np.arange(3).reshape(1, 3), name="sliver")
    cell = Viewcell(np.array([[-1.0, 1.5, -1.0], [1.0, 1.9, 1.0]]))
    for res in (64, 128):
        rows = (2 * np.arange(res) + 1) / res - 1
        seen = False
        for y in (1.5, 1.7, 1.9):
            ends = np.array([(1.7 - y) / d for d in (7.0, 9.0)]
                            + [(1.7 + 4e-6 - y) / d for d in (7.0, 9.0)])
            seen |= bool(np.any((rows >= ends.min()) & (rows <= ends.max())))
        got = check_valid(core.compute(scene, cell, core.make_params(
            resolution=res, runs=1, first_orientation="axis", jitter=0.0, small="samples")), scene)
        assert got == ({0} if seen else set()), (res, seen)
        assert seen == (res == 128)  # the case is built so both branches are exercised


def _between_rows(occluder: str) -> Scene:
    """A 2 cm triangle 50 m down -Z at a vertical tangent of 0.001-0.0014: between the row
    centres +-1/64 of a 32 px axis-aligned face for every eye at y 1.7 (which only moves in x),
    so no centre ever meets it; ``occluder`` "wall" (a wall 10 m away) or "sphere" (5 m across,
    25 m away) hides it from every such eye, "none" leaves it in plain view, "speck" puts a
    1.2 m x 2 cm board 25 m away in every line of sight to it, itself between the same rows,
    and "slat" a 3 mm one in every line of sight to its centroid that leaves its corners in
    view (the centroid's lines cross the slat's plane at y 1.7283, the corners' at 1.725 and
    1.735). For "straddle" the triangle stands at tangents -0.0005 to 0.0005, within half a
    pixel of the rows of centres on both sides (its box holds pixels of each, in two tiles),
    over a wall 10 m away whose top edge stays 5 mm below every line of sight to it: the row
    below sees the wall, nearer, all along the segment (those pixels close, and the triangle
    passes them by), the row above sees nothing, and the centroid's image stays in the row
    below."""
    tris = [[(0.0, 1.75, -50.0), (0.02, 1.75, -50.0), (0.0, 1.77, -50.0)]]
    if occluder == "straddle":
        tris = [[(0.0, 1.675, -50.0), (0.02, 1.675, -50.0), (0.0, 1.725, -50.0)]]
    if occluder in ("speck", "slat"):
        y0, y1 = (1.72, 1.74) if occluder == "speck" else (1.727, 1.730)
        tris += [[(-0.6, y0, -25), (0.6, y0, -25), (0.6, y1, -25)],
                 [(-0.6, y0, -25), (0.6, y1, -25), (-0.6, y1, -25)]]
    if occluder in ("wall", "straddle"):
        top = 10.0 if occluder == "wall" else 1.69
        tris += [[(-20, -10, -10), (20, -10, -10), (20, top, -10)],
                 [(-20, -10, -10), (20, top, -10), (-20, top, -10)]]
    v = np.array(tris, dtype=np.float64).reshape(-1, 3)
    kw = {}
    if occluder == "sphere":
        kw = dict(sphere_centers=np.array([[[0.0, 1.7, -25.0]]]), sphere_radii=np.array([5.0]))
    return Scene(v, np.arange(len(v)).reshape(-1, 3), name="between_rows", **kw)


@pytest.mark.parametrize("occluder", ["none", "wall", "sphere", "speck", "slat", "straddle"])
def test_footprint_finds_a_triangle_between_the_samples_and_nothing_hidden(occluder):
    """``small="samples"`` (the paper) reports what a pixel centre sees: not a sub-pixel
    triangle that stays between two rows of centres along the whole segment. "footprint"
    samples it at its centroid too: reported in plain view, not behind a wall or a sphere,
    nor behind a board no pixel sample meets either (its centroid ray is cast past the
    pixels' envelopes, and the board, reported itself, stops it). "corners" samples near its
    corners as well: it finds the triangle past a slat that hides its centroid from every
    eye, and past a wall's edge where its centroid's image stays in the closed row below
    and its corners show in the tile above, where "footprint" does not; and it reports
    nothing hidden either."""
    scene = _between_rows(occluder)
    p, q = np.array([-1.0, 1.7, 0.0]), np.array([1.0, 1.7, 0.0])
    kw = dict(resolution=32, runs=1, jitter=0.0, first_orientation="axis")
    paper = CORE.compute_segment(scene, p, q, CORE.make_params(small="samples", **kw))
    wall = [1, 2] if occluder in ("wall", "straddle") else []
    assert paper.triangle_ids.tolist() == wall
    for small in ("footprint", "corners"):
        got = CORE.compute_segment(scene, p, q, CORE.make_params(small=small, **kw))
        want = {"none": [0], "sphere": [], "speck": [1, 2], "slat": [1, 2]}.get(occluder, wall)
        if small == "corners" and occluder in ("slat", "straddle"):
            want = [0] + want
        assert got.triangle_ids.tolist() == want, small
        if occluder in ("none", "speck", "slat", "straddle"):
            assert got.stats["footprint_candidates"] > 0
        # Two tiles may both mark a triangle before either sees the other's mark.
        found = len(want) - len(wall)
        assert found <= got.stats.get("footprint_seen", 0) <= 2 * found, small


def test_footprint_is_refused_with_witnesses():
    geom = scene_geometries(_between_rows("none"))[0]
    with pytest.raises(ValueError, match="witness"):
        segment_visible(geom, np.zeros(3), np.ones(3), witness=np.zeros((geom.n_ids, 5)),
                        footprint=True)


def test_cutting_sides_in_clutter_keeps_the_set():
    """Dense grass sweeps across the cube along a cell's side: the core cuts the sides
    (``cuts``) and finds the same set as without cuts, at its pixel samples (the centroid
    samples of ``small="footprint"`` are placed per piece)."""
    scene = make_scene("grass", triangles=5000, seed=2)
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(len(grid) // 2)
    cut = CORE.compute(scene, cell, CORE.make_params(resolution=32, small="samples"))
    whole = CORE.compute(scene, cell, CORE.make_params(resolution=32, cuts=0, small="samples"))
    assert cut.stats.get("splits", 0) > 0 and "splits" not in whole.stats
    assert np.array_equal(cut.triangle_ids, whole.triangle_ids)
