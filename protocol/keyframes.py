"""Binary keyframe frames: how moving triangles and spheres move, server to client.

A dynamic scene's vertices follow keyframes (``k`` times, piecewise linear in between, clamped
outside). Geometry frames (``protocol.frames``) carry a triangle's rest (first keyframe)
corners; a keyframe frame carries, for a set of triangle ids, the corners at every keyframe. A
sphere frame carries spheres whole: id (index into the scene's spheres), radius, colour and the
centre at every keyframe (k = 1 for a sphere that does not move).

Byte layout, both kinds, all little-endian, no padding between fields::

    offset        size   type       field
    0             4      bytes      magic b"PVSG" (bytes 0-7 as every frame: route by kind)
    4             2      uint16     protocol version (``PROTOCOL_VERSION``)
    6             1      uint8      frame kind: 3 = triangle keyframes, 4 = spheres
    7             1      uint8      flags (0; reserved)
    8             4      int32      cell id (-1: not tied to a cell)
    12            4      uint32     seq of the pose that triggered the stream
    16            4      uint32     chunk index i (0-based)
    20            4      uint32     chunk count c (i < c) of this keyframe stream
    24            4      uint32     item count n (triangles or spheres)
    28            4      uint32     keyframes K of the items (1..MAX_KEYFRAMES)
    32            4      uint32     first keyframe j0 carried by this frame
    36            4      uint32     keyframes m carried by this frame (m >= 1, j0 + m <= K)
    40            24     3 float64  origin (x, y, z), metres
    64            8m     float64    times[m]: seconds of keyframes j0..j0+m-1, increasing
    64 + 8m       4n     int32      ids[n]
  kind 3 (triangle keyframes), then:
    68 + 8m + ..  36mn   float32    corners[m, n, 3, 3] minus origin, metres
                                    (frame length 64 + 8m + 4n + 36mn)
  kind 4 (spheres), then:
    ..            4n     float32    radii[n], metres (> 0)
    ..            12mn   float32    centres[m, n, 3] minus origin, metres
    ..            3n     uint8      colours[n, 3] RGB
                                    (frame length 64 + 8m + 11n + 12mn)

Positions travel as float32 offsets from a float64 origin (the centre of the frame's bounding
box), as in geometry frames. Times are the scene's keyframe times (``Scene.state_times`` for
triangles, ``Scene.sphere_times`` for spheres).

Chunking. ``chunk_keyframes`` / ``chunk_spheres`` put as many items with all their keyframes
(j0 = 0, m = K) in a frame as fit ``max_frame_bytes``. When not even one item's K keyframes fit,
the keyframes are split into windows: the frames of one id set follow each other with j0 = 0,
m, 2m, ... and ``KeyframeAssembler`` joins them on the client. Anything malformed raises
``FrameError``.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from protocol.frames import MAGIC, FrameError, FrameKind, unpack_header
from protocol.ints import INT32_MAX, UINT32_MAX
from protocol.version import PROTOCOL_VERSION

_HEADER = struct.Struct("<4sHBBiIIIIIII3d")
#: Header size in bytes (64).
HEADER_BYTES = _HEADER.size
#: Most keyframes an item may have.
MAX_KEYFRAMES = 4096
_U32_MAX = UINT32_MAX
_I32_MAX = INT32_MAX
#: Wire bytes per item that do not depend on the keyframe count, and per item and keyframe.
_FIXED = {FrameKind.KEYFRAMES: 4, FrameKind.SPHERES: 4 + 4 + 3}
_PER_KEY = {FrameKind.KEYFRAMES: 36, FrameKind.SPHERES: 12}


@dataclass(frozen=True)
class KeyframeChunk:
    """One decoded triangle keyframe frame (or a whole assembled set, j0 = 0 and m = K).

    Attributes
    ----------
    cell, seq, index, count : header fields (see the module docstring).
    origin : (3,) float64, metres.
    ids : (n,) int32 triangle ids (rows of the scene's face array).
    keyframes : K, the items' keyframe count; ``key_start`` j0, the first one in this frame.
    times : (m,) float64 seconds of this frame's keyframes.
    positions : (m, n, 3, 3) float32 corners relative to ``origin``, metres.
    """

    cell: int
    seq: int
    index: int
    count: int
    origin: np.ndarray
    ids: np.ndarray
    keyframes: int
    key_start: int
    times: np.ndarray
    positions: np.ndarray

    def __len__(self) -> int:
        return int(len(self.ids))

    @property
    def complete(self) -> bool:
        """Whether this frame holds every keyframe of its items."""
        return self.key_start == 0 and len(self.times) == self.keyframes

    @property
    def triangles(self) -> np.ndarray:
        """(m, n, 3, 3) float64 absolute corner positions, metres."""
        return self.positions.astype(np.float64) + self.origin


@dataclass(frozen=True)
class SphereChunk:
    """One decoded sphere frame (or an assembled set). Fields as ``KeyframeChunk``, with
    ``radii`` (n,) float32 metres, ``colors`` (n, 3) uint8 and ``centers`` (m, n, 3) float32
    relative to ``origin`` in place of ``positions``; ``ids`` index the scene's spheres."""

    cell: int
    seq: int
    index: int
    count: int
    origin: np.ndarray
    ids: np.ndarray
    keyframes: int
    key_start: int
    times: np.ndarray
    radii: np.ndarray
    colors: np.ndarray
    centers: np.ndarray

    def __len__(self) -> int:
        return int(len(self.ids))

    @property
    def complete(self) -> bool:
        return self.key_start == 0 and len(self.times) == self.keyframes

    @property
    def absolute_centers(self) -> np.ndarray:
        """(m, n, 3) float64 absolute centres, metres."""
        return self.centers.astype(np.float64) + self.origin


# --------------------------------------------------------------------------------- sizes
def keyframe_frame_bytes(kind: FrameKind, n: int, m: int) -> int:
    """Size in bytes of a frame of ``kind`` with ``n`` items and ``m`` keyframes."""
    kind = FrameKind(kind)
    return HEADER_BYTES + 8 * int(m) + int(n) * (_FIXED[kind] + _PER_KEY[kind] * int(m))


def frame_plan(kind: FrameKind, keyframes: int, max_frame_bytes: int) -> tuple[int, int]:
    """(items per frame, keyframes per frame) for items of ``keyframes`` keyframes under
    ``max_frame_bytes``: all keyframes per frame when one item's fit, else keyframe windows.
    ValueError when not even one keyframe of one item fits."""
    kind = FrameKind(kind)
    k, cap = int(keyframes), int(max_frame_bytes)
    fixed, per = _FIXED[kind], _PER_KEY[kind]
    m = k if keyframe_frame_bytes(kind, 1, k) <= cap else (cap - HEADER_BYTES - fixed) // (8 + per)
    if m < 1:
        raise ValueError(
            f"max_frame_bytes={cap} cannot hold one keyframe of one item "
            f"(needs {keyframe_frame_bytes(kind, 1, 1)} bytes)"
        )
    m = min(m, k)
    n = (cap - HEADER_BYTES - 8 * m) // (fixed + per * m)
    return max(1, n), m


# --------------------------------------------------------------------------------- encoding
def _check_u32(name: str, value: int) -> int:
    value = int(value)
    if not 0 <= value <= _U32_MAX:
        raise ValueError(f"{name} must fit in uint32, got {value}")
    return value


def _check_ids(ids: np.ndarray) -> np.ndarray:
    ids = np.asarray(ids)
    if ids.ndim != 1:
        raise ValueError(f"ids must be 1-D, got shape {ids.shape}")
    if len(ids) and not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"ids must be integers, got {ids.dtype}")
    if len(ids) and (ids.min() < 0 or ids.max() > _I32_MAX):
        raise ValueError("ids must be in [0, 2**31)")
    return ids


