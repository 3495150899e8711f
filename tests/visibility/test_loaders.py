"""Loading real third-party scenes and files written by trimesh."""

import json

import numpy as np
import pytest
import trimesh

from tests.visibility.real_scenes import REAL, SHARED_SCENES, real_grid, real_path, real_scene
from visibility.loaders import SceneLoadError, _face_colors, load_scene


def test_shared_scenes_are_present():
    assert SHARED_SCENES.is_dir(), f"the real scenes are expected at {SHARED_SCENES}"


@pytest.mark.parametrize("name", REAL)
def test_real_scene_loads_in_metres_with_ids_as_trimesh_orders_them(name):
    path = real_path(name)
    side = json.loads(path.with_suffix(".json").read_text())
    scene = real_scene(name)
    assert scene.n_triangles == side["triangles"]
    assert scene.n_objects == side["objects"]
    ref = trimesh.load(str(path), force="scene", process=False).to_geometry()
    np.testing.assert_array_equal(scene.faces, ref.faces)
    np.testing.assert_allclose(scene.vertices, ref.vertices * side["scale"])
    obj = np.asarray(ref.vertex_attributes["_OBJECT_ID"]).reshape(len(ref.vertices), -1)[:, 0]
    np.testing.assert_array_equal(scene.object_ids, obj[ref.faces[:, 0]])
    np.testing.assert_allclose(
        scene.bounds()[0],
        np.array(side["bbox_min"]) * side["scale"],
        atol=1e-3 * side["scale"] + 1e-3,
    )
    assert scene.valid_faces.sum() > 0.9 * scene.n_triangles
    grid = real_grid(name)
    assert len(grid) > 0, f"{name}: no walkable cells found"
    # Cells lie inside the scene's horizontal extent.
    b = scene.bounds()
    centres = grid.boxes.mean(axis=1)
    assert np.all(centres[:, 0] >= b[0, 0] - grid.cell_size)
    assert np.all(centres[:, 0] <= b[1, 0] + grid.cell_size)


def test_obj_and_ply_round_trip(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    for ext in (".obj", ".ply"):
        p = tmp_path / f"ball{ext}"
        mesh.export(p)
        s = load_scene(p, scale=2.0)
        assert s.n_triangles == len(mesh.faces)
        np.testing.assert_allclose(np.abs(s.vertices).max(), 2.0, rtol=1e-5)


def test_z_up_sidecar_rotates_to_y_up(tmp_path):
    mesh = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 0, 5]], [[0, 1, 2]], process=False)
    p = tmp_path / "tall.ply"
    mesh.export(p)
    (tmp_path / "tall.json").write_text(json.dumps({"up": "z"}))
    s = load_scene(p)
    assert s.bounds()[1, 1] == pytest.approx(5.0)


def test_parts_fill_one_array_each_in_final_dtypes(tmp_path):
    # Three instances of two meshes, one moved twice, one with its own colour, Z-up and scaled.
    ball = trimesh.creation.icosphere(subdivisions=1)
    box = trimesh.creation.box()
    box.visual.face_colors = [10, 200, 30, 255]
    move = np.eye(4)
    move[:3, 3] = [5.0, 0.0, 2.0]
    scene = trimesh.Scene()
    scene.add_geometry(ball, node_name="ball")
    scene.add_geometry(box, node_name="box1", transform=move)
    scene.add_geometry(box, node_name="box2", transform=move @ move)
    path = tmp_path / "parts.glb"
    scene.export(path)
    (tmp_path / "parts.json").write_text(json.dumps({"up": "z", "scale": 0.5}))
    s = load_scene(path)
    ref = trimesh.load(str(path), force="scene", process=False).dump(concatenate=False)
    v = np.concatenate([g.vertices for g in ref]) * 0.5
    np.testing.assert_array_equal(s.vertices, np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1))
    offsets = np.cumsum([0] + [len(g.vertices) for g in ref[:-1]])
    np.testing.assert_array_equal(
        s.faces, np.concatenate([g.faces + o for g, o in zip(ref, offsets, strict=True)]))
    np.testing.assert_array_equal(s.object_ids, np.repeat(np.arange(3), [len(g.faces)
                                                                       for g in ref]))
    assert s.object_names == [g.metadata["name"] for g in ref]
    np.testing.assert_array_equal(s.colors, np.concatenate([_face_colors(g) for g in ref]))
    assert len(np.unique(s.colors, axis=0)) > 1
    # The scene owns its arrays (no view keeps a trimesh mesh alive), in their final dtypes.
    for a, dtype in ((s.vertices, np.float64), (s.faces, np.int32), (s.object_ids, np.int32),
                     (s.colors, np.uint8)):
        root = a if a.base is None else a.base
        assert a.dtype == dtype and a.flags.c_contiguous
        assert root.base is None and root.nbytes == a.nbytes


def test_bad_files_give_clear_errors(tmp_path):
    with pytest.raises(SceneLoadError):
        load_scene(tmp_path / "missing.glb")
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"not a glb at all")
    with pytest.raises(SceneLoadError):
        load_scene(bad)
    txt = tmp_path / "scene.txt"
    txt.write_text("x")
    with pytest.raises(SceneLoadError):
        load_scene(txt)


