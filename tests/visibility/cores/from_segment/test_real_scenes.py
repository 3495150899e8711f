"""from_segment's promise on the real scenes: exact at its jittered pixel samples along a segment.

lavaducts (a Quake level), Den Haag and Lyon (georeferenced city tiles) from
``../shared/scenes``: the longest segment the core walks by default (the open floor's outline,
``view_segments``) in the cell a seeded walk stands in, under the core's first (oblique) cube
and a randomly turned one: every triangle that Embree rays through the same jittered samples
hit first, at 48 points of the segment, is in the segment's set (a hit the set lacks is
re-cast in float64 before it counts, since Embree works in float32), and every triangle in the
set is the nearest surface at its witness (time, pixel sample), by a float64 brute-force ray
cast. Not the kitchen: the brute-force casts over its 1M triangles would take minutes.
"""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.bench_matrix import SHARED_SCENES
from benchmarks.bench_real_cells import walk_cells
from tests.grouping import on_one_worker
from tests.visibility.segment_reference import nearest_at_pixel, prepare, unwitnessed
from visibility.cores.from_segment.core import SUBPIXEL_CANDIDATES, oblique_rotation, view_segments
from visibility.cores.from_segment.geometry import scene_geometries
from visibility.cores.from_segment.raster import sample_offset
from visibility.cores.from_segment.segment import segment_visible
from visibility.loaders import load_scene
from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations, random_rotation
from visibility.viewcells import ViewcellGrid

#: Real scenes: out of the fast lane (``-m "not slow"``), always in CI.
pytestmark = pytest.mark.slow

RES, JITTER, SEED, POINTS = 32, 0.5, 7, 48


#: Each scene's tests on one worker (``bash scripts/test.sh`` distributes by ``xdist_group``),
#: so the scene is loaded and its segment found once.
@pytest.fixture(scope="module", params=[
    on_one_worker(f"from_segment_{n}", n)
    for n in ("lavaducts", "denhaag", "lyon_vilo3d")])
def walked(request):
    """A real scene and the longest default segment of the cell a seeded walk stands in."""
    path = SHARED_SCENES / f"{request.param}.glb"
    assert path.exists(), f"{path} is missing: the real scenes are part of the set-up"
    scene = load_scene(path)
    grid = ViewcellGrid.for_scene(scene)
    cell = grid.cell(walk_cells(scene, seed=1, k=1)[0])
    segs, how = view_segments(scene, cell.box, eye_levels=1)
    assert how == "open"
    a, b = max(segs, key=lambda s: float(np.linalg.norm(s[1] - s[0])))
    return scene, cell, a, b


