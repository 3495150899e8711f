"""Golden samples of the wire protocol, written by the Python encoders: every frame kind (valid
and malformed) and every server message (valid and not), with what the Python decoders make
of each. The JavaScript decoder of the browser viewer (``server/viewer/decode.js``) is checked
against the same files (``tests/viewer/test_decode_js.py``).

``write_golden(folder)`` writes ``NAME.bin`` / ``NAME.json`` samples and ``manifest.json``:
``[{"name", "files": [...], "what": "frame" | "assemble" | "message", "expect": ...}]`` where
``expect`` is ``{"ok": true, "value": <normalised decode>}`` or ``{"ok": false, "error":
"FrameError" | <ErrorCode>}``. ``tests/protocol/golden/`` holds the committed copy;
``PVS_WRITE_GOLDEN=1 pytest tests/protocol/test_golden_frames.py`` rewrites it.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from protocol.cubemap import CubemapFrame, decode_cubemap, encode_cubemap
from protocol.frames import FrameError, FrameKind, GeometryChunk, decode_geometry, encode_geometry
from protocol.keyframes import (
    KeyframeAssembler,
    KeyframeChunk,
    SphereChunk,
    chunk_keyframes,
    decode_keyframes,
    decode_spheres,
    encode_keyframes,
    encode_spheres,
)
from protocol.messages import (
    CellBegin,
    CellEnd,
    Drop,
    Error,
    GridInfo,
    Limits,
    ProtocolError,
    SceneInfo,
    Welcome,
    dump_message,
    parse_server_message,
)

#: Where the committed copy lives.
GOLDEN_DIR = Path(__file__).with_name("golden")


def _flat(a: np.ndarray) -> list:
    """A flat list of an array's values, +-inf as the strings "inf" / "-inf" (not JSON)."""
    out = []
    for v in np.asarray(a).reshape(-1).tolist():
        out.append(v if not (isinstance(v, float) and math.isinf(v)) else
                   ("inf" if v > 0 else "-inf"))
    return out


def normalise(decoded: Any) -> dict:
    """The JSON form both decoders' results are compared in."""
    if isinstance(decoded, GeometryChunk):
        return {"kind": 1, "cell": decoded.cell, "seq": decoded.seq, "index": decoded.index,
                "count": decoded.count, "origin": _flat(decoded.origin), "ids": _flat(decoded.ids),
                "positions": _flat(decoded.positions), "colors": _flat(decoded.colors)}
    if isinstance(decoded, CubemapFrame):
        return {"kind": 2, "cell": decoded.cell, "resolution": decoded.resolution,
                "center": _flat(decoded.center), "r1": decoded.r1, "r2": decoded.r2,
                "range_lo": decoded.range_lo, "range_hi": decoded.range_hi,
                "colors": _flat(decoded.colors), "ranges": _flat(decoded.ranges)}
    if isinstance(decoded, KeyframeChunk | SphereChunk):
        out = {"kind": 3 if isinstance(decoded, KeyframeChunk) else 4, "cell": decoded.cell,
               "seq": decoded.seq, "index": decoded.index, "count": decoded.count,
               "origin": _flat(decoded.origin), "ids": _flat(decoded.ids),
               "keyframes": decoded.keyframes, "key_start": decoded.key_start,
               "times": _flat(decoded.times)}
        if isinstance(decoded, KeyframeChunk):
            out["positions"] = _flat(decoded.positions)
        else:
            out.update(radii=_flat(decoded.radii), centers=_flat(decoded.centers),
                       colors=_flat(decoded.colors))
        return out
    return decoded.model_dump(mode="json")


def decode_frame(data: bytes) -> Any:
    """The Python decoder for a frame's kind byte (geometry's for anything else)."""
    kind = data[6] if len(data) > 6 else None
    return {FrameKind.CUBEMAP: decode_cubemap, FrameKind.KEYFRAMES: decode_keyframes,
            FrameKind.SPHERES: decode_spheres}.get(kind, decode_geometry)(data)


def expect(run: Callable[[], Any]) -> dict:
    """What the Python side makes of a sample: its normalised value or the error's name/code."""
    try:
        return {"ok": True, "value": normalise(run())}
    except FrameError:
        return {"ok": False, "error": "FrameError"}
    except ProtocolError as exc:
        return {"ok": False, "error": str(exc.code)}


def _assemble(frames: list[bytes]) -> Any:
    asm = KeyframeAssembler()
    out = None
    for f in frames:
        chunk = decode_frame(f)
        out = asm.add(chunk)
    if out is None:
        raise FrameError("incomplete keyframe set")
    return out


