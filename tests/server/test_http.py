"""HTTP routes of the real server on loopback: answers and every error path."""

from __future__ import annotations

import concurrent.futures as cf
import json

import httpx
import numpy as np
import pytest

from protocol.version import PROTOCOL_VERSION
from tests.conftest import SlowCore, make_tiny_scene, near_ids

# After every test the server still answers /health.
pytestmark = pytest.mark.usefixtures("still_healthy")


def _error(r: httpx.Response, status: int, code: str) -> str:
    assert r.status_code == status, r.text
    body = r.json()
    assert body["error"]["code"] == code, body
    assert body["error"]["message"]
    return body["error"]["message"]


TINY = make_tiny_scene()


def test_health(http):
    body = http.get("/health").json()
    assert body["status"] == "ok" and body["version"] == PROTOCOL_VERSION
    assert body["compute"]["workers"] == 2
    assert {"cache", "inflight", "computed"} <= set(body["compute"])


def test_scene_listing_loads_nothing(http, server_app):
    scenes = {s["name"]: s for s in http.get("/scenes").json()["scenes"]}
    assert scenes["tiny"]["kind"] == "memory"
    assert scenes["box"]["kind"] == "file" and scenes["broken"]["kind"] == "file"
    assert "outside" not in scenes  # a symlink out of the scenes folder is never served
    for name in server_app.state.server.settings.generated:
        assert scenes[name]["kind"] == "generated"
        assert scenes[name]["loaded"] is False
    assert not server_app.state.server.catalog.is_loaded("broken")


def test_scene_summary(http):
    body = http.get("/scenes/tiny").json()
    assert body["name"] == "tiny" and body["kind"] == "memory"
    assert body["triangles"] == TINY.n_triangles == 221
    assert body["valid_triangles"] == 218
    assert body["degenerate"] == {"zero_area": 1, "non_finite": 1, "repeated_index": 1,
                                  "out_of_range": 0}
    np.testing.assert_allclose(body["bounds"], TINY.bounds())
    grid = body["grid"]
    assert grid["cells"] == 8 and grid["cell_size"] == 4.0
    listing = {s["name"]: s for s in http.get("/scenes").json()["scenes"]}
    assert listing["tiny"]["loaded"] is True


def test_file_scene_uses_its_sidecar(http):
    body = http.get("/scenes/box").json()
    assert body["kind"] == "file" and body["triangles"] == 12
    assert body["grid"]["cell_size"] == 3.0  # the sidecar's, not the server default
    assert body["grid"]["cells"] == 4


def test_cells(http):
    body = http.get("/scenes/tiny/cells").json()
    cells = body["cells"]
    assert len(cells) == body["grid"]["cells"] == 8
    assert [c["id"] for c in cells] == list(range(8))
    box = np.array(cells[0]["box"])
    assert box.shape == (2, 3) and np.all(box[1] >= box[0])
    np.testing.assert_allclose(box[:, [0, 2]], [[0, 0], [4, 4]])


def test_cell_pvs_matches_the_core(http):
    cells = http.get("/scenes/tiny/cells").json()["cells"]
    for cell in (0, 5):
        r = http.get(f"/scenes/tiny/cells/{cell}/pvs", params={"core": "test_near",
                                                               "radius": "4.5"})
        assert r.status_code == 200, r.text
        body = r.json()
        expected = near_ids(TINY, np.array(cells[cell]["box"]), 4.5)
        assert body["triangle_ids"] == expected.tolist()
        assert body["count"] == len(expected) > 0
        assert body["cell"] == cell and body["core"] == "test_near"
        assert body["granularity"] == "triangle" and body["params"]["radius"] == 4.5
        assert body["seconds"] >= 0 and body["box"] == cells[cell]["box"]
        # NaN and arrays in a core's stats arrive as JSON null and lists.
        assert body["stats"]["nan_stat"] is None and body["stats"]["hist"] == [0, 1, 2]


def test_object_granularity(http):
    r = http.get("/scenes/tiny/cells/0/pvs", params={"core": "test_near", "radius": 4.5,
                                                     "granularity": "object"})
    body = r.json()
    assert body["granularity"] == "object" and body["object_ids"]
    objs = np.unique(TINY.object_ids[body["triangle_ids"]])
    assert objs.tolist() == sorted(body["object_ids"])
    # Every valid triangle of each listed object is in.
    full = np.nonzero(np.isin(TINY.object_ids, objs) & TINY.valid_faces)[0]
    assert body["triangle_ids"] == full.tolist()


