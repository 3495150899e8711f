"""Keyframe and sphere frames: documented layout, round trips, chunking (with keyframe windows),
the client-side assembler, malformed input."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.frames import MAGIC, FrameError, FrameKind, encode_geometry
from protocol.keyframes import (
    HEADER_BYTES,
    MAX_KEYFRAMES,
    KeyframeAssembler,
    chunk_keyframes,
    chunk_spheres,
    decode_keyframes,
    decode_spheres,
    encode_keyframes,
    encode_spheres,
    frame_plan,
    keyframe_frame_bytes,
)
from protocol.version import PROTOCOL_VERSION


def _moving(n: int, k: int, seed: int = 0, offset: float = 0.0):
    rng = np.random.default_rng(seed)
    ids = rng.choice(10 * n + 10, size=n, replace=False).astype(np.int64)
    times = np.cumsum(rng.uniform(0.05, 0.5, k))
    pos = rng.uniform(-20, 20, size=(k, n, 3, 3)) + offset
    return ids, times, pos


def _spheres(n: int, k: int, seed: int = 0, offset: float = 0.0):
    rng = np.random.default_rng(seed)
    ids = np.arange(n, dtype=np.int64) * 3
    times = np.cumsum(rng.uniform(0.05, 0.5, k))
    cen = rng.uniform(-20, 20, size=(k, n, 3)) + offset
    radii = rng.uniform(0.1, 2.0, n)
    cols = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    return ids, times, cen, radii, cols


def test_keyframe_layout_matches_the_documented_offsets():
    ids, times, pos = _moving(2, 3)
    data = encode_keyframes(ids, times, pos, keyframes=5, key_start=1, cell=7, seq=9, index=1,
                            count=3, origin=[1, 2, 3])
    n, m = 2, 3
    assert HEADER_BYTES == 64
    assert len(data) == keyframe_frame_bytes(FrameKind.KEYFRAMES, n, m)
    assert len(data) == 64 + 8 * m + 4 * n + 36 * m * n
    assert data[0:4] == MAGIC and struct.unpack_from("<H", data, 4)[0] == PROTOCOL_VERSION
    assert data[6] == FrameKind.KEYFRAMES == 3 and data[7] == 0
    assert struct.unpack_from("<iIIIIIII", data, 8) == (7, 9, 1, 3, n, 5, 1, m)
    assert struct.unpack_from("<3d", data, 40) == (1.0, 2.0, 3.0)
    np.testing.assert_array_equal(np.frombuffer(data, "<f8", m, 64), times)
    assert np.frombuffer(data, "<i4", n, 64 + 8 * m).tolist() == ids.tolist()
    rel = np.frombuffer(data, "<f4", 9 * m * n, 64 + 8 * m + 4 * n).reshape(m, n, 3, 3)
    np.testing.assert_allclose(rel + [1, 2, 3], pos, atol=1e-4)


def test_sphere_layout_matches_the_documented_offsets():
    ids, times, cen, radii, cols = _spheres(2, 3)
    data = encode_spheres(ids, times, cen, radii, cols, cell=4, seq=1, origin=[0, 0, 0])
    n, m = 2, 3
    assert len(data) == keyframe_frame_bytes(FrameKind.SPHERES, n, m)
    assert len(data) == 64 + 8 * m + 11 * n + 12 * m * n
    assert data[6] == FrameKind.SPHERES == 4
    assert struct.unpack_from("<iIIIIIII", data, 8) == (4, 1, 0, 1, n, m, 0, m)
    p = 64 + 8 * m + 4 * n
    np.testing.assert_allclose(np.frombuffer(data, "<f4", n, p), radii, rtol=1e-6)
    p += 4 * n
    np.testing.assert_allclose(np.frombuffer(data, "<f4", 3 * m * n, p).reshape(m, n, 3), cen,
                               atol=1e-5)
    p += 12 * m * n
    assert np.frombuffer(data, np.uint8, 3 * n, p).reshape(n, 3).tolist() == cols.tolist()


@settings(max_examples=30, deadline=None)
@given(n=st.integers(0, 20), k=st.integers(1, 12), seed=st.integers(0, 2**31),
       offset=st.sampled_from([0.0, 1e5, -3.7e6]), cell=st.integers(-1, 2**31 - 1))
def test_round_trips(n, k, seed, offset, cell):
    ids, times, pos = _moving(n, k, seed, offset)
    c = decode_keyframes(encode_keyframes(ids, times, pos, cell=cell, seq=3))
    assert (c.cell, c.seq, c.keyframes, c.key_start, len(c)) == (cell, 3, k, 0, n)
    assert c.complete and c.ids.dtype == np.int32 and c.ids.tolist() == ids.tolist()
    np.testing.assert_array_equal(c.times, times)
    # float32 offsets from the bounding-box centre: relative precision of the extent (40 m).
    np.testing.assert_allclose(c.triangles, pos, atol=40 * 2e-7 * 4)
    sid, st_, cen, radii, cols = _spheres(n, k, seed, offset)
    s = decode_spheres(encode_spheres(sid, st_, cen, radii, cols, cell=cell))
    assert s.ids.tolist() == sid.tolist() and s.colors.tolist() == cols.tolist()
    np.testing.assert_allclose(s.absolute_centers, cen, atol=40 * 2e-7 * 4)
    np.testing.assert_allclose(s.radii, radii, rtol=1e-6)


def test_chunking_respects_the_limit_and_keeps_everything():
    ids, times, pos = _moving(40, 10, seed=1)
    limit = 2000
    frames = list(chunk_keyframes(ids, times, pos, cell=2, seq=5, max_frame_bytes=limit))
    per, m = frame_plan(FrameKind.KEYFRAMES, 10, limit)
    assert m == 10 and per == (limit - 64 - 80) // (4 + 360) and len(frames) == -(-40 // per)
    chunks = [decode_keyframes(f) for f in frames]
    assert all(len(f) <= limit for f in frames) and all(c.complete for c in chunks)
    assert [c.index for c in chunks] == list(range(len(frames)))
    assert {c.count for c in chunks} == {len(frames)} and {c.cell for c in chunks} == {2}
    got = np.concatenate([c.ids for c in chunks])
    assert got.tolist() == ids.tolist()
    np.testing.assert_allclose(np.concatenate([c.triangles for c in chunks], axis=1), pos,
                               atol=1e-4)
    assert list(chunk_keyframes(ids[:0], times, pos[:, :0], max_frame_bytes=limit)) == []


def test_windows_split_keyframes_that_do_not_fit_and_the_assembler_joins_them():
    ids, times, pos = _moving(5, 40, seed=2, offset=1e5)
    limit = 600  # one triangle with 40 keyframes needs 64 + 320 + 4 + 1440 bytes
    per, m = frame_plan(FrameKind.KEYFRAMES, 40, limit)
    assert m < 40 and per >= 1
    frames = list(chunk_keyframes(ids, times, pos, max_frame_bytes=limit))
    assert all(len(f) <= limit for f in frames)
    asm = KeyframeAssembler()
    done = []
    for f in frames:
        c = decode_keyframes(f)
        assert not c.complete
        out = asm.add(c)
        if out is not None:
            done.append(out)
    assert not asm.pending and asm.abandoned == 0
    assert np.concatenate([d.ids for d in done]).tolist() == ids.tolist()
    for d in done:
        assert d.complete and d.keyframes == 40
        np.testing.assert_array_equal(d.times, times)
    np.testing.assert_allclose(np.concatenate([d.triangles for d in done], axis=1), pos,
                               atol=0.05)  # float32 offsets 1e5 m out: ~1 cm
    # Spheres too.
    sid, st_, cen, radii, cols = _spheres(7, 60, seed=3)
    sframes = list(chunk_spheres(sid, st_, cen, radii, cols, max_frame_bytes=300))
    assert all(len(f) <= 300 for f in sframes) and len(sframes) > 7
    sdone = [x for x in (asm.add(decode_spheres(f)) for f in sframes) if x is not None]
    assert np.concatenate([d.ids for d in sdone]).tolist() == sid.tolist()
    np.testing.assert_allclose(np.concatenate([d.absolute_centers for d in sdone], axis=1), cen,
                               atol=1e-4)


def test_assembler_rejects_windows_out_of_order():
    ids, times, pos = _moving(1, 40, seed=4)
    frames = [decode_keyframes(f) for f in chunk_keyframes(ids, times, pos, max_frame_bytes=600)]
    assert len(frames) >= 3
    asm = KeyframeAssembler()
    with pytest.raises(FrameError, match="continue"):
        asm.add(frames[1])  # no set pending
    asm.add(frames[0])
    with pytest.raises(FrameError, match="continue"):
        asm.add(frames[2])  # a gap
    assert not asm.pending
    asm.add(frames[0])
    asm.add(frames[0])  # a new set before the last window: the pending one is abandoned
    assert asm.abandoned == 1 and asm.pending
    other = decode_keyframes(encode_keyframes([9], times[:2] + 100, pos[:2], keyframes=40,
                                              key_start=frames[1].key_start))
    with pytest.raises(FrameError, match="continue"):
        asm.add(other)  # other ids


def test_plan_and_limits():
    with pytest.raises(ValueError, match="cannot hold one keyframe"):
        frame_plan(FrameKind.KEYFRAMES, 3, HEADER_BYTES + 8 + 4 + 36 - 1)
    assert frame_plan(FrameKind.KEYFRAMES, 3, HEADER_BYTES + 8 + 4 + 36) == (1, 1)
    assert frame_plan(FrameKind.SPHERES, 1, 1 << 20)[1] == 1
    with pytest.raises(ValueError, match="keyframes must be"):
        encode_keyframes([1], np.arange(MAX_KEYFRAMES + 1.0),
                         np.zeros((MAX_KEYFRAMES + 1, 1, 3, 3)))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"ids": [-1]}, "ids"),
        ({"ids": [0.5]}, "integers"),
        ({"times": [0.0, 0.0]}, "increasing"),
        ({"times": [0.0, np.nan]}, "increasing"),
        ({"times": [0.0]}, "times"),
        ({"positions": np.full((2, 1, 3, 3), np.inf)}, "finite"),
        ({"positions": np.zeros((2, 2, 3, 3))}, r"\(m, 1, 3, 3\)"),
        ({"key_start": 1}, "exceed"),
        ({"keyframes": 0}, "keyframes"),
        ({"index": 1, "count": 1}, "index"),
        ({"cell": 2**31}, "int32"),
        ({"seq": -1}, "uint32"),
    ],
)
def test_encode_rejects_bad_input(kwargs, match):
    args = {"ids": [1], "times": [0.0, 1.0], "positions": np.zeros((2, 1, 3, 3))}
    args.update(kwargs)
    ids, times, pos = args.pop("ids"), args.pop("times"), args.pop("positions")
    with pytest.raises(ValueError, match=match):
        encode_keyframes(np.asarray(ids), times, pos, **args)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"radii": [0.0]}, "radii"),
        ({"radii": [np.nan]}, "radii"),
        ({"colors": [[0, 0, 300]]}, "uint8"),
        ({"colors": [[0, 0]]}, r"\(1, 3\)"),
        ({"centers": np.zeros((2, 1, 2))}, r"\(m, 1, 3\)"),
    ],
)
def test_encode_spheres_rejects_bad_input(kwargs, match):
    args = {"ids": [1], "times": [0.0, 1.0], "centers": np.zeros((2, 1, 3)), "radii": [1.0],
            "colors": [[1, 2, 3]]}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        encode_spheres(np.asarray(args.pop("ids")), args.pop("times"), args.pop("centers"),
                       args.pop("radii"), args.pop("colors"))


def _good() -> bytes:
    ids, times, pos = _moving(3, 2, seed=5)
    return encode_keyframes(ids, times, pos, cell=1, seq=2)


def _good_spheres() -> bytes:
    return encode_spheres(*_spheres(3, 2, seed=6))


def _patch(data: bytes, offset: int, fmt: str, *values) -> bytes:
    b = bytearray(data)
    struct.pack_into(fmt, b, offset, *values)
    return bytes(b)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d[:10], "too short"),
        (lambda d: d[:-1], "must be"),
        (lambda d: d + b"\0", "must be"),
        (lambda d: b"XXXX" + d[4:], "magic"),
        (lambda d: _patch(d, 4, "<H", PROTOCOL_VERSION + 1), "version"),
        (lambda d: _patch(d, 6, "<B", FrameKind.GEOMETRY), "kind"),
        (lambda d: _patch(d, 7, "<B", 1), "flags"),
        (lambda d: _patch(d, 16, "<II", 1, 1), "out of range"),
        (lambda d: _patch(d, 24, "<I", 4), "must be"),
        (lambda d: _patch(d, 24, "<I", 2**32 - 1), "must be"),
        (lambda d: _patch(d, 28, "<I", 0), "keyframe count"),
        (lambda d: _patch(d, 28, "<I", MAX_KEYFRAMES + 1), "keyframe count"),
        (lambda d: _patch(d, 32, "<I", 1), "out of range"),
        (lambda d: _patch(d, 36, "<I", 0), "out of range"),
        (lambda d: _patch(d, 40, "<d", float("nan")), "origin"),
        (lambda d: _patch(d, 64, "<d", 1e9), "increasing"),
        (lambda d: _patch(d, 64 + 8, "<d", float("inf")), "increasing"),
        (lambda d: _patch(d, 80, "<i", -5), "negative"),
        (lambda d: _patch(d, 80 + 12 + 8, "<f", float("nan")), "non-finite"),
    ],
)
def test_decode_keyframes_rejects_malformed(mutate, match):
    decode_keyframes(_good())
    with pytest.raises(FrameError, match=match):
        decode_keyframes(mutate(_good()))


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: _patch(d, 80 + 12, "<f", 0.0), "radii"),
        (lambda d: _patch(d, 80 + 12, "<f", float("-inf")), "radii"),
        (lambda d: _patch(d, 80 + 24, "<f", float("nan")), "centres"),
        (lambda d: _patch(d, 6, "<B", FrameKind.KEYFRAMES), "kind|must be"),
    ],
)
def test_decode_spheres_rejects_malformed(mutate, match):
    decode_spheres(_good_spheres())
    with pytest.raises(FrameError, match=match):
        decode_spheres(mutate(_good_spheres()))


def test_a_geometry_frame_is_not_a_keyframe_frame():
    geo = encode_geometry(np.arange(3), np.zeros((3, 3, 3)), np.zeros((3, 3), np.uint8))
    with pytest.raises(FrameError):
        decode_keyframes(geo)
    with pytest.raises(FrameError):
        decode_spheres(geo)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400))
def test_random_bytes_only_raise_frame_error(data):
    for dec in (decode_keyframes, decode_spheres):
        try:
            dec(data)
        except FrameError:
            pass


@settings(max_examples=60, deadline=None)
@given(cut=st.integers(0, 64 + 16 + 12 + 216 - 1))
def test_every_truncation_is_detected(cut):
    with pytest.raises(FrameError):
        decode_keyframes(_good()[:cut])
