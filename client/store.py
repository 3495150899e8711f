"""The client's geometry store: the triangles received so far, by id.

Chunks are appended as they arrive (cheap) and merged into one id-sorted set of arrays when
someone reads (``arrays``, ``len``, ``ids``...) or once the waiting chunks outgrow what is held
(``MERGE_ROWS``), so receiving N chunks costs O(total) rather than O(N * total). A triangle
received twice keeps its latest data. ``version`` bumps on every change so a renderer re-uploads
only when the content changed. Thread-safe: the network session writes from its event loop while
a renderer reads from another thread.

Bounded by the scene, whatever a server sends: given the scene's triangle (and sphere) count, as
the welcome says it, the store refuses ids outside [0, count) (ValueError), holds one copy per
id once merged, and never lets chunks waiting to merge exceed ``max(MERGE_ROWS, rows held)``
rows, so a server repeating the same triangles cannot grow it past about twice the scene.

Dynamic scenes. A moving triangle also has keyframes (its corners at the scene's keyframe times,
``protocol.keyframes``), kept by id and dropped with the triangle; ``triangles_at(t)`` and
``layers_at(t)`` give the held triangles at scene time t, interpolated piecewise linearly between
keyframes and clamped to their range, exactly as ``visibility.scene.Scene.vertices_at``. Spheres
(id, radius, colour, centre per keyframe) are kept apart (``spheres_at(t)``): the server's drops
name triangles only, so spheres stay until ``clear``.
"""

from __future__ import annotations

import threading

import numpy as np

from protocol.frames import GeometryChunk
from protocol.keyframes import KeyframeChunk, SphereChunk

#: Rows (triangles, keyframed triangles or spheres) that may wait unmerged beyond the rows held;
#: past ``max(MERGE_ROWS, held)`` the store merges at once, which keeps merging O(total) (each
#: merge at least doubles what it has to do) and the waiting copies bounded.
MERGE_ROWS = 1 << 16


