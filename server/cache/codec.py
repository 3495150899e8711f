"""Keys and values of the shared (Redis) cache: pure functions, no I/O.

Keys name everything a value depends on, so replicas that differ in anything never meet each
other's values. A PVS is stored under its ``PVSKey.shared()`` (``server.cache.key``:
``pvs:v<key version>:<scene hash>:<core>:<params hash>:<box|segment>:<region hash>``), the
same for a grid cell and an ad-hoc box with the same corners. A cell's near-far cubemap is
stored under ``cubemap_key`` (``cell_key`` with ``cubemap`` as its core and a digest of radii,
resolution and the scene's colours, which the fingerprint leaves out, as its parameters:
``pvs:v<FORMAT_VERSION>:<scene hash>:cubemap:<params hash>:<cell>:<box hash>``; the cell id is
there for people reading the keys, ``redis-cli --scan``, the box hash for the machines). The
scene hash is the scene's content fingerprint (``visibility.scene.scene_fingerprint``).

Values are compact binary with a header carrying the format version and a checksum of the key
and body, so a value copied under another key, truncated or of another format is refused
(``BadEntry``), never served:

- a PVS: ``PVS_HEADER``, the granularity, then the triangle ids (and the object and sphere ids
  when present) as sorted id arrays stored as little-endian int32 gaps, zlib level 1 over the
  lot (the gaps of a sorted id set are small numbers, so they compress well at little cost;
  figures: docs/deploying.md, ``benchmarks/bench_redis.py``); read back, the ids are checked as the
  on-disk cache checks them (sorted, unique, below the scene's triangle count);
- a blob (an encoded cubemap frame): ``BLOB_HEADER`` then the bytes, zlib level 1 when that
  saves at least an eighth.
"""

from __future__ import annotations

import hashlib
import re
import struct
import zlib

import numpy as np

from server.cache.checks import BadEntry, check_ids
from visibility.cores.base import PVS

#: Version of keys and values; bump it whenever either changes meaning (old values then simply
#: miss, and expire by their TTL).
FORMAT_VERSION = 1
NAMESPACE = "pvs"
PVS_MAGIC = b"PVSr"
BLOB_MAGIC = b"PVSb"
#: magic, version, flags, granularity length, n_triangles (-1: unknown), seconds, ids, objects,
#: spheres, checksum.
PVS_HEADER = struct.Struct("<4sBBHqdIII8s")
#: magic, version, flags, raw length, checksum.
BLOB_HEADER = struct.Struct("<4sBBxxI8s")
F_ZLIB = 1
F_OBJECTS = 2
F_SPHERES = 4
#: Most sphere ids a value may claim (spheres are few; the bound stops a bad header's
#: decompression from claiming gigabytes).
MAX_SPHERES = 1 << 24

_SAFE = re.compile(r"[^A-Za-z0-9_.-]")


def digest(text: str | bytes, size: int = 8) -> str:
    """blake2b of ``text``, ``size`` bytes, as hex."""
    data = text.encode() if isinstance(text, str) else text
    return hashlib.blake2b(data, digest_size=size).hexdigest()


def box_digest(box: np.ndarray) -> str:
    """8 hex digits naming a region's corners (float64, metres)."""
    return digest(np.ascontiguousarray(box, dtype="<f8").tobytes(), 4)


def token(text: str) -> str:
    """``text`` fit for one part of a key: key parts are separated by ':', so a core name
    holding one must not shift the others."""
    return _SAFE.sub("_", text) or "_"


def cell_key(fingerprint: str, core: str, params_key: str, cell: int, box: np.ndarray) -> str:
    """The shared-cache key of a value kept per grid cell (module docstring: cubemaps)."""
    return (f"{NAMESPACE}:v{FORMAT_VERSION}:{token(fingerprint)}:{token(core)}:"
            f"{digest(params_key)}:{int(cell)}:{box_digest(box)}")


def cubemap_key(fingerprint: str, colours: str, r1: float, r2: float, resolution: int,
                cell: int, box: np.ndarray) -> str:
    """The shared-cache key of a cell's encoded cubemap frame (module docstring); ``colours``
    is ``colours_digest`` of the scene."""
    params = f"r1={float(r1)!r},r2={float(r2)!r},resolution={int(resolution)},colours={colours}"
    return cell_key(fingerprint, "cubemap", params, cell, box)


def colours_digest(colors: np.ndarray) -> str:
    """16 hex digits naming a scene's per-face colours."""
    a = np.ascontiguousarray(colors, dtype=np.uint8)
    return digest(repr(a.shape).encode() + a.tobytes())


def _gaps(ids: np.ndarray) -> bytes:
    a = np.asarray(ids, dtype=np.int64)
    return np.diff(a, prepend=0).astype("<i4").tobytes()


def _ungap(raw: bytes, name: str, upper: int | None) -> np.ndarray:
    ids = np.cumsum(np.frombuffer(raw, dtype="<i4").astype(np.int64))
    if len(ids) > 1 and np.any(ids[1:] <= ids[:-1]):
        raise BadEntry(f"{name} are not sorted and unique")
    return check_ids(name, ids, upper)


def _checksum(key: str, head: bytes, body: bytes) -> bytes:
    h = hashlib.blake2b(digest_size=8)
    h.update(key.encode())
    h.update(b"\0")
    h.update(head)
    h.update(body)
    return h.digest()


