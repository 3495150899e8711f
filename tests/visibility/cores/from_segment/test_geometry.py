"""The scene's clusters (``from_segment.geometry``) as a per-scene build: built once, whether
by a server's load or by the first cell."""

from __future__ import annotations

from visibility.cores.base import get_core
from visibility.cores.from_segment.geometry import GEOMETRY_BUILD, scene_geometries
from visibility.generators import make_scene
from visibility.scene_cache import per_scene


def test_the_build_makes_the_clusters_the_cells_then_use():
    scene = make_scene("village", triangles=3_000, seed=4)
    assert get_core("from_segment").scene_builds(scene) == [GEOMETRY_BUILD]
    built, _ = per_scene(scene, GEOMETRY_BUILD.kind, GEOMETRY_BUILD.build, GEOMETRY_BUILD.persist)
    assert scene_geometries(scene) is built
    assert sum(len(g.cl_start) - 1 for g in built) > 0
