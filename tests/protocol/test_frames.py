"""Binary geometry frames: documented layout, round trips, chunking, malformed input."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.frames import (
    HEADER_BYTES,
    MAGIC,
    TRIANGLE_BYTES,
    FrameError,
    FrameKind,
    chunk_count,
    chunk_geometry,
    decode_geometry,
    encode_geometry,
    frame_bytes,
    triangles_per_frame,
)
from protocol.version import PROTOCOL_VERSION


def _tris(n: int, seed: int = 0, offset: float = 0.0, extent: float = 50.0):
    rng = np.random.default_rng(seed)
    ids = rng.choice(10 * n + 10, size=n, replace=False).astype(np.int64)
    tris = rng.uniform(-extent, extent, size=(n, 3, 3)) + offset
    cols = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    return ids, tris, cols


def test_layout_matches_the_documented_offsets():
    ids, tris, cols = _tris(2)
    data = encode_geometry(ids, tris, cols, cell=7, seq=9, index=1, count=3, origin=[1, 2, 3])
    assert HEADER_BYTES == 56 and TRIANGLE_BYTES == 43
    assert len(data) == frame_bytes(2) == 56 + 43 * 2
    assert data[0:4] == MAGIC == b"PVSG"
    assert struct.unpack_from("<H", data, 4)[0] == PROTOCOL_VERSION
    assert data[6] == FrameKind.GEOMETRY == 1 and data[7] == 0
    assert struct.unpack_from("<iIIII", data, 8) == (7, 9, 1, 3, 2)
    assert struct.unpack_from("<I", data, 28)[0] == 0
    assert struct.unpack_from("<3d", data, 32) == (1.0, 2.0, 3.0)
    assert list(struct.unpack_from("<2i", data, 56)) == ids.tolist()
    rel = np.frombuffer(data, "<f4", 18, 64).reshape(2, 3, 3)
    np.testing.assert_allclose(rel + [1, 2, 3], tris, atol=1e-4)
    assert np.frombuffer(data, np.uint8, 6, 56 + 40 * 2).reshape(2, 3).tolist() == cols.tolist()


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 60), seed=st.integers(0, 2**31),
       offset=st.sampled_from([0.0, -1e3, 1e5, 3.7e6]), cell=st.integers(-1, 2**31 - 1),
       seq=st.integers(0, 2**32 - 1))
def test_round_trip(n, seed, offset, cell, seq):
    ids, tris, cols = _tris(n, seed, offset)
    data = encode_geometry(ids, tris, cols, cell=cell, seq=seq, index=0, count=1)
    assert len(data) == frame_bytes(n)
    chunk = decode_geometry(data)
    assert (chunk.cell, chunk.seq, chunk.index, chunk.count, len(chunk)) == (cell, seq, 0, 1, n)
    assert chunk.ids.dtype == np.int32 and chunk.ids.tolist() == ids.tolist()
    assert chunk.colors.dtype == np.uint8 and np.array_equal(chunk.colors, cols)
    assert chunk.positions.dtype == np.float32 and chunk.positions.shape == (n, 3, 3)
    # Offsets from the chunk centre are at most the half extent (50 m): float32 keeps them to
    # ~50 * 2**-24 = 3e-6 m, however far from the world origin the scene is.
    out = chunk.triangles
    assert out.dtype == np.float64
    np.testing.assert_allclose(out, tris, rtol=0, atol=1e-5)


def test_far_offset_precision_beats_plain_float32():
    ids, tris, cols = _tris(50, 1, offset=1e5, extent=2.0)
    out = decode_geometry(encode_geometry(ids, tris, cols)).triangles
    err = np.abs(out - tris).max()
    plain = np.abs(tris.astype(np.float32).astype(np.float64) - tris).max()
    assert err < 1e-6 < plain  # float32 at 1e5 m only resolves ~4 mm


def test_chunking_respects_the_limit_and_keeps_everything():
    ids, tris, cols = _tris(1000, 3)
    limit = 4096
    frames = list(chunk_geometry(ids, tris, cols, cell=4, seq=11, max_frame_bytes=limit))
    per = triangles_per_frame(limit)
    assert per == (limit - 56) // 43
    assert len(frames) == chunk_count(1000, limit) == -(-1000 // per)
    assert all(len(f) <= limit for f in frames)
    chunks = [decode_geometry(f) for f in frames]
    assert [c.index for c in chunks] == list(range(len(frames)))
    assert {c.count for c in chunks} == {len(frames)} and {c.cell for c in chunks} == {4}
    assert np.concatenate([c.ids for c in chunks]).tolist() == ids.tolist()
    np.testing.assert_array_equal(np.concatenate([c.colors for c in chunks]), cols)
    np.testing.assert_allclose(np.concatenate([c.triangles for c in chunks]), tris, atol=1e-5)


def test_chunking_default_limit_and_empty():
    ids, tris, cols = _tris(30000, 4)
    frames = list(chunk_geometry(ids, tris, cols))
    assert len(frames) == 2 and all(len(f) <= 1 << 20 for f in frames)
    assert list(chunk_geometry(ids[:0], tris[:0], cols[:0])) == []
    assert chunk_count(0) == 0
    with pytest.raises(ValueError, match="cannot hold one triangle"):
        triangles_per_frame(HEADER_BYTES + TRIANGLE_BYTES - 1)
    with pytest.raises(ValueError):
        list(chunk_geometry(ids, tris[:5], cols))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"ids": [-1]}, "ids"),
        ({"ids": [2**31]}, "ids"),
        ({"ids": [0.5]}, "integers"),
        ({"triangles": np.full((1, 3, 3), np.nan)}, "finite"),
        ({"triangles": np.zeros((1, 3))}, r"\(1, 3, 3\)"),
        ({"colors": np.zeros((1, 4), np.uint8)}, r"\(1, 3\)"),
        ({"colors": [[0, 0, 256]]}, "uint8"),
        ({"index": 2, "count": 2}, "index"),
        ({"cell": 2**31}, "int32"),
        ({"seq": -1}, "uint32"),
        ({"triangles": np.full((1, 3, 3), 1e39)}, "float32"),
    ],
)
def test_encode_rejects_bad_input(kwargs, match):
    args = {"ids": [1], "triangles": np.zeros((1, 3, 3)), "colors": [[1, 2, 3]]}
    args.update(kwargs)
    ids, tris, cols = args.pop("ids"), args.pop("triangles"), args.pop("colors")
    if "origin" not in args and np.all(np.isfinite(tris)) and np.abs(tris).max() > 1e38:
        args["origin"] = [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=match):
        encode_geometry(np.asarray(ids), tris, cols, **args)


def _good() -> bytes:
    ids, tris, cols = _tris(3, 5)
    return encode_geometry(ids, tris, cols, cell=1, seq=2)


def _patch(data: bytes, offset: int, fmt: str, *values) -> bytes:
    b = bytearray(data)
    struct.pack_into(fmt, b, offset, *values)
    return bytes(b)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d[:10], "too short"),
        (lambda d: b"", "too short"),
        (lambda d: d[:-1], "must be"),
        (lambda d: d + b"\0", "must be"),
        (lambda d: b"XXXX" + d[4:], "magic"),
        (lambda d: _patch(d, 4, "<H", PROTOCOL_VERSION + 1), "version"),
        (lambda d: _patch(d, 6, "<B", 9), "kind"),
        (lambda d: _patch(d, 7, "<B", 1), "reserved"),
        (lambda d: _patch(d, 28, "<I", 5), "reserved"),
        (lambda d: _patch(d, 16, "<II", 1, 1), "out of range"),
        (lambda d: _patch(d, 20, "<I", 0), "out of range"),
        (lambda d: _patch(d, 24, "<I", 4), "must be"),
        (lambda d: _patch(d, 24, "<I", 2**32 - 1), "must be"),
        (lambda d: _patch(d, 32, "<d", float("inf")), "origin"),
        (lambda d: _patch(d, 56 + 12, "<f", float("nan")), "non-finite"),
        (lambda d: _patch(d, 56, "<i", -5), "negative"),
    ],
)
def test_decode_rejects_malformed(mutate, match):
    decode_geometry(_good())  # the unmutated frame is fine
    with pytest.raises(FrameError, match=match):
        decode_geometry(mutate(_good()))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400))
def test_random_bytes_only_raise_frame_error(data):
    try:
        decode_geometry(data)
    except FrameError:
        pass


@settings(max_examples=100, deadline=None)
@given(cut=st.integers(0, 56 + 43 * 3 - 1))
def test_every_truncation_is_detected(cut):
    with pytest.raises(FrameError):
        decode_geometry(_good()[:cut])


def test_decode_accepts_bytearray_and_memoryview():
    data = _good()
    a = decode_geometry(bytearray(data))
    b = decode_geometry(memoryview(data))
    assert a.ids.tolist() == b.ids.tolist() == decode_geometry(data).ids.tolist()
