"""Fuzzing against the live server: hypothesis on the WebSocket protocol (random and mutated
messages), schemathesis on the OpenAPI spec. Never a 500, never an ``internal`` error, never a
dead server. Bounded: a few dozen examples each."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.asyncio.client import connect

from protocol.frames import FrameError, decode_geometry, encode_geometry
from protocol.messages import Hello, Pose, dump_message, parse_server_message

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


async def _exchange(url: str, first_hello: bool, frames: list) -> list:
    """Open a session (with a valid hello or not), send ``frames``, collect what comes back
    for a short while; returns [(kind, payload)] with the close code last."""
    out = []
    async with connect(url, open_timeout=30, compression=None, max_size=None) as ws:
        try:
            if first_hello:
                await ws.send(dump_message(Hello(scene="tiny", core="test_near",
                                                 params={"radius": 3.0})))
            for f in frames:
                await ws.send(f)
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
    schema = schemathesis.openapi.from_url(live_server + "/openapi.json")
    for result in schema.get_all_operations():
        op = result.ok()

        @settings(max_examples=OPENAPI_EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=op.as_strategy())
        def check(case):
            # Every default check but "schema-valid data is accepted": the schema cannot say
            # that a box's max must not be below its min, nor which core parameters a core
            # takes (the core checks them: 422, documented).
            case.call_and_validate(
                timeout=60, excluded_checks=[schemathesis.checks.positive_data_acceptance])

        check()


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