def _sample_dirs(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(6 R^2, 3) world directions (depth 1 per unit) of every jittered sample, and (6 R^2, 3)
    their (face, row, col)."""
    rows, cols = np.divmod(np.arange(RES * RES), RES)
    dirs, where = [], []
    for f, r in enumerate(cube_face_rotations(rot)):
        off = np.array([sample_offset(f, int(i), int(j), RES, JITTER, SEED)
                        for i, j in zip(rows, cols, strict=True)])
        x = (cols + 0.5 + off[:, 0]) * (2.0 / RES) - 1.0
        y = 1.0 - (rows + 0.5 - off[:, 1]) * (2.0 / RES)
        dirs.append(np.stack([x, y, -np.ones_like(x)], axis=1) @ r)
        where.append(np.stack([np.full_like(rows, f), rows, cols], axis=1))
    return np.concatenate(dirs), np.concatenate(where)


@pytest.mark.parametrize("turn", ["oblique", "random"])
def test_exact_at_its_jittered_samples_on_real_scenes(walked, turn):
    from trimesh import Trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    scene, cell, a, b = walked
    rot = oblique_rotation() if turn == "oblique" else random_rotation(np.random.default_rng(3))
    geom = scene_geometries(scene)[0]
    wit = np.zeros((geom.n_ids, 5))
    vis = segment_visible(geom, a, b, rot, resolution=RES, witness=wit, jitter=JITTER,
                          seed=SEED)
    assert vis.sum() > 100

    valid = np.flatnonzero(scene.valid_faces)
    centre = np.asarray(cell.box).mean(axis=0)  # Embree is float32: work near the cell
    mesh = Trimesh(scene.vertices - centre, scene.faces[valid], process=False, validate=False)
    caster = RayMeshIntersector(mesh)
    dirs, where = _sample_dirs(rot)
    rots = cube_face_rotations(rot)
    # The float64 references see the scene the core sees: faces the loader kept out of
    # computation (807 zero-area ones in lavaducts, which float rounding would still let rays
    # hit) collapse to a point.
    faces = scene.faces.copy()
    faces[~scene.valid_faces] = 0
    prepared = prepare(scene.vertices, faces)
    seen = 0
    for t in np.linspace(0.0, 1.0, POINTS):
        eye = a + t * (b - a)
        # Start each ray at the near plane, as the kernels clip.
        hit = caster.intersects_first(eye - centre + DEFAULT_NEAR * dirs, dirs)
        ok = hit >= 0
        ids = valid[hit[ok]]
        seen += len(np.unique(ids))
        for k in np.flatnonzero(ok)[~vis[ids]]:
            f, row, col = where[k]
            off = sample_offset(int(f), int(row), int(col), RES, JITTER, SEED)
            got, _ = nearest_at_pixel(scene.vertices, faces, eye, rots[f], RES, int(row),
                                      int(col), offset=off, prepared=prepared)
            assert got < 0 or vis[got], (t, f, row, col, got)
    assert seen > 0
    v = scene.vertices
    assert unwitnessed(wit, vis, v, v, faces, a, b, RES, rot, jitter=JITTER, seed=SEED) == []


@pytest.mark.parametrize("corners", [False, True], ids=["footprint", "corners"])
def test_footprint_adds_only_what_eyes_on_the_segment_see(walked, corners):
    """The footprint rule (``footprint=True``, the core's ``small="footprint"``; with
    ``corners``, ``small="corners"``) adds to the samples' set only triangles that
    float64-confirmed Embree rays from eyes on the segment itself, aimed at random points of
    each, see (``ray_aimed``): each was found by a sample placed on it, so none is a
    guess."""
    from visibility.ray_aimed import aimed_seen

    scene, cell, a, b = walked
    geom = scene_geometries(scene)[0]
    kw = dict(resolution=RES, jitter=JITTER, seed=SEED)
    base = segment_visible(geom, a, b, oblique_rotation(), **kw)
    stats: dict = {}
    more = segment_visible(geom, a, b, oblique_rotation(), stats=stats, footprint=True,
                           corners=corners, **kw)
    assert np.all(more[base])  # it only adds
    added = np.flatnonzero(more & ~base)
    assert stats["footprint_candidates"] > 0 and stats.get("footprint_seen", 0) >= len(added)
    if "lyon" in scene.name:  # far sub-pixel roofs: there it finds some (lavaducts: none)
        assert len(added) > 0

    def on_segment(n: int, rng: np.random.Generator) -> np.ndarray:
        return a + rng.random(n)[:, None] * (b - a)

    got = aimed_seen(scene, np.asarray(cell.box), added, rays=64, most=4096, seed=1,
                     eyes=on_segment)
    assert np.setdiff1d(added, got.ids).tolist() == []


def test_subpixel_runs_only_on_the_sub_pixel_city(walked):
    """At the defaults the walked cell takes the extra turned cube on the Lyon tile, whose
    answer is mostly far facade detail under a pixel (its footprint rule tests many
    triangles per triangle found), and not on lavaducts or Den Haag."""
    from visibility.cores.base import get_core

    scene, cell, _, _ = walked
    core = get_core("from_segment")
    pvs = core.compute(scene, cell, core.make_params())
    lyon = "lyon" in scene.name
    assert (pvs.stats["subpixel_ratio"] > SUBPIXEL_CANDIDATES) == lyon
    assert pvs.stats["runs"] == (2 if lyon else 1)