def encode_pvs(key: str, pvs: PVS, n_triangles: int | None = None, compress: bool = True) -> bytes:
    """The value of ``pvs`` stored under ``key`` (module docstring). ``n_triangles``: the
    scene's triangle count, stored so readers can bound the ids; ``compress`` False stores the
    gaps without zlib (for measurements). Raises BadEntry for ids a reader would refuse."""
    n = -1 if n_triangles is None else int(n_triangles)
    ids = check_ids("triangle ids", np.asarray(pvs.triangle_ids), n if n >= 0 else None)
    arrays: list[np.ndarray] = [ids]
    flags = F_ZLIB if compress else 0
    n_obj = n_sph = 0
    if pvs.object_ids is not None:
        arrays.append(check_ids("object ids", np.asarray(pvs.object_ids), None))
        flags |= F_OBJECTS
        n_obj = len(arrays[-1])
    if pvs.sphere_ids is not None:
        arrays.append(check_ids("sphere ids", np.asarray(pvs.sphere_ids), None))
        flags |= F_SPHERES
        n_sph = len(arrays[-1])
    payload = b"".join(_gaps(a) for a in arrays)
    if compress:
        payload = zlib.compress(payload, 1)
    gran = pvs.granularity.encode()
    body = gran + payload
    fields = (PVS_MAGIC, FORMAT_VERSION, flags, len(gran), n, float(pvs.seconds), len(ids),
              n_obj, n_sph)
    head = PVS_HEADER.pack(*fields, b"\0" * 8)[:-8]
    return head + _checksum(key, head, body) + body


def _inflate(data: bytes, size: int) -> bytes:
    """``data`` decompressed, refusing anything but exactly ``size`` bytes (no bombs)."""
    try:
        d = zlib.decompressobj()
        out = d.decompress(data, size)
        if len(out) != size or d.unconsumed_tail or not d.eof:
            raise BadEntry("its payload has another length than its header says")
    except zlib.error:
        raise BadEntry("its payload is not zlib") from None
    return out


def decode_pvs(key: str, value: bytes, n_triangles: int | None = None) -> PVS | None:
    """The PVS in ``value`` read under ``key``; None for another format version (a miss);
    BadEntry for a value failing a check. ``n_triangles``: the scene's triangle count (ids
    must lie below it and the stored count must equal it)."""
    if len(value) < PVS_HEADER.size:
        raise BadEntry("shorter than its header")
    magic, version, flags, n_gran, stored_n, seconds, n_ids, n_obj, n_sph, check = \
        PVS_HEADER.unpack_from(value)
    if magic != PVS_MAGIC:
        raise BadEntry("not a PVS value")
    if version != FORMAT_VERSION:
        return None
    head, body = value[:PVS_HEADER.size - 8], value[PVS_HEADER.size:]
    if _checksum(key, head, body) != check:
        raise BadEntry("checksum mismatch (another key's value, or damaged)")
    if n_triangles is not None and stored_n >= 0 and stored_n != int(n_triangles):
        raise BadEntry(f"it is for {stored_n} triangles, the scene has {n_triangles}")
    upper = int(n_triangles) if n_triangles is not None else (stored_n if stored_n >= 0 else None)
    if upper is not None and (n_ids > upper or n_obj > upper) or n_sph > MAX_SPHERES:
        raise BadEntry("it claims more ids than the scene holds")
    gran = body[:n_gran].decode("utf-8", "replace")
    if gran not in ("triangle", "object"):
        raise BadEntry(f"unknown granularity {gran!r}")
    payload = body[n_gran:]
    size = 4 * (n_ids + n_obj + n_sph)
    if flags & F_ZLIB:
        payload = _inflate(payload, size)
    elif len(payload) != size:
        raise BadEntry("its payload has another length than its header says")
    ids = _ungap(payload[:4 * n_ids], "triangle ids", upper)
    at = 4 * n_ids
    obj = sph = None
    if flags & F_OBJECTS:
        obj = _ungap(payload[at:at + 4 * n_obj], "object ids", None)
        at += 4 * n_obj
    if flags & F_SPHERES:
        sph = _ungap(payload[at:at + 4 * n_sph], "sphere ids", None)
    return PVS(ids, granularity=gran, object_ids=obj, sphere_ids=sph,
               stats={"seconds": float(seconds), "redis": True})


def encode_blob(key: str, data: bytes) -> bytes:
    """The value of ``data`` (an encoded cubemap frame) under ``key``: compressed when that
    saves at least an eighth."""
    flags, body = 0, bytes(data)
    packed = zlib.compress(body, 1)
    if len(packed) <= len(body) - len(body) // 8:
        flags, body = F_ZLIB, packed
    head = BLOB_HEADER.pack(BLOB_MAGIC, FORMAT_VERSION, flags, len(data), b"\0" * 8)[:-8]
    return head + _checksum(key, head, body) + body


def decode_blob(key: str, value: bytes, max_bytes: int) -> bytes | None:
    """The bytes in ``value`` read under ``key``; None for another format version; BadEntry
    for a failing value or one whose bytes exceed ``max_bytes``."""
    if len(value) < BLOB_HEADER.size:
        raise BadEntry("shorter than its header")
    magic, version, flags, size, check = BLOB_HEADER.unpack_from(value)
    if magic != BLOB_MAGIC:
        raise BadEntry("not a blob value")
    if version != FORMAT_VERSION:
        return None
    head, body = value[:BLOB_HEADER.size - 8], value[BLOB_HEADER.size:]
    if _checksum(key, head, body) != check:
        raise BadEntry("checksum mismatch (another key's value, or damaged)")
    if size > max_bytes:
        raise BadEntry(f"it claims {size} bytes, over the {max_bytes} allowed")
    if flags & F_ZLIB:
        return _inflate(body, size)
    if len(body) != size:
        raise BadEntry("its payload has another length than its header says")
    return body
