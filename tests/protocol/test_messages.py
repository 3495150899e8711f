"""JSON message schemas: round trips, strictness, NaN rejection, error codes."""

from __future__ import annotations

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from protocol.codes import FATAL, CloseCode, ErrorCode, close_code_for, is_fatal
from protocol.ints import INT32_MAX, UINT16_MAX, UINT32_MAX
from protocol.messages import (
    BoxPvsRequest,
    Bye,
    CellBegin,
    CellEnd,
    Drop,
    Error,
    GridInfo,
    Hello,
    Limits,
    Pose,
    ProtocolError,
    SceneInfo,
    Welcome,
    dump_message,
    parse_client_message,
    parse_server_message,
)
from protocol.version import PROTOCOL_VERSION

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
vec3 = st.tuples(finite, finite, finite)
u32 = st.integers(min_value=0, max_value=2**32 - 1)
id32 = st.integers(min_value=0, max_value=2**31 - 1)
names = st.text(min_size=1, max_size=40)
param_values = st.one_of(st.booleans(), st.integers(-(2**40), 2**40), finite, st.text(max_size=10),
                         st.none())


def _pose_json(**overrides) -> str:
    d = {"type": "pose", "seq": 3, "t": 0.5, "position": [1.0, 1.7, 2.0],
         "forward": [0.0, 0.0, -1.0]}
    d.update(overrides)
    return json.dumps(d)


@settings(max_examples=30, deadline=None)
@given(seq=u32, t=finite, position=vec3, forward=vec3,
       velocity=st.one_of(st.none(), vec3))
def test_pose_round_trip(seq, t, position, forward, velocity):
    pose = Pose(seq=seq, t=t, position=position, forward=forward, velocity=velocity)
    back = parse_client_message(dump_message(pose))
    assert back == pose
    assert back.position == position  # floats survive JSON exactly


@settings(max_examples=40, deadline=None)
@given(scene=names, core=names, params=st.dictionaries(st.text(max_size=12), param_values,
                                                       max_size=5),
       budget=st.one_of(st.none(), st.integers(1, 10**9)))
def test_hello_round_trip(scene, core, params, budget):
    hello = Hello(scene=scene, core=core, params=params, budget=budget)
    assert parse_client_message(dump_message(hello)) == hello


@settings(max_examples=40, deadline=None)
@given(cell=id32, seq=u32, n=id32, new=id32, chunks=u32, seconds=finite, cached=st.booleans(),
       code=st.sampled_from(list(ErrorCode)), message=st.text(max_size=50))
def test_server_messages_round_trip(cell, seq, n, new, chunks, seconds, cached, code, message):
    for msg in (
        CellBegin(cell=cell, seq=seq, triangles=n, new=new, chunks=chunks),
        CellEnd(cell=cell, seq=seq, seconds=seconds, compute_seconds=seconds, cached=cached),
        Error(code=code, message=message, fatal=is_fatal(code), seq=seq),
    ):
        assert parse_server_message(dump_message(msg)) == msg


def _welcome() -> Welcome:
    return Welcome(
        session="abc",
        scene=SceneInfo(name="tiny", kind="memory", triangles=10, valid_triangles=9, vertices=30,
                        objects=2, bounds=((0, 0, 0), (1, 2, 3)), degenerate={"zero_area": 1}),
        grid=GridInfo(cell_size=4.0, origin_xz=(0, 0), cells=8, levels=1, eye_range=(1.5, 1.9),
                      bounds=((0, 1.5, 0), (16, 1.9, 8))),
        core="sampling", params={"resolution": 32, "granularity": "triangle"}, budget=None,
        limits=Limits(max_frame_bytes=1 << 20, max_message_bytes=65536), near_plane=0.05,
    )


def test_welcome_round_trip_and_version():
    w = _welcome()
    text = dump_message(w)
    assert json.loads(text)["version"] == PROTOCOL_VERSION
    assert parse_server_message(text) == w


@pytest.mark.parametrize("near", [0, -0.05, "0.05", None, float("inf"), "missing"])
def test_welcome_near_plane_is_a_required_positive_distance(near):
    d = json.loads(dump_message(_welcome()))
    if near == "missing":
        del d["near_plane"]
    else:
        d["near_plane"] = near
    with pytest.raises(ProtocolError, match="near_plane"):
        parse_server_message(json.dumps(d).replace("Infinity", "1e999"))


def test_bye_round_trip():
    assert parse_client_message(dump_message(Bye())) == Bye()
    assert parse_client_message('{"type": "bye", "reason": "done"}').reason == "done"


