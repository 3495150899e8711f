"""Fuzzing against the live server: hypothesis on the WebSocket protocol (random and mutated
messages), schemathesis on the OpenAPI spec. Never a 500, never an ``internal`` error, never a
dead server. Bounded: a few dozen examples each. The same against a server with access control
(``server.auth``), with a token, and malformed ``Authorization`` headers and token subprotocols
on its protected routes."""

from __future__ import annotations

import asyncio
import json
import time
from collections import Counter

import httpx
import numpy as np
import pytest
import schemathesis
import websockets
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect
from websockets.headers import validate_subprotocols

from protocol.auth import SUBPROTOCOL, TOKEN_SUBPROTOCOL_PREFIX
from protocol.frames import FrameError, decode_geometry, encode_geometry
from protocol.messages import Hello, Pose, dump_message, parse_server_message
from tests.conftest import make_tiny_scene, serving

FUZZ = settings(max_examples=30, deadline=None,
                suppress_health_check=list(HealthCheck))

VALID = [
    json.loads(dump_message(Hello(scene="tiny", core="test_near", params={"radius": 3.0}))),
    json.loads(dump_message(Pose(seq=1, t=0.5, position=(2.0, 1.7, 2.0),
                                 forward=(0.0, 0.0, -1.0), velocity=(1.0, 0.0, 0.0)))),
    {"type": "bye"},
]

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats(allow_nan=True)
    | st.text(max_size=20),
    lambda children: st.lists(children, max_size=4)
    | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12,
)


@st.composite
def mutated(draw) -> str:
    """A valid message with one field replaced, removed or added."""
    msg = dict(draw(st.sampled_from(VALID)))
    action = draw(st.sampled_from(["replace", "remove", "add", "type"]))
    keys = sorted(msg)
    if action == "replace":
        msg[draw(st.sampled_from(keys))] = draw(json_values)
    elif action == "remove":
        msg.pop(draw(st.sampled_from(keys)))
    elif action == "add":
        msg[draw(st.text(max_size=10))] = draw(json_values)
    else:
        msg["type"] = draw(st.text(max_size=12))
    return json.dumps(msg)


client_frames = st.one_of(
    mutated(),
    st.text(max_size=200),
    st.binary(max_size=200),
    json_values.map(json.dumps),
)


async def _exchange(url: str, first_hello: bool, frames: list, **kw) -> list:
    """Open a session (with a valid hello or not; ``kw`` to ``connect``), send ``frames``,
    collect what comes back for a short while; returns [(kind, payload)] with the close code
    last."""
    out = []
    async with connect(url, open_timeout=30, compression=None, max_size=None, **kw) as ws:
        try:
            if first_hello:
                await ws.send(dump_message(Hello(scene="tiny", core="test_near",
                                                 params={"radius": 3.0})))
            for f in frames:
                await ws.send(f)
        except websockets.ConnectionClosed:
            pass  # the server closed first (a refusal): what it sent before is still queued
        try:
            while True:
                raw = await asyncio.wait_for(ws.recv(), 0.5)
                if isinstance(raw, str):
                    out.append(("text", parse_server_message(raw)))
        except (TimeoutError, Exception):
            pass
        out.append(("close", ws.close_code))
    return out


@FUZZ
@given(first_hello=st.booleans(), frames=st.lists(client_frames, min_size=1, max_size=3))
def test_protocol_fuzz_never_crashes_the_server(live_server, ws_endpoint, first_hello, frames):
    got = asyncio.run(asyncio.wait_for(_exchange(ws_endpoint, first_hello, frames), 60))
    for kind, payload in got:
        if kind == "text" and payload.type == "error":
            assert payload.code != "internal", payload.message
        if kind == "close":
            assert payload != 1011
    r = httpx.get(live_server + "/health", timeout=30)
    assert r.status_code == 200