def _check_times(times: np.ndarray, m: int) -> np.ndarray:
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if len(t) != m or m < 1:
        raise ValueError(f"need {max(m, 1)} keyframe times, got {len(t)}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ValueError("keyframe times must be finite and strictly increasing")
    return t


def _origin_of(points: np.ndarray, origin: np.ndarray | None) -> np.ndarray:
    if origin is None:
        flat = points.reshape(-1, 3)
        origin = (flat.min(axis=0) + flat.max(axis=0)) / 2 if len(flat) else np.zeros(3)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(origin)):
        raise ValueError("origin must be finite")
    return origin


def _relative(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(points)):
        raise ValueError("positions must be finite")
    with np.errstate(over="ignore"):
        rel = (points - origin).astype("<f4")
    if not np.all(np.isfinite(rel)):
        raise ValueError("offsets from the origin overflow float32")
    return rel


def _header(kind: FrameKind, cell: int, seq: int, index: int, count: int, n: int,
            keyframes: int, key_start: int, m: int, origin: np.ndarray) -> bytes:
    if not -(2**31) <= int(cell) <= _I32_MAX:
        raise ValueError(f"cell must fit in int32, got {cell}")
    index, count = _check_u32("index", index), _check_u32("count", count)
    if index >= count:
        raise ValueError(f"chunk index {index} must be < count {count}")
    keyframes, key_start = int(keyframes), int(key_start)
    if not 1 <= keyframes <= MAX_KEYFRAMES:
        raise ValueError(f"keyframes must be in [1, {MAX_KEYFRAMES}], got {keyframes}")
    if key_start < 0 or key_start + m > keyframes:
        raise ValueError(f"keyframes {key_start}..{key_start + m - 1} exceed {keyframes}")
    return _HEADER.pack(MAGIC, PROTOCOL_VERSION, int(kind), 0, int(cell), _check_u32("seq", seq),
                        index, count, n, keyframes, key_start, m, *origin.tolist())


