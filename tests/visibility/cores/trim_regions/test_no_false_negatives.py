"""False-negative pixels within the paper's bound (Sec. 6.4: at most 0.005 % of a frame's pixels)
for Δ up to 0.2 m, by the method alone (the defaults: no sampling add-on): frames from eyes
with random cube orientations inside the cell, rendered from the full scene, must show no more
than that share of pixels whose triangle the PVS lacks (``trim_regions.quality.frame_errors``).
Generated scenes in the quick tests; the real scenes of ../shared/scenes (lavaducts, the Lyon
tile, Den Haag and the kitchen) are ``slow`` and fail when missing. The kitchen's middle cell
holds the bound at the defaults (small triangles rasterized conservatively); at the paper's
pixel centres (``small="centres"``) it is over the bound (traced in
docs/cores/trim_regions.md) and held to its measured figure."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from visibility.cores.base import get_core
from visibility.cores.trim_regions.core import DEFAULT_MAX_DELTA
from visibility.cores.trim_regions.quality import FRAME_NEAR, frame_errors
from visibility.generators import make_scene
from visibility.ray_frames import RayFrames, first_open_cell, ray_frames
from visibility.viewcells import Viewcell, ViewcellGrid

#: The paper's bound on false-negative pixels per frame (Wonka et al. 2006's 0.005 %).
BOUND = 5e-5
CORE = get_core("trim_regions")


@cache
def _scene(name: str, triangles: int):
    return make_scene(name, triangles=triangles)


#: Open cell centres found so far, by (scene id, which): each search casts rays over a whole
#: Embree scene of the scene (seconds on the 1M-triangle kitchen), and a test asks for the
#: same cell more than once. The scenes are cached for the run, so their ids stay theirs.
_CENTRES: dict[tuple[int, int], np.ndarray] = {}


def _box(scene, which: int, delta: float) -> np.ndarray:
    """The cube of diagonal 2 delta around the middle (0) or a third (1) of the scene's grid."""
    key = (id(scene), which)
    if key not in _CENTRES:
        grid = ViewcellGrid.for_scene(scene)
        _CENTRES[key] = grid.cell(first_open_cell(scene, grid, len(grid) // 2 if which == 0
                                                  else len(grid) // 3)).center
    c = _CENTRES[key]
    h = delta / np.sqrt(3.0)
    return np.stack([c - h, c + h])


def _errors(scene, which: int, delta: float, frames: int = 8, seed: int = 3,
            cast: RayFrames | None = None, **params):
    box = _box(scene, which, delta)
    pvs = CORE.compute(scene, Viewcell(box), CORE.make_params(max_delta=delta, **params))
    e = frame_errors(scene, pvs.triangle_ids, box, n_points=frames, resolution=256, seed=seed,
                     frames=cast)
    # Judged from eyes in open space: a cell whose eyes all stand inside geometry proves
    # nothing.
    assert e["frames"] > 0, "no eye of the cell stands in open space"
    return e


@pytest.mark.parametrize("delta", [0.05, 0.2])
@pytest.mark.parametrize("name,which", [("rooms", 0), ("village", 1), ("city", 0)])
def test_false_negative_pixels_on_generated_scenes(name, which, delta):
    e = _errors(_scene(name, 10_000), which, delta)
    assert e["fn_pixel_rate_max"] <= BOUND, (name, delta, e["fn_pixels_max"], e["missed"][:20])
    # A PVS at all, and not the whole scene.
    assert e["gt"] <= e["pvs"] < _scene(name, 10_000).n_triangles


@pytest.mark.slow
def test_small_triangles_between_vstars_samples_on_the_100k_city():
    # The 100k city's middle cell at Δ 0.2 m was over the bound by the method alone until
    # v*'s gather tested small triangles against the samples around them
    # (hulls.touching_samples): clutter v* sees between its samples per pixel.
    e = _errors(_scene("city", 100_000), 0, 0.2, frames=24, seed=1)
    assert e["fn_pixel_rate_max"] <= BOUND, (e["fn_pixels_max"], e["missed"][:20])


@pytest.mark.slow
@pytest.mark.parametrize("delta", [0.05, 0.2, DEFAULT_MAX_DELTA])
@pytest.mark.parametrize("name,which", [("lyon_vilo3d", 0), ("lyon_vilo3d", 1), ("denhaag", 0)])
def test_false_negative_pixels_on_real_scenes(name, which, delta):
    from tests.visibility.real_scenes import REAL, real_scene

    assert name in REAL, f"the real scene {name} of ../shared/scenes is missing"
    e = _errors(real_scene(name), which, delta)
    assert e["fn_pixel_rate_max"] <= BOUND, (name, delta, e["fn_pixels_max"], e["missed"][:20])


@pytest.mark.slow
#: The first cell's in-between widths are ``long`` (the second cell's found the bugs below).
@pytest.mark.parametrize("which,delta", [
    *[(1, d) for d in (0.05, 0.1, 0.2, 0.3, DEFAULT_MAX_DELTA)],
    *[(0, d) for d in (0.05, 0.2, DEFAULT_MAX_DELTA)],
    *[pytest.param(0, d, marks=pytest.mark.long) for d in (0.1, 0.3)],
])
def test_false_negative_pixels_on_lavaducts(which, delta):
    from tests.visibility.real_scenes import REAL, real_scene

    assert "lavaducts" in REAL, "the real scene lavaducts of ../shared/scenes is missing"
    e = _errors(real_scene("lavaducts"), which, delta, frames=24, seed=1)
    # The second cell's 325 pixels at Δ 0.1 m in benchmarks/results/trim_regions.md (24
    # frames, seed 1) were a wall 7 cm from an eye cut by the frames' near plane, not a miss
    # (quality.FRAME_NEAR, test_quality). Its 1,380 at Δ 0.3 m were eyes behind one wall of
    # a corner (its plane passes through the sphere: silhouettes.AMBIGUOUS) seeing past the
    # other wall's end a wall seen from behind, which closed the trimmed interval and was
    # dropped as the occluder's own back (test_resolve). At Δ 0.4 m (then past the default
    # max_delta) both cells were over it until an interval's front face took the trim of its
    # rim in front of it: a corner the ray passes (test_resolve).
    assert e["fn_pixel_rate_max"] <= BOUND, (delta, which, e["fn_pixels_max"], e["missed"][:20])


@pytest.mark.slow
@pytest.mark.xdist_group("kitchen")
def test_false_negative_pixels_in_the_kitchens_clutter():
    # The 1M kitchen's middle cell at Δ 0.2 m, as benchmarks/bench_trim_regions.py measures it
    # (24 frames, seed 1). At the defaults the method rasterizes the small triangles behind
    # trimmed occluders conservatively (every pixel they touch) and holds the bound; at pixel
    # centres (small="centres", the paper) 127 pixels in the worst frame (the bound is 19.7):
    # triangles behind trimmed occluders under no pixel centre, many of them slivers seen
    # edge-on from v*, held to that figure so that it can only fall. (It was 98 while the
    # gather's pixel-square test let slivers reach squares past their tips, hulls._touches,
    # which caught some of these by chance.) The sampling add-on (gather_eyes) only adds to
    # the answer (test_core), so it holds the bound wherever the method does.
    from tests.visibility.real_scenes import REAL, real_scene

    assert "kitchen" in REAL, "the real scene kitchen of ../shared/scenes is missing"
    scene = real_scene("kitchen")
    # Both answers judged by the same frames, cast once.
    cast = ray_frames(scene, _box(scene, 0, 0.2), 24, 256, 1, FRAME_NEAR)
    alone = _errors(scene, 0, 0.2, frames=24, seed=1, cast=cast)
    assert alone["fn_pixel_rate_max"] <= BOUND, (alone["fn_pixels_max"], alone["missed"][:20])
    centres = _errors(scene, 0, 0.2, frames=24, seed=1, cast=cast, small="centres")
    assert centres["fn_pixels_max"] <= 127, (centres["fn_pixels_max"], centres["missed"][:20])
    assert centres["pvs"] < alone["pvs"] < scene.n_triangles


#: A lavaducts wall (the plane x = -18.694 m, facing the room at larger x) and a point of the
#: void behind it, world metres.
WALL_X = -18.694
VOID = np.array([-18.9232, -2.0762, 42.1664])


@pytest.mark.slow
@pytest.mark.parametrize("into_room", [0.1, 0.2])
def test_a_cube_across_a_wall_with_its_centre_in_the_void(into_room):
    # The sphere's centre and v* stand behind the wall; the cube reaches into_room metres into
    # the room. From v* the rays start behind a sloped wall seen from its back, whose rim
    # (the edge it shares with the wall through the cube) lies in front of it: 642 and 2,292
    # pixels were missed in the worst of these frames until a back face took its rim's trims
    # in front of it (test_resolve).
    from tests.visibility.real_scenes import REAL, real_scene

    assert "lavaducts" in REAL, "the real scene lavaducts of ../shared/scenes is missing"
    scene = real_scene("lavaducts")
    h = 0.3 / np.sqrt(3.0)
    c = VOID.copy()
    c[0] = WALL_X + into_room - h
    box = np.stack([c - h, c + h])
    pvs = CORE.compute(scene, Viewcell(box), CORE.make_params(max_delta=0.3))
    e = frame_errors(scene, pvs.triangle_ids, box, n_points=12, resolution=256, seed=1)
    assert e["frames"] > 0
    assert e["fn_pixel_rate_max"] <= BOUND, (into_room, e["fn_pixels_max"], e["missed"][:20])


#: A lavaducts cube (Δ 0.3 m, centre in world metres) where the hidden-solid seal paired two
#: walls of the open level that follow one another on a ray as one solid (22 pixels over
#: 8 frames before resolve read the back one's trims up to the next surface).
WALLS_IN_A_ROW = np.array([-21.207609606581862, 6.415502107422084, 59.81013878215189])


@pytest.mark.slow
def test_random_cubes_of_lavaducts():
    # Cubes of Δ 0.3 m at random places of the grid's cells (seeded, as the benchmark's
    # random-cells table draws its 30), eyes in their open space: the level's walls run
    # through many of them; and the cube where two walls in a row were taken for one solid.
    from benchmarks.bench_trim_regions import random_open_cubes
    from tests.visibility.real_scenes import REAL, real_scene

    assert "lavaducts" in REAL, "the real scene lavaducts of ../shared/scenes is missing"
    scene = real_scene("lavaducts")
    h = 0.3 / np.sqrt(3.0)
    box = np.stack([WALLS_IN_A_ROW - h, WALLS_IN_A_ROW + h])
    cubes = [(box, ray_frames(scene, box, 8, 256, 1, FRAME_NEAR))]
    for box, cast in cubes + random_open_cubes(scene, 4, frames=8, delta=0.3):
        assert len(cast.eyes) > 0
        pvs = CORE.compute(scene, Viewcell(box), CORE.make_params(max_delta=0.3))
        e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
        assert e["fn_pixel_rate_max"] <= BOUND, (box, e["fn_pixels_max"], e["missed"][:20])


def _kitchen_cube_errors(centre: np.ndarray, delta: float) -> dict:
    """``frame_errors`` of the kitchen's cube of circumscribed radius ``delta`` around
    ``centre`` (world metres), one sphere, on 8 frames of seed 1 (bench_trim_delta's)."""
    from tests.visibility.real_scenes import REAL, real_scene

    assert "kitchen" in REAL, "the real scene kitchen of ../shared/scenes is missing"
    scene = real_scene("kitchen")
    h = delta / np.sqrt(3.0)
    box = np.stack([centre - h, centre + h])
    pvs = CORE.compute(scene, Viewcell(box), CORE.make_params(max_delta=delta))
    e = frame_errors(scene, pvs.triangle_ids, box, n_points=8, resolution=256, seed=1)
    assert e["frames"] > 0
    return e


#: A kitchen cube (Δ 0.3 m, centre in world metres; the benchmark's random cell 3) where
#: cabinet panels are crossed nearly edge-on and bevelled strips lie under larger pixels: 53
#: pixels over 8 frames until an interval took its far rim's trims behind its back face
#: and a hidden span needed its face across the pixel (test_resolve).
EDGE_ON_PANELS = np.array([0.8723, 1.8222, 0.9506])
#: The benchmark's random kitchen cube 6 at Δ 0.41 m (its centre, world metres): a post wound
#: inside out below the cell whose side face's plane passes through the sphere; faced out,
#: v*'s ray leaves the post by that face, which eyes beyond its plane see face on. 35 pixels
#: in the first of its 8 frames (the bound is 19.7) while that face was taken for the post's
#: own unseen back (test_resolve).
POST_SIDE = np.array([-0.4562004422691799, 1.7380998047558234, -0.722164645551425])


#: The kitchen's cubes below are ``long``: benchmarks/bench_trim_regions.py draws them (its
#: random kitchen cubes) and the causes they found have known-answer tests in test_resolve.
@pytest.mark.slow
@pytest.mark.long
@pytest.mark.xdist_group("kitchen")
@pytest.mark.parametrize("centre,delta", [
    pytest.param(EDGE_ON_PANELS, 0.3, id="among_cabinet_panels"),
    pytest.param(POST_SIDE, 0.41, id="above_a_post_whose_side_plane_cuts_the_sphere"),
])
def test_a_kitchen_cube(centre, delta):
    e = _kitchen_cube_errors(centre, delta)
    assert e["fn_pixel_rate_max"] <= BOUND, (e["fn_pixels_max"], e["missed"][:20])


@pytest.mark.slow
@pytest.mark.long
@pytest.mark.xdist_group("kitchen")
def test_a_kitchen_cube_beside_inside_out_boards():
    # The first of the random kitchen cubes bench_trim_delta draws at Δ 0.41 m (one sphere):
    # the kitchen's boards and posts are closed parts wound inside out, whose far sides the
    # k-buffer took for their front faces, sealing pixels behind their near sides' trims.
    # 21 pixels in the worst of its 8 frames (the bound is 19.7) until such parts face out
    # for a cell outside them (cache.faced_out_for).
    from benchmarks.bench_trim_regions import random_open_cubes
    from tests.visibility.real_scenes import REAL, real_scene

    assert "kitchen" in REAL, "the real scene kitchen of ../shared/scenes is missing"
    scene = real_scene("kitchen")
    (box, cast), = random_open_cubes(scene, 1, delta=0.41)
    pvs = CORE.compute(scene, Viewcell(box), CORE.make_params(max_delta=0.41))
    e = frame_errors(scene, pvs.triangle_ids, box, frames=cast)
    assert e["fn_pixel_rate_max"] <= BOUND, (e["fn_pixels_max"], e["missed"][:20])


@pytest.mark.slow
def test_the_servers_1_m_cell_at_the_defaults():
    # The server's 1 m cell (1 m across the ground, the grid's eye range high) of lavaducts,
    # as the benchmark's box-cell table takes it: the defaults cover it with 2 x 2 spheres of
    # about max_delta, and eyes anywhere in the box (beyond each sphere's own sub-box) must
    # keep within the bound too.
    from tests.visibility.real_scenes import REAL, real_scene

    assert "lavaducts" in REAL, "the real scene lavaducts of ../shared/scenes is missing"
    scene = real_scene("lavaducts")
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(first_open_cell(scene, grid, len(grid) // 2))
    half = 0.5 * np.array([1.0, cell.box[1][1] - cell.box[0][1], 1.0])
    box = np.stack([cell.center - half, cell.center + half])
    pvs = CORE.compute(scene, Viewcell(box), CORE.make_params())
    assert pvs.stats["spheres"] == 4, pvs.stats["spheres"]
    e = frame_errors(scene, pvs.triangle_ids, box, n_points=12, resolution=256, seed=1)
    assert e["frames"] > 0
    assert e["fn_pixel_rate_max"] <= BOUND, (e["fn_pixels_max"], e["missed"][:20])
