"""Binary cubemap frames: the far region of a cell (near-far partitioning) as colour + range.

Byte layout of a cubemap frame, all little-endian, no padding between fields::

    offset  size      type        field
    0       4         bytes       magic b"PVSG" (as geometry frames: bytes 0-7 route by kind)
    4       2         uint16      protocol version (``PROTOCOL_VERSION``)
    6       1         uint8       frame kind (``FrameKind.CUBEMAP`` = 2)
    7       1         uint8       flags: bit 0 = payload zlib-compressed; other bits 0
    8       4         int32       cell id (-1: not tied to a cell)
    12      4         uint32      face resolution R (1..MAX_RESOLUTION)
    16      24        3 float64   centre O (x, y, z), metres
    40      8         float64     r1, metres
    48      8         float64     r2, metres (0 < r1 < r2)
    56      8         float64     range_lo, metres (0 when no texel has a range)
    64      8         float64     range_hi, metres (range_lo <= range_hi)
    72      4         uint32      payload length in bytes (as sent)
    76      4         uint32      reserved (0)
    80      ...       payload, zlib-compressed when flag bit 0 is set; raw, it is
                      6 R R 3 uint8  colours[face, row, col, rgb]
                      6 R R   uint16 range codes[face, row, col]

Faces and texels follow ``visibility.raster.camera`` (face order +X, -X, +Y, -Y, +Z, -Z; row 0
at the top). Range is the Euclidean distance from O (not z).

Range encoding and its precision. Code 0 means empty (+inf, nothing far in that direction).
Code k in 1..65535 means ``range_lo * (range_hi / range_lo) ** ((k - 1) / 65534)``: uniform in
log-range, so the error is relative. Rounding to the nearest code gives a worst-case relative
error of ``exp(ln(range_hi / range_lo) / (2 * 65534)) - 1`` (``range_precision``). The encoder
sets range_lo = max(smallest range, range_hi / MAX_RANGE_RATIO) with MAX_RANGE_RATIO = 1e7, so
every range in [range_hi / 1e7, range_hi] decodes within ``MAX_RELATIVE_ERROR`` = 1.231e-4 of
its true value (1.2 cm at 100 m); a range under range_hi / 1e7 (never seen with a near plane of
5 cm and ranges under 500 km) is clamped up to range_lo. A city cubemap (ranges 40-700 m) gets
a bound of about 2.2e-5.

Anything malformed raises ``FrameError``; the decompressed size is capped at the size the header
announces, so a small frame cannot expand into a large allocation.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from protocol.frames import MAGIC, FrameError, FrameKind, unpack_header
from protocol.version import PROTOCOL_VERSION

_HEADER = struct.Struct("<4sHBBiI3d4dII")
#: Header size in bytes (80).
HEADER_BYTES = _HEADER.size
#: Largest face resolution a frame may carry.
MAX_RESOLUTION = 2048
#: Largest range_hi / range_lo ratio the encoder keeps (smaller ranges are clamped).
MAX_RANGE_RATIO = 1e7
_CODES = 65534  # codes 1..65535 span [range_lo, range_hi]
#: Flag bit: payload is zlib-compressed.
FLAG_ZLIB = 1
_I32 = 2**31
_F32_EPS = 2.0**-23  # relative rounding bound of a float32 (covers round-to-nearest twice)


def range_precision(range_lo: float, range_hi: float) -> float:
    """Worst-case relative error of a decoded range for the given encoding bounds (metres):
    half a code step in log-range plus the float32 rounding of the decoded value."""
    if not range_lo > 0 or range_hi < range_lo:
        return 0.0
    return math.expm1(math.log(range_hi / range_lo) / (2 * _CODES)) + _F32_EPS


#: Worst-case relative range error of any frame (the ratio capped at MAX_RANGE_RATIO).
MAX_RELATIVE_ERROR = range_precision(1.0, MAX_RANGE_RATIO)


@dataclass(frozen=True)
class CubemapFrame:
    """One decoded cubemap frame.

    Attributes
    ----------
    cell : int, the cell id (-1: none).
    center : (3,) float64 cubemap centre O, metres.
    colors : (6, R, R, 3) uint8 RGB.
    ranges : (6, R, R) float32 Euclidean distance from O in metres, +inf where empty.
    r1, r2 : float, near-far radii in metres.
    range_lo, range_hi : float, the range encoding bounds (metres); see ``precision``.
    """

    cell: int
    center: np.ndarray
    colors: np.ndarray
    ranges: np.ndarray
    r1: float
    r2: float
    range_lo: float = 0.0
    range_hi: float = 0.0

    @property
    def resolution(self) -> int:
        return int(self.colors.shape[1])

    @property
    def precision(self) -> float:
        """Worst-case relative error of ``ranges`` against the ranges that were encoded."""
        return range_precision(self.range_lo, self.range_hi)


def payload_bytes(resolution: int) -> int:
    """Uncompressed payload size (bytes) of a frame of face resolution ``resolution``."""
    return 6 * int(resolution) ** 2 * 5


def _check_radii(r1: float, r2: float, err: type[Exception]) -> tuple[float, float]:
    r1, r2 = float(r1), float(r2)
    if not (math.isfinite(r1) and math.isfinite(r2) and 0.0 < r1 < r2):
        raise err(f"need finite radii 0 < r1 < r2, got r1={r1}, r2={r2}")
    return r1, r2


def encode_ranges(ranges: np.ndarray) -> tuple[np.ndarray, float, float]:
    """uint16 codes (same shape) and the bounds (range_lo, range_hi) of float ``ranges`` in
    metres (> 0, or +inf for empty). See the module docstring."""
    r = np.asarray(ranges, dtype=np.float64)
    if np.isnan(r).any() or (r <= 0).any() or np.isneginf(r).any():
        raise ValueError("ranges must be positive metres or +inf (empty)")
    hit = np.isfinite(r)
    codes = np.zeros(r.shape, dtype=np.uint16)
    if not hit.any():
        return codes, 0.0, 0.0
    hi = float(r[hit].max())
    lo = max(float(r[hit].min()), hi / MAX_RANGE_RATIO)
    if hi == lo:
        codes[hit] = 1
        return codes, lo, hi
    span = math.log(hi / lo)
    x = (np.log(np.maximum(r[hit], lo)) - math.log(lo)) * (_CODES / span)
    codes[hit] = (np.rint(np.clip(x, 0, _CODES)) + 1).astype(np.uint16)
    return codes, lo, hi


def decode_ranges(codes: np.ndarray, range_lo: float, range_hi: float) -> np.ndarray:
    """float32 ranges (metres, +inf for code 0) of uint16 ``codes`` with the given bounds."""
    c = np.asarray(codes)
    out = np.full(c.shape, np.inf, dtype=np.float32)
    hit = c != 0
    if range_hi == range_lo:
        out[hit] = range_lo
        return out
    span = math.log(range_hi / range_lo)
    out[hit] = (range_lo * np.exp((c[hit].astype(np.float64) - 1.0) * (span / _CODES))).astype(
        np.float32
    )
    return out


def encode_cubemap(
    cell: int,
    center: np.ndarray,
    colors: np.ndarray,
    ranges: np.ndarray,
    r1: float,
    r2: float,
    *,
    compress: bool = True,
    level: int = 6,
) -> bytes:
    """One cubemap frame.

    Parameters
    ----------
    cell : cell id (int32; -1 for none).
    center : (3,) cubemap centre O, metres, finite.
    colors : (6, R, R, 3) uint8 RGB.
    ranges : (6, R, R) float Euclidean distances from O in metres (> 0), +inf where empty.
    r1, r2 : near-far radii, metres (0 < r1 < r2).
    compress : zlib-compress the payload (flag bit 0); ``level`` is zlib's level.

    Returns the frame's bytes. Raises ValueError on inconsistent input.
    """
    if not -_I32 <= int(cell) < _I32:
        raise ValueError(f"cell must fit in int32, got {cell}")
    c = np.asarray(center, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"center must be a finite 3-vector, got {center!r}")
    r1, r2 = _check_radii(r1, r2, ValueError)
    col = np.asarray(colors)
    if col.ndim != 4 or col.shape[0] != 6 or col.shape[1] != col.shape[2] or col.shape[3] != 3:
        raise ValueError(f"colors must be (6, R, R, 3), got {col.shape}")
    res = col.shape[1]
    if not 1 <= res <= MAX_RESOLUTION:
        raise ValueError(f"resolution must be in [1, {MAX_RESOLUTION}], got {res}")
    if col.dtype != np.uint8:
        raise ValueError(f"colors must be uint8, got {col.dtype}")
    rng = np.asarray(ranges)
    if rng.shape != (6, res, res):
        raise ValueError(f"ranges must be (6, {res}, {res}), got {rng.shape}")
    codes, lo, hi = encode_ranges(rng)
    payload = np.ascontiguousarray(col).tobytes() + codes.astype("<u2").tobytes()
    flags = 0
    if compress:
        payload = zlib.compress(payload, level)
        flags |= FLAG_ZLIB
    header = _HEADER.pack(
        MAGIC, PROTOCOL_VERSION, FrameKind.CUBEMAP, flags, int(cell), res, *c.tolist(),
        r1, r2, lo, hi, len(payload), 0,
    )
    return header + payload


def decode_cubemap(data: bytes | bytearray | memoryview) -> CubemapFrame:
    """The ``CubemapFrame`` in a cubemap frame; ``FrameError`` when the bytes are not one."""
    buf = memoryview(data).cast("B")
    (_, _, _, flags, cell, res, cx, cy, cz, r1, r2, lo, hi, plen, reserved) = unpack_header(
        buf, _HEADER, FrameKind.CUBEMAP)
    if flags & ~FLAG_ZLIB or reserved != 0:
        raise FrameError(f"unknown flags {flags} or non-zero reserved field {reserved}")
    if not 1 <= res <= MAX_RESOLUTION:
        raise FrameError(f"resolution {res} out of range [1, {MAX_RESOLUTION}]")
    center = np.array([cx, cy, cz], dtype=np.float64)
    if not np.all(np.isfinite(center)):
        raise FrameError("non-finite cubemap centre")
    r1, r2 = _check_radii(r1, r2, FrameError)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi):
        raise FrameError(f"bad range bounds [{lo}, {hi}]")
    if (lo == 0.0) != (hi == 0.0) or (lo > 0 and hi / lo > MAX_RANGE_RATIO * (1 + 1e-9)):
        raise FrameError(f"bad range bounds [{lo}, {hi}]")
    if len(buf) != HEADER_BYTES + plen:
        raise FrameError(f"frame must be {HEADER_BYTES + plen} bytes, got {len(buf)}")
    raw_len = payload_bytes(res)
    payload = buf[HEADER_BYTES:]
    if flags & FLAG_ZLIB:
        d = zlib.decompressobj()
        try:
            raw = d.decompress(payload, raw_len)
        except zlib.error as exc:
            raise FrameError(f"corrupt compressed payload: {exc}") from exc
        if len(raw) != raw_len or d.unconsumed_tail or not d.eof or d.unused_data:
            raise FrameError(f"compressed payload does not hold exactly {raw_len} bytes")
    else:
        raw = bytes(payload)
        if len(raw) != raw_len:
            raise FrameError(f"payload must be {raw_len} bytes, got {len(raw)}")
    n = 6 * res * res
    colors = np.frombuffer(raw, dtype=np.uint8, count=3 * n).reshape(6, res, res, 3).copy()
    codes = np.frombuffer(raw, dtype="<u2", count=n, offset=3 * n).reshape(6, res, res)
    if hi == 0.0 and np.any(codes):
        raise FrameError("range codes present but the range bounds are empty")
    ranges = decode_ranges(codes, lo, hi)
    return CubemapFrame(int(cell), center, colors, ranges, r1, r2, float(lo), float(hi))
