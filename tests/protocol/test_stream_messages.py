"""Messages added for delta streams, prefetch and near-far: drop, prefetch/partial flags,
welcome features, segment requests, the slow-client code."""

from __future__ import annotations

import pytest

from protocol.codes import CloseCode, ErrorCode, close_code_for, is_fatal
from protocol.messages import (
    BoxPvsRequest,
    CellBegin,
    CellEnd,
    Drop,
    Hello,
    ProtocolError,
    dump_message,
    parse_client_message,
    parse_server_message,
)


def test_drop_round_trip_and_validation():
    d = Drop(ids=[3, 1, 2], cells=[4])
    back = parse_server_message(dump_message(d))
    assert isinstance(back, Drop) and back.ids == [3, 1, 2] and back.cells == [4]
    with pytest.raises(ProtocolError):
        parse_server_message('{"type": "drop", "ids": [-1]}')
    with pytest.raises(ProtocolError):
        parse_server_message('{"type": "drop", "ids": ["1"]}')


def test_prefetch_partial_and_near_far_fields():
    b = CellBegin(cell=1, seq=2, triangles=3, new=3, chunks=1, prefetch=True,
                  near_far={"r1": 40.0, "r2": 80.0, "center": [0, 1, 2], "cubemap": True})
    assert parse_server_message(dump_message(b)) == b
    e = CellEnd(cell=1, seq=2, seconds=0.1, partial=True, prefetch=True)
    assert parse_server_message(dump_message(e)).partial
    # Defaults keep older messages valid.
    assert not parse_server_message(
        '{"type": "cell_end", "cell": 1, "seq": 0, "seconds": 0}').partial


def test_hello_prefetch_flag():
    assert parse_client_message(dump_message(Hello(scene="s", prefetch=False))).prefetch is False
    assert Hello(scene="s").prefetch is None
    with pytest.raises(ProtocolError):
        parse_client_message('{"type": "hello", "scene": "s", "prefetch": "yes"}')


def test_segment_request():
    r = BoxPvsRequest(segment=((3, 1, 0), (1, 1, 2)))
    assert r.region() == ((1, 1, 0), (3, 1, 2))
    assert BoxPvsRequest(box=((0, 0, 0), (1, 1, 1))).region() == ((0, 0, 0), (1, 1, 1))
    for bad in ({}, {"box": ((0, 0, 0), (1, 1, 1)), "segment": ((0, 0, 0), (1, 1, 1))}):
        with pytest.raises(ValueError):
            BoxPvsRequest(**bad)


def test_slow_client_code():
    assert is_fatal(ErrorCode.SLOW_CLIENT)
    assert close_code_for(ErrorCode.SLOW_CLIENT) == CloseCode.SLOW_CLIENT == 4008