def test_second_request_is_cached(http):
    params = {"core": "test_near", "radius": "3.25"}
    first = http.get("/scenes/tiny/cells/3/pvs", params=params).json()
    second = http.get("/scenes/tiny/cells/3/pvs", params=params).json()
    assert first["cached"] is False and second["cached"] is True
    assert first["triangle_ids"] == second["triangle_ids"]
    assert second["seconds"] == first["seconds"]  # the original computation's time


def test_identical_inflight_requests_share_one_computation(http, live_server):
    before = SlowCore.calls
    params = {"core": "test_slow", "radius": "4", "delay": "0.5"}

    def get(_):
        with httpx.Client(base_url=live_server, timeout=60) as c:
            return c.get("/scenes/tiny/cells/2/pvs", params=params).json()

    with cf.ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(get, range(4)))
    assert SlowCore.calls - before == 1
    assert len({json.dumps(a["triangle_ids"]) for a in answers}) == 1


def test_box_pvs(http):
    box = [[1.0, 1.5, 1.0], [3.0, 1.9, 3.0]]
    r = http.post("/scenes/tiny/pvs", json={"box": box, "core": "test_near",
                                            "params": {"radius": 2.5}})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["cell"] is None and body["box"] == box
    assert body["triangle_ids"] == near_ids(TINY, np.array(box), 2.5).tolist()


@pytest.mark.parametrize("core", ["sampling", "cos", "from_segment"])
def test_box_thinner_than_the_extent_floor_is_the_point_it_is(http, core):
    """A 1e-300 m box is answered as the point it is (``viewcells.MIN_EXTENT``): 200, quickly,
    the point's PVS, and the box the answer names is the point."""
    from visibility.cores.base import available_cores

    if core not in available_cores():
        pytest.skip(f"core {core!r} is not installed")
    params = {"resolution": 32}
    tiny = [[0.0, 0.0, 0.0], [1e-300, 1e-300, 1e-300]]
    point = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    r = http.post("/scenes/tiny/pvs", json={"box": tiny, "core": core, "params": params})
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["box"] == point
    assert got["seconds"] < 30  # the point's cost, not a 1e-300 m cell's
    want = http.post("/scenes/tiny/pvs", json={"box": point, "core": core, "params": params})
    assert want.status_code == 200, want.text
    assert got["triangle_ids"] == want.json()["triangle_ids"]
    assert want.json()["cached"]  # one region, one cache entry


def test_default_core_is_the_settings_core(http, server_app):
    from visibility.cores.base import available_cores

    default = server_app.state.server.settings.core
    r = http.post("/scenes/tiny/pvs", json={"box": [[1, 1.5, 1], [2, 1.9, 2]],
                                            "params": {"resolution": 16}})
    if default in available_cores():
        assert r.status_code == 200, r.text
        assert r.json()["core"] == default
    else:  # the default core is not written yet
        _error(r, 404, "unknown_core")


def test_far_scene_is_consistent(http):
    a = http.get("/scenes/tiny/cells/1/pvs", params={"core": "test_near"}).json()
    b = http.get("/scenes/tiny_far/cells/1/pvs", params={"core": "test_near"}).json()
    assert a["triangle_ids"] == b["triangle_ids"]


# --------------------------------------------------------------------------- error paths
@pytest.mark.parametrize(
    "path",
    [
        "/scenes/nope",
        "/scenes/nope/cells",
        "/scenes/nope/cells/0/pvs?core=test_near",
        "/scenes/..%2Fsecret_outside",
        "/scenes/%2E%2E",
        "/scenes/a..b",
        "/scenes/outside",
        "/scenes/box.obj",
        "/scenes/%00",
    ],
)
def test_unknown_scene_404(http, path):
    r = http.get(path)
    if r.status_code == 404 and r.json()["error"]["code"] == "not_found":
        return  # the router itself refused the path: no scene lookup happened at all
    _error(r, 404, "unknown_scene")


def test_unknown_scene_post_404(http):
    _error(http.post("/scenes/nope/pvs", json={"box": [[0, 0, 0], [1, 1, 1]],
                                                "core": "test_near"}), 404, "unknown_scene")


