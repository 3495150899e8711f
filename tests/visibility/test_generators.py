"""Tests of the deterministic scene generators (visibility/generators)."""

from __future__ import annotations

import json
import time
from functools import cache

import numpy as np
import pytest

from visibility.generators import (
    DEFAULT_TRIANGLES,
    GENERATORS,
    available_generators,
    make_scene,
)
from visibility.generators import _mesh as gm
from visibility.generators import stress as stress_mod
from visibility.scene import Scene, WalkArea
from visibility.viewcells import ViewcellGrid

#: Every registered generator: each is held to the same properties.
MINE = sorted(GENERATORS)


def size(s: Scene) -> int:
    """What a generator's size counts: spheres for sphere scenes (their ``triangles`` argument
    is the sphere count), triangles otherwise."""
    return s.n_spheres if "spheres" in s.meta else s.n_triangles


def requested(s: Scene) -> int:
    return int(s.meta["spheres"] if "spheres" in s.meta else s.meta["requested_triangles"])


@cache
def scene(name: str, triangles: int, seed: int = 0, floors: int | None = None) -> Scene:
    kw = {} if floors is None else {"floors": floors}
    return make_scene(name, triangles=triangles, seed=seed, **kw)


# ----------------------------------------------------------------------------- helpers
def first_hits(tris: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, ...]:
    """(triangle index or -1, distance) of the nearest hit of each ray (Moller-Trumbore)."""
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    hit = np.full(len(origins), -1)
    dist = np.full(len(origins), np.inf)
    for r, (o, d) in enumerate(zip(origins, dirs, strict=True)):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-14
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        good = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        if good.any():
            k = np.flatnonzero(good)[np.argmin(t[good])]
            hit[r], dist[r] = k, t[k]
    return hit, dist


def segment_blocked(tris: np.ndarray, a: np.ndarray, b: np.ndarray, eps: float = 1e-6) -> bool:
    """Whether the open segment a-b crosses any of the triangles."""
    d = b - a
    length = np.linalg.norm(d)
    hit, dist = first_hits(tris, a[None], (d / length)[None])
    return bool(hit[0] >= 0 and dist[0] < length - eps)