@pytest.mark.parametrize("bad", ["NaN", "Infinity", "-Infinity"])
@pytest.mark.parametrize("field", ["position", "forward", "velocity"])
def test_non_finite_pose_rejected(bad, field):
    text = _pose_json().replace("}", f', "{field}": [0, {bad}, 0]}}') if field == "velocity" \
        else _pose_json(**{field: [0.0, 0.0, 0.0]}).replace("[0.0, 0.0, 0.0]", f"[0, {bad}, 0]")
    with pytest.raises(ProtocolError) as exc:
        parse_client_message(text)
    assert exc.value.code == ErrorCode.INVALID_POSE
    assert exc.value.seq == 3
    assert "finite" in exc.value.message


def test_non_finite_t_rejected_and_python_construction_too():
    with pytest.raises(ProtocolError):
        parse_client_message(_pose_json().replace('"t": 0.5', '"t": NaN'))
    with pytest.raises(ValidationError):
        Pose(seq=0, t=0.0, position=(math.inf, 0, 0), forward=(0, 0, 1))


@pytest.mark.parametrize(
    "text, code",
    [
        ("not json", ErrorCode.BAD_JSON),
        ('{"type": "pose",', ErrorCode.BAD_JSON),
        ("[1, 2, 3]", ErrorCode.BAD_JSON),
        ('"hello"', ErrorCode.BAD_JSON),
        ("1" * 5000, ErrorCode.BAD_JSON),  # over Python's int-digit limit
        ("[" * 100000, ErrorCode.BAD_JSON),  # nesting beyond the recursion limit
        ('{"seq": 1}', ErrorCode.INVALID_MESSAGE),
        ('{"type": 7}', ErrorCode.INVALID_MESSAGE),
        ('{"type": "teleport"}', ErrorCode.UNKNOWN_TYPE),
        ('{"type": "welcome"}', ErrorCode.UNKNOWN_TYPE),  # a server type from a client
        ('{"type": "hello"}', ErrorCode.INVALID_HELLO),  # scene missing
        ('{"type": "hello", "scene": "a", "colour": "red"}', ErrorCode.INVALID_HELLO),
        ('{"type": "hello", "scene": "a", "budget": 0}', ErrorCode.INVALID_HELLO),
        ('{"type": "hello", "scene": "a", "version": "1"}', ErrorCode.INVALID_HELLO),
        ('{"type": "hello", "scene": ""}', ErrorCode.INVALID_HELLO),
        ('{"type": "bye", "extra": 1}', ErrorCode.INVALID_MESSAGE),
    ],
)
def test_client_parse_errors_have_codes(text, code):
    with pytest.raises(ProtocolError) as exc:
        parse_client_message(text)
    assert exc.value.code == code


@pytest.mark.parametrize(
    "overrides",
    [
        {"seq": "3"},  # strings are not numbers
        {"seq": True},  # nor are booleans
        {"seq": -1},
        {"seq": 1.5},
        {"t": "0.5"},
        {"position": [1, 2]},
        {"position": [1, 2, 3, 4]},
        {"position": "1,2,3"},
        {"forward": None},
        {"unknown": 1},
    ],
)
def test_pose_is_strict(overrides):
    with pytest.raises(ProtocolError) as exc:
        parse_client_message(_pose_json(**overrides))
    assert exc.value.code == ErrorCode.INVALID_POSE


def test_pose_accepts_integers_for_floats():
    pose = parse_client_message(_pose_json(position=[1, 2, 3], t=4))
    assert pose.position == (1.0, 2.0, 3.0) and pose.t == 4.0


def test_server_parse_rejects_client_types_and_unknown_fields():
    with pytest.raises(ProtocolError) as exc:
        parse_server_message(dump_message(Bye()))
    assert exc.value.code == ErrorCode.UNKNOWN_TYPE
    d = json.loads(dump_message(CellBegin(cell=1, seq=2, triangles=3, new=3, chunks=1)))
    d["surprise"] = True
    with pytest.raises(ProtocolError) as exc:
        parse_server_message(json.dumps(d))
    assert exc.value.code == ErrorCode.INVALID_MESSAGE


@settings(max_examples=100, deadline=None)
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_garbage_only_raises_protocol_error(data):
    for parse in (parse_client_message, parse_server_message):
        try:
            parse(data)
        except ProtocolError as exc:
            assert isinstance(exc.code, ErrorCode)


@settings(max_examples=60, deadline=None)
@given(st.dictionaries(st.sampled_from(["type", "seq", "t", "position", "forward", "scene",
                                        "velocity", "x"]),
                       st.one_of(st.sampled_from(["pose", "hello", "bye", "nope"]), finite,
                                 st.integers(), st.lists(finite, max_size=4), st.none()),
                       max_size=6))
def test_random_objects_only_raise_protocol_error(obj):
    try:
        msg = parse_client_message(json.dumps(obj))
    except ProtocolError:
        return
    assert msg.type in ("pose", "hello", "bye")