def test_unknown_cell_404(http):
    msg = _error(http.get("/scenes/tiny/cells/8/pvs", params={"core": "test_near"}), 404,
                 "unknown_cell")
    assert "0..7" in msg
    _error(http.get("/scenes/tiny/cells/-1/pvs", params={"core": "test_near"}), 404,
           "unknown_cell")
    _error(http.get("/scenes/tiny/cells/99999999999999999999/pvs",
                    params={"core": "test_near"}), 404, "unknown_cell")


def test_non_integer_cell_422(http):
    _error(http.get("/scenes/tiny/cells/abc/pvs"), 422, "validation")


def test_unknown_core_404(http):
    msg = _error(http.get("/scenes/tiny/cells/0/pvs", params={"core": "nope"}), 404,
                 "unknown_core")
    assert "test_near" in msg  # the message lists what exists


@pytest.mark.parametrize(
    "params",
    [
        {"bogus": "1"},
        {"resolution": "abc"},
        {"resolution": "4"},
        {"resolution": "32.5"},
        {"radius": "nan"},
        {"radius": "inf"},
        {"radius": "-1"},
        {"granularity": "pixel"},
    ],
)
def test_bad_params_422(http, params):
    _error(http.get("/scenes/tiny/cells/0/pvs", params={"core": "test_near", **params}), 422,
           "bad_params")


@pytest.mark.parametrize(
    "body, code",
    [
        ({"box": [[0, 0, 0], [1, -1, 1]], "core": "test_near"}, "validation"),  # inverted
        ({"box": [[0, 0, 0], [1, 1]], "core": "test_near"}, "validation"),
        ({"box": [[0, 0, 0], [1, 1, 1]], "core": "test_near", "zzz": 1}, "validation"),
        ({"core": "test_near"}, "validation"),
        ({"box": [[0, 0, 0], [1, 1, 1]], "core": "test_near", "params": {"radius": 0}},
         "bad_params"),
        ({"box": [[0, 0, 0], [1, 1, 1]], "core": "nope"}, "unknown_core"),
    ],
)
def test_box_errors(http, body, code):
    status = 404 if code == "unknown_core" else 422
    _error(http.post("/scenes/tiny/pvs", json=body), status, code)


