"""``Accept`` negotiation with q-values, the HTTP request-body limit (413) and the count of HTTP
bytes in ``/metrics``: the parser itself and the real server on loopback."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from protocol.frames import decode_geometry, frame_bytes
from server.negotiation import choose_media_type, parse_accept
from tests.conftest import make_tiny_scene, near_ids

JSON, IDS, GEO = "application/json", "application/octet-stream", "application/vnd.pvs.geometry"
OFFERED = (JSON, IDS, GEO)
TINY = make_tiny_scene()


# --------------------------------------------------------------------------- parser
def test_parse_accept_reads_q_and_skips_malformed_ranges():
    got = parse_accept('Application/JSON; charset=utf-8; q=0.5, */*;q=0.1, text/*, bogus, '
                       'a/b;q=zz, */html, x/y;q="0.3", z/w;q=7')
    assert got == [("application", "json", 0.5), ("*", "*", 0.1), ("text", "*", 1.0),
                   ("x", "y", 0.3), ("z", "w", 1.0)]
    assert parse_accept(None) == [] and parse_accept("") == []


@pytest.mark.parametrize("accept, want", [
    (None, JSON),
    ("", JSON),
    ("*/*", JSON),
    (IDS, IDS),
    (GEO, GEO),
    (f"{JSON};q=0.5, {IDS}", IDS),
    (f"{GEO};q=0.9, {JSON};q=0.1", GEO),
    (f"{IDS};q=0, */*", JSON),
    (f"{JSON};q=0, {IDS};q=0.2, */*;q=0.1", IDS),
    # The most specific range sets the q: json is excluded even though application/* allows it.
    (f"application/*;q=0.8, {JSON};q=0", IDS),
    # Equal q: the type named explicitly beats one matched by a wildcard.
    (f"*/*, {GEO}", GEO),
    # Substrings of other types are not these types.
    ("application/json-patch+json, */*;q=0.1", JSON),
    ("application/octet-stream-like", None),
    ("text/html", None),
    (f"{JSON};q=0, {IDS};q=0, {GEO};q=0", None),
    ("*/*;q=0", None),
])
def test_choose_media_type(accept, want):
    assert choose_media_type(accept, OFFERED) == want


# --------------------------------------------------------------------------- live server
# (``http`` and ``still_healthy`` come from tests/server/conftest.py.)
def _pvs(http: httpx.Client, accept: str | None) -> httpx.Response:
    headers = {} if accept is None else {"accept": accept}
    return http.get("/scenes/tiny/cells/3/pvs", params={"core": "test_near", "radius": 4.5},
                    headers=headers)


#: Cell boxes of the tiny scene's grid, as the server reports them (filled by ``boxes``).
_BOXES: dict[int, np.ndarray] = {}


@pytest.fixture(scope="module", autouse=True)
def boxes(http):
    for c in http.get("/scenes/tiny/cells").json()["cells"]:
        _BOXES[c["id"]] = np.asarray(c["box"], dtype=np.float64)


def _want() -> np.ndarray:
    """The ids every form of ``_pvs`` must carry."""
    want = near_ids(TINY, _BOXES[3], 4.5)
    assert len(want) > 0
    return want


@pytest.mark.parametrize("accept, kind", [
    (f"{JSON};q=0.5, {IDS}", IDS),
    (f"{IDS};q=0.2, {GEO};q=0.9, {JSON};q=0.1", GEO),
    (f"{IDS};q=0, */*", JSON),
    ("application/json-patch+json, */*;q=0.1", JSON),
])
def test_route_answers_the_preferred_form(http, still_healthy, accept, kind):
    r = _pvs(http, accept)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].split(";")[0] == kind
    want = _want()
    if kind == JSON:
        assert r.json()["triangle_ids"] == want.tolist()
    elif kind == IDS:
        np.testing.assert_array_equal(np.frombuffer(r.content, "<i4"), want)
    else:
        ids, p = [], 0
        while p < len(r.content):
            n = int(np.frombuffer(r.content[p + 24:p + 28], "<u4")[0])
            ids.append(decode_geometry(r.content[p:p + frame_bytes(n)]).ids)
            p += frame_bytes(n)
        np.testing.assert_array_equal(np.concatenate(ids), want)


@pytest.mark.parametrize("accept", ["text/html", f"{JSON};q=0, {IDS};q=0, {GEO};q=0",
                                    "application/octet-stream-like"])
def test_route_406_when_no_form_is_acceptable(http, still_healthy, accept):
    r = _pvs(http, accept)
    assert r.status_code == 406, r.text
    assert r.json()["error"]["code"] == "not_acceptable"


def test_oversized_bodies_are_413_json(http, still_healthy, settings):
    """A body over ``max_body_bytes`` is refused whether its length is declared or streamed
    (chunked), with the JSON error body; the server then answers a normal body."""
    limit = settings.max_body_bytes
    big = b'{"box": [[0, 0, 0], [1, 1, 1]], "pad": "' + b"x" * (limit + 10) + b'"}'
    r = http.post("/scenes/tiny/pvs", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413, r.text
    assert r.json()["error"]["code"] == "too_big"

    def chunks():
        for i in range(0, len(big), 64 * 1024):
            yield big[i:i + 64 * 1024]

    with httpx.Client(base_url=str(http.base_url), timeout=60) as fresh:
        r = fresh.post("/scenes/tiny/pvs", content=chunks(),
                       headers={"content-type": "application/json"})
    assert "content-length" not in r.request.headers  # it really was chunked
    assert r.status_code == 413, r.text
    assert r.json()["error"]["code"] == "too_big"
    ok = http.post("/scenes/tiny/pvs", json={"box": _BOXES[3].tolist(), "core": "test_near",
                                             "params": {"radius": 4.5}})
    assert ok.status_code == 200 and ok.json()["triangle_ids"] == _want().tolist()


def _metric(http: httpx.Client, name: str) -> float:
    for line in http.get("/metrics").text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[-1])
    raise AssertionError(f"{name} not in /metrics")


def test_http_bytes_are_counted(http, still_healthy):
    before = _metric(http, "pvs_http_bytes_sent_total")
    r = _pvs(http, IDS)
    r2 = _pvs(http, JSON)
    after = _metric(http, "pvs_http_bytes_sent_total")
    # At least the two answers (the first /metrics answer is counted too, once sent).
    assert after - before >= len(r.content) + len(r2.content) > 0