def encode_keyframes(
    ids: np.ndarray,
    times: np.ndarray,
    positions: np.ndarray,
    *,
    keyframes: int | None = None,
    key_start: int = 0,
    cell: int = -1,
    seq: int = 0,
    index: int = 0,
    count: int = 1,
    origin: np.ndarray | None = None,
) -> bytes:
    """One triangle keyframe frame.

    Parameters
    ----------
    ids : (n,) triangle ids in [0, 2**31).
    times : (m,) seconds of the keyframes carried, strictly increasing.
    positions : (m, n, 3, 3) absolute corner positions at those times, metres, finite.
    keyframes, key_start : K (default m) and j0: the frame carries keyframes j0..j0+m-1 of K.
    cell, seq, index, count : header fields (``index < count``).
    origin : (3,) float64; default the centre of the positions' bounding box.

    Returns the frame's bytes. Raises ValueError on inconsistent input.
    """
    ids = _check_ids(ids)
    n = len(ids)
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 4 or pos.shape[1:] != (n, 3, 3):
        raise ValueError(f"positions must be (m, {n}, 3, 3), got {pos.shape}")
    m = pos.shape[0]
    t = _check_times(times, m)
    origin = _origin_of(pos, origin)
    rel = _relative(pos, origin)
    head = _header(FrameKind.KEYFRAMES, cell, seq, index, count, n,
                   m if keyframes is None else keyframes, key_start, m, origin)
    return b"".join((head, t.astype("<f8").tobytes(), ids.astype("<i4").tobytes(),
                     rel.tobytes()))


def encode_spheres(
    ids: np.ndarray,
    times: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    colors: np.ndarray,
    *,
    keyframes: int | None = None,
    key_start: int = 0,
    cell: int = -1,
    seq: int = 0,
    index: int = 0,
    count: int = 1,
    origin: np.ndarray | None = None,
) -> bytes:
    """One sphere frame: ``ids`` (n,) sphere indices, ``times`` (m,) seconds, ``centers``
    (m, n, 3) absolute metres, ``radii`` (n,) metres (> 0), ``colors`` (n, 3) uint8; the other
    arguments as ``encode_keyframes``. Raises ValueError on inconsistent input."""
    ids = _check_ids(ids)
    n = len(ids)
    c = np.asarray(centers, dtype=np.float64)
    if c.ndim != 3 or c.shape[1:] != (n, 3):
        raise ValueError(f"centers must be (m, {n}, 3), got {c.shape}")
    m = c.shape[0]
    t = _check_times(times, m)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(r) != n or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"radii must be {n} finite positive metres")
    cols = np.asarray(colors)
    if cols.shape != (n, 3):
        raise ValueError(f"colors must be ({n}, 3), got {cols.shape}")
    if cols.dtype != np.uint8:
        if n and (not np.issubdtype(cols.dtype, np.integer) or cols.min() < 0 or cols.max() > 255):
            raise ValueError("colors must be uint8 (integers in [0, 255])")
        cols = cols.astype(np.uint8)
    origin = _origin_of(c, origin)
    rel = _relative(c, origin)
    head = _header(FrameKind.SPHERES, cell, seq, index, count, n,
                   m if keyframes is None else keyframes, key_start, m, origin)
    return b"".join((head, t.astype("<f8").tobytes(), ids.astype("<i4").tobytes(),
                     r.astype("<f4").tobytes(), rel.tobytes(),
                     np.ascontiguousarray(cols).tobytes()))


