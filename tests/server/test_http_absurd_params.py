"""Absurd parameters over HTTP with the real cores (``sampling``, ``from_segment``) on the real
server: each is a 4xx JSON error, never a computation that hogs the machine, never a 500, and
the server keeps answering."""

from __future__ import annotations

import json

import httpx
import pytest

REAL_CORES = ("sampling", "from_segment")


# After every request the server is up and answering.
pytestmark = pytest.mark.usefixtures("still_healthy")


def _client_error(r: httpx.Response, status: int, code: str) -> None:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json")
    err = r.json()["error"]
    assert err["code"] == code and err["message"], err


#: Query parameters no real core accepts (each core's parameters plus the shared ones).
ABSURD = [
    ("sampling", {"resolution": "1000000"}),
    ("sampling", {"resolution": "-64"}),
    ("sampling", {"resolution": "nan"}),
    ("sampling", {"resolution": "64.5"}),
    ("sampling", {"samples": str(10**6)}),
    ("sampling", {"samples": "-1"}),
    ("sampling", {"samples": "0"}),
    ("sampling", {"batch": "inf"}),
    ("sampling", {"granularity": "voxel"}),
    ("sampling", {"runs": str(10**6)}),  # not a sampling parameter at all
    ("from_segment", {"resolution": "1000000"}),
    ("from_segment", {"runs": str(10**6)}),
    ("from_segment", {"runs": "-3"}),
    ("from_segment", {"near": "nan"}),
    ("from_segment", {"near": "-0.1"}),
    ("from_segment", {"near": "1e300"}),
    ("from_segment", {"eye_levels": "7"}),
    ("from_segment", {"depth_knots": "-1"}),
    ("from_segment", {"batch_triangles": "1"}),
    # Seeds are uint32 (numpy generators): past it, or past int64, is out of range.
    ("sampling", {"seed": str(2**32)}),
    ("sampling", {"seed": str(2**64)}),
    ("sampling", {"seed": "-1"}),
    ("from_segment", {"seed": str(10**30)}),
]


@pytest.mark.parametrize("core, params", ABSURD)
def test_absurd_cell_params_are_422(http, core, params):
    r = http.get("/scenes/tiny/cells/1/pvs", params={"core": core, **params})
    _client_error(r, 422, "bad_params")
    assert str(next(iter(params))) in r.json()["error"]["message"]


@pytest.mark.parametrize("core, params", ABSURD)
def test_absurd_region_params_are_422(http, core, params):
    """The same parameters in a POST body (typed JSON values, NaN as the JSON extension)."""
    typed = {k: _json_value(v) for k, v in params.items()}
    for region in ({"box": [[1, 1.7, 1], [3, 1.7, 3]]},
                   {"segment": [[1, 1.7, 1], [3, 1.7, 1]]}):
        r = _post(http, {**region, "core": core, "params": typed})
        assert r.status_code == 422, r.text
        # NaN/inf are refused already by the body's model, the rest by the core's checks.
        assert r.json()["error"]["code"] in ("bad_params", "validation")


def _post(http: httpx.Client, body: dict) -> httpx.Response:
    """POST ``body`` as JSON with NaN/Infinity written as the usual JSON extension literals
    (httpx itself refuses them)."""
    return http.post("/scenes/tiny/pvs", content=json.dumps(body),
                     headers={"content-type": "application/json"})


def _json_value(v: str):
    try:
        return int(v)
    except ValueError:
        pass
    try:
        return float(v)  # "nan" -> NaN, sent as the JSON extension literal NaN
    except ValueError:
        return v


@pytest.mark.parametrize("core", REAL_CORES)
@pytest.mark.parametrize("cell", ["8", "1000000", "99999999999999999999", "-1"])
def test_cell_out_of_range_is_404(http, core, cell):
    """The tiny grid has cells 0..7: anything else is ``unknown_cell`` (never a wrapped index
    such as -1 meaning the last cell)."""
    r = http.get(f"/scenes/tiny/cells/{cell}/pvs", params={"core": core})
    _client_error(r, 404, "unknown_cell")


@pytest.mark.parametrize("core", REAL_CORES)
@pytest.mark.parametrize("region, code", [
    ({"box": [[0, 0, 0], [1, float("nan"), 1]]}, "validation"),
    ({"segment": [[0, 0, 0], [float("inf"), 1, 1]]}, "validation"),
    # Finite but absurd: overflows the cores' arithmetic into a wrong answer if computed.
    ({"box": [[0, 0, 0], [1e308, 1e308, 1e308]]}, "unsupported_region"),
    ({"segment": [[-1e300, 1.7, 0], [1e300, 1.7, 0]]}, "unsupported_region"),
    ({"box": [[5e4, 0, 5e4], [5e4 + 4, 3, 5e4 + 4]]}, "unsupported_region"),
])
def test_non_finite_or_far_regions_are_refused(http, core, region, code):
    r = _post(http, {**region, "core": core, "params": {"resolution": 16}})
    _client_error(r, 422, code)


def test_regions_near_a_far_scene_are_answered(http):
    """The margin is relative to the scene's bounds: a box 100 km out is refused for the tiny
    scene but answered for its copy 100 km from the origin, and a box 10 m outside the tiny
    scene is still answered."""
    r = _post(http, {"box": [[1e5 + 1, 1, 1e5 + 1], [1e5 + 3, 2, 1e5 + 3]],
                     "core": "test_near", "params": {"radius": 2.0}})
    _client_error(r, 422, "unsupported_region")
    far_box = http.get("/scenes/tiny_far/cells").json()["cells"][1]["box"]
    r2 = http.post("/scenes/tiny_far/pvs", json={"box": far_box, "core": "test_near",
                                                 "params": {"radius": 2.0}})
    assert r2.status_code == 200 and r2.json()["box"] == far_box, r2.text
    r3 = _post(http, {"box": [[-12, 1, -12], [-10, 2, -10]], "core": "test_near",
                      "params": {"radius": 2.0}})
    assert r3.status_code == 200, r3.text


@pytest.mark.parametrize("core", REAL_CORES)
def test_real_cores_still_answer_after_the_abuse(http, core):
    """A sane request after all of the above is computed (the workers are all alive)."""
    r = http.get("/scenes/tiny/cells/1/pvs", params={"core": core, "resolution": "16"})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["core"] == core and body["cell"] == 1 and body["count"] > 0