def check_ids(ids: np.ndarray, count: int | None, what: str) -> np.ndarray:
    """``ids`` as a 1-D integer array when every id is in [0, count) ([0, 2**31) when ``count``
    is None: ids are int32 on the wire); ValueError naming the bound otherwise.

    Parameters
    ----------
    ids : (n,) integer ids.
    count : the scene's number of such items (the welcome's), or None.
    what : what the ids name, for the message ("triangle", "sphere").
    """
    ids = np.asarray(ids)
    n = len(ids) if ids.ndim == 1 else 0
    if ids.ndim != 1 or (n and not np.issubdtype(ids.dtype, np.integer)):
        raise ValueError(f"{what} ids must be a 1-D integer array, got {ids.dtype} {ids.shape}")
    bound = int(np.iinfo(np.int32).max) + 1 if count is None else int(count)
    if n and (ids.min() < 0 or ids.max() >= bound):
        scope = "2**31" if count is None else f"{bound}, the scene's {what} count"
        raise ValueError(f"{what} ids must be in [0, {scope}), got ids from {int(ids.min())} "
                         f"to {int(ids.max())}")
    return ids


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def latest_copies(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ``ids`` (n,) in arrival order, possibly repeated: the sorted unique ids (int32) and,
    per unique id, the index of its latest copy. A stable sort keeps arrival order within equal
    ids, so the last of each run is the latest (np.unique is hash-based and many times slower
    in numpy 2.x)."""
    order = np.argsort(ids, kind="stable")
    s = ids[order]
    last = np.ones(len(s), dtype=bool)
    last[:-1] = s[1:] != s[:-1]
    return s[last].astype(np.int32), order[last]


def keyframe_weights(times: np.ndarray, t: float) -> tuple[int, int, float]:
    """(i, j, w): position at scene time ``t`` (seconds) is ``(1 - w) * key[i] + w * key[j]``
    for keyframes at ``times`` (k,) increasing; ``t`` is clamped to [times[0], times[-1]], as
    ``visibility.scene.Scene.vertices_at`` does."""
    k = len(times)
    if k == 1:
        return 0, 0, 0.0
    tc = float(np.clip(t, times[0], times[-1]))
    i = int(np.clip(np.searchsorted(times, tc, side="right") - 1, 0, k - 2))
    return i, i + 1, (tc - float(times[i])) / float(times[i + 1] - times[i])


class _Tracks:
    """Items by id (sorted) with positions at shared keyframe times: ``pos`` (n, k, *shape)
    float64 and per-item ``extra`` arrays. Not locked: the owning store locks."""

    def __init__(self, shape: tuple[int, ...], extra: dict[str, tuple[tuple, type]]) -> None:
        self.shape = shape
        self.extra_spec = extra
        self.times: np.ndarray | None = None
        self.ids = np.zeros(0, dtype=np.int32)
        self.pos = np.zeros((0, 1, *shape))
        self.extra = {k: np.zeros((0, *s), dtype=d) for k, (s, d) in extra.items()}
        self._pending: list[tuple[np.ndarray, np.ndarray, dict]] = []
        self._pending_rows = 0

    def add(self, ids: np.ndarray, times: np.ndarray, pos: np.ndarray, extra: dict) -> None:
        """``pos`` (k, n, *shape) as on the wire; ValueError when ``times`` differ from the
        keyframe times already held (one scene has one set of keyframe times)."""
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        if len(times) < 1 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise ValueError("keyframe times must be finite and strictly increasing")
        if self.times is None or not np.array_equal(self.times, times):
            if len(self.ids) or self._pending:
                raise ValueError(f"keyframe times {times.tolist()[:4]}... differ from the held "
                                 f"ones {self.times.tolist()[:4]}...")
            self.times = times
            self.pos = np.zeros((0, len(times), *self.shape))
        self._pending.append((ids.astype(np.int32), np.moveaxis(pos, 0, 1).copy(), extra))
        self._pending_rows += len(ids)
        if self._pending_rows > max(MERGE_ROWS, len(self.ids)):
            self.merge()

    def merge(self) -> None:
        if not self._pending:
            return
        ids = np.concatenate([self.ids] + [p[0] for p in self._pending])
        pos = np.concatenate([self.pos] + [p[1] for p in self._pending])
        extra = {k: np.concatenate([self.extra[k]] + [p[2][k] for p in self._pending])
                 for k in self.extra}
        self._pending.clear()
        self._pending_rows = 0
        # Latest data wins for repeated ids (as for geometry).
        self.ids, src = latest_copies(ids)
        self.pos = pos[src]
        self.extra = {k: v[src] for k, v in extra.items()}

    def keep(self, mask: np.ndarray) -> int:
        removed = int(len(mask) - np.count_nonzero(mask))
        if removed:
            self.ids, self.pos = self.ids[mask], self.pos[mask]
            self.extra = {k: v[mask] for k, v in self.extra.items()}
        return removed

    def clear(self) -> None:
        self._pending.clear()
        self._pending_rows = 0
        self.keep(np.zeros(len(self.ids), dtype=bool))

    def at(self, t: float | None) -> np.ndarray:
        """(n, *shape) float64 positions at scene time t (seconds; None: the first keyframe)."""
        if not len(self.ids):
            return np.zeros((0, *self.shape))
        if t is None:
            return self.pos[:, 0].copy()
        i, j, w = keyframe_weights(self.times, t)
        if w == 0.0:
            return self.pos[:, i].copy()
        return (1.0 - w) * self.pos[:, i] + w * self.pos[:, j]

    @property
    def nbytes(self) -> int:
        n = self.ids.nbytes + self.pos.nbytes + sum(v.nbytes for v in self.extra.values())
        return n + sum(a.nbytes + b.nbytes for a, b, _ in self._pending)


class GeometryStore:
    """Triangles by id: absolute float64 corner positions (metres) and uint8 RGB colours.

    Parameters
    ----------
    budget : most triangles the client means to hold (None: no limit). The store does not evict
        by itself (it cannot know what is still visible); ``over_budget`` tells when the holder
        should ``retain`` the current PVS.
    scene_triangles : the scene's triangle count (the welcome's ``scene.triangles``): triangle
        ids (geometry and keyframes) outside [0, scene_triangles) are refused. None: any int32
        id.
    scene_spheres : the scene's sphere count (``scene.spheres``), the same for sphere ids.
    """

    def __init__(self, budget: int | None = None, *, scene_triangles: int | None = None,
                 scene_spheres: int | None = None) -> None:
        if budget is not None and int(budget) <= 0:
            raise ValueError(f"budget must be positive, got {budget}")
        for name, count in (("scene_triangles", scene_triangles),
                            ("scene_spheres", scene_spheres)):
            if count is not None and int(count) < 0:
                raise ValueError(f"{name} must be >= 0, got {count}")
        self.budget = None if budget is None else int(budget)
        self.scene_triangles = None if scene_triangles is None else int(scene_triangles)
        self.scene_spheres = None if scene_spheres is None else int(scene_spheres)
        self._lock = threading.RLock()
        self._ids = np.zeros(0, dtype=np.int32)
        self._tris = np.zeros((0, 3, 3), dtype=np.float64)
        self._colors = np.zeros((0, 3), dtype=np.uint8)
        self._pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._pending_rows = 0
        self.version = 0
        self._out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._keys = _Tracks((3, 3), {})
        self._spheres = _Tracks((3,), {"radii": ((), np.float64), "colors": ((3,), np.uint8)})
        self._static_out: tuple[int, tuple, np.ndarray] | None = None

    # ----------------------------------------------------------------------------- writing
    def add(self, ids: np.ndarray, triangles: np.ndarray, colors: np.ndarray) -> None:
        """Add (or replace) triangles: ``ids`` (n,) ints in [0, scene_triangles), ``triangles``
        (n, 3, 3) metres, ``colors`` (n, 3) uint8. ValueError on ids out of range, inconsistent
        shapes or non-finite positions (nothing is added then)."""
        ids = check_ids(ids, self.scene_triangles, "triangle")
        n = len(ids)
        tris = np.asarray(triangles, dtype=np.float64)
        cols = np.asarray(colors)
        if tris.shape != (n, 3, 3) or cols.shape != (n, 3):
            raise ValueError(
                f"need triangles ({n}, 3, 3) and colors ({n}, 3), got {tris.shape}, {cols.shape}"
            )
        if not np.all(np.isfinite(tris)):
            raise ValueError("triangle positions must be finite")
        if n == 0:
            return
        with self._lock:
            self._pending.append((ids.astype(np.int32), tris.copy(), cols.astype(np.uint8)))
            self._pending_rows += n
            self._changed()
            if self._pending_rows > max(MERGE_ROWS, len(self._ids)):
                self._merge()

    def add_chunk(self, chunk: GeometryChunk) -> None:
        """Add a decoded geometry frame (positions made absolute in float64)."""
        self.add(chunk.ids, chunk.triangles, chunk.colors)

    def add_keyframes(self, ids: np.ndarray, times: np.ndarray, positions: np.ndarray) -> None:
        """Add (or replace) the keyframes of moving triangles: ``ids`` (n,), ``times`` (k,)
        seconds increasing, ``positions`` (k, n, 3, 3) corner positions in metres. Kept whether
        or not the triangle itself is held yet (frames may arrive in either order). ValueError on
        ids outside [0, scene_triangles), bad shapes, non-finite positions, or times that
        differ from the keyframe times held."""
        ids = check_ids(ids, self.scene_triangles, "triangle")
        n = len(ids)
        pos = np.asarray(positions, dtype=np.float64)
        k = len(np.asarray(times).reshape(-1))
        if pos.shape != (k, n, 3, 3):
            raise ValueError(f"positions must be ({k}, {n}, 3, 3), got {pos.shape}")
        if not np.all(np.isfinite(pos)):
            raise ValueError("keyframe positions must be finite")
        if n == 0:
            return
        with self._lock:
            self._keys.add(ids, times, pos, {})
            self._changed()

    def add_keyframe_chunk(self, chunk: KeyframeChunk) -> None:
        """Add a decoded keyframe frame holding all its items' keyframes (``chunk.complete``;
        windows are joined first by ``protocol.keyframes.KeyframeAssembler``)."""
        if not chunk.complete:
            raise ValueError("a keyframe window: join the windows first (KeyframeAssembler)")
        self.add_keyframes(chunk.ids, chunk.times, chunk.triangles)

    def add_spheres(self, ids: np.ndarray, times: np.ndarray, centers: np.ndarray,
                    radii: np.ndarray, colors: np.ndarray) -> None:
        """Add (or replace) spheres: ``ids`` (s,) sphere indices in [0, scene_spheres), ``times``
        (k,) seconds, ``centers`` (k, s, 3) metres, ``radii`` (s,) metres > 0, ``colors`` (s, 3)
        uint8."""
        ids = check_ids(ids, self.scene_spheres, "sphere")
        n = len(ids)
        c = np.asarray(centers, dtype=np.float64)
        k = len(np.asarray(times).reshape(-1))
        r = np.asarray(radii, dtype=np.float64).reshape(-1)
        cols = np.asarray(colors)
        if c.shape != (k, n, 3) or r.shape != (n,) or cols.shape != (n, 3):
            raise ValueError(f"need centers ({k}, {n}, 3), radii ({n},), colors ({n}, 3); got "
                             f"{c.shape}, {r.shape}, {cols.shape}")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(r)) and np.all(r > 0)):
            raise ValueError("sphere centres must be finite and radii finite and positive")
        if n == 0:
            return
        with self._lock:
            self._spheres.add(ids, times, c, {"radii": r, "colors": cols.astype(np.uint8)})
            self._changed()

    def add_sphere_chunk(self, chunk: SphereChunk) -> None:
        """Add a decoded sphere frame holding all its spheres' keyframes."""
        if not chunk.complete:
            raise ValueError("a sphere keyframe window: join the windows first")
        self.add_spheres(chunk.ids, chunk.times, chunk.absolute_centers, chunk.radii,
                         chunk.colors)

    def drop(self, ids: np.ndarray) -> int:
        """Remove these triangle ids and their keyframes (absent ones are ignored); returns how
        many triangles were removed."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        with self._lock:
            self._merge()
            keep = ~np.isin(self._ids, ids)
            removed = int(len(keep) - np.count_nonzero(keep))
            if removed:
                self._set(self._ids[keep], self._tris[keep], self._colors[keep])
            if self._keys.keep(~np.isin(self._keys.ids, ids)):
                self._changed()
            return removed

    def retain(self, ids: np.ndarray) -> int:
        """Keep only these ids (e.g. the current PVS); returns how many were removed."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        with self._lock:
            self._merge()
            keep = np.isin(self._ids, ids)
            removed = int(len(keep) - np.count_nonzero(keep))
            if removed:
                self._set(self._ids[keep], self._tris[keep], self._colors[keep])
            if self._keys.keep(np.isin(self._keys.ids, ids)):
                self._changed()
            return removed

    def clear(self) -> None:
        """Remove everything (triangles, keyframes, spheres)."""
        with self._lock:
            self._pending.clear()
            self._pending_rows = 0
            self._keys.clear()
            self._spheres.clear()
            self._set(self._ids[:0], self._tris[:0], self._colors[:0])

    # ----------------------------------------------------------------------------- reading
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids (k,) int32 sorted, triangles (k, 3, 3) float64 metres, colors (k, 3) uint8).

        The same read-only arrays are returned until the store changes (compare ``version``).
        """
        with self._lock:
            self._merge()
            if self._out is None:
                self._out = (_readonly(self._ids.copy()), _readonly(self._tris.copy()),
                             _readonly(self._colors.copy()))
            return self._out

    def snapshot(self) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """(version, ids, triangles, colors) read atomically: the version that matches the arrays
        even while the network thread keeps adding (reading ``version`` and ``arrays()`` one
        after the other can pair new version with old arrays)."""
        with self._lock:
            return (self.version, *self.arrays())

    @property
    def ids(self) -> np.ndarray:
        """(k,) int32 sorted ids held."""
        return self.arrays()[0]

    def keyframes(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """(ids (m,) int32 sorted, times (k,) seconds or None, positions (m, k, 3, 3) float64):
        the keyframes held (copies)."""
        with self._lock:
            self._keys.merge()
            return self._keys.ids.copy(), (None if self._keys.times is None
                                           else self._keys.times.copy()), self._keys.pos.copy()

    def layers_at(self, t: float | None) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray],
                                                  tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The held triangles at scene time ``t`` (seconds; None: the first keyframe, i.e. at
        rest) in two parts: ((ids, triangles, colors) of those without keyframes, the same for
        those with keyframes, their corners interpolated at t). The first part's arrays are the
        same objects until ``version`` changes, so a renderer uploads the static part once and
        only the moving part per t."""
        with self._lock:
            ids, tris, cols = self.arrays()
            self._keys.merge()
            if self._static_out is None or self._static_out[0] != self.version:
                pos = np.searchsorted(self._keys.ids, ids)
                pos = np.clip(pos, 0, max(len(self._keys.ids) - 1, 0))
                moving = ((self._keys.ids[pos] == ids) if len(self._keys.ids)
                          else np.zeros(len(ids), dtype=bool))
                still = ~moving
                static = tuple(_readonly(a[still].copy()) for a in (ids, tris, cols))
                self._static_out = (self.version, static, moving)
            _, static, moving = self._static_out
            mids = ids[moving]
            rows = np.searchsorted(self._keys.ids, mids)
            mtris = self._keys.at(t)[rows] if len(mids) else np.zeros((0, 3, 3))
            return static, (mids, mtris, cols[moving])

    def triangles_at(self, t: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, triangles (k, 3, 3) float64 metres, colors) of every held triangle at scene
        time ``t`` (seconds): keyframed ones interpolated, the others as received."""
        (si, st, sc), (mi, mt, mc) = self.layers_at(t)
        order = np.argsort(np.concatenate([si, mi]), kind="stable")
        return (np.concatenate([si, mi])[order], np.concatenate([st, mt])[order],
                np.concatenate([sc, mc])[order])

    def spheres_at(self, t: float | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ids (s,) int32, centres (s, 3) float64 metres at scene time ``t`` seconds (None: the
        first keyframe), radii (s,) metres, colors (s, 3) uint8) of the spheres held."""
        with self._lock:
            self._spheres.merge()
            sp = self._spheres
            return (sp.ids.copy(), sp.at(t), sp.extra["radii"].copy(),
                    sp.extra["colors"].copy())

    @property
    def n_spheres(self) -> int:
        """Spheres held."""
        with self._lock:
            self._spheres.merge()
            return int(len(self._spheres.ids))

    def __len__(self) -> int:
        with self._lock:
            self._merge()
            return int(len(self._ids))

    def contains(self, ids: np.ndarray) -> np.ndarray:
        """(n,) bool: which of ``ids`` the store holds."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        with self._lock:
            self._merge()
            held = self._ids
            pos = np.clip(np.searchsorted(held, ids), 0, max(len(held) - 1, 0))
            return (held[pos] == ids) if len(held) else np.zeros(len(ids), dtype=bool)

    def __contains__(self, tid: object) -> bool:
        return bool(self.contains(np.array([tid]))[0])

    @property
    def over_budget(self) -> bool:
        """True when a budget is set and the store holds more triangles than it."""
        return self.budget is not None and len(self) > self.budget

    @property
    def nbytes(self) -> int:
        """Memory held by the merged arrays and pending chunks, bytes."""
        with self._lock:
            n = self._ids.nbytes + self._tris.nbytes + self._colors.nbytes
            n += self._keys.nbytes + self._spheres.nbytes
            return n + sum(a.nbytes + b.nbytes + c.nbytes for a, b, c in self._pending)

    # ----------------------------------------------------------------------------- internals
    def _changed(self) -> None:
        self.version += 1
        self._out = None

    def _set(self, ids: np.ndarray, tris: np.ndarray, colors: np.ndarray) -> None:
        self._ids, self._tris, self._colors = ids, tris, colors
        self._changed()

    def _merge(self) -> None:
        if not self._pending:
            return
        ids = np.concatenate([self._ids] + [p[0] for p in self._pending])
        tris = np.concatenate([self._tris] + [p[1] for p in self._pending])
        cols = np.concatenate([self._colors] + [p[2] for p in self._pending])
        self._pending.clear()
        self._pending_rows = 0
        # Latest data wins for repeated ids.
        self._ids, src = latest_copies(ids)
        self._tris, self._colors = tris[src], cols[src]
        # Merging does not change the content, so version stays; cached outputs are stale.
        self._out = None