def _windows(kind: FrameKind, n: int, k: int, max_frame_bytes: int) -> list[tuple[slice, slice]]:
    """(item slice, keyframe slice) of every frame, id slices outer so that the windows of one
    id set follow each other."""
    per, m = frame_plan(kind, k, max_frame_bytes)
    out = []
    for i0 in range(0, n, per):
        for j0 in range(0, k, m):
            out.append((slice(i0, min(n, i0 + per)), slice(j0, min(k, j0 + m))))
    return out


def chunk_keyframes(
    ids: np.ndarray,
    times: np.ndarray,
    positions: np.ndarray,
    *,
    cell: int = -1,
    seq: int = 0,
    max_frame_bytes: int,
) -> Iterator[bytes]:
    """Frames of at most ``max_frame_bytes`` bytes carrying the keyframes of triangles ``ids``
    (n,): ``times`` (K,) seconds, ``positions`` (K, n, 3, 3) absolute metres. Nothing for n = 0;
    each frame is encoded only when asked for. ValueError when one keyframe of one triangle does
    not fit (see ``frame_plan``)."""
    ids = np.asarray(ids)
    pos = np.asarray(positions)
    k = len(np.asarray(times).reshape(-1))
    if pos.ndim != 4 or pos.shape[:2] != (k, len(ids)):
        raise ValueError(f"positions must be ({k}, {len(ids)}, 3, 3), got {pos.shape}")
    if not len(ids):
        return
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    plan = _windows(FrameKind.KEYFRAMES, len(ids), k, max_frame_bytes)
    for i, (s, w) in enumerate(plan):
        yield encode_keyframes(ids[s], t[w], pos[w, s], keyframes=k, key_start=w.start,
                               cell=cell, seq=seq, index=i, count=len(plan))


def chunk_spheres(
    ids: np.ndarray,
    times: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    colors: np.ndarray,
    *,
    cell: int = -1,
    seq: int = 0,
    max_frame_bytes: int,
) -> Iterator[bytes]:
    """Frames of at most ``max_frame_bytes`` bytes carrying spheres ``ids`` (n,): ``times``
    (K,) seconds, ``centers`` (K, n, 3) absolute metres, ``radii`` (n,), ``colors`` (n, 3)."""
    ids = np.asarray(ids)
    c = np.asarray(centers)
    k = len(np.asarray(times).reshape(-1))
    if c.ndim != 3 or c.shape[:2] != (k, len(ids)):
        raise ValueError(f"centers must be ({k}, {len(ids)}, 3), got {c.shape}")
    if not len(ids):
        return
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    r, col = np.asarray(radii), np.asarray(colors)
    plan = _windows(FrameKind.SPHERES, len(ids), k, max_frame_bytes)
    for i, (s, w) in enumerate(plan):
        yield encode_spheres(ids[s], t[w], c[w, s], r[s], col[s], keyframes=k, key_start=w.start,
                             cell=cell, seq=seq, index=i, count=len(plan))


# --------------------------------------------------------------------------------- decoding
def _decode_header(buf: memoryview, want: FrameKind) -> tuple:
    (_, _, _, flags, cell, seq, index, count, n, k, j0, m, ox, oy, oz) = unpack_header(
        buf, _HEADER, want)
    if flags != 0:
        raise FrameError(f"reserved flags must be 0, got {flags}")
    if count < 1 or index >= count:
        raise FrameError(f"chunk index {index} out of range for count {count}")
    if not 1 <= k <= MAX_KEYFRAMES:
        raise FrameError(f"keyframe count {k} out of range [1, {MAX_KEYFRAMES}]")
    if m < 1 or j0 + m > k:
        raise FrameError(f"keyframes {j0}..{j0 + m - 1} out of range for {k}")
    expected = keyframe_frame_bytes(want, n, m)
    if len(buf) != expected:
        raise FrameError(f"frame of {n} items and {m} keyframes must be {expected} bytes, "
                         f"got {len(buf)}")
    origin = np.array([ox, oy, oz], dtype=np.float64)
    if not np.all(np.isfinite(origin)):
        raise FrameError("non-finite origin")
    p = HEADER_BYTES
    times = np.frombuffer(buf, dtype="<f8", count=m, offset=p).astype(np.float64)
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise FrameError("keyframe times must be finite and strictly increasing")
    p += 8 * m
    ids = np.frombuffer(buf, dtype="<i4", count=n, offset=p).astype(np.int32)
    if n and ids.min() < 0:
        raise FrameError("negative id")
    p += 4 * n
    return cell, seq, index, count, n, k, j0, m, origin, times, ids, p


