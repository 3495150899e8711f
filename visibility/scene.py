"""The scene model: triangles with stable ids, per-face object ids and colours, optional motion.

Conventions: Y-up, right-handed, metres. A triangle id is the row index of ``Scene.faces`` and
never changes for a scene. Geometry is kept in float64; the wire uses float32.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from visibility.ids import unique_inverse

#: Smallest triangle area (m^2) that still counts as a surface; below it a face is degenerate.
MIN_FACE_AREA = 1e-12
#: Faces (or vertices) per block of the per-face passes (validity, bounds, hashing, centroids):
#: their temporaries stay a few tens of MB instead of growing with the scene.
FACE_BLOCK = 1 << 18


def _as_faces(faces: np.ndarray) -> np.ndarray:
    """(m, 3) int32 C-contiguous faces: ``faces`` itself when it already is, else converted
    (indices past int32 wrap as ``astype`` wraps them; non-integers go through int64)."""
    f = np.asarray(faces)
    if f.dtype == np.int32:
        return np.ascontiguousarray(f).reshape(-1, 3)
    if not np.issubdtype(f.dtype, np.integer):
        f = np.asarray(f, dtype=np.int64)
    return np.ascontiguousarray(f.reshape(-1, 3).astype(np.int32))


@dataclass(frozen=True)
class WalkArea:
    """Where people walk: axis-aligned XZ rectangles, each with its floor height.

    ``rects`` is (w, 6) float64 rows ``[x0, z0, x1, z1, floor_y, ceiling_y]`` in metres; rows
    of 5 are accepted and get an open sky (``ceiling_y = inf``). A viewcell's eye range is cut
    0.1 m under the ceiling.
    """

    rects: np.ndarray
    eye_height: float = 1.7
    #: Vertical range of the eye above the floor that a viewcell covers, (low, high) metres.
    eye_range: tuple[float, float] = (1.5, 1.9)

    def __post_init__(self) -> None:
        rects = np.asarray(self.rects, dtype=np.float64)
        if rects.size == 0:
            rects = np.zeros((0, 6))
        if rects.ndim != 2 or rects.shape[1] not in (5, 6):
            raise ValueError(f"walk rects must be (w, 5) or (w, 6), got {rects.shape}")
        if rects.shape[1] == 5:
            rects = np.concatenate([rects, np.full((len(rects), 1), np.inf)], axis=1)
        if not np.all(np.isfinite(rects[:, :5])):
            raise ValueError("walk rects must be finite (the ceiling may be inf)")
        object.__setattr__(self, "rects", rects)


@dataclass(frozen=True)
class DegenerateReport:
    """Counts of faces kept out of computation, by reason (a face may have several reasons)."""

    zero_area: int = 0
    non_finite: int = 0
    repeated_index: int = 0
    out_of_range: int = 0

    @property
    def total_reasons(self) -> int:
        return self.zero_area + self.non_finite + self.repeated_index + self.out_of_range

    def as_dict(self) -> dict[str, int]:
        return {
            "zero_area": self.zero_area,
            "non_finite": self.non_finite,
            "repeated_index": self.repeated_index,
            "out_of_range": self.out_of_range,
        }


def _lerp_keyframes(frames: np.ndarray, times: np.ndarray, t: float) -> np.ndarray:
    """Piecewise-linear interpolation of keyframes (k, ...) at ``times`` (k,), clamped.

    Exact at the keyframes, and for values that do not change between two keyframes (static
    vertices stay bit for bit where they are: the scene hierarchy recognises its vertices by
    them)."""
    t = float(np.clip(t, times[0], times[-1]))
    i = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
    w = (t - times[i]) / (times[i + 1] - times[i])
    if w >= 1.0:
        return frames[i + 1].copy()
    return frames[i] + w * (frames[i + 1] - frames[i])


@dataclass(eq=False)
class Scene:
    """A triangle scene.

    Attributes
    ----------
    vertices : (n, 3) float64, metres, the rest state.
    faces : (m, 3) int32, indices into ``vertices``. Triangle id = row index.
    object_ids : (m,) int32, object (mesh/node) each face belongs to.
    colors : (m, 3) uint8, RGB per face.
    states : optional (k, n, 3) float64 keyframes of vertex positions; position is piecewise
        linear in time between ``state_times``. ``vertices`` equals ``states[0]`` when present.
    state_times : optional (k,) float64 seconds, increasing.
    sphere_centers : optional (k, s, 3) float64 (k = 1 for static spheres), metres.
    sphere_radii : optional (s,) float64, metres.
    sphere_colors : optional (s, 3) uint8.
    walk : optional WalkArea where people walk (generators fill it; loaders leave it to detection).
    """

    vertices: np.ndarray
    faces: np.ndarray
    object_ids: np.ndarray | None = None
    colors: np.ndarray | None = None
    name: str = "scene"
    states: np.ndarray | None = None
    state_times: np.ndarray | None = None
    sphere_centers: np.ndarray | None = None
    sphere_radii: np.ndarray | None = None
    sphere_colors: np.ndarray | None = None
    walk: WalkArea | None = None
    object_names: list[str] | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = _as_faces(self.faces)
        m = len(self.faces)
        if self.object_ids is None:
            self.object_ids = np.zeros(m, dtype=np.int32)
        self.object_ids = np.ascontiguousarray(self.object_ids, dtype=np.int32).reshape(m)
        if self.colors is None:
            self.colors = np.full((m, 3), 200, dtype=np.uint8)
        self.colors = np.ascontiguousarray(self.colors, dtype=np.uint8).reshape(m, 3)
        if self.states is not None:
            self.states = np.ascontiguousarray(self.states, dtype=np.float64)
            if self.states.ndim != 3 or self.states.shape[1:] != self.vertices.shape:
                raise ValueError(
                    f"states must be (k, {len(self.vertices)}, 3), got {self.states.shape}"
                )
            k = self.states.shape[0]
            if self.state_times is None:
                self.state_times = np.arange(k, dtype=np.float64)
            self.state_times = np.asarray(self.state_times, dtype=np.float64).reshape(k)
            if k > 1 and not np.all(np.diff(self.state_times) > 0):
                raise ValueError("state_times must be strictly increasing")
        if self.sphere_radii is not None:
            self.sphere_radii = np.asarray(self.sphere_radii, dtype=np.float64).reshape(-1)
            s = len(self.sphere_radii)
            c = np.asarray(self.sphere_centers, dtype=np.float64)
            self.sphere_centers = c.reshape(-1, s, 3)
            if self.sphere_colors is None:
                self.sphere_colors = np.full((s, 3), 180, dtype=np.uint8)
            self.sphere_colors = np.asarray(self.sphere_colors, dtype=np.uint8).reshape(s, 3)
        self._valid: np.ndarray | None = None
        self._report: DegenerateReport | None = None

    # ----------------------------------------------------------------------------- sizes
    @property
    def n_triangles(self) -> int:
        return int(len(self.faces))

    @property
    def n_vertices(self) -> int:
        return int(len(self.vertices))

    @property
    def n_spheres(self) -> int:
        return 0 if self.sphere_radii is None else int(len(self.sphere_radii))

    @property
    def is_dynamic(self) -> bool:
        """True when vertices or spheres move over time."""
        moving_tris = self.states is not None and self.states.shape[0] > 1
        moving_spheres = self.sphere_centers is not None and self.sphere_centers.shape[0] > 1
        return bool(moving_tris or moving_spheres)

    @property
    def n_objects(self) -> int:
        return int(self.object_ids.max()) + 1 if len(self.object_ids) else 0

    # ----------------------------------------------------------------------------- validity
    def _classify(self) -> None:
        n = len(self.vertices)
        f = self.faces
        m = len(f)
        verts = self.vertices if self.states is None else self.states.reshape(-1, n, 3)
        if verts.ndim == 2:
            verts = verts[None]
        finite_v = np.ones(n, dtype=bool)
        for v in verts:
            finite_v &= np.all(np.isfinite(v), axis=1)
        valid = np.empty(m, dtype=bool)
        counts = np.zeros(4, dtype=np.int64)  # zero area, non-finite, repeated, out of range
        # Face blocks bound the temporaries (corners, edges, cross products, per-reason flags)
        # to a few tens of MB whatever the scene's size; every test is per face.
        for s in range(0, m, FACE_BLOCK):
            fb = f[s:s + FACE_BLOCK]
            out_of_range = np.any((fb < 0) | (fb >= n), axis=1)
            repeated = (fb[:, 0] == fb[:, 1]) | (fb[:, 1] == fb[:, 2]) | (fb[:, 0] == fb[:, 2])
            if n:
                fi = np.where(out_of_range[:, None], 0, fb) if out_of_range.any() else fb
                non_finite = ~np.all(finite_v[fi], axis=1)
                # A moving face counts as a surface if it has area in any state.
                has_area = np.zeros(len(fb), dtype=bool)
                for v in verts:
                    a, b, c = v[fi[:, 0]], v[fi[:, 1]], v[fi[:, 2]]
                    # Relative to the first vertex keeps the cross product exact-ish at 1e5 m
                    # offsets.
                    with np.errstate(invalid="ignore", over="ignore"):
                        area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
                    has_area |= np.isfinite(area2) & (area2 > 2 * MIN_FACE_AREA)
                zero_area = ~has_area & ~non_finite
            else:
                non_finite = np.zeros(len(fb), dtype=bool)
                zero_area = np.ones(len(fb), dtype=bool)
            valid[s:s + len(fb)] = ~(out_of_range | repeated | non_finite | zero_area)
            counts += [np.count_nonzero(zero_area & ~repeated & ~out_of_range),
                       np.count_nonzero(non_finite & ~out_of_range),
                       np.count_nonzero(repeated), np.count_nonzero(out_of_range)]
        self._valid = valid
        self._report = DegenerateReport(
            zero_area=int(counts[0]), non_finite=int(counts[1]),
            repeated_index=int(counts[2]), out_of_range=int(counts[3]),
        )

    @property
    def valid_faces(self) -> np.ndarray:
        """(m,) bool: faces that take part in computation (finite, in range, non-zero area)."""
        if self._valid is None:
            self._classify()
        return self._valid

    @property
    def degenerate_report(self) -> DegenerateReport:
        """How many faces are kept out of computation and why."""
        if self._report is None:
            self._classify()
        return self._report

    # ----------------------------------------------------------------------------- geometry
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 [min, max] over finite vertices of valid faces (all states), metres."""
        used = self.used_vertices()
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        # By vertex blocks: no copy of the used vertices (or of every state's) is made whole.
        for s in range(0, len(used), FACE_BLOCK):
            u = used[s:s + FACE_BLOCK]
            if not u.any():
                continue
            v = (self.vertices[s:s + FACE_BLOCK][u] if self.states is None
                 else self.states[:, s:s + FACE_BLOCK][:, u].reshape(-1, 3))
            lo = np.minimum(lo, v.min(axis=0))
            hi = np.maximum(hi, v.max(axis=0))
        if self.n_spheres:
            c = self.sphere_centers.reshape(-1, 3)
            r = np.tile(self.sphere_radii, self.sphere_centers.shape[0])[:, None]
            lo = np.minimum(lo, (c - r).min(axis=0))
            hi = np.maximum(hi, (c + r).max(axis=0))
        if not np.all(lo <= hi):
            return np.zeros((2, 3))
        return np.stack([lo, hi])

    def used_vertices(self) -> np.ndarray:
        """(n,) bool: the vertices that some valid face uses."""
        used = np.zeros(self.n_vertices, dtype=bool)
        valid = self.valid_faces
        for s in range(0, self.n_triangles, FACE_BLOCK):
            used[self.faces[s:s + FACE_BLOCK][valid[s:s + FACE_BLOCK]].reshape(-1)] = True
        return used

    def vertices_at(self, t: float) -> np.ndarray:
        """(n, 3) float64 vertex positions at time t (seconds), clamped to the keyframe range."""
        if self.states is None or self.states.shape[0] == 1:
            return self.vertices
        return _lerp_keyframes(self.states, self.state_times, t)

    @property
    def sphere_times(self) -> np.ndarray | None:
        """(k,) float64 seconds of the sphere keyframes: the generator's ``meta["sphere_times"]``,
        else ``state_times`` when they have as many keyframes, else 0, 1, 2, ...; None without
        spheres."""
        if not self.n_spheres:
            return None
        k = self.sphere_centers.shape[0]
        times = self.meta.get("sphere_times")
        if times is not None and len(times) == k:
            return np.asarray(times, dtype=np.float64)
        if self.state_times is not None and len(self.state_times) == k:
            return self.state_times
        return np.arange(k, dtype=np.float64)

    def time_range(self) -> tuple[float, float]:
        """(first, last) keyframe time in seconds over vertex and sphere keyframes; (0, 0) for a
        static scene."""
        ends = [t[[0, -1]] for t in (self.state_times if self.states is not None else None,
                                      self.sphere_times) if t is not None and len(t) > 1]
        if not ends:
            return 0.0, 0.0
        return float(min(e[0] for e in ends)), float(max(e[1] for e in ends))

    def sphere_centers_at(self, t: float) -> np.ndarray:
        """(s, 3) float64 sphere centres at time t (seconds), piecewise linear between the sphere
        keyframes and clamped to their range; (0, 3) without spheres."""
        if not self.n_spheres:
            return np.zeros((0, 3))
        c = self.sphere_centers
        if c.shape[0] == 1:
            return c[0]
        return _lerp_keyframes(c, self.sphere_times, t)

    def centroids(self, t: float | None = None) -> np.ndarray:
        """(m, 3) float64 centroid of every triangle (at time t, seconds, when given), metres;
        NaN rows for faces with an index out of range. Equal to ``triangles().mean(axis=1)``
        without its (m, 3, 3) temporary."""
        v = self.vertices if t is None else self.vertices_at(t)
        n = len(v)
        out = np.empty((self.n_triangles, 3))
        for s in range(0, self.n_triangles, FACE_BLOCK):
            fb = self.faces[s:s + FACE_BLOCK]
            bad = np.any((fb < 0) | (fb >= n), axis=1)
            with np.errstate(invalid="ignore", over="ignore"):
                c = v[np.where(bad[:, None], 0, fb) if n else fb].mean(axis=1)
            c[bad] = np.nan
            out[s:s + len(fb)] = c
        return out

    def triangles(self, ids: np.ndarray | None = None, t: float | None = None) -> np.ndarray:
        """(len(ids), 3, 3) float64 corner positions of the given triangle ids (all by default)."""
        v = self.vertices if t is None else self.vertices_at(t)
        f = self.faces if ids is None else self.faces[np.asarray(ids, dtype=np.int64)]
        return v[f]

    def subset(self, ids: np.ndarray) -> Scene:
        """A new static scene holding only the given triangle ids (renumbered 0..len-1)."""
        ids = np.asarray(ids, dtype=np.int64)
        f = self.faces[ids]
        used, inv = unique_inverse(f.reshape(-1))
        return Scene(
            vertices=self.vertices[used],
            faces=inv.reshape(-1, 3),
            object_ids=self.object_ids[ids],
            colors=self.colors[ids],
            name=f"{self.name}[subset]",
        )

    def summary(self) -> dict:
        """A JSON-friendly description: counts, bounds, motion, degenerate faces."""
        b = self.bounds()
        return {
            "name": self.name,
            "triangles": self.n_triangles,
            "vertices": self.n_vertices,
            "objects": self.n_objects,
            "spheres": self.n_spheres,
            "dynamic": self.is_dynamic,
            "states": 1 if self.states is None else int(self.states.shape[0]),
            "bounds": b.tolist(),
            "degenerate": self.degenerate_report.as_dict(),
            "valid_triangles": int(np.count_nonzero(self.valid_faces)),
        }


