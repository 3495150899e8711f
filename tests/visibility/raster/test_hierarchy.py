"""The scene hierarchy: every drawable static face in exactly one leaf, boxes that hold their
triangles and children, moving faces kept out, and a file that round-trips and is checked."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.generators import make_scene
from visibility.raster.hierarchy import (
    FORMAT,
    Hierarchy,
    build_hierarchy,
    candidates_in_box,
    drawable_faces,
    ready_hierarchy,
    scene_hierarchy,
)
from visibility.scene import Scene, moving_faces
from visibility.scene_cache import peek, set_store


def _leaf_of(h: Hierarchy) -> np.ndarray:
    leaf = np.full(h.n_faces, -1, dtype=np.int64)
    leaf[h.order] = np.arange(len(h.order)) // h.leaf_size
    return leaf


@pytest.mark.parametrize("leaf_size", [1, 5, 16])
def test_every_static_face_in_one_leaf_and_boxes_hold_it(leaf_size):
    scene = make_scene("city", 4000, seed=2)
    h = build_hierarchy(scene.vertices, scene.faces, leaf_size=leaf_size)
    assert np.array_equal(np.sort(h.order), np.flatnonzero(drawable_faces(scene.vertices,
                                                                          scene.faces)))
    slots = h.n_leaf_slots
    assert slots & (slots - 1) == 0 and slots >= h.n_leaves
    tri = scene.vertices[scene.faces]  # (m, 3, 3)
    leaf = _leaf_of(h)
    box = h.boxes[slots + leaf[h.order]]
    assert np.all(tri[h.order].min(axis=1) >= box[:, 0])
    assert np.all(tri[h.order].max(axis=1) <= box[:, 1])
    # The leaf-ordered copy draws the same corners.
    assert np.array_equal(h.vertices[h.faces], scene.vertices[scene.faces[h.order]])
    inner = np.arange(1, slots)
    for child in (2 * inner, 2 * inner + 1):
        full = h.boxes[child, 0, 0] <= h.boxes[child, 1, 0]
        assert np.all(h.boxes[inner[full], 0] <= h.boxes[child[full], 0])
        assert np.all(h.boxes[inner[full], 1] >= h.boxes[child[full], 1])


def test_undrawable_faces_are_left_out():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 7], [2, 1, 0]], dtype=np.int32)
    h = build_hierarchy(v, f)
    assert sorted(h.order.tolist()) == [0, 3]
    empty = build_hierarchy(v, f[[1, 2]])
    assert len(empty.order) == 0 and empty.boxes[1, 0, 0] > empty.boxes[1, 1, 0]


def test_moving_faces_are_loose():
    scene = make_scene("swaying_grass", 1000, seed=0)
    moving = moving_faces(scene)
    assert moving.any() and (~moving & scene.valid_faces).any()
    h = scene_hierarchy(scene)
    assert np.array_equal(np.sort(h.loose), np.flatnonzero(moving))
    assert not np.isin(h.order, h.loose).any()


def test_save_load_round_trip_and_checks(tmp_path):
    scene = make_scene("village", 3000, seed=1)
    h = build_hierarchy(scene.vertices, scene.faces)
    p = tmp_path / "h.npz"
    h.save(p)
    back = Hierarchy.load(p, scene.vertices, scene.faces)
    assert back is not None
    for name in ("order", "boxes", "faces", "vertices", "loose"):
        assert np.array_equal(getattr(back, name), getattr(h, name)), name
    assert back.leaf_size == h.leaf_size
    other = np.concatenate([scene.faces, scene.faces[:1]])
    assert Hierarchy.load(p, scene.vertices, other) is None  # another scene's faces
    assert Hierarchy.load(tmp_path / "missing.npz", scene.vertices, scene.faces) is None
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    assert Hierarchy.load(tmp_path / "bad.npz", scene.vertices, scene.faces) is None
    np.savez(tmp_path / "old.npz", format=np.array("bvh-0"), order=h.order, boxes=h.boxes,
             leaf_size=np.array(16), n_faces=np.array(scene.n_triangles), loose=h.loose)
    assert FORMAT != "bvh-0"
    assert Hierarchy.load(tmp_path / "old.npz", scene.vertices, scene.faces) is None


def test_kept_on_disk_by_content_hash(tmp_path):
    set_store(tmp_path)
    try:
        a = make_scene("village", 3000, seed=3)
        ha = scene_hierarchy(a)
        files = list((tmp_path / "scenes").rglob("*.npz"))
        assert len(files) == 1
        # The same geometry in a new scene object (a restart) reads the file: not rebuilt.
        b = make_scene("village", 3000, seed=3)
        hb = scene_hierarchy(b)
        assert hb.stats.get("loaded") and np.array_equal(ha.order, hb.order)
        # Other geometry never meets that file.
        c = make_scene("village", 3000, seed=4)
        assert not scene_hierarchy(c).stats.get("loaded")
        assert len(list((tmp_path / "scenes").rglob("*.npz"))) == 2
    finally:
        set_store(None)


def test_ready_hierarchy_never_waits_and_builds_in_the_background():
    import time

    scene = make_scene("city", 60_000, seed=5)
    assert peek(scene, "raster/hierarchy") is None
    first = ready_hierarchy(scene)
    assert first is None  # not built yet: the caller draws everything meanwhile
    deadline = time.monotonic() + 120
    while ready_hierarchy(scene) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    h = ready_hierarchy(scene)
    assert h is not None and h.n_faces == scene.n_triangles
    small = Scene(np.eye(3), np.array([[0, 1, 2]]))
    assert ready_hierarchy(small) is None and peek(small, "raster/hierarchy") is None


@pytest.mark.parametrize("name", ["city", "swaying_grass"])
def test_candidates_in_box_hold_every_face_that_meets_it(name):
    """Brute force over every face: each drawable one whose bounds meet a random box (some
    unbounded upwards) is a candidate, and on a static city the candidates are far fewer
    than the scene."""
    scene = make_scene(name, 4000, seed=5)
    h = scene_hierarchy(scene)
    tri = scene.triangles().astype(np.float64)
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    drawable = drawable_faces(scene.vertices, scene.faces)
    rng = np.random.default_rng(1)
    slo, shi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    fewer = 0
    for k in range(40):
        c = rng.uniform(slo, shi)
        half = rng.uniform(0.0, 0.1, 3) * (shi - slo)
        lo, hi = c - half, c + half
        if k % 2:
            hi[1] = np.inf
        meets = drawable & np.all((thi >= lo) & (tlo <= hi), axis=1)
        cand = candidates_in_box(h, lo, hi)
        assert len(np.unique(cand)) == len(cand)
        assert set(np.flatnonzero(meets)) <= set(cand.tolist())
        assert set(h.loose.tolist()) <= set(cand.tolist())
        fewer += len(cand) < 0.5 * scene.n_triangles
    # Swaying grass moves everywhere: every face is loose, a candidate of every box.
    assert fewer >= 30 if name == "city" else fewer == 0


def test_a_damaged_file_is_not_read(tmp_path):
    scene = make_scene("village", 3000, seed=3)
    scene_hierarchy(scene).save(tmp_path / "h.npz")
    (tmp_path / "cut.npz").write_bytes((tmp_path / "h.npz").read_bytes()[:100])
    assert Hierarchy.load(tmp_path / "cut.npz", scene.vertices, scene.faces) is None