@FUZZ
@given(data=st.binary(max_size=300), flip=st.integers(0, 10_000), value=st.integers(0, 255))
def test_frame_decoder_fuzz(data, flip, value):
    """Random bytes, and valid frames with one byte changed, decode or raise FrameError."""
    ids = np.arange(3)
    frame = bytearray(encode_geometry(ids, np.ones((3, 3, 3)), np.zeros((3, 3), np.uint8)))
    frame[flip % len(frame)] = value
    for blob in (data, bytes(frame)):
        try:
            chunk = decode_geometry(blob)
        except FrameError:
            continue
        assert np.all(np.isfinite(chunk.positions)) and np.all(chunk.ids >= 0)


# --------------------------------------------------------------------------- schemathesis
#: Generated requests per operation: enough to reach every documented error, a few seconds each.
OPENAPI_EXAMPLES = 25


def test_openapi_fuzz(live_server):
    """Every operation of the OpenAPI spec, generated requests (the cell route's core
    parameters included): never a 5xx, and every answer is one the schema documents (status,
    content type, headers, body), and schema-invalid requests are refused with a 4xx.
    Operations one by one (``schemathesis.pytest.from_fixture``
    does not run under this pytest)."""
    _openapi_fuzz(live_server, OPENAPI_EXAMPLES)


def _openapi_fuzz(url: str, examples: int, headers: dict[str, str] | None = None) -> Counter:
    """``test_openapi_fuzz`` against the server at ``url``, every request with ``headers``; the
    answers' statuses and their counts."""
    schema = schemathesis.openapi.from_url(url + "/openapi.json")
    statuses: Counter = Counter()
    for result in schema.get_all_operations():
        op = result.ok()

        @settings(max_examples=examples, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=op.as_strategy())
        def check(case):
            # Every default check but "schema-valid data is accepted": the schema cannot say
            # that a box's max must not be below its min, nor which core parameters a core
            # takes (the core checks them: 422, documented).
            response = case.call_and_validate(
                timeout=60, headers=headers,
                excluded_checks=[schemathesis.checks.positive_data_acceptance])
            statuses[response.status_code] += 1

        check()
    return statuses


def test_openapi_covers_every_route(live_server):
    spec = httpx.get(live_server + "/openapi.json", timeout=30).json()
    labels = {(m.upper(), p) for p, ops in spec["paths"].items() for m in ops}
    assert ("GET", "/metrics") in labels and ("GET", "/cores") in labels
    assert ("POST", "/scenes/{scene}/pvs") in labels
    cell_route = spec["paths"]["/scenes/{scene}/cells/{cell}/pvs"]["get"]
    declared = {p["name"] for p in cell_route.get("parameters", [])}
    assert {"core", "granularity", "resolution", "samples", "runs", "seed"} <= declared


# --------------------------------------------------------------------------- robustness probes
#: Extents around the review's 1e-300 m box: zero, subnormal, tiny, ordinary.
extents = st.sampled_from([0.0, 5e-324, 1e-300, 1e-200, 1e-12, 1e-6, 0.5, 3.0])
#: Core parameters around the limits: each at, just inside and far outside its range.
hostile_params = st.fixed_dictionaries({}, optional={
    "resolution": st.sampled_from([7, 8, 64, 4096, 4097, 2**31, -1]),
    "samples": st.sampled_from([0, 1, 1000, 100_000, 100_001, 2**63]),
    "seed": st.sampled_from([-1, 0, 2**32 - 1, 2**32, 2**64]),
})