def decode_keyframes(data: bytes | bytearray | memoryview) -> KeyframeChunk:
    """The ``KeyframeChunk`` in a triangle keyframe frame; ``FrameError`` when the bytes are
    not one."""
    buf = memoryview(data).cast("B")
    cell, seq, index, count, n, k, j0, m, origin, times, ids, p = _decode_header(
        buf, FrameKind.KEYFRAMES)
    pos = np.frombuffer(buf, dtype="<f4", count=9 * m * n, offset=p).astype(np.float32)
    if not np.all(np.isfinite(pos)):
        raise FrameError("non-finite keyframe positions")
    return KeyframeChunk(int(cell), int(seq), int(index), int(count), origin, ids, int(k),
                         int(j0), times, pos.reshape(m, n, 3, 3))


def decode_spheres(data: bytes | bytearray | memoryview) -> SphereChunk:
    """The ``SphereChunk`` in a sphere frame; ``FrameError`` when the bytes are not one."""
    buf = memoryview(data).cast("B")
    cell, seq, index, count, n, k, j0, m, origin, times, ids, p = _decode_header(
        buf, FrameKind.SPHERES)
    radii = np.frombuffer(buf, dtype="<f4", count=n, offset=p).astype(np.float32)
    p += 4 * n
    centers = np.frombuffer(buf, dtype="<f4", count=3 * m * n, offset=p).astype(np.float32)
    p += 12 * m * n
    colors = np.frombuffer(buf, dtype=np.uint8, count=3 * n, offset=p).reshape(n, 3).copy()
    if not np.all(np.isfinite(radii)) or np.any(radii <= 0):
        raise FrameError("sphere radii must be finite and positive")
    if not np.all(np.isfinite(centers)):
        raise FrameError("non-finite sphere centres")
    return SphereChunk(int(cell), int(seq), int(index), int(count), origin, ids, int(k),
                       int(j0), times, radii, colors, centers.reshape(m, n, 3))


# --------------------------------------------------------------------------------- assembly
class KeyframeAssembler:
    """Joins the keyframe windows of one id set (frames split along time, see the module
    docstring) into one complete chunk; a receiver keeps one per frame kind.

    ``add`` returns the complete chunk (j0 = 0, m = K, offsets from the first window's origin)
    once its last window arrives, else None. A window that does not continue the pending set
    (other ids, other K, a gap, times not increasing) raises FrameError and discards the set; a
    new set (or a complete frame) arriving before the pending set's last window discards the
    pending one and counts it in ``abandoned``.
    """

    def __init__(self) -> None:
        self._parts: list[KeyframeChunk | SphereChunk] = []
        self._next = 0
        #: Incomplete sets discarded because another set began before their last window.
        self.abandoned = 0

    @property
    def pending(self) -> bool:
        """Whether windows of an incomplete set are held."""
        return bool(self._parts)

    def add(self, chunk: KeyframeChunk | SphereChunk) -> KeyframeChunk | SphereChunk | None:
        """Take one decoded frame; the complete set once it is, else None."""
        if chunk.key_start == 0:
            if self._parts:
                self.abandoned += 1
                self._reset()
            if chunk.complete:
                return chunk
        else:
            first = self._parts[0] if self._parts else None
            if (first is None or chunk.key_start != self._next or type(chunk) is not type(first)
                    or chunk.keyframes != first.keyframes
                    or not np.array_equal(chunk.ids, first.ids)
                    or chunk.times[0] <= self._parts[-1].times[-1]):
                self._reset()
                raise FrameError(f"keyframe window starting at {chunk.key_start} does not "
                                 "continue the pending set")
        self._parts.append(chunk)
        self._next = chunk.key_start + len(chunk.times)
        if self._next < chunk.keyframes:
            return None
        parts = self._parts
        self._reset()
        return _join(parts)

    def _reset(self) -> None:
        self._parts = []
        self._next = 0


def _join(parts: list) -> KeyframeChunk | SphereChunk:
    first = parts[0]
    origin = first.origin
    times = np.concatenate([p.times for p in parts])
    if isinstance(first, KeyframeChunk):
        pos = np.concatenate([(p.positions.astype(np.float64) + (p.origin - origin))
                              for p in parts]).astype(np.float32)
        return KeyframeChunk(first.cell, first.seq, first.index, first.count, origin, first.ids,
                             first.keyframes, 0, times, pos)
    cen = np.concatenate([(p.centers.astype(np.float64) + (p.origin - origin))
                          for p in parts]).astype(np.float32)
    return SphereChunk(first.cell, first.seq, first.index, first.count, origin, first.ids,
                       first.keyframes, 0, times, first.radii, first.colors, cen)
