"""Georeferenced scenes: coordinates of 1e6-1e7 m (UTM-like eastings and northings) keep their
millimetres from the file through the scene, the rasterizer, a core and the wire.

The same generated city is written twice: at a UTM-like offset and at the origin. The origin copy
is the offset one minus the offset, which float64 computes exactly (Sterbenz: both operands are
within a factor of two), so the two files hold the very same shape and any difference in what the
server makes of them comes from the coordinates' magnitude alone.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from client.session import Session
from server.catalog import wire_origin
from tests.conftest import serving
from visibility.generators import make_scene
from visibility.loaders import load_scene
from visibility.raster import render_cubemap
from visibility.viewcells import spread_evenly

#: An easting past 1e6 m and a northing near 1e7 m, with an altitude: none of them round.
OFFSET = np.array([1_234_567.891, 310.25, 9_876_543.21])
#: float32 keeps 24 bits: a coordinate r metres from its origin is off by at most r * 2^-24.
F32_REL = 2.0 ** -24
TIMEOUT = 120.0


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """An OBJ of the mesh, every coordinate written with all its float64 digits."""
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def city_pair(tmp_path_factory) -> dict:
    """The city at the offset (``geo.obj``) and at the origin (``local.obj``) with their walk
    areas in sidecars, and the exact coordinates each file holds."""
    folder = tmp_path_factory.mktemp("georef") / "scenes"
    folder.mkdir()
    city = make_scene("city", 20_000, seed=0)
    far = city.vertices + OFFSET
    near = far - OFFSET  # exact: far and OFFSET are within a factor of two on every axis
    assert np.array_equal(near + OFFSET, far)
    rects = city.walk.rects[:, :5].copy()
    far_rects = rects + OFFSET[[0, 2, 0, 2, 1]]
    near_rects = far_rects - OFFSET[[0, 2, 0, 2, 1]]
    for stem, v, r in (("geo", far, far_rects), ("local", near, near_rects)):
        _write_obj(folder / f"{stem}.obj", v, city.faces)
        (folder / f"{stem}.json").write_text(json.dumps(
            {"walk": {"rects": r.tolist()}, "cell_size": 4.0}))
    return {"folder": folder, "faces": city.faces, "far": far, "near": near}


def test_offset_files_load_to_the_millimetre(city_pair, tmp_path):
    far, faces = city_pair["far"], city_pair["faces"]
    geo = load_scene(city_pair["folder"] / "geo.obj")
    # Text coordinates parse to the float64 written: exact, not just millimetres.
    np.testing.assert_array_equal(geo.triangles(), far[faces])
    assert np.array_equal(geo.valid_faces, load_scene(city_pair["folder"] / "local.obj")
                          .valid_faces)
    # A georeferenced glTF keeps float32 positions near its node and the offset in the node's
    # float64 matrix: the loader composes them in float64.
    import trimesh

    local = far - OFFSET
    node = np.eye(4)
    node[:3, 3] = OFFSET
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(local, faces, process=False), node_name="city",
                       transform=node)
    scene.export(tmp_path / "geo.glb")
    glb = load_scene(tmp_path / "geo.glb")
    err = np.abs(glb.triangles() - far[faces])
    bound = np.abs(local[faces]) * F32_REL + np.spacing(np.abs(far[faces]))
    assert np.all(err <= bound)
    assert err.max() < 1e-3


def test_render_at_the_offset_is_the_render_at_the_origin(city_pair):
    far_scene = load_scene(city_pair["folder"] / "geo.obj")
    near_scene = load_scene(city_pair["folder"] / "local.obj")
    rect = far_scene.walk.rects[0]
    eye_far = np.array([(rect[0] + rect[2]) / 2, rect[4] + 1.7, (rect[1] + rect[3]) / 2])
    eye_near = eye_far - OFFSET  # exact, as the vertices: the same eye of the same shape
    depth_far, ids_far = render_cubemap(far_scene.vertices, far_scene.faces, eye_far, 128,
                                        face_mask=far_scene.valid_faces)
    depth_near, ids_near = render_cubemap(near_scene.vertices, near_scene.faces, eye_near, 128,
                                          face_mask=near_scene.valid_faces)
    assert (ids_far >= 0).mean() > 0.5  # a street view, not an empty sky
    np.testing.assert_array_equal(ids_far, ids_near)
    np.testing.assert_array_equal(depth_far, depth_near)


def test_served_offset_scene_computes_the_same_pvs_and_keeps_millimetres(city_pair, settings):
    far, faces = city_pair["far"], city_pair["faces"]
    with serving(settings, scenes_dir=city_pair["folder"], generated={}) as (url, app):
        with httpx.Client(base_url=url, timeout=TIMEOUT) as http:
            cells = {s: http.get(f"/scenes/{s}/cells").json()["cells"] for s in ("geo", "local")}
            info = {s: http.get(f"/scenes/{s}").json() for s in ("geo", "local")}
            # The geometry analysis (a height field?) reaches the same verdict at the offset.
            assert info["geo"]["is_2_5d"] == info["local"]["is_2_5d"]
            assert info["geo"]["is_2_5d"]["source"] != "meta"
            assert info["geo"]["valid_triangles"] == info["local"]["valid_triangles"]
            assert len(cells["geo"]) == len(cells["local"]) > 3
            box_far = np.array([c["box"] for c in cells["geo"]])
            box_near = np.array([c["box"] for c in cells["local"]])
            # The grids are the same cells; the eye range is added to each floor height, which
            # rounds at the altitude's float64 step.
            assert [c["ij"] for c in cells["geo"]] == [c["ij"] for c in cells["local"]]
            assert np.all(np.abs(box_far - OFFSET - box_near) <= np.spacing(np.abs(box_far)))
            picks = spread_evenly(np.arange(len(cells["geo"])), 3)
            pvs = {}
            for s in ("geo", "local"):
                for cid in picks:
                    body = http.get(f"/scenes/{s}/cells/{cid}/pvs",
                                    params={"core": "sampling"}).json()
                    pvs[s, cid] = body["triangle_ids"]
            for cid in picks:
                assert len(pvs["geo", cid]) > 0
                assert pvs["geo", cid] == pvs["local", cid]
        origin = wire_origin(app.state.server.catalog.get("geo").scene)
        cid = picks[1]
        centre = box_far[cid].mean(axis=0).tolist()

        async def stream():
            s = await Session.connect(url, "geo", "sampling", prefetch=False)
            await s.send_pose(0, 0.0, centre, (0.0, 0.0, -1.0))
            await s.wait_cell(cid, TIMEOUT)
            await s.close()
            return s

        s = asyncio.run(asyncio.wait_for(stream(), TIMEOUT))
    assert not s.errors and not s.local_errors
    ids, tris, _ = s.store.arrays()
    np.testing.assert_array_equal(ids, np.sort(pvs["geo", cid]))
    # The wire holds float32 offsets from the scene's origin (a whole-metre point near its
    # centre, 1e7 m out here): each coordinate is off by at most its float32 rounding.
    expected = far[faces[ids]]
    err = np.abs(tris - expected)
    assert np.all(err <= np.abs(expected - origin) * F32_REL + np.spacing(np.abs(expected)))
    assert err.max() < 1e-3
