"""The disk tier: PVS as checked ``.npz`` files that survive restarts (``DiskPVSCache``)."""

from __future__ import annotations

import hashlib
import io
import logging
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from server.cache.checks import BadEntry, check_ids
from server.cache.key import PVSKey
from visibility.cores.base import PVS
from visibility.scene_cache import load_npz

log = logging.getLogger(__name__)

#: Format tag of on-disk PVS entries. Entries without it (or with another) are from an older
#: server: a miss, recomputed and overwritten, never read.
DISK_FORMAT = "pvs-disk-2"


def _checksum(key_repr: str, n_triangles: int, granularity: str, ids: np.ndarray,
              objects: np.ndarray | None, spheres: np.ndarray | None) -> str:
    """blake2b (16 bytes, hex) of an entry's key, triangle count, granularity and id arrays
    (little-endian int32, each prefixed by its length, absent arrays marked)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(key_repr.encode())
    h.update(b"\0%d\0%s\0" % (int(n_triangles), granularity.encode()))
    for arr in (ids, objects, spheres):
        if arr is None:
            h.update(b"-")
            continue
        a = np.ascontiguousarray(arr, dtype="<i4")
        h.update(b"%d:" % len(a))
        h.update(a.tobytes())
    return h.hexdigest()


class DiskPVSCache:
    """PVS as ``.npz`` files under ``folder`` (one per key), surviving restarts. Caches are
    checked, not trusted.

    Keys are ``PVSKey``s: their first item names the scene's geometry (its fingerprint, so a
    changed scene file or generator size never meets old files), the rest the region, core,
    parameters and key version. File name: ``<sha256 of the fingerprint>/<sha256 of
    repr(key)>.npz``. An entry carries its format
    (``DISK_FORMAT``), the key's ``repr``, the scene fingerprint, the parameters (the rest of
    the key), the scene's triangle count when the writer knew it, the ids, granularity,
    seconds and a blake2b checksum of key, count and ids. On read the key, fingerprint and
    parameters must match, the checksum must match, and the ids must be sorted unique int32 in
    [0, n_triangles) (the caller's ``n_triangles``, which must also equal the stored one, or
    else the stored one). An entry failing any check (or unreadable: truncated, not a zip) is
    logged without its path, deleted, counted in ``rejected`` and is a miss, so it is
    recomputed and never served; an entry of an older format is a plain miss. Writes go to a
    temporary file renamed into place, so a crash never leaves a half file under a real name.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.hits = 0
        self.misses = 0
        self.rejected = 0
        self.corrupt = 0
        self.outdated = 0
        self.writes = 0
        self.write_errors = 0
        self._lock = threading.Lock()

    def path(self, key: PVSKey) -> Path:
        """Where the PVS of ``key`` lives."""
        digest = hashlib.sha256(repr(key).encode()).hexdigest()[:40]
        scene = hashlib.sha256(key.fingerprint.encode()).hexdigest()[:16]
        return self.folder / scene / f"{digest}.npz"

    def _count(self, name: str) -> None:
        with self._lock:
            setattr(self, name, getattr(self, name) + 1)

    def _read(self, p: Path, key: PVSKey, n_triangles: int | None) -> PVS | None:
        """The checked PVS in ``p``; None for an older format; BadEntry for a bad entry."""
        try:
            z = load_npz(p)
        except Exception as exc:  # truncated, not a zip, unreadable: np.load raises many types
            raise BadEntry(f"unreadable ({type(exc).__name__})") from None
        try:
            if "format" not in z or str(z["format"]) != DISK_FORMAT:
                return None
            key_repr = repr(key)
            if str(z["key"]) != key_repr:
                raise BadEntry("it holds another key")
            if str(z["fingerprint"]) != key.fingerprint:
                raise BadEntry("it is from another scene fingerprint")
            if str(z["params"]) != repr(tuple(key)[1:]):
                raise BadEntry("it holds other parameters")
            stored_n = int(z["n_triangles"])
            if n_triangles is not None and stored_n >= 0 and stored_n != int(n_triangles):
                raise BadEntry(f"it is for {stored_n} triangles, the scene has {n_triangles}")
            upper = int(n_triangles) if n_triangles is not None else \
                (stored_n if stored_n >= 0 else None)
            granularity = str(z["granularity"])
            raw_ids = z["triangle_ids"]
            raw_obj = z["object_ids"] if bool(z["has_objects"]) else None
            raw_sph = z["sphere_ids"] if bool(z["has_spheres"]) else None
            if str(z["checksum"]) != _checksum(key_repr, stored_n, granularity, raw_ids,
                                               raw_obj, raw_sph):
                raise BadEntry("checksum mismatch")
            ids = check_ids("triangle ids", raw_ids, upper)
            obj = None if raw_obj is None else check_ids("object ids", raw_obj, None)
            sph = None if raw_sph is None else check_ids("sphere ids", raw_sph, None)
            seconds = float(z["seconds"])
        except BadEntry:
            raise
        except Exception as exc:  # missing fields, wrong types
            raise BadEntry(f"malformed ({type(exc).__name__})") from None
        return PVS(ids, granularity=granularity, object_ids=obj, sphere_ids=sph,
                   stats={"seconds": seconds, "disk": True})

    def get(self, key: PVSKey, n_triangles: int | None = None) -> PVS | None:
        """The stored, checked PVS of ``key`` or None (missing, older format or rejected).

        ``n_triangles``: the scene's triangle count; ids must lie below it (without it, below
        the count stored with the entry, when its writer gave one).
        """
        p = self.path(key)
        if not p.is_file():
            self._count("misses")
            return None
        try:
            pvs = self._read(p, key, n_triangles)
        except BadEntry as exc:
            self._reject(p, key, str(exc))
            return None
        if pvs is None:
            self._count("outdated")
            self._count("misses")
            return None
        self._count("hits")
        return pvs

    def check(self, key: PVSKey, n_triangles: int | None = None) -> bool:
        """Whether a valid entry for ``key`` is on disk (a bad one is rejected and deleted);
        counts no hit or miss."""
        p = self.path(key)
        if not p.is_file():
            return False
        try:
            return self._read(p, key, n_triangles) is not None
        except BadEntry as exc:
            self._reject(p, key, str(exc))
            return False

    def _reject(self, p: Path, key: PVSKey, why: str) -> None:
        # The scene fingerprint identifies the entry well enough; the path stays out of logs.
        log.warning("rejected an on-disk PVS cache entry of scene %s (%s): %s; recomputing",
                    key.fingerprint[:16], key.core, why)
        self._count("rejected")
        if why.startswith(("unreadable", "malformed")):
            self._count("corrupt")
        self._count("misses")
        try:
            p.unlink()
        except OSError:
            pass

    def put(self, key: PVSKey, pvs: PVS, n_triangles: int | None = None) -> bool:
        """Store ``pvs`` under ``key``; True when written. Errors are logged (without the
        path) and counted in ``write_errors``, never raised. ``n_triangles``: the scene's
        triangle count, stored so readers that do not know it can still bound the ids."""
        p = self.path(key)
        tmp = p.with_name(f".{p.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            n = -1 if n_triangles is None else int(n_triangles)
            ids = np.ascontiguousarray(pvs.triangle_ids, dtype=np.int32)
            obj = None if pvs.object_ids is None else np.asarray(pvs.object_ids, np.int32)
            sph = None if pvs.sphere_ids is None else np.asarray(pvs.sphere_ids, np.int32)
            key_repr = repr(key)
            # Never write what a reader would reject.
            check_ids("triangle ids", ids, n if n >= 0 else None)
            empty = np.zeros(0, np.int32)
            buf = io.BytesIO()
            np.savez(buf, format=np.array(DISK_FORMAT), key=np.array(key_repr),
                     fingerprint=np.array(key.fingerprint), params=np.array(repr(tuple(key)[1:])),
                     n_triangles=np.array(n), triangle_ids=ids,
                     granularity=np.array(pvs.granularity), seconds=np.array(pvs.seconds),
                     has_objects=np.array(obj is not None),
                     object_ids=obj if obj is not None else empty,
                     has_spheres=np.array(sph is not None),
                     sphere_ids=sph if sph is not None else empty,
                     checksum=np.array(_checksum(key_repr, n, pvs.granularity, ids, obj, sph)))
            p.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(buf.getvalue())
            os.replace(tmp, p)
        except Exception as exc:  # a full disk or a bad PVS must not fail the request
            log.warning("could not write an on-disk PVS cache entry of scene %s: %s",
                        key.fingerprint[:16], exc if isinstance(exc, BadEntry) else
                        type(exc).__name__)
            self._count("write_errors")
            try:
                tmp.unlink()
            except OSError:
                pass
            return False
        self._count("writes")
        return True

    def stats(self) -> dict[str, Any]:
        """Hits, misses, rejected entries (of which corrupt: unreadable), outdated (older
        format) entries, writes and write errors. No paths: stats are shown to clients."""
        with self._lock:
            return {"hits": self.hits, "misses": self.misses, "rejected": self.rejected,
                    "corrupt": self.corrupt, "outdated": self.outdated, "writes": self.writes,
                    "write_errors": self.write_errors}