@settings(max_examples=40, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(lo=st.tuples(*[st.sampled_from([0.0, 1.0, 2.5, -1e-300])] * 3),
       size=st.tuples(extents, extents, extents), params=hostile_params)
def test_hostile_boxes_and_parameters_are_answered_quickly(live_server, lo, size, params):
    """Neighbours of the review's findings (vanishing boxes, parameters at and past their
    limits): every answer is a 200 or a documented refusal (422, 429, 503), never a 500, and
    within seconds: a computation the deadline cannot hold is refused or stopped."""
    box = [list(lo), [a + b for a, b in zip(lo, size, strict=True)]]
    t0 = time.monotonic()
    r = httpx.post(live_server + "/scenes/tiny/pvs", params={"deadline": 2},
                   json={"box": box, "params": params}, timeout=60)
    assert r.status_code in (200, 422, 429, 503), r.text
    assert time.monotonic() - t0 < 15
    if r.status_code != 200:
        assert r.json()["error"]["code"] in (
            "validation", "bad_params", "over_limit", "unsupported_region",
            "too_many_requests", "busy", "deadline_exceeded")


# --------------------------------------------------------------------------- a protected server
#: The protected server's tokens: one with every scene, one limited to "tiny".
TOKEN = "fuzz-token-0123456789abcdef"
LIMITED = "fuzz-limited-0123456789abc"
#: Fewer schemathesis examples per operation than on the open server: the same routes.
PROTECTED_EXAMPLES = 10
#: Protected routes the header fuzz picks from (method, path, JSON body).
PROTECTED_ROUTES = [("GET", "/scenes", None), ("GET", "/scenes/tiny", None),
                    ("GET", "/scenes/tiny/cells", None), ("GET", "/cores", None),
                    ("GET", "/metrics", None), ("GET", "/scenes/tiny/cells/0/pvs", None),
                    ("POST", "/scenes/tiny/pvs", {"box": [[1, 1, 1], [2, 2, 2]]}),
                    ("GET", "/no/such/route", None)]


@pytest.fixture(scope="module")
def protected_server(settings, registered_test_cores, tmp_path_factory):
    """The real server with access control: TOKEN (every scene, as PVS_TOKENS gives) and
    LIMITED (a tokens file: "tiny" only); yields its base URL."""
    path = tmp_path_factory.mktemp("fuzz_auth") / "tokens.json"
    path.write_text(json.dumps({"tokens": {LIMITED: {"scenes": ["tiny"]}}}))
    with serving(settings, scenes={"tiny": make_tiny_scene(), "tiny_far": make_tiny_scene(1e5)},
                 tokens=[TOKEN], tokens_file=str(path)) as (url, _):
        yield url


#: What a header value can be on the wire (h11 refuses the rest before it is sent): visible
#: ASCII and obs-text, inner spaces and tabs.
header_values = st.from_regex(
    rb"\A[\x21-\x7e\x80-\xff]([\x20-\x7e\x80-\xff\t]{0,80}[\x21-\x7e\x80-\xff])?\Z")


@st.composite
def near_tokens(draw) -> str:
    """A valid token with one character replaced, inserted or removed, or cut short."""
    t = list(draw(st.sampled_from([TOKEN, LIMITED])))
    i = draw(st.integers(0, len(t) - 1))
    action = draw(st.sampled_from(["replace", "insert", "remove", "cut"]))
    c = draw(st.characters(min_codepoint=0x21, max_codepoint=0x7e))
    if action == "replace":
        t[i] = c
    elif action == "insert":
        t.insert(i, c)
    elif action == "remove":
        del t[i]
    else:
        # At least one character: "Bearer " with nothing after it ends in a space, which no
        # HTTP client sends (h11 refuses the header; hypothesis found it).
        t = t[:max(i, 1)]
    return "".join(t)


authorizations = st.one_of(
    header_values,
    near_tokens().map(lambda t: f"Bearer {t}".encode()),
    st.tuples(st.sampled_from([b"Bearer", b"bearer", b"Basic", b"Token", b"Bearer\t"]),
              header_values).map(lambda p: p[0] + b" " + p[1]),
)


@FUZZ
@given(route=st.sampled_from(PROTECTED_ROUTES), value=authorizations)
def test_malformed_authorization_is_401_on_every_protected_route(protected_server, route,
                                                                 value):
    """Whatever the Authorization header holds, a protected route answers 401 with the JSON
    error body and a Bearer challenge, or (the rare mutation that is still a known token) the
    route's own answer; never a 5xx, and the server lives."""
    method, path, body = route
    r = httpx.request(method, protected_server + path, json=body, timeout=60,
                      headers={"Authorization": value})
    scheme, _, token = value.decode("latin-1").strip().partition(" ")
    if scheme.lower() == "bearer" and token.strip() in (TOKEN, LIMITED):
        assert r.status_code < 500
    else:
        assert r.status_code == 401, (value, r.status_code, r.text)
        assert r.headers["www-authenticate"].startswith('Bearer realm="pvs"')
        assert r.json()["error"]["code"] == "unauthorized"
    assert httpx.get(protected_server + "/health", timeout=30).status_code == 200


subprotocol_tokens = st.one_of(
    near_tokens(), st.text(alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7e,
                                                  exclude_characters='()<>@,;:\\"/[]?={}'),
                           max_size=40))