def _patch(data: bytes, offset: int, fmt: str, value: Any) -> bytes:
    b = bytearray(data)
    struct.pack_into(fmt, b, offset, value)
    return bytes(b)


def frame_samples() -> dict[str, list[bytes]]:
    """{name: frames} of every frame kind; a name with several frames is one keyframe set."""
    rng = np.random.default_rng(17)
    n = 5
    tris = rng.uniform(-3, 3, size=(n, 3, 3)) + [1e5, 2.0, -4e4]  # far from the world origin
    cols = rng.integers(0, 256, size=(n, 3), dtype=np.uint8)
    geo = encode_geometry(np.array([4, 0, 99, 7, 3]), tris, cols, cell=12, seq=70000, index=1,
                          count=3, origin=np.round(tris.reshape(-1, 3).mean(axis=0)))
    res = 4
    ccols = rng.integers(0, 256, size=(6, res, res, 3), dtype=np.uint8)
    ranges = np.exp(rng.uniform(np.log(20.0), np.log(900.0), size=(6, res, res)))
    ranges[rng.random(ranges.shape) < 0.3] = np.inf
    cube_z = encode_cubemap(5, [3.0, 1.7, -2.0], ccols, ranges, 50.0, 100.0)
    cube_raw = encode_cubemap(6, [3.0, 1.7, -2.0], ccols, ranges, 40.0, 80.0, compress=False)
    cube_empty = encode_cubemap(0, [0.0, 0.0, 0.0], ccols, np.full((6, res, res), np.inf),
                                50.0, 100.0)
    cube_one = encode_cubemap(1, [0.0, 0.0, 0.0], ccols, np.where(np.isinf(ranges), np.inf, 70.0),
                              50.0, 100.0)
    k, m = 3, 2
    times = np.array([0.0, 0.5, 2.0])
    kpos = rng.uniform(-1, 1, size=(k, m, 3, 3)) + [10.0, 1.0, 5.0]
    keys = encode_keyframes(np.array([8, 2]), times, kpos, cell=4, seq=9)
    windows = list(chunk_keyframes(np.array([8, 2]), np.linspace(0, 1, 8),
                                   rng.uniform(-1, 1, size=(8, 2, 3, 3)), cell=4, seq=9,
                                   max_frame_bytes=64 + 8 * 3 + 2 * (4 + 36 * 3)))
    centres = rng.uniform(-5, 5, size=(k, 2, 3))
    spheres = encode_spheres(np.array([1, 0]), times, centres, np.array([0.5, 1.25]),
                             np.array([[255, 0, 10], [3, 200, 90]], dtype=np.uint8), cell=2)
    bad_zlib = bytearray(cube_z)
    bad_zlib[90] ^= 0xFF
    payload = zlib.compress(ccols.tobytes() + np.zeros((6, res, res), "<u2").tobytes())
    junk = cube_z[:72] + struct.pack("<II", len(payload) + 3, 0) + payload + b"abc"
    nan_geo = bytearray(geo)
    struct.pack_into("<f", nan_geo, 56 + 4 * n + 8, float("nan"))
    neg_id = _patch(geo, 56 + 4, "<i", -3)
    back_times = _patch(keys, 64 + 8, "<d", -1.0)
    zero_radius = _patch(spheres, 64 + 8 * k + 4 * 2, "<f", 0.0)
    return {
        "geometry": [geo],
        "geometry_empty": [encode_geometry(np.zeros(0, int), np.zeros((0, 3, 3)),
                                           np.zeros((0, 3), np.uint8))],
        "cubemap_zlib": [cube_z],
        "cubemap_raw": [cube_raw],
        "cubemap_empty": [cube_empty],
        "cubemap_one_range": [cube_one],
        "keyframes": [keys],
        "keyframe_windows": windows,
        "spheres": [spheres],
        "bad_truncated": [geo[:-1]],
        "bad_short": [geo[:20]],
        "bad_magic": [b"XVSG" + geo[4:]],
        "bad_version": [_patch(geo, 4, "<H", 1)],
        "bad_kind": [_patch(geo, 6, "<B", 9)],
        "bad_flags": [_patch(geo, 7, "<B", 1)],
        "bad_index": [_patch(geo, 16, "<I", 3)],
        "bad_nan_position": [bytes(nan_geo)],
        "bad_negative_id": [neg_id],
        "bad_origin": [_patch(geo, 40, "<d", float("inf"))],
        "bad_cubemap_zlib": [bytes(bad_zlib)],
        "bad_cubemap_junk": [junk],
        "bad_cubemap_radii": [_patch(cube_raw, 48, "<d", 10.0)],
        "bad_cubemap_resolution": [_patch(cube_raw, 12, "<I", 0)],
        "bad_cubemap_length": [cube_raw + b"\0"],
        "bad_keyframe_times": [back_times],
        "bad_keyframe_count": [_patch(keys, 28, "<I", 0)],
        "bad_sphere_radius": [zero_radius],
        "bad_window_gap": [windows[0], windows[3]],
        "bad_window_orphan": [windows[1]],
    }


