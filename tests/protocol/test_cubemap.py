"""Cubemap frames: layout, range precision, malformed input."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from protocol.cubemap import (
    HEADER_BYTES,
    MAX_RELATIVE_ERROR,
    decode_cubemap,
    encode_cubemap,
    payload_bytes,
    range_precision,
)
from protocol.frames import FrameError, FrameKind, encode_geometry

C = np.array([10.0, 1.7, -3.0])


def _cube(res: int = 16, seed: int = 0, lo: float = 0.05, hi: float = 1e4):
    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, size=(6, res, res, 3), dtype=np.uint8)
    ranges = np.exp(rng.uniform(np.log(lo), np.log(hi), size=(6, res, res))).astype(np.float32)
    ranges[rng.random(ranges.shape) < 0.2] = np.inf
    return colors, ranges


@pytest.mark.parametrize("compress", [True, False])
def test_round_trip_within_stated_precision(compress):
    colors, ranges = _cube()
    data = encode_cubemap(3, C, colors, ranges, 50.0, 100.0, compress=compress)
    assert data[:4] == b"PVSG" and data[6] == FrameKind.CUBEMAP
    if not compress:
        assert len(data) == HEADER_BYTES + payload_bytes(16)
    f = decode_cubemap(data)
    assert f.cell == 3 and np.array_equal(f.center, C) and (f.r1, f.r2) == (50.0, 100.0)
    assert f.resolution == 16 and np.array_equal(f.colors, colors)
    assert np.array_equal(np.isinf(f.ranges), np.isinf(ranges))
    hit = np.isfinite(ranges)
    err = np.abs(f.ranges[hit].astype(np.float64) / ranges[hit] - 1.0)
    assert f.precision <= MAX_RELATIVE_ERROR < 1.25e-4
    assert err.max() <= f.precision
    # The bound is not loose by much: the worst error is at least a third of it.
    assert err.max() > f.precision / 3


def test_precision_tightens_with_a_narrow_range_span():
    colors, ranges = _cube(lo=40.0, hi=700.0)
    f = decode_cubemap(encode_cubemap(0, C, colors, ranges, 50.0, 100.0))
    assert f.precision == pytest.approx(range_precision(f.range_lo, f.range_hi))
    assert f.precision < 2.5e-5
    hit = np.isfinite(ranges)
    assert np.max(np.abs(f.ranges[hit] / ranges[hit] - 1.0)) <= f.precision


def test_constant_and_empty_ranges():
    colors, _ = _cube(8)
    const = np.full((6, 8, 8), 123.5, dtype=np.float32)
    assert np.all(decode_cubemap(encode_cubemap(0, C, colors, const, 1, 2)).ranges == 123.5)
    empty = np.full((6, 8, 8), np.inf, dtype=np.float32)
    f = decode_cubemap(encode_cubemap(-1, C, colors, empty, 1, 2))
    assert np.all(np.isinf(f.ranges)) and f.precision == 0.0 and f.cell == -1


def test_encode_rejects_bad_input():
    colors, ranges = _cube(8)
    bad = [
        dict(colors=colors[:5]),
        dict(colors=colors.astype(np.int16)),
        dict(ranges=ranges[:, :4]),
        dict(ranges=np.where(np.isinf(ranges), -1.0, ranges)),
        dict(ranges=np.where(np.isinf(ranges), np.nan, ranges)),
        dict(center=[0.0, np.nan, 0.0]),
        dict(r1=5.0, r2=4.0),
        dict(cell=2**31),
    ]
    for kw in bad:
        args = dict(cell=0, center=C, colors=colors, ranges=ranges, r1=1.0, r2=2.0) | kw
        with pytest.raises(ValueError):
            encode_cubemap(**args)


def test_decode_rejects_malformed_frames():
    colors, ranges = _cube(8)
    good = encode_cubemap(0, C, colors, ranges, 1.0, 2.0)
    raw = encode_cubemap(0, C, colors, ranges, 1.0, 2.0, compress=False)
    header = bytearray(good[:HEADER_BYTES])

    def patched(fmt: str, offset: int, value) -> bytes:
        h = bytearray(header)
        struct.pack_into(fmt, h, offset, value)
        return bytes(h) + good[HEADER_BYTES:]

    bad = [
        b"",
        good[:HEADER_BYTES - 1],
        good[:-1],
        good + b"\0",
        raw[:-2],
        b"XXXX" + good[4:],
        patched("<H", 4, 999),  # version
        patched("<B", 7, 2),  # unknown flag
        patched("<I", 12, 0),  # resolution 0
        patched("<I", 12, 4096),  # resolution too large
        patched("<I", 12, 9),  # resolution disagreeing with the payload
        patched("<d", 16, float("nan")),  # centre
        patched("<d", 40, 3.0),  # r1 > r2
        patched("<d", 56, -1.0),  # range_lo
        patched("<I", 76, 1),  # reserved
        good[:HEADER_BYTES] + b"\x78\x9c" + b"\xff" * (len(good) - HEADER_BYTES - 2),
        encode_geometry(np.arange(2), np.zeros((2, 3, 3)) + [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                        np.zeros((2, 3), np.uint8)),
    ]
    for data in bad:
        with pytest.raises(FrameError):
            decode_cubemap(data)
    # A payload that inflates beyond the announced size is refused without inflating it all.
    bomb = zlib.compress(b"\0" * (payload_bytes(8) * 50))
    h = bytearray(header)
    struct.pack_into("<I", h, 72, len(bomb))
    with pytest.raises(FrameError):
        decode_cubemap(bytes(h) + bomb)
