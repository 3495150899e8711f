"""Binary frames (WebSocket binary messages) carrying triangle geometry from server to client.

Byte layout of a geometry frame, version 1, all little-endian, no padding between fields::

    offset     size  type        field
    0          4     bytes       magic b"PVSG"
    4          2     uint16      protocol version (``PROTOCOL_VERSION``)
    6          1     uint8       frame kind (1 = geometry; other values reserved)
    7          1     uint8       flags (0; reserved)
    8          4     int32       cell id (-1: not tied to a cell)
    12         4     uint32      seq of the pose that triggered the stream
    16         4     uint32      chunk index i (0-based)
    20         4     uint32      chunk count c (i < c) of this cell stream
    24         4     uint32      triangle count n
    28         4     uint32      reserved (0)
    32         24    3 float64   origin (x, y, z) metres
    56         4n    int32       ids[n]: triangle ids (rows of the scene's face array)
    56 + 4n    36n   float32     positions[n, 3, 3]: corner positions minus origin, metres
    56 + 40n   3n    uint8       colours[n, 3]: RGB per triangle
    56 + 43n                     end (the frame is exactly this long)

Positions travel as float32 offsets from a float64 origin (the centre of the chunk's bounding
box), so scenes far from the world origin keep millimetre precision on the wire. The header is
``HEADER_BYTES`` long and each triangle costs ``TRIANGLE_BYTES``.

``encode_geometry`` / ``decode_geometry`` write and read one frame; ``chunk_geometry`` splits a set
of triangles into frames that each fit ``max_frame_bytes``. Anything malformed raises
``FrameError``.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from protocol.ints import UINT32_MAX
from protocol.version import PROTOCOL_VERSION

MAGIC = b"PVSG"
_HEADER = struct.Struct("<4sHBBiIIIII3d")
HEADER_BYTES = _HEADER.size  # 56
#: Wire bytes per triangle: id (4) + 9 float32 (36) + RGB (3).
TRIANGLE_BYTES = 4 + 36 + 3
#: Default cap on one frame's size (bytes).
DEFAULT_MAX_FRAME_BYTES = 1 << 20
_U32_MAX = UINT32_MAX


class FrameKind(IntEnum):
    """The kind byte (offset 6) of a binary frame; every kind shares bytes 0-7 (magic, version,
    kind, flags), so a receiver routes a frame by its kind before decoding it."""

    GEOMETRY = 1
    #: A near-far cubemap (colour + range) of a cell's far region; see ``protocol.cubemap``.
    CUBEMAP = 2
    #: Keyframe corner positions of moving triangles; see ``protocol.keyframes``.
    KEYFRAMES = 3
    #: Spheres (radius, colour, centre per keyframe); see ``protocol.keyframes``.
    SPHERES = 4


class FrameError(ValueError):
    """Bytes that are not a valid frame (truncated, wrong magic/version/kind, inconsistent sizes,
    non-finite numbers)."""


def unpack_header(buf: memoryview, header: struct.Struct, kind: FrameKind) -> tuple:
    """The fields of ``header`` at the start of frame ``buf``, after the checks every frame kind
    shares: at least a header long, magic, protocol version, and ``kind`` at byte 6.

    Raises
    ------
    FrameError
        When the bytes cannot be a frame of ``kind``.
    """
    if len(buf) < header.size:
        raise FrameError(f"frame too short: {len(buf)} bytes < {header.size}-byte header")
    fields = header.unpack_from(buf)
    magic, version, got = fields[0], fields[1], fields[2]
    if magic != MAGIC:
        raise FrameError(f"bad magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version != PROTOCOL_VERSION:
        raise FrameError(f"frame version {version}, this code speaks {PROTOCOL_VERSION}")
    if got != kind:
        raise FrameError(f"frame kind {got} is not {kind.name.lower()} ({int(kind)})")
    return fields


@dataclass(frozen=True)
class GeometryChunk:
    """One decoded geometry frame.

    Attributes
    ----------
    cell : int, the cell id (-1: none).
    seq : int, the pose seq that triggered the stream.
    index, count : int, this chunk's index and the number of chunks of the stream.
    origin : (3,) float64, metres.
    ids : (n,) int32 triangle ids.
    positions : (n, 3, 3) float32 corners relative to ``origin``, metres.
    colors : (n, 3) uint8 RGB.
    """

    cell: int
    seq: int
    index: int
    count: int
    origin: np.ndarray
    ids: np.ndarray
    positions: np.ndarray
    colors: np.ndarray

    def __len__(self) -> int:
        return int(len(self.ids))

    @property
    def triangles(self) -> np.ndarray:
        """(n, 3, 3) float64 absolute corner positions, metres."""
        return self.positions.astype(np.float64) + self.origin


def frame_bytes(n: int) -> int:
    """Size in bytes of a geometry frame holding ``n`` triangles."""
    return HEADER_BYTES + TRIANGLE_BYTES * int(n)


def triangles_per_frame(max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> int:
    """The most triangles one frame of at most ``max_frame_bytes`` bytes holds (>= 1)."""
    n = (int(max_frame_bytes) - HEADER_BYTES) // TRIANGLE_BYTES
    if n < 1:
        raise ValueError(
            f"max_frame_bytes={max_frame_bytes} cannot hold one triangle "
            f"(needs {frame_bytes(1)} bytes)"
        )
    return n


def _check_u32(name: str, value: int) -> int:
    value = int(value)
    if not 0 <= value <= _U32_MAX:
        raise ValueError(f"{name} must fit in uint32, got {value}")
    return value


def encode_geometry(
    ids: np.ndarray,
    triangles: np.ndarray,
    colors: np.ndarray,
    *,
    cell: int = -1,
    seq: int = 0,
    index: int = 0,
    count: int = 1,
    origin: np.ndarray | None = None,
) -> bytes:
    """One geometry frame.

    Parameters
    ----------
    ids : (n,) integer triangle ids in [0, 2**31).
    triangles : (n, 3, 3) absolute corner positions, metres (float64 preferred), finite.
    colors : (n, 3) uint8 RGB.
    cell, seq, index, count : header fields (``index < count``).
    origin : (3,) float64; default the centre of the triangles' bounding box.

    Returns the frame's bytes (``frame_bytes(n)`` long). Raises ValueError on inconsistent input.
    """
    ids = np.asarray(ids)
    n = len(ids)
    if ids.ndim != 1:
        raise ValueError(f"ids must be 1-D, got shape {ids.shape}")
    if n and not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"ids must be integers, got {ids.dtype}")
    if n and (ids.min() < 0 or ids.max() > np.iinfo(np.int32).max):
        raise ValueError("ids must be in [0, 2**31)")
    tris = np.asarray(triangles, dtype=np.float64)
    if tris.shape != (n, 3, 3):
        raise ValueError(f"triangles must be ({n}, 3, 3), got {tris.shape}")
    cols = np.asarray(colors)
    if cols.shape != (n, 3):
        raise ValueError(f"colors must be ({n}, 3), got {cols.shape}")
    if cols.dtype != np.uint8:
        if n and (not np.issubdtype(cols.dtype, np.integer) or cols.min() < 0 or cols.max() > 255):
            raise ValueError("colors must be uint8 (integers in [0, 255])")
        cols = cols.astype(np.uint8)
    if not np.all(np.isfinite(tris)):
        raise ValueError("triangles must be finite")
    if origin is None:
        flat = tris.reshape(-1, 3)
        # Per column: numpy's axis-0 reduction over rows of 3 is far slower.
        origin = np.array([(flat[:, k].min() + flat[:, k].max()) / 2 for k in range(3)]) \
            if n else np.zeros(3)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(origin)):
        raise ValueError("origin must be finite")
    if not -(2**31) <= int(cell) < 2**31:
        raise ValueError(f"cell must fit in int32, got {cell}")
    index, count = _check_u32("index", index), _check_u32("count", count)
    if index >= count:
        raise ValueError(f"chunk index {index} must be < count {count}")
    with np.errstate(over="ignore"):
        rel = (tris - origin).astype("<f4")
    if not np.all(np.isfinite(rel)):
        raise ValueError("triangle offsets from the origin overflow float32")
    header = _HEADER.pack(
        MAGIC, PROTOCOL_VERSION, FrameKind.GEOMETRY, 0, int(cell), _check_u32("seq", seq),
        index, count, n, 0, *origin.tolist(),
    )
    return b"".join(
        (header, ids.astype("<i4").tobytes(), rel.tobytes(), np.ascontiguousarray(cols).tobytes())
    )


def decode_geometry(data: bytes | bytearray | memoryview) -> GeometryChunk:
    """The ``GeometryChunk`` in a geometry frame; ``FrameError`` when the bytes are not one."""
    buf = memoryview(data).cast("B")
    (_, _, _, flags, cell, seq, index, count, n, reserved, ox, oy, oz) = unpack_header(
        buf, _HEADER, FrameKind.GEOMETRY)
    if flags != 0 or reserved != 0:
        raise FrameError(f"reserved header fields must be 0 (flags={flags}, reserved={reserved})")
    if count < 1 or index >= count:
        raise FrameError(f"chunk index {index} out of range for count {count}")
    expected = frame_bytes(n)
    if len(buf) != expected:
        raise FrameError(f"frame of {n} triangles must be {expected} bytes, got {len(buf)}")
    origin = np.array([ox, oy, oz], dtype=np.float64)
    if not np.all(np.isfinite(origin)):
        raise FrameError("non-finite origin")
    p = HEADER_BYTES
    ids = np.frombuffer(buf, dtype="<i4", count=n, offset=p).astype(np.int32)
    p += 4 * n
    pos = np.frombuffer(buf, dtype="<f4", count=9 * n, offset=p).astype(np.float32).reshape(n, 3, 3)
    p += 36 * n
    cols = np.frombuffer(buf, dtype=np.uint8, count=3 * n, offset=p).reshape(n, 3).copy()
    if n and ids.min() < 0:
        raise FrameError("negative triangle id")
    if not np.all(np.isfinite(pos)):
        raise FrameError("non-finite triangle positions")
    return GeometryChunk(int(cell), int(seq), int(index), int(count), origin, ids, pos, cols)


def chunk_count(n: int, max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> int:
    """How many frames ``chunk_geometry`` makes for ``n`` triangles (0 for none)."""
    per = triangles_per_frame(max_frame_bytes)
    return -(-int(n) // per)


def chunk_geometry(
    ids: np.ndarray,
    triangles: np.ndarray,
    colors: np.ndarray,
    *,
    cell: int = -1,
    seq: int = 0,
    max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
    origin: np.ndarray | None = None,
) -> Iterator[bytes]:
    """Frames of at most ``max_frame_bytes`` bytes carrying the given triangles, in order.

    ``ids`` (n,), ``triangles`` (n, 3, 3) metres, ``colors`` (n, 3) uint8 as in
    ``encode_geometry``. Yields ``chunk_count(n, max_frame_bytes)`` frames (none when n = 0);
    each is encoded only when asked for, so a sender holds one frame at a time. Every frame
    carries the same ``origin`` (default ``common_origin`` of all the triangles), so a vertex
    that two frames hold decodes to the same position in both (``common_origin``).
    """
    ids = np.asarray(ids)
    n = len(ids)
    if len(triangles) != n or len(colors) != n:
        raise ValueError(
            f"ids, triangles and colors must have one row per triangle ({n}, "
            f"{len(triangles)}, {len(colors)})"
        )
    per = triangles_per_frame(max_frame_bytes)
    count = chunk_count(n, max_frame_bytes)
    if origin is None and count > 1:
        origin = common_origin(np.asarray(triangles, dtype=np.float64).reshape(-1, 3))
    for i in range(count):
        s = slice(i * per, min(n, (i + 1) * per))
        yield encode_geometry(
            ids[s], triangles[s], colors[s], cell=cell, seq=seq, index=i, count=count,
            origin=origin,
        )


def common_origin(points: np.ndarray) -> np.ndarray:
    """(3,) float64 origin for every frame of a set of points (m, 3) metres: the centre of their
    bounding box in whole metres, NaN rows ignored (zeros for none).

    Frames of one set must share an origin: with one of its own per frame, a vertex held by
    two frames is rounded to float32 twice, differently, and the client sees cracks along the
    edges it shares (0.04 % of the pixels of a 2 km city tile's skyline). The price is float32
    precision over half the set's extent: 0.06 mm at 1 km, 2 mm at 30 km."""
    v = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    v = v[np.isfinite(v).all(axis=1)]
    return np.round((v.min(axis=0) + v.max(axis=0)) / 2) if len(v) else np.zeros(3)
