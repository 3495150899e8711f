"""2.5D detection from the geometry (visibility.scene_analysis): generated and real scenes, small
hand-built cases for each rule, the meta override and the per-scene cache."""

from __future__ import annotations

import gc
import weakref
from functools import cache

import numpy as np
import pytest

from tests.conftest import _box
from tests.visibility.real_scenes import REAL, real_scene
from visibility import scene_analysis as sa
from visibility.generators import make_scene
from visibility.scene import Scene

#: What each real scene is (looked at by hand): Den Haag and Lyon are LoD2 city tiles (extruded
#: buildings with roofs, Den Haag on a TIN terrain), the kitchen is a furnished room (table tops
#: over the floor, a ceiling over all), Lavaducts a Quake level (rooms stacked over rooms, seen
#: from inside). A scene dropped into ../shared/scenes later gets the generic checks only.
REAL_EXPECTED = {"denhaag": True, "lyon_vilo3d": True, "kitchen": False, "lavaducts": False}


@cache
def generated(name: str) -> Scene:
    return make_scene(name, triangles=20_000, seed=0)


def scene_of(parts: list[tuple[np.ndarray, np.ndarray]], **meta) -> Scene:
    verts, faces, n = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.append(f + n)
        n += len(v)
    f = np.concatenate(faces)
    return Scene(vertices=np.concatenate(verts), faces=f, object_ids=np.zeros(len(f), np.int32),
                 colors=np.full((len(f), 3), 128, np.uint8), name="hand", meta=dict(meta))