def message_samples() -> dict[str, str]:
    """{name: text} of server messages, valid ones from the Python models."""
    welcome = Welcome(
        session="abc", core="sampling", params={"samples": 4, "resolution": 128},
        scene=SceneInfo(name="rooms", kind="generated", triangles=10038, valid_triangles=10038,
                        vertices=30114, objects=40, bounds=((-10, 0, -15), (10, 3.2, 15)),
                        source={"generator": "rooms", "triangles": 10000, "seed": 0}),
        grid=GridInfo(cell_size=4.0, origin_xz=(-10.0, -15.0), cells=30, levels=1,
                      eye_range=(1.5, 1.9), bounds=((-10, 1.5, -15), (10, 1.9, 15))),
        limits=Limits(max_frame_bytes=1 << 20, max_message_bytes=65536), prefetch=True,
        features={"cores": ["from_segment", "sampling"], "cubemap": {"on": False}},
        near_plane=0.05)
    good = {
        "msg_welcome": dump_message(welcome),
        "msg_cell_begin": dump_message(CellBegin(cell=3, seq=7, triangles=100, new=40, chunks=2,
                                                 near_far={"r1": 50.0, "r2": 100.0,
                                                           "center": [1, 2, 3], "cubemap": True,
                                                           "cubemap_cell": 3},
                                                 answer="first")),
        "msg_cell_end": dump_message(CellEnd(cell=3, seq=7, seconds=0.25, cached=True)),
        "msg_drop": dump_message(Drop(ids=[5, 9, 11], cells=[2])),
        "msg_error": dump_message(Error(code="outside_grid", message="no cell", seq=3)),
        "msg_minimal_cell_end": '{"type": "cell_end", "cell": 1, "seq": 0, "seconds": 1}',
    }
    bad = {
        "msg_bad_json": "{not json",
        "msg_bad_array": "[1, 2]",
        "msg_bad_no_type": '{"cell": 1}',
        "msg_bad_unknown_type": '{"type": "teleport"}',
        "msg_bad_negative_cell": '{"type": "cell_end", "cell": -1, "seq": 0, "seconds": 1}',
        "msg_bad_string_number": '{"type": "cell_end", "cell": "1", "seq": 0, "seconds": 1}',
        "msg_bad_extra_field": '{"type": "drop", "ids": [1], "colour": "red"}',
        "msg_bad_missing_field": '{"type": "cell_begin", "cell": 1, "seq": 0}',
        "msg_bad_answer": '{"type": "cell_end", "cell": 1, "seq": 0, "seconds": 1, '
                          '"answer": "maybe"}',
        "msg_bad_seq": '{"type": "cell_end", "cell": 1, "seq": 4294967296, "seconds": 1}',
    }
    return {**good, **bad}


def write_golden(folder: Path) -> list[dict]:
    """Write every sample and ``manifest.json`` into ``folder``; the manifest."""
    folder.mkdir(parents=True, exist_ok=True)
    manifest = []
    for name, frames in frame_samples().items():
        files = []
        for i, data in enumerate(frames):
            fname = f"{name}.bin" if len(frames) == 1 else f"{name}_{i}.bin"
            (folder / fname).write_bytes(data)
            files.append(fname)
        if len(frames) == 1 and not name.startswith("bad_window"):
            entry = {"what": "frame", "expect": expect(lambda d=frames[0]: decode_frame(d))}
        else:
            entry = {"what": "assemble", "expect": expect(lambda f=frames: _assemble(f))}
        manifest.append({"name": name, "files": files, **entry})
    for name, text in message_samples().items():
        (folder / f"{name}.json").write_text(text)
        manifest.append({"name": name, "files": [f"{name}.json"], "what": "message",
                         "expect": expect(lambda t=text: parse_server_message(t))})
    # One entry per line: a readable diff when a sample changes.
    (folder / "manifest.json").write_text(
        "[\n" + ",\n".join(json.dumps(e) for e in manifest) + "\n]\n")
    return manifest