@pytest.mark.parametrize(
    "raw",
    [
        '{"box": [[0, NaN, 0], [1, 1, 1]], "core": "test_near"}',
        '{"box": [[0, 0, 0], [Infinity, 1, 1]], "core": "test_near"}',
        '{"box": [[0, 0, 0], [1, 1, 1]], "core": "test_near", "params": {"radius": NaN}}',
        "{not json",
        "[]",
    ],
)
def test_box_nan_and_malformed_422(http, raw):
    r = http.post("/scenes/tiny/pvs", content=raw, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["code"] in ("validation", "bad_params")


def test_failing_core_500(http):
    msg = _error(http.get("/scenes/tiny/cells/0/pvs", params={"core": "test_fail"}), 500,
                 "compute_failed")
    assert "deliberate failure" in msg


def test_core_that_does_not_fit_422(http):
    _error(http.get("/scenes/tiny/cells/0/pvs", params={"core": "test_picky"}), 422,
           "unsupported_scene")


def test_broken_scene_file_500_and_retry(http):
    for _ in range(2):  # a failed load is not cached as loaded; it fails again, cleanly
        msg = _error(http.get("/scenes/broken"), 500, "scene_load_failed")
        assert "broken" in msg


def test_unknown_route_and_method(http):
    _error(http.get("/nothing/here"), 404, "not_found")
    r = http.delete("/scenes")
    _error(r, 405, "method_not_allowed")
    assert r.headers["allow"] == "GET"
    assert http.put("/scenes/tiny/pvs").headers["allow"] == "POST"


def test_unparsable_body_400(http):
    r = http.post("/scenes/tiny/pvs", content=b"\xff\xfe{", headers={
        "content-type": "application/json"})
    _error(r, 400, "bad_request")


def test_openapi_docs(http):
    assert http.get("/docs").status_code == 200
    spec = http.get("/openapi.json").json()
    for path in ("/health", "/scenes", "/scenes/{scene}", "/scenes/{scene}/cells",
                 "/scenes/{scene}/cells/{cell}/pvs", "/scenes/{scene}/pvs", "/cores"):
        assert path in spec["paths"]


def test_openapi_documents_every_status(http):
    """The statuses each route answers, and no FastAPI default 422 shape we never send."""
    paths = http.get("/openapi.json").json()["paths"]

    def statuses(path, method="get"):
        return set(paths[path][method]["responses"])

    assert statuses("/scenes/{scene}") == statuses("/scenes/{scene}/cells") == {
        "200", "404", "500"}
    assert statuses("/cores") == {"200", "404", "500"}
    assert statuses("/scenes/{scene}/cells/{cell}/pvs") == {
        "200", "404", "406", "422", "429", "500", "503"}
    assert statuses("/scenes/{scene}/pvs", "post") == {
        "200", "400", "404", "406", "413", "422", "429", "500", "503"}
    error = paths["/scenes/{scene}"]["get"]["responses"]["404"]["content"]["application/json"]
    assert error["schema"]["$ref"].endswith("/ErrorResponse")
    assert "HTTPValidationError" not in json.dumps(paths)


def test_openapi_box_or_segment_is_one_of(http):
    schemas = http.get("/openapi.json").json()["components"]["schemas"]
    body = next(v for k, v in schemas.items() if k.startswith("BoxPvsRequest"))
    assert [b["required"] for b in body["oneOf"]] == [["box"], ["segment"]]


# --------------------------------------------------------------------------- cores
def test_cores_lists_every_core_with_its_parameters(http, server_app):
    from visibility.cores.base import available_cores

    body = http.get("/cores").json()
    assert body["default"] == server_app.state.server.settings.core
    assert "fit" not in body or body["fit"] is None
    cores = {c["name"]: c for c in body["cores"]}
    assert set(cores) == set(available_cores())
    radius = next(p for p in cores["test_near"]["params"] if p["name"] == "radius")
    assert radius["default"] == 5.0


def test_cores_fit_a_scene(http):
    fit = http.get("/cores", params={"scene": "tiny"}).json()["fit"]
    by_core = {f["core"]: f for f in fit["cores"]}
    assert by_core["test_near"]["ok"] is True
    assert by_core["test_picky"]["ok"] is False and by_core["test_picky"]["why"]
    assert fit["auto"]["core"] in by_core and fit["auto"]["why"]
    _error(http.get("/cores", params={"scene": "nope"}), 404, "unknown_scene")


# --------------------------------------------------------------------------- auto core
def test_auto_core_on_the_http_routes(http, server_app):
    """``core=auto`` picks a real core for the scene, as the WebSocket does, and says why."""
    from visibility.cores.base import available_cores

    name = _generated_with_sampling(server_app)
    quick = {"resolution": 32}
    r = http.get(f"/scenes/{name}/cells/0/pvs", params={"core": "auto", **quick})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["core"] in available_cores() and body["chosen_because"]
    assert body["chosen_because"] not in ("requested", "server default")
    box = http.get(f"/scenes/{name}/cells").json()["cells"][0]["box"]
    r = http.post(f"/scenes/{name}/pvs", json={"box": box, "core": "auto", "params": quick})
    assert r.status_code == 200, r.text
    assert r.json()["core"] == body["core"]
    assert r.json()["chosen_because"] == body["chosen_because"]
    r = http.get(f"/scenes/{name}/cells/0/pvs", params={"core": "auto", **quick},
                 headers={"accept": "application/octet-stream"})
    assert r.status_code == 200
    assert r.headers["x-pvs-core"] == body["core"] and r.headers["x-pvs-core-reason"]


def test_named_core_says_it_was_requested(http):
    body = http.get("/scenes/tiny/cells/0/pvs", params={"core": "test_near"}).json()
    assert body["chosen_because"] == "requested"


# --------------------------------------------------------------------------- generated scenes
def _generated_with_sampling(server_app):
    gens = sorted(server_app.state.server.settings.generated)

    return "rooms" if "rooms" in gens else gens[0]


def test_generated_scene_with_sampling_core(http, server_app):
    name = _generated_with_sampling(server_app)
    info = http.get(f"/scenes/{name}").json()
    assert info["kind"] == "generated" and info["triangles"] > 0 and info["grid"]["cells"] > 0
    r = http.get(f"/scenes/{name}/cells/0/pvs",
                 params={"core": "sampling", "resolution": 32, "samples": 4})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["count"] > 0 and body["count"] == len(body["triangle_ids"])
    assert body["triangle_ids"] == sorted(set(body["triangle_ids"]))
    assert max(body["triangle_ids"]) < info["triangles"]