def ground(size: float = 20.0, y: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """An up-facing square on y, centred on the origin."""
    h = size / 2
    v = np.array([[-h, y, -h], [h, y, -h], [h, y, h], [-h, y, h]], dtype=np.float64)
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def flipped(part: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    return part[0], part[1][:, ::-1].copy()


# --------------------------------------------------------------------------- generated scenes
@pytest.mark.parametrize(("name", "expected"), [("city", True), ("village", False),
                                                ("rooms", False)])
def test_generated_scenes_are_judged_from_their_geometry(name, expected):
    """The geometry alone (meta ignored) agrees with what each generator states: the city's
    extruded towers are a height field; the village's arches, overhangs and trees and the
    multi-floor rooms put open space under surfaces."""
    scene = generated(name)
    r = sa.analyse_2_5d(scene)
    assert r.is_2_5d is expected, r.reason
    assert r.is_2_5d is scene.meta["is_2_5d"]
    assert r.source == "geometry" and r.reason and r.samples > 0
    if expected:
        assert r.violating_share <= sa.MAX_VIOLATING_SHARE and "height field" in r.reason
    else:
        assert r.violating_share > sa.MAX_VIOLATING_SHARE and "overhang" in r.reason


# --------------------------------------------------------------------------- real scenes
@pytest.mark.parametrize("name", REAL)
def test_real_scenes_are_judged_from_their_geometry(name):
    """No sidecar states ``is_2_5d``: the geometry decides, and says why."""
    scene = real_scene(name)
    flat, how = sa.is_2_5d(scene)
    assert how["source"] == "geometry" and how["reason"], how
    assert how["occupied_cells"] > 0 and 0.0 <= how["violating_share"] <= 1.0
    if name in REAL_EXPECTED:
        assert flat is REAL_EXPECTED[name], how["reason"]
    if name == "lavaducts":
        # Seen from inside: the top surfaces are ceilings facing down.
        assert "face down" in how["reason"]


# --------------------------------------------------------------------------- rules, by hand
def test_a_box_on_the_ground_is_2_5d():
    r = sa.analyse_2_5d(scene_of([ground(), _box((-2, 0, -2), (2, 5, 2))]))
    assert r.is_2_5d, r.reason
    # The box's bottom face lies on the ground (no clearance): no open space, no violation.
    assert r.violating_cells == 0


def test_a_table_over_the_ground_is_not():
    """A slab 1 m above the ground, as wide as most of it: open space under a surface."""
    r = sa.analyse_2_5d(scene_of([ground(), _box((-8, 1.0, -8), (8, 1.2, 8))]))
    assert not r.is_2_5d and "overhang" in r.reason
    assert r.violating_share > 0.5


def test_a_slab_thinner_than_the_clearance_is_not_an_overhang():
    r = sa.analyse_2_5d(scene_of([ground(), _box((-8, 0.2, -8), (8, 1.2, 8))]))
    assert r.is_2_5d, r.reason


def test_a_small_overhang_stays_under_the_share_limit():
    """A 1 m^2 canopy over a 400 m^2 ground: 0.25% of the footprint, below the 2% limit."""
    r = sa.analyse_2_5d(scene_of([ground(), _box((0, 3, 0), (1, 3.2, 1))]))
    assert r.is_2_5d and 0 < r.violating_share < sa.MAX_VIOLATING_SHARE, r.reason


def test_a_room_seen_from_inside_is_not():
    """Inward-facing box (a room): its ceiling is the top surface and faces down."""
    r = sa.analyse_2_5d(scene_of([flipped(_box((-5, 0, -5), (5, 3, 5)))]))
    assert not r.is_2_5d and "face down" in r.reason
    assert r.top_up_share < 0.5


def test_clockwise_winding_in_the_meta_flips_the_facing():
    inward = scene_of([flipped(_box((-5, 0, -5), (5, 3, 5)))], winding="cw")
    assert sa.analyse_2_5d(inward).is_2_5d


def test_only_walls_is_a_height_field():
    v = np.array([[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]], dtype=np.float64)
    r = sa.analyse_2_5d(scene_of([(v, np.array([[0, 1, 2], [0, 2, 3]]))]))
    assert r.is_2_5d and r.wall_area_share == pytest.approx(1.0)


def test_far_from_the_origin_is_judged_the_same():
    near = scene_of([ground(), _box((-8, 1.0, -8), (8, 1.2, 8))])
    far = scene_of([(v + [1e5, 0, 1e5], f) for v, f in (ground(), _box((-8, 1, -8), (8, 1.2, 8)))])
    a, b = sa.analyse_2_5d(near), sa.analyse_2_5d(far)
    assert a.is_2_5d == b.is_2_5d is False
    assert b.violating_share == pytest.approx(a.violating_share, abs=0.02)


def test_no_valid_triangles_is_not_2_5d():
    v = np.zeros((3, 3))
    r = sa.analyse_2_5d(scene_of([(v, np.array([[0, 1, 2]]))]))
    assert not r.is_2_5d and "no valid" in r.reason


# --------------------------------------------------------------------------- meta and cache
def test_the_meta_overrides_the_geometry():
    scene = scene_of([ground(), _box((-8, 1.0, -8), (8, 1.2, 8))], is_2_5d=True)
    flat, how = sa.is_2_5d(scene)
    assert flat and how["source"] == "meta" and "sidecar" in how["reason"]
    scene.meta["is_2_5d"] = None  # a sidecar's null states nothing
    assert sa.is_2_5d(scene)[0] is False


def test_scene_is_2_5d_analyses_once_and_reads_the_meta_every_time():
    scene = scene_of([ground(), _box((-2, 0, -2), (2, 5, 2))])
    flat, first = sa.scene_is_2_5d(scene)
    assert flat and first["source"] == "geometry"
    again = sa.scene_is_2_5d(scene)[1]
    assert again == first  # the same measurement (its timing included): not analysed twice
    scene.meta["is_2_5d"] = False
    assert sa.scene_is_2_5d(scene) == (False, sa.stated_2_5d(scene).as_dict())
    del scene.meta["is_2_5d"]
    assert sa.scene_is_2_5d(scene)[1] == first


def test_the_cache_lets_unloaded_scenes_go():
    kept, dropped = scene_of([ground()]), scene_of([ground()])
    sa.scene_is_2_5d(kept)
    sa.scene_is_2_5d(dropped)
    assert kept in sa._CACHE and dropped in sa._CACHE
    gone = weakref.ref(dropped)
    del dropped
    gc.collect()
    # Other tests' scenes may be collected here too, so count only these two.
    assert gone() is None
    assert kept in sa._CACHE
    assert all(k is not None for k in sa._CACHE.keys())