def walk_samples(s: Scene, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) random eye points in the walk rects at eye height (floor + 1.7)."""
    r = s.walk.rects[rng.integers(0, len(s.walk.rects), n)]
    x = r[:, 0] + rng.random(n) * (r[:, 2] - r[:, 0])
    z = r[:, 1] + rng.random(n) * (r[:, 3] - r[:, 1])
    return np.stack([x, r[:, 4] + 1.7, z], 1)


# ----------------------------------------------------------------------------- registry
def test_registry_lists_every_generator_and_default():
    assert set(MINE) <= set(available_generators())
    assert set(DEFAULT_TRIANGLES) == set(GENERATORS)
    for name in ("grass", "swaying_grass", "spheres"):
        assert name in GENERATORS
    assert available_generators() == sorted(available_generators())


def test_unknown_and_missing_generators_raise_keyerror(monkeypatch):
    with pytest.raises(KeyError, match="unknown generator"):
        make_scene("no_such_scene")
    monkeypatch.setitem(GENERATORS, "ghost", "visibility.generators.ghost_module:generate")
    assert "ghost" not in available_generators()
    with pytest.raises(KeyError, match="unavailable"):
        make_scene("ghost")


def test_default_size_is_used_when_triangles_is_none():
    s = make_scene("stress")
    assert s.n_triangles == DEFAULT_TRIANGLES["stress"]


@pytest.mark.parametrize("name", MINE)
def test_bad_arguments_raise_valueerror(name):
    # Ten triangles build no street, room or meadow; ten spheres are a fine sphere scene.
    too_few = () if "spheres" in scene(name, 10_000).meta else (10,)
    for bad in (*too_few, 0, -5, 2.5, True, 10**9):
        with pytest.raises(ValueError):
            make_scene(name, triangles=bad)
    with pytest.raises(ValueError):
        make_scene(name, triangles=10_000, seed=-1)


def test_generator_specific_arguments():
    with pytest.raises(ValueError, match="floors"):
        make_scene("rooms", triangles=10_000, floors=3)
    with pytest.raises(ValueError, match="offset"):
        make_scene("stress", triangles=2_000, offset=float("nan"))
    with pytest.raises(TypeError):
        make_scene("city", triangles=10_000, no_such_option=1)


# ----------------------------------------------------------------------------- all scenes
@pytest.mark.parametrize("name", MINE)
def test_deterministic_for_a_seed(name):
    a = make_scene(name, triangles=10_000, seed=3)
    b = make_scene(name, triangles=10_000, seed=3)
    c = make_scene(name, triangles=10_000, seed=4)
    assert a.vertices.tobytes() == b.vertices.tobytes()  # bit-identical, NaNs included
    assert np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.object_ids, b.object_ids)
    assert np.array_equal(a.colors, b.colors)
    assert np.array_equal(a.walk.rects, b.walk.rects)
    if a.n_spheres:  # the spheres are what the seed places
        assert np.array_equal(a.sphere_centers, b.sphere_centers)
        assert not np.array_equal(a.sphere_centers, c.sphere_centers)
    else:
        assert a.vertices.shape != c.vertices.shape or not np.array_equal(
            a.vertices, c.vertices, equal_nan=True)


@pytest.mark.parametrize("triangles", [10_000, 100_000])
@pytest.mark.parametrize("name", MINE)
def test_triangle_count_within_tolerance(name, triangles):
    s = scene(name, triangles)
    assert abs(size(s) / triangles - 1) <= 0.2, size(s)
    assert requested(s) == triangles


@pytest.mark.parametrize("name", MINE)
def test_arrays_ids_colours_and_meta(name):
    s = scene(name, 10_000)
    m = s.n_triangles
    assert s.vertices.dtype == np.float64 and s.vertices.shape[1] == 3
    assert s.faces.dtype == np.int32 and s.faces.shape == (m, 3)
    assert s.faces.min() >= 0 and s.faces.max() < s.n_vertices
    assert s.object_ids.dtype == np.int32 and s.object_ids.shape == (m,)
    assert s.colors.dtype == np.uint8 and s.colors.shape == (m, 3)
    assert s.object_ids.min() == 0
    # Object ids are dense-ish and colours vary per object and face orientation (sphere scenes:
    # the spheres are the objects, on one ground).
    assert len(np.unique(s.object_ids)) >= 10 or s.n_spheres >= 10
    assert len(np.unique(s.colors, axis=0)) >= (20 if not s.n_spheres else 2)
    assert s.name == name and s.meta["generator"] == name
    assert isinstance(s.meta["is_2_5d"], bool)
    assert s.walk is not None and s.walk.eye_height == 1.7 and s.walk.eye_range == (1.5, 1.9)
    assert np.all(s.walk.rects[:, 2] > s.walk.rects[:, 0])
    assert np.all(s.walk.rects[:, 3] > s.walk.rects[:, 1])
    valid = s.valid_faces
    assert np.all(np.isfinite(s.vertices[s.faces[valid]]))


@pytest.mark.parametrize("triangles", [10_000, 100_000])
@pytest.mark.parametrize("name", MINE)
def test_walk_rects_are_open_space(name, triangles):
    s = scene(name, triangles)
    # Meadows declare the triangles the walker wades through (``walk_through_from``).
    wade_from = s.meta.get("walk_through_from", s.n_triangles)
    assert np.all(gm.walk_violations(s) >= wade_from)


@pytest.mark.parametrize("name", MINE)
def test_walk_rects_sampled_vertical_segments_hit_nothing(name):
    """Independent of the box test: vertical rays from floor + 0.1 up to floor + 2.0."""
    s = scene(name, 10_000)
    rng = np.random.default_rng(0)
    pts = walk_samples(s, 300, rng)
    pts[:, 1] -= 1.6  # floor + 0.1
    ids = np.flatnonzero(s.valid_faces)
    tris = s.triangles(ids[ids < s.meta.get("walk_through_from", s.n_triangles)])
    # Only triangles whose XZ box holds a sample can be hit.
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    near = np.zeros(len(tris), bool)
    for p in pts:
        near |= (lo[:, 0] <= p[0]) & (hi[:, 0] >= p[0]) & (lo[:, 2] <= p[2]) & (hi[:, 2] >= p[2])
    cand = tris[near]
    up = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    hit, dist = first_hits(cand, pts, up)
    assert not np.any((hit >= 0) & (dist < 1.9)), pts[(hit >= 0) & (dist < 1.9)][:5]


@pytest.mark.parametrize("name", ["city", "village", "rooms"])
def test_surfaces_face_the_walker(name):
    """From eye points in the walk area, every first hit is a front face: solids wind outward,
    floors face up and ceilings down."""
    s = scene(name, 10_000)
    rng = np.random.default_rng(1)
    eyes = walk_samples(s, 200, rng)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ids = np.flatnonzero(s.valid_faces)
    tris = s.triangles(ids)
    hit, _ = first_hits(tris, eyes, d)
    n = gm.face_normals(s.vertices, s.faces[ids[hit[hit >= 0]]])
    assert (hit >= 0).sum() >= 50
    assert np.all(np.einsum("ij,ij->i", n, d[hit >= 0]) < 0)


@pytest.mark.parametrize("name", MINE)
def test_viewcell_grid_covers_the_walk_area(name):
    s = scene(name, 10_000)
    grid = ViewcellGrid.for_scene(s)
    assert len(grid) > 0
    # Every cell has a walkable point (its centre, or, over a corridor narrower than a cell,
    # the nearest point of the corridor), and it lies in the cell.
    centre = np.array([grid.walk_point(c) for c in range(len(grid))])
    assert np.all((centre >= grid.boxes[:, 0] - 1e-9) & (centre <= grid.boxes[:, 1] + 1e-9))
    r = s.walk.rects
    inside = ((centre[:, None, 0] >= r[None, :, 0]) & (centre[:, None, 0] <= r[None, :, 2])
              & (centre[:, None, 2] >= r[None, :, 1]) & (centre[:, None, 2] <= r[None, :, 3]))
    assert inside.any(axis=1).all()


@pytest.mark.parametrize("name", MINE)
def test_meta_is_json_friendly(name):
    s = scene(name, 10_000)
    assert json.loads(json.dumps(s.meta))["generator"] == name


# ----------------------------------------------------------------------------- per scene
def test_city_viewcells_are_free_of_geometry():
    """Sidewalks are wider than half a cell, so 4 m cells centred on a street stay clear."""
    s = scene("city", 10_000)
    boxes = ViewcellGrid.for_scene(s).boxes.copy()
    boxes[:, 0] += 1e-3
    boxes[:, 1] -= 1e-3
    boxes[:, 0, 1] -= 1.4  # from floor + 0.1 up to the top of the cell
    assert len(boxes) > 50
    assert len(gm.triangles_in_boxes(s, boxes)) == 0
    # The check itself sees buildings: boxes 20 m up the street sides hit walls.
    high = boxes[::10].copy()
    high[:, :, 1] += 20.0
    high[:, 0, [0, 2]] -= 4.0
    high[:, 1, [0, 2]] += 4.0
    assert len(gm.triangles_in_boxes(s, high)) > 0


def test_city_is_2_5d_and_streets_are_long():
    s = scene("city", 10_000)
    assert s.meta["is_2_5d"] is True
    n = gm.face_normals(s.vertices, s.faces)
    # Every face is a vertical wall or an upward roof/ground: a height field.
    assert np.all((np.abs(n[:, 1]) < 1e-9) | (n[:, 1] > 1 - 1e-9))
    r = s.walk.rects
    width = np.minimum(r[:, 2] - r[:, 0], r[:, 3] - r[:, 1])
    assert np.all((width >= 10.0) & (width <= 16.0))
    assert s.meta["buildings"] >= 20


def test_city_grows_and_details_with_the_budget():
    small, large = scene("city", 10_000), scene("city", 100_000)
    area = [np.prod(np.ptp(x.walk.rects[:, [0, 1]], axis=0)) for x in (small, large)]
    assert area[1] > area[0]
    assert large.meta["detail"] > small.meta["detail"]
    assert large.meta["buildings"] > small.meta["buildings"]


@pytest.mark.slow
def test_city_one_million_triangles():
    t0 = time.perf_counter()
    s = make_scene("city", triangles=1_000_000, seed=0)
    seconds = time.perf_counter() - t0
    assert abs(s.n_triangles / 1e6 - 1) <= 0.2
    assert s.meta["is_2_5d"] is True
    assert len(gm.walk_violations(s)) == 0
    # Generous bound (shared 2-core CI); measured ~2 s on a quiet machine.
    assert seconds < 30, seconds


def test_village_has_overhangs_and_arches_over_streets():
    s = scene("village", 100_000)
    assert s.meta["is_2_5d"] is False
    assert s.meta["arches"] > 0 and s.meta["trees"] > 0 and s.meta["houses"] > 50
    c = s.triangles().mean(axis=1)
    r = s.walk.rects
    over = np.zeros(len(c), bool)
    for x0, z0, x1, z1 in r[:, :4]:
        over |= (c[:, 0] > x0) & (c[:, 0] < x1) & (c[:, 2] > z0) & (c[:, 2] < z1)
    above = over & (c[:, 1] > 2.0) & (c[:, 1] < 10.0)
    # Walkable under: geometry above the streets, none below head height (other test).
    assert above.sum() > 100
    n = gm.face_normals(s.vertices, s.faces[above])
    assert np.any(n[:, 1] < -0.99)  # soffits and arch intrados face down onto the street


def test_village_streets_are_narrow_and_jog():
    s = scene("village", 10_000)
    r = s.walk.rects
    width = np.minimum(r[:, 2] - r[:, 0], r[:, 3] - r[:, 1])
    assert np.median(width) < 7.0
    # Segments of one street line are offset from each other (jogs at the crossings).
    assert len(np.unique(np.round(r[:, 1], 3))) > len(r) // 3


@pytest.mark.parametrize("floors", [1, 2])
def test_rooms_levels_ceilings_and_doors(floors):
    s = scene("rooms", 10_000, floors=floors)
    assert s.meta["floors"] == floors
    r = s.walk.rects
    levels = np.unique(r[:, 4])
    assert np.allclose(levels, [0.0, 3.5][:floors])
    # Room rects have the 3 m ceiling, door passages the 2.1 m lintel.
    gap = np.unique(np.round(r[:, 5] - r[:, 4], 6))
    assert set(gap.tolist()) == {2.1, 3.0}
    grid = ViewcellGrid.for_scene(s)
    assert len(np.unique(grid.floor)) == floors
    assert np.all(grid.boxes[:, 1, 1] <= grid.floor + 1.9 + 1e-9)
    assert len(gm.walk_violations(s)) == 0
    # Straight down from the walk area: a floor facing up; straight up: a face looking down.
    rng = np.random.default_rng(3)
    eyes = walk_samples(s, 60, rng)
    ids = np.flatnonzero(s.valid_faces)
    tris = s.triangles(ids)
    for d, want_y, want_n in (((0, -1, 0), 0.0, 1.0), ((0, 1, 0), 3.0, -1.0)):
        dirs = np.tile(np.array(d, float), (len(eyes), 1))
        hit, dist = first_hits(tris, eyes, dirs)
        assert np.all(hit >= 0)
        n = gm.face_normals(s.vertices, s.faces[ids[hit]])
        assert np.allclose(n[:, 1], want_n)
        y = eyes[:, 1] + dirs[:, 1] * dist
        floor = eyes[:, 1] - 1.7
        # Going up: the ceiling, a lamp under it, or a door lintel over a passage.
        up = (y > floor + 2.8) | np.isclose(y, floor + 2.1)
        ok = np.isclose(y, floor + want_y) | ((want_y > 0) & up)
        assert ok.all()


def test_rooms_doors_connect_every_room():
    """Room rects joined by door passages form one connected set per level."""
    s = scene("rooms", 100_000)
    r = s.walk.rects
    rooms = r[np.isclose(r[:, 5] - r[:, 4], 3.0)]
    doors = r[np.isclose(r[:, 5] - r[:, 4], 2.1)]
    parent = list(range(len(rooms)))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for d in doors:
        touch = np.flatnonzero((rooms[:, 0] <= d[2] + 1e-9) & (rooms[:, 2] >= d[0] - 1e-9)
                               & (rooms[:, 1] <= d[3] + 1e-9) & (rooms[:, 3] >= d[1] - 1e-9))
        assert len(touch) == 2
        parent[find(touch[0])] = find(touch[1])
    assert len({find(i) for i in range(len(rooms))}) == 1


# ----------------------------------------------------------------------------- stress
CASES = ["ground", "wall", "hidden", "visible", "slivers", "zero_area", "repeated_index",
         "non_finite", "edge_on", "eye_plane", "coplanar", "intersecting", "huge"]


def test_stress_cases_present_with_objects_and_purpose():
    s = scene("stress", 10_000)
    cases = s.meta["cases"]
    assert list(cases) == CASES
    assert set(s.meta["case_purpose"]) == set(CASES)
    for name, ids in cases.items():
        assert isinstance(ids, list) and len(ids) > 0
        assert np.all(s.object_ids[ids] == s.meta["case_objects"][name])
    start, stop = s.meta["clutter_range"]
    assert stop == s.n_triangles == 10_000
    assert start == sum(len(v) for v in cases.values())


def test_stress_degenerate_report_counts_the_cases():
    s = scene("stress", 10_000)
    cases = s.meta["cases"]
    rep = s.degenerate_report
    assert rep.zero_area == len(cases["zero_area"]) == 4
    assert rep.repeated_index == len(cases["repeated_index"]) == 4
    assert rep.non_finite == len(cases["non_finite"]) == 4
    bad = np.flatnonzero(~s.valid_faces)
    expected = cases["zero_area"] + cases["repeated_index"] + cases["non_finite"]
    assert sorted(bad.tolist()) == sorted(expected)


def test_stress_offset_applies_to_everything():
    s = scene("stress", 2_000)
    o = make_scene("stress", triangles=2_000, offset=0.0)
    assert s.meta["offset"] == [1e5, 0.0, 1e5]
    assert np.allclose(s.walk.rects[0, :5], [1e5, 1e5, 1e5 + 8, 1e5 + 4, 0.0])
    assert np.allclose(o.walk.rects[0, :5], [0, 0, 8, 4, 0])
    fin = np.isfinite(o.vertices).all(axis=1)
    assert np.allclose(s.vertices[fin] - [1e5, 0, 1e5], o.vertices[fin], atol=1e-9)
    c = make_scene("stress", triangles=2_000, offset=(1.0, 2.0, 3.0))
    assert np.allclose(c.walk.rects[0, :5], [1, 3, 9, 7, 2])
    grid = ViewcellGrid.for_scene(s)
    assert len(grid) == 2
    assert np.allclose(grid.boxes, np.array(s.meta["cells"]))


def test_stress_slivers_huge_and_planes():
    s = scene("stress", 10_000)
    cases = s.meta["cases"]
    t = s.triangles(cases["slivers"]) - s.meta["offset"]
    e = np.linalg.norm(t[:, [1, 2, 0]] - t, axis=2)
    area = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1) / 2
    aspect = e.max(axis=1) ** 2 / (2 * area)  # longest edge over its altitude
    assert np.all((aspect > 5e5) & (aspect < 2e6)) and np.all(area > 1e-9)
    assert np.all(s.valid_faces[cases["slivers"]])
    huge = s.triangles(cases["huge"])[0]
    assert np.ptp(huge[:, 0]) > 10_000 and np.ptp(huge[:, 2]) > 10_000
    eye = s.triangles(cases["eye_plane"])[:, :, 1]
    assert np.allclose(np.sort(eye[:, 0]), [1.5, 1.7, 1.9]) and np.all(np.ptp(eye, axis=1) == 0)
    # Each edge-on triangle's plane holds a whole edge segment of a viewcell at eye height.
    cells = np.array(s.meta["cells"])
    segs = []
    for lo, hi in cells:
        x0, x1, z0, z1, y = lo[0], hi[0], lo[2], hi[2], 1.7
        segs += [((x0, y, z0), (x1, y, z0)), ((x1, y, z0), (x1, y, z1)),
                 ((x1, y, z1), (x0, y, z1)), ((x0, y, z1), (x0, y, z0)),
                 ((x0, lo[1], z1), (x0, hi[1], z1))]
    segs = np.array(segs)
    for tri in s.triangles(cases["edge_on"]):
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        n /= np.linalg.norm(n)
        dist = np.abs((segs - tri[0]) @ n)  # (segments, 2)
        assert np.any(np.all(dist < 1e-6, axis=1))
    # Coplanar: one plane; intersecting: an edge of each pair's second triangle crosses the first.
    cop = s.triangles(cases["coplanar"])
    assert np.ptp(cop[:, :, 2]) == 0 and np.array_equal(cop[0], cop[2])
    inter = s.triangles(cases["intersecting"])
    for a, b in ((inter[0], inter[1]), (inter[2], inter[3])):
        crosses = [segment_blocked(a[None], b[i], b[(i + 1) % 3]) for i in range(3)]
        assert any(crosses)


def test_stress_visible_is_in_plain_view_and_hidden_is_hidden():
    s = scene("stress", 10_000)
    cases = s.meta["cases"]
    off = np.array(s.meta["offset"])
    rng = np.random.default_rng(2)
    cells = np.array(s.meta["cells"])
    lo, hi = cells[:, 0].min(axis=0), cells[:, 1].max(axis=0)
    eyes = lo + rng.random((40, 3)) * (hi - lo)
    eyes = np.concatenate([eyes, [lo, hi, [lo[0], hi[1], hi[2]], [hi[0], lo[1], lo[2]]]])
    vtri = s.triangles(cases["visible"])[0]
    # Only triangles reaching into the box around the cells and the target can block.
    box_lo = np.minimum(lo, vtri.min(axis=0)) - 1.0
    box_hi = np.maximum(hi, vtri.max(axis=0)) + 1.0
    tris = s.triangles()
    near = s.valid_faces & np.all(tris.max(axis=1) >= box_lo, axis=1) & np.all(
        tris.min(axis=1) <= box_hi, axis=1)
    near[cases["visible"]] = False
    others = tris[near]
    assert len(others) > 10  # ground tiles, coplanar and intersecting cases at least
    bary = np.array([[1, 1, 1], [4, 1, 1], [1, 4, 1], [1, 1, 4]], float)
    targets = (bary / bary.sum(axis=1, keepdims=True)) @ vtri
    for e in eyes:
        for p in targets:
            assert not segment_blocked(others - e, np.zeros(3), p - e)
    wall = s.triangles(cases["wall"]) - off
    hidden = s.triangles(cases["hidden"]).reshape(-1, 3) - off
    for e in eyes - off:
        for p in hidden:
            assert segment_blocked(wall, e, p)


def test_stress_clutter_stays_out_of_the_quiet_zone():
    s = scene("stress", 10_000)
    start, stop = s.meta["clutter_range"]
    t = s.triangles(np.arange(start, stop)) - s.meta["offset"]
    q = stress_mod.QUIET
    lo, hi = t.min(axis=1), t.max(axis=1)
    inside = (hi[:, 0] > q[0]) & (lo[:, 0] < q[2]) & (hi[:, 2] > q[1]) & (lo[:, 2] < q[3])
    assert not inside.any()
    assert np.all(s.valid_faces[start:stop])


# ----------------------------------------------------------------------------- mesh helpers
def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    t = verts[faces]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6)


def test_patch_grid_counts_and_orientation():
    v, f, pid, iu, iv = gm.patch_grid([[0, 0, 0], [5, 0, 0]], [[2, 0, 0], [0, 0, 3]],
                                      [[0, 1, 0], [0, 2, 0]], [2, 3], [1, 4])
    assert len(f) == 2 * (2 * 1 + 3 * 4) and len(v) == 3 * 2 + 4 * 5
    n = gm.face_normals(v, f)
    assert np.allclose(n[pid == 0], [0, 0, 1]) and np.allclose(n[pid == 1], [-1, 0, 0])
    assert iu.max() == 2 and iv.max() == 3


@pytest.mark.parametrize("hand", [1.0, -1.0])
def test_solids_are_closed_outward_and_counted(hand):
    rng = np.random.default_rng(5)
    b = gm.SolidBatch()
    for k in (3, 4, 7):
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        prof = np.stack([np.cos(ang), np.sin(ang)], 1) * rng.uniform(1, 3)
        if rng.random() < 0.5:
            prof = prof[::-1]
        b.add(prof, rng.normal(size=3), [1, 0, 0], [0, 0, hand], [0, 2.5, 0], obj=k, step=0.4,
              nv=3, cap0=True, cap1=True)
    s = b.freeze()
    mesh = gm.solids_mesh(s)
    assert np.array_equal(np.bincount(mesh.solid), gm.solids_count(s))
    for i in range(len(s)):
        f = mesh.faces[mesh.solid == i]
        assert signed_volume(mesh.verts, f) > 0
        n = gm.face_normals(mesh.verts, f)
        kind = mesh.kind[mesh.solid == i]
        assert np.allclose(n[kind == 1], [0, 1, 0]) and np.allclose(n[kind == 2], [0, -1, 0])


def test_boxes_and_blobs_are_closed_and_outward():
    v, f, box, side = gm.box_mesh([[0, 0, 0], [2, 1, 1]], [[1, 2, 3], [4, 5, 6]])
    assert np.isclose(signed_volume(v, f[box == 0]), 6.0)
    assert np.isclose(signed_volume(v, f[box == 1]), 2 * 4 * 5)
    n = gm.face_normals(v, f)
    axis = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])
    assert np.allclose(n, axis[side])
    bv, bf, blob = gm.blob_mesh([[0, 0, 0], [5, 0, 0]], [[1, 2, 1], [1, 1, 1]], 2,
                                np.random.default_rng(0))
    assert len(bf) == 2 * 320
    assert signed_volume(bv, bf[blob == 0]) > 0 and signed_volume(bv, bf[blob == 1]) > 0


def test_tri_box_overlap_exact_cases():
    tris = np.array([
        [[-1, 0, 0], [1, 0, 0], [0, 1, 0]],        # through the box
        [[2, 2, 0], [3, 2, 0], [2, 3, 0]],         # far away
        [[0.9, 2.5, 0], [2.5, 0.9, 0], [2.5, 2.5, 0]],  # bbox overlaps, triangle does not
        [[-5, -5, 0.2], [5, -5, 0.2], [0, 5, 0.2]],     # larger than the box, cutting it
        [[-5, -5, 1.2], [5, -5, 1.2], [0, 5, 1.2]],     # larger, above it
    ], float)
    got = gm.tri_box_overlap(tris, np.zeros(3), np.ones(3))
    assert got.tolist() == [True, False, False, True, False]


def test_walk_violations_finds_an_intruder():
    v, f, _, side = gm.box_mesh([[1, 0, 1]], [[2, 1, 2]])
    s = Scene(v, f, walk=WalkArea(rects=[[0, 0, 4, 4, 0]]))
    # All but the bottom (at floor level, under floor + 0.1) enter the open space.
    assert gm.walk_violations(s).tolist() == np.flatnonzero(side != 2).tolist()
    s = Scene(v, f, walk=WalkArea(rects=[[2, 0, 4, 4, 0]]))  # box touches the border only
    assert len(gm.walk_violations(s)) == 0
    s = Scene(v + [0, 2.5, 0], f, walk=WalkArea(rects=[[0, 0, 4, 4, 0]]))  # above head height
    assert len(gm.walk_violations(s)) == 0


# ----------------------------------------------------------------------------------- memory
def _solid_batch(n: int = 40) -> gm.Solids:
    """``n`` random swept solids of 3 to 8 corners with capped ends and facade grids."""
    rng = np.random.default_rng(11)
    b = gm.SolidBatch()
    for i in range(n):
        k = int(rng.integers(3, 9))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        prof = np.stack([np.cos(ang), np.sin(ang)], 1) * rng.uniform(2, 9)
        b.add(prof, rng.normal(size=3) * 20, [1, 0, 0], [0, 0, 1], [0, rng.uniform(3, 30), 0],
              obj=i, step=rng.uniform(0.5, 3), nv=int(rng.integers(1, 9)),
              cap0=bool(rng.random() < 0.5), cap1=True, tag=i % 3)
    return b.freeze()


def test_solid_mesh_pieces_join_to_the_whole_mesh():
    s = _solid_batch()
    whole = list(gm.solids_mesh_parts(s, max_faces=1 << 30))
    assert len(whole) == 3  # walls, caps at s = 1, caps at s = 0
    pieces = list(gm.solids_mesh_parts(s, max_faces=60))
    assert len(pieces) > 10
    mesh = gm.solids_mesh(s)
    # Each piece is within the limit unless it is one wall or one cap.
    for p in pieces:
        assert len(p.faces) <= 60 or len(np.unique(p.solid)) == 1
        assert p.faces.min() == 0 and p.faces.max() == len(p.verts) - 1
    offsets = np.cumsum([0] + [len(p.verts) for p in pieces[:-1]])
    np.testing.assert_array_equal(np.concatenate([p.verts for p in pieces]), mesh.verts)
    np.testing.assert_array_equal(
        np.concatenate([p.faces + o for p, o in zip(pieces, offsets, strict=True)]), mesh.faces)
    for name in ("solid", "kind", "edge", "iu", "iv", "nu"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in pieces]),
                                      getattr(mesh, name))
    assert np.array_equal(np.bincount(mesh.solid, minlength=len(s)), gm.solids_count(s))


def test_mesh_parts_hand_the_pieces_over_in_final_dtypes():
    parts = gm.MeshParts()
    v, f, _, _ = gm.box_mesh([[0, 0, 0]], [[1, 1, 1]])
    assert parts.add(v, f, 3, [10.4, 300.0, -5.0]).tolist() == list(range(12))
    assert parts.add(v + 5, f, np.arange(12), np.full((12, 3), 7, np.uint8))[0] == 12
    verts, faces, obj, rgb = parts.build()
    assert verts.dtype == np.float64 and faces.dtype == np.int32
    assert obj.dtype == np.int32 and rgb.dtype == np.uint8
    np.testing.assert_array_equal(faces[12:], f + 8)
    assert rgb[0].tolist() == [10, 255, 0] and rgb[12].tolist() == [7, 7, 7]
    # Handed over: the parts are empty, so the pieces are no longer held twice.
    assert parts.n_faces == 0 and len(parts.build()[1]) == 0
    parts.n_vertices = 2**31 - 5
    with pytest.raises(ValueError, match="int32"):
        parts.add(v, f, 0, [1, 2, 3])


def test_to_rgb_and_shading_by_blocks_equal_one_pass(monkeypatch):
    s = make_scene("city", 5000, seed=2)
    rng = np.random.default_rng(0)
    rgb = rng.uniform(-20, 280, (s.n_triangles, 3))
    one = gm.to_rgb(rgb), gm.shade_by_normal(s.vertices, s.faces, s.colors)
    monkeypatch.setattr(gm, "FACE_BLOCK", 97)
    np.testing.assert_array_equal(gm.to_rgb(rgb), one[0])
    np.testing.assert_array_equal(gm.shade_by_normal(s.vertices, s.faces, s.colors), one[1])


def test_city_generation_peak_stays_near_the_scene_size(monkeypatch):
    """The city is generated piece by piece into its final dtypes: at no time does it hold
    more than the finished arrays twice over (the pieces and the joined scene), plus blocks."""
    import tracemalloc

    import visibility.scene as scene_module

    monkeypatch.setattr(gm, "FACE_BLOCK", 1 << 14)
    monkeypatch.setattr(scene_module, "FACE_BLOCK", 1 << 14)
    make_scene("city", 2000, seed=1)  # imports and caches out of the measurement
    tracemalloc.start()
    try:
        s = make_scene("city", 300_000, seed=0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    kept = s.vertices.nbytes + s.faces.nbytes + s.object_ids.nbytes + s.colors.nbytes
    assert peak <= 2 * kept