def test_load_errors_name_the_file_not_its_folder(tmp_path):
    """Servers show these messages to clients: the file's name, never the folder it is in."""
    quad = "v 0 0 0\nv 1 0 0\nv 1 0 1\nf 1 2 3\n"
    cases = {"missing.obj": None, "bad.glb": b"not a glb at all", "side.obj": quad}
    for name, content in cases.items():
        if isinstance(content, bytes):
            (tmp_path / name).write_bytes(content)
        elif content is not None:
            (tmp_path / name).write_text(content)
    (tmp_path / "side.json").write_text('{"scale": ')
    for name in cases:
        with pytest.raises(SceneLoadError) as err:
            load_scene(tmp_path / name)
        assert name.split(".")[0] in str(err.value) and str(tmp_path) not in str(err.value)


def test_strip_paths_leaves_file_names():
    from visibility.loaders import strip_paths

    text = "[Errno 2] No such file: '/srv/pvs/scenes/a.obj' (see /srv/pvs/scenes/)"
    assert strip_paths(text, "/srv/pvs/scenes") == "[Errno 2] No such file: 'a.obj' (see )"
    # Folders not named are removed by shape; relative paths and units are left alone.
    assert strip_paths("cannot open /home/u/x/b.bin") == "cannot open b.bin"
    assert strip_paths("speed 3 m/s, see docs/a.md, ratio 1/2") == \
        "speed 3 m/s, see docs/a.md, ratio 1/2"


def test_over_the_limit_errors_say_which_limit(tmp_path):
    from visibility.loaders import SceneTooLarge

    path = tmp_path / "strip.ply"
    _grid_mesh(5).export(path)
    with pytest.raises(SceneTooLarge) as err:
        load_scene(path, max_triangles=9)
    assert (err.value.file, err.value.limit, err.value.param) == ("strip.ply", 9, "max_triangles")
    assert err.value.detail == "declares 10 triangles"
    with pytest.raises(SceneTooLarge) as err:
        load_scene(path, max_bytes=10)
    assert (err.value.limit, err.value.param) == (10, "max_bytes")


def test_degenerate_faces_in_a_file_are_reported_not_fatal(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], float)
    f = np.array([[0, 1, 2], [0, 1, 3], [1, 1, 2]])
    p = tmp_path / "deg.ply"
    trimesh.Trimesh(v, f, process=False).export(p)
    s = load_scene(p)
    assert s.n_triangles == 3
    assert s.valid_faces.tolist() == [True, False, False]
    assert s.degenerate_report.zero_area == 1


# ----------------------------------------------------------------------------- size limits
def _grid_mesh(n_quads: int) -> trimesh.Trimesh:
    """A flat strip of ``n_quads`` quads (2 n_quads triangles)."""
    x = np.arange(n_quads + 1, dtype=np.float64)
    v = np.concatenate([np.stack([x, 0 * x, 0 * x], 1), np.stack([x, 0 * x, 0 * x + 1], 1)])
    i = np.arange(n_quads)
    j = i + n_quads + 1
    f = np.concatenate([np.stack([i, j, i + 1], 1), np.stack([i + 1, j, j + 1], 1)])
    return trimesh.Trimesh(v, f, process=False)


@pytest.mark.parametrize("ext", [".ply", ".glb", ".obj"])
def test_files_over_the_triangle_limit_are_refused_before_loading(tmp_path, ext, monkeypatch):
    from visibility import loaders

    path = tmp_path / f"strip{ext}"
    _grid_mesh(50).export(path)
    assert loaders.count_triangles(path) == 100
    assert load_scene(path, max_triangles=100).n_triangles == 100
    # The declared count refuses the file before trimesh parses it.
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: pytest.fail("parsed an absurd file"))
    with pytest.raises(SceneLoadError, match="max_triangles") as err:
        load_scene(path, max_triangles=99)
    assert "100 triangles" in str(err.value)


def test_a_file_that_understates_its_triangles_is_refused_after_loading(tmp_path, monkeypatch):
    from visibility import loaders

    path = tmp_path / "strip.ply"
    _grid_mesh(50).export(path)
    monkeypatch.setattr(loaders, "count_triangles", lambda p: 1)
    with pytest.raises(SceneLoadError, match="holds 100 triangles"):
        load_scene(path, max_triangles=99)


def test_files_over_the_byte_limit_are_refused(tmp_path):
    path = tmp_path / "strip.ply"
    _grid_mesh(50).export(path)
    with pytest.raises(SceneLoadError, match="max_bytes"):
        load_scene(path, max_bytes=path.stat().st_size - 1)
    assert load_scene(path, max_bytes=path.stat().st_size).n_triangles == 100


def test_real_scenes_are_within_the_default_limits():
    from visibility.loaders import MAX_FILE_BYTES, MAX_TRIANGLES, count_triangles

    for name in REAL:
        side = json.loads(real_path(name).with_suffix(".json").read_text())
        assert count_triangles(real_path(name)) == side["triangles"] < MAX_TRIANGLES
        assert real_path(name).stat().st_size < MAX_FILE_BYTES