def test_box_request_validation():
    ok = BoxPvsRequest(box=((0, 0, 0), (1, 2, 3)))
    assert ok.box[1] == (1.0, 2.0, 3.0) and ok.core is None and ok.params == {}
    BoxPvsRequest(box=((1, 1, 1), (1, 1, 1)))  # a point is a valid (degenerate) box
    with pytest.raises(ValidationError, match="max < min"):
        BoxPvsRequest(box=((0, 0, 0), (1, -1, 1)))
    with pytest.raises(ValidationError):
        BoxPvsRequest(box=((0, 0, math.nan), (1, 1, 1)))
    with pytest.raises(ValidationError):
        BoxPvsRequest.model_validate({"box": [[0, 0, 0], [1, 1, 1]], "extra": 1})


def test_codes_table():
    for code, close in FATAL.items():
        assert is_fatal(code)
        assert close_code_for(code) == close
        assert close in (1001, 1003, 1008, 1009, 1011) or 4000 <= close <= 4999
    for code in (ErrorCode.OUTSIDE_GRID, ErrorCode.INVALID_POSE, ErrorCode.UNKNOWN_TYPE,
                 ErrorCode.COMPUTE_FAILED):
        assert not is_fatal(code)
        assert close_code_for(code) == CloseCode.NORMAL
    assert close_code_for("too_big") == 1009
    assert close_code_for("binary_unsupported") == 1003
    with pytest.raises(ValueError):
        is_fatal("no_such_code")


# --------------------------------------------------------------------------- wire integer bounds
@pytest.mark.parametrize("seq", [UINT32_MAX + 1, 2**64, 10**30, -1])
def test_pose_seq_past_uint32_is_an_invalid_pose(seq):
    # Frames carry seq in a uint32 header field: a larger one is refused here, not by the
    # encoder, and the error names no seq (the wire could not carry it either).
    with pytest.raises(ProtocolError) as exc:
        parse_client_message(_pose_json(seq=seq))
    assert exc.value.code == ErrorCode.INVALID_POSE
    assert exc.value.seq is None
    assert "seq" in exc.value.message


def test_pose_seq_bounds_are_inclusive():
    assert parse_client_message(_pose_json(seq=0)).seq == 0
    assert parse_client_message(_pose_json(seq=UINT32_MAX)).seq == UINT32_MAX


@pytest.mark.parametrize("field, value", [
    ("budget", UINT32_MAX + 1), ("budget", -1), ("version", UINT16_MAX + 1), ("version", -1),
    ("params", {"seed": 2**63}), ("params", {"resolution": -(2**63) - 1}),
    ("params", {"list": [1, 2**70]}),
])
def test_hello_integers_past_the_wire_are_invalid(field, value):
    text = json.dumps({"type": "hello", "scene": "s", field: value})
    with pytest.raises(ProtocolError) as exc:
        parse_client_message(text)
    assert exc.value.code == ErrorCode.INVALID_HELLO


def test_hello_integers_at_the_bounds_are_valid():
    hello = parse_client_message(json.dumps({
        "type": "hello", "scene": "s", "budget": UINT32_MAX, "version": UINT16_MAX,
        "params": {"seed": UINT32_MAX, "big": 2**63 - 1, "small": -(2**63)}}))
    assert hello.budget == UINT32_MAX and hello.params["small"] == -(2**63)


@pytest.mark.parametrize("message", [
    {"type": "cell_begin", "cell": INT32_MAX + 1, "seq": 0, "triangles": 0, "new": 0,
     "chunks": 0},
    {"type": "cell_begin", "cell": 0, "seq": UINT32_MAX + 1, "triangles": 0, "new": 0,
     "chunks": 0},
    {"type": "cell_begin", "cell": 0, "seq": 0, "triangles": 2**31 + 1, "new": 0, "chunks": 0},
    {"type": "cell_end", "cell": 0, "seq": 2**64, "seconds": 0},
    {"type": "drop", "ids": [INT32_MAX + 1]},
    {"type": "drop", "ids": [0], "cells": [2**40]},
    {"type": "error", "code": "x", "message": "", "seq": UINT32_MAX + 1},
])
def test_server_integers_past_the_wire_are_invalid(message):
    # A client meets a hostile server's numbers at the same edge.
    with pytest.raises(ProtocolError) as exc:
        parse_server_message(json.dumps(message))
    assert exc.value.code == ErrorCode.INVALID_MESSAGE


def test_server_integers_at_the_bounds_are_valid():
    d = Drop(ids=[0, INT32_MAX], cells=[INT32_MAX])
    assert parse_server_message(dump_message(d)) == d
    e = Error(code="x", message="", seq=UINT32_MAX)
    assert parse_server_message(dump_message(e)) == e