def scene_fingerprint(scene: Scene) -> str:
    """A 16-hex-digit hash of what a PVS of ``scene`` depends on: vertices, faces, per-face
    object ids, vertex keyframes and spheres (not colours, names or metadata).

    Two scenes with equal fingerprints have the same triangle ids at the same places, so caches
    that outlive a process (on-disk PVS, ground truth) key on it instead of the scene's name.
    """
    h = hashlib.blake2b(digest_size=8)
    for arr, dtype in ((scene.vertices, np.float64), (scene.faces, np.int64),
                       (scene.object_ids, np.int32), (scene.states, np.float64),
                       (scene.sphere_centers, np.float64), (scene.sphere_radii, np.float64)):
        if arr is None:
            h.update(b"-")
            continue
        # The shape separates arrays, so (n, 3) + (0,) never hashes like (n - 1, 3) + (3,).
        h.update(repr(arr.shape).encode())
        # Row blocks in C order: the same bytes as the whole array's, without a converted copy
        # (int32 faces become int64) or a bytes copy of it.
        flat = arr.reshape(len(arr), -1) if arr.ndim else arr.reshape(1, 1)
        for s in range(0, len(flat), FACE_BLOCK):
            h.update(np.ascontiguousarray(flat[s:s + FACE_BLOCK], dtype=dtype).data)
    return h.hexdigest()


def moving_faces(scene: Scene) -> np.ndarray:
    """(m,) bool: the valid faces with a corner whose position differs between the scene's
    keyframes (all False for a static scene).

    The one definition of a moving (dynamic) face: the server streams their keyframes, near-far
    never bakes them into a cubemap, the client draws them per frame.
    """
    if scene.states is None or scene.states.shape[0] < 2:
        return np.zeros(scene.n_triangles, dtype=bool)
    moves = np.any(scene.states != scene.states[:1], axis=(0, 2))
    # Out-of-range corners are clipped, not trusted: such faces are invalid and masked below.
    f = np.clip(scene.faces, 0, max(scene.n_vertices - 1, 0))
    return np.any(moves[f], axis=1) & scene.valid_faces