@FUZZ
@given(value=st.one_of(authorizations.map(lambda v: ("header", v)),
                       subprotocol_tokens.map(lambda v: ("subprotocol", v))))
def test_ws_malformed_credentials_close_with_4401(protected_server, value):
    """A WebSocket whose credential is not a known token, by header or subprotocol, gets the
    ``unauthorized`` error and the 4401 close, whatever it sends; never 1011."""
    how, v = value
    if how == "header":
        kw = {"additional_headers": {"Authorization": v.decode("latin-1")}}
        scheme, _, token = kw["additional_headers"]["Authorization"].strip().partition(" ")
        known = scheme.lower() == "bearer" and token.strip() in (TOKEN, LIMITED)
    else:
        kw = {"subprotocols": [SUBPROTOCOL, TOKEN_SUBPROTOCOL_PREFIX + v]}
        known = v in (TOKEN, LIMITED)
        try:  # a name the client library itself refuses to send (e.g. a ':' from near_tokens)
            validate_subprotocols(kw["subprotocols"])
        except ValueError:
            return
    url = protected_server.replace("http://", "ws://") + "/ws"
    try:
        got = asyncio.run(asyncio.wait_for(_exchange(url, True, [], **kw), 60))
    except websockets.InvalidHandshake:  # a value the client library itself will not send
        return
    close = got[-1][1]
    assert close != 1011
    if not known:
        assert close == 4401, (value, got)
        assert [p.code for k, p in got if k == "text"] == ["unauthorized"]
    assert httpx.get(protected_server + "/health", timeout=30).status_code == 200


@FUZZ
@given(first_hello=st.booleans(), frames=st.lists(client_frames, min_size=1, max_size=3))
def test_protocol_fuzz_with_a_token_never_crashes_the_server(protected_server, first_hello,
                                                             frames):
    """The protocol fuzz above, on the protected server with the limited token: its sessions
    get past the token check, so every message reaches the protocol's own checks."""
    url = protected_server.replace("http://", "ws://") + "/ws"
    got = asyncio.run(asyncio.wait_for(_exchange(
        url, first_hello, frames, additional_headers={"Authorization": f"Bearer {LIMITED}"}),
        60))
    for kind, payload in got:
        if kind == "text" and payload.type == "error":
            assert payload.code not in ("internal", "unauthorized"), payload.message
        if kind == "close":
            assert payload not in (1011, 4401)
    assert httpx.get(protected_server + "/health", timeout=30).status_code == 200


def test_openapi_fuzz_protected(protected_server):
    """The OpenAPI fuzz on the protected server with a token: its schema documents the 401
    and 403 its operations can answer, and every answer conforms."""
    statuses = _openapi_fuzz(protected_server, PROTECTED_EXAMPLES,
                             {"Authorization": f"Bearer {LIMITED}"})
    # The token was sent and taken: answers, and 403s for scenes outside its list (generated
    # names), documented; no 401.
    assert statuses[200] > 0 and statuses[403] > 0 and statuses[401] == 0, statuses
