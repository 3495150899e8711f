"""An independent reference for conservative cores: dense random ray casting from a cell.

Eyes are drawn at random in the cell's box (uniformly inside, a share on its faces, and its 8
corners), never on a grid; each eye casts rays in random directions (uniform on the sphere),
optionally plus rays aimed at random points of given triangles (``aim``: a slit, a target),
and every triangle a ray hits first is seen. Nothing here shares code with the rasterizer or the
cores: two engines cast the rays,

* ``"embree"``: Intel Embree (``embreex``) over the scene's valid triangles, in float32; and
* ``"exact"``: a float64 Moller-Trumbore caster (numba) over every triangle, for small scenes
  and for tolerance cases (1e-13..1e-8 m), which float32 cannot judge.

Both work in a frame centred on the cell: vertices minus the cell centre in float64 (then float32
for Embree), so precision follows the cell's size, not the coordinates' magnitude
(georeferenced scenes sit 1e6 m from their origin). A triangle Embree reports can be confirmed
in float64 (``confirm``): each of its witness rays is cast again, exactly, over the whole scene.

**Near plane.** A client drawing with near plane ``d`` clips everything at view depth below
``d`` (``visibility.raster.camera``: depth is the distance along the view axis). Each eye gets a
random cube orientation, as a cubemap client has; a ray in direction ``u`` lies in the cube
face whose forward axis ``f`` is nearest to it, and is clipped up to ``t_c = d / (u . f)`` along
the ray: what it hits first beyond ``t_c`` is what that client sees there, including what lies
behind a wall nearer than the near plane. ``nears`` lists the near planes whose views are
united (0: an eye that sees every surface however close).

**Open space.** An eye inside geometry (inside a closed solid: a building, a wall's thickness)
is dropped: the cores promise what eyes in open space see. An eye counts as inside when nearly
all its random rays (near plane 0, ``INSIDE_SHARE``) first hit the back of a triangle
(counter-clockwise front faces, clockwise when the scene's ``meta["winding"]`` is ``"cw"``).

Conventions: Y-up, right-handed, metres; triangle ids are row indices of ``scene.faces``.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numba import get_num_threads, njit, prange

from visibility.exact_grid import build_grid, grid_first_hits, ray_triangle
from visibility.raster.camera import DEFAULT_NEAR, random_rotations
from visibility.scene import Scene

#: Rays cast per batch (Embree query or exact kernel call): bounds the temporaries.
BATCH_RAYS = 1 << 17
#: Fewest rays per thread when ``EmbreeCaster.first_hits`` splits a batch over threads.
CAST_CHUNK_MIN = 1 << 15
#: Witness rays kept per seen triangle (for ``confirm`` and for failure messages).
WITNESSES = 4
#: Share of an eye's random rays (near plane 0) that must hit a back face first for the eye to
#: count as inside geometry (inside a closed solid all of them do; an eye in open space among
#: single-sided surfaces of either facing sees about as many fronts as backs).
INSIDE_SHARE = 0.9
#: Engines.
ENGINES = ("embree", "exact")
#: Triangles from which ``ExactCaster`` walks a grid rather than testing every triangle.
GRID_MIN = 2048


@dataclass
class RaySample:
    """What the rays of one cell saw.

    Attributes
    ----------
    ids : (k,) int64 sorted ids of the triangles hit first by some ray.
    centre : (3,) float64 the cell centre (the frame's origin), metres.
    eyes : (e, 3) float64 the eyes kept (in open space), world metres.
    dropped : eyes dropped as inside geometry.
    rays : rays cast (over every near plane, dropped eyes included).
    witness_id : (w,) int64 triangle of each witness ray; ``witness_eye`` (w, 3) its eye
        (world metres), ``witness_dir`` (w, 3) its unit direction, ``witness_tmin`` (w,) where
        along the ray the near plane clipped it, ``witness_t`` (w,) the hit's distance from
        the eye, metres.
    engine : "embree" or "exact".
    nears : the near planes (metres) whose views are united.
    """

    ids: np.ndarray
    centre: np.ndarray
    eyes: np.ndarray
    dropped: int
    rays: int
    witness_id: np.ndarray
    witness_eye: np.ndarray
    witness_dir: np.ndarray
    witness_tmin: np.ndarray
    witness_t: np.ndarray
    engine: str
    nears: tuple[float, ...]


# ------------------------------------------------------------------------------ sampling
def draw_eyes(box: np.ndarray, n: int, rng: np.random.Generator,
              boundary_share: float = 0.25) -> np.ndarray:
    """(n + 8, 3) float64 eyes of the closed box (2, 3) [min, max] metres: ``n`` drawn at
    random, ``boundary_share`` of them uniformly on its faces (a face picked by area) and the
    rest uniformly inside, then its 8 corners. No grid: every coordinate is a fresh draw."""
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
        raise ValueError(f"box must be finite with max >= min, got {b.tolist()}")
    n = int(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    size = b[1] - b[0]
    u = rng.random((n, 3))
    n_face = int(round(float(boundary_share) * n))
    area = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
    if n_face and area.sum() > 0.0:
        axis = rng.choice(3, size=n_face, p=area / area.sum())
        u[np.arange(n_face), axis] = rng.integers(0, 2, size=n_face).astype(np.float64)
    pts = b[0] + u * size
    corners = np.array([[b[(c >> a) & 1, a] for a in range(3)] for c in range(8)])
    return np.clip(np.concatenate([pts, corners]), b[0], b[1])


def random_directions(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 unit vectors drawn uniformly on the sphere."""
    d = rng.normal(size=(int(n), 3))
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.where(norm > 0.0, norm, 1.0)
    d[norm[:, 0] == 0.0] = (0.0, 0.0, 1.0)
    return d


def aimed_directions(eye: np.ndarray, aim: np.ndarray, n: int,
                     rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 unit directions from ``eye`` (3,) to uniformly random points of random
    triangles of ``aim`` (k, 3, 3) (each picked with the same chance), both in one frame."""
    k = rng.integers(0, len(aim), size=int(n))
    a, b = rng.random(int(n)), rng.random(int(n))
    flip = a + b > 1.0
    a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
    t = aim[k]
    p = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
    d = p - eye
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(norm > 0.0, norm, 1.0)


def near_clip(dirs: np.ndarray, cube: np.ndarray, near: float) -> np.ndarray:
    """(n,) float64 distance along each unit ray (n, 3) below which a cubemap client oriented
    by ``cube`` (3, 3) (its rows: the face axes) with near plane ``near`` metres clips: its view
    depth there is t (u . f), f the axis of the face holding u (the largest |cube @ u|)."""
    if near <= 0.0:
        return np.zeros(len(dirs))
    c = np.abs(dirs @ np.asarray(cube, dtype=np.float64).T).max(axis=1)
    return float(near) / c


# ------------------------------------------------------------------------------ exact caster
@njit(cache=True, nogil=True, parallel=True)
def exact_first_hits(tri, lo, hi, orig, dirs, tmin, out_id, out_t):  # pragma: no cover
    """First hit of each ray (float64): ``tri`` (k, 3, 3) triangles with boxes ``lo``, ``hi``
    (k, 3); ray r starts at ``orig[r]`` (3,) in direction ``dirs[r]`` and counts hits at
    distance >= ``tmin[r]``. Writes the triangle's row (-1: none) and distance."""
    for r in prange(orig.shape[0]):
        ox, oy, oz = orig[r, 0], orig[r, 1], orig[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        ix = 1.0 / dx if dx != 0.0 else np.inf
        iy = 1.0 / dy if dy != 0.0 else np.inf
        iz = 1.0 / dz if dz != 0.0 else np.inf
        best = np.inf
        bid = -1
        t0 = tmin[r]
        for i in range(tri.shape[0]):
            # Slab test on the triangle's box first (rejects most of a large scene cheaply).
            a0 = -np.inf
            a1 = np.inf
            ok = True
            for k in range(3):
                o = ox if k == 0 else (oy if k == 1 else oz)
                iv = ix if k == 0 else (iy if k == 1 else iz)
                if iv == np.inf:
                    if o < lo[i, k] or o > hi[i, k]:
                        ok = False
                        break
                    continue
                s0 = (lo[i, k] - o) * iv
                s1 = (hi[i, k] - o) * iv
                if s0 > s1:
                    s0, s1 = s1, s0
                a0 = max(a0, s0)
                a1 = min(a1, s1)
            if not ok:
                continue
            # A loose slab test (flat boxes have zero thickness): Moller-Trumbore decides.
            slack = 1e-9 * (abs(a0) + abs(a1)) + 1e-300
            if a0 > a1 + slack or a1 < t0 - slack or a0 > best + slack:
                continue
            t = ray_triangle(tri, i, ox, oy, oz, dx, dy, dz)
            if t >= t0 and t < best:
                best = t
                bid = i
        out_id[r] = bid
        out_t[r] = best


class ExactCaster:
    """``exact_first_hits`` over a fixed triangle set (k, 3, 3), in the cell's frame; from
    ``GRID_MIN`` triangles on through a uniform grid (``visibility.exact_grid``), which gives
    the same answer faster."""

    def __init__(self, tri: np.ndarray) -> None:
        self.tri = np.ascontiguousarray(tri, dtype=np.float64)
        self.lo = np.ascontiguousarray(self.tri.min(axis=1))
        self.hi = np.ascontiguousarray(self.tri.max(axis=1))
        self.grid = build_grid(self.lo, self.hi) if len(self.tri) >= GRID_MIN else None

    def first_hits(self, orig: np.ndarray, dirs: np.ndarray, tmin: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        n = len(orig)
        out_id = np.empty(n, dtype=np.int64)
        out_t = np.empty(n)
        # Writable C-ordered float64, as the kernels are compiled for: a read-only input (one
        # eye broadcast to one ray reads as contiguous) would compile them a second time.
        orig, dirs, tmin = (np.require(a, dtype=np.float64, requirements=("C", "W"))
                            for a in (orig, dirs, tmin))
        if self.grid is not None:
            grid_first_hits(self.tri, self.grid, orig, dirs, tmin, out_id, out_t)
        elif len(self.tri):
            exact_first_hits(self.tri, self.lo, self.hi, orig, dirs, tmin, out_id, out_t)
        else:
            out_id[:] = -1
            out_t[:] = np.inf
        return out_id, out_t


class EmbreeCaster:
    """Embree first hits over a fixed triangle set (k, 3, 3) in the cell's frame, float32."""

    def __init__(self, tri: np.ndarray) -> None:
        try:
            from embreex import mesh_construction, rtcore_scene
        except ImportError as exc:  # the reference needs it: say so, never fall back
            raise ImportError("the ray reference's 'embree' engine needs embreex "
                              "(pip install embreex)") from exc
        self._scene = rtcore_scene.EmbreeScene()
        self._n = len(tri)
        if self._n:
            mesh_construction.TriangleMesh(self._scene,
                                           np.ascontiguousarray(tri, dtype=np.float32))
            # The first run commits the scene (builds its BVH): done here, alone, so that
            # later runs may share it from several threads.
            one = np.zeros((1, 3), dtype=np.float32)
            self._scene.run(one, one + np.float32(1.0))

    def first_hits(self, orig: np.ndarray, dirs: np.ndarray, tmin: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        n = len(orig)
        if self._n == 0 or n == 0:
            return np.full(n, -1, dtype=np.int64), np.full(n, np.inf)
        # Embree starts every ray at its origin (tnear 0): a clipped ray starts at its clip.
        start = np.empty((n, 3), dtype=np.float32)
        d32 = np.empty((n, 3), dtype=np.float32)
        # Contiguous, as most callers pass them (a broadcast eye is read-only, layout A):
        # _ray_starts compiles once.
        tmin = np.ascontiguousarray(tmin)
        _ray_starts(np.ascontiguousarray(orig), np.ascontiguousarray(dirs), tmin, start, d32)
        ids = np.empty(n, dtype=np.int64)
        t = np.empty(n)
        # embreex casts one ray at a time with the GIL released: large batches are split over
        # numba's threads (each ray's answer is its own, so the split changes nothing).
        parts = min(get_num_threads(), n // CAST_CHUNK_MIN)
        if parts < 2:
            self._cast(start, d32, tmin, ids, t)
            return ids, t
        cuts = np.linspace(0, n, parts + 1).astype(np.int64)
        with ThreadPoolExecutor(parts) as pool:
            list(pool.map(lambda k: self._cast(start[cuts[k]:cuts[k + 1]],
                                               d32[cuts[k]:cuts[k + 1]],
                                               tmin[cuts[k]:cuts[k + 1]],
                                               ids[cuts[k]:cuts[k + 1]],
                                               t[cuts[k]:cuts[k + 1]]), range(parts)))
        return ids, t

    def _cast(self, start: np.ndarray, d32: np.ndarray, tmin: np.ndarray, ids: np.ndarray,
              t: np.ndarray) -> None:
        res = self._scene.run(start, d32, output=1)
        _ray_hits(res["primID"], res["geomID"], res["tfar"], tmin, ids, t)


@njit(cache=True, nogil=True)
def _ray_starts(orig, dirs, tmin, start, d32):  # pragma: no cover - numba
    """Embree's float32 rays: origins moved to their clip distance ``tmin``, directions."""
    for r in range(orig.shape[0]):
        for c in range(3):
            start[r, c] = orig[r, c] + tmin[r] * dirs[r, c]
            d32[r, c] = dirs[r, c]


@njit(cache=True, nogil=True)
def _ray_hits(prim, geom, tfar, tmin, ids, t):  # pragma: no cover - numba
    """Embree's answers as triangle rows (-1: none) and distances from the unclipped origin
    (inf: none)."""
    for r in range(prim.shape[0]):
        if geom[r] < 0:
            ids[r] = -1
            t[r] = np.inf
        else:
            ids[r] = prim[r]
            t[r] = tfar[r] + tmin[r]


# ------------------------------------------------------------------------------ reference
def frame_triangles(scene: Scene, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Valid triangles of a static scene relative to ``centre`` (float64, (k, 3, 3)) and their
    ids (k,)."""
    if scene.is_dynamic:
        raise ValueError("the ray reference takes static scenes (its rays see the rest state "
                         f"only); {scene.name!r} moves")
    valid = np.flatnonzero(scene.valid_faces)
    tri = scene.vertices[scene.faces[valid]] - centre
    return np.ascontiguousarray(tri, dtype=np.float64), valid.astype(np.int64)


def front_normals(tri: np.ndarray, scene: Scene) -> np.ndarray:
    """(k, 3) front-face normals (not unit) of triangles (k, 3, 3) of ``scene``
    (counter-clockwise fronts, clockwise when its ``meta["winding"]`` is ``"cw"``)."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return -n if str(scene.meta.get("winding", "ccw")).lower() == "cw" else n


def back_hits(dirs: np.ndarray, hit: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(n,) bool: rays (n, 3) whose first hit ``hit`` (n,) (-1: none) is the back of its
    triangle (``normals``, ``front_normals``): the open-space test counts them, since from
    inside a solid nearly every ray meets a back face first (``INSIDE_SHARE``)."""
    back = np.empty(len(dirs), dtype=np.bool_)
    _back_hits(np.asarray(dirs), np.asarray(hit), np.asarray(normals), back)
    return back


@njit(cache=True, nogil=True)
def _back_hits(dirs, hit, normals, back):  # pragma: no cover - numba
    for r in range(hit.shape[0]):
        h = hit[r]
        back[r] = h >= 0 and (dirs[r, 0] * normals[h, 0] + dirs[r, 1] * normals[h, 1]
                              + dirs[r, 2] * normals[h, 2]) > 0.0


def ray_reference(
    scene: Scene,
    box: np.ndarray,
    n_eyes: int = 256,
    n_dirs: int = 1024,
    seed: int = 0,
    nears: Sequence[float] = (0.0, DEFAULT_NEAR),
    aim: np.ndarray | None = None,
    n_aim: int = 0,
    engine: str = "embree",
    boundary_share: float = 0.25,
    eyes: np.ndarray | None = None,
) -> RaySample:
    """Triangles seen first by random rays from random eyes in open space of the cell ``box``.

    Parameters
    ----------
    scene : a static scene; its valid faces are cast against.
    box : (2, 3) float64 [min, max] metres, the cell.
    n_eyes : eyes drawn at random (``draw_eyes``: plus the 8 corners), before dropping those
        inside geometry.
    n_dirs : random directions per eye (uniform on the sphere).
    seed : seeds eyes, directions, aims and cube orientations.
    nears : near planes (metres, >= 0) whose views are united (module docstring).
    aim : optional (k, 3, 3) world triangles; ``n_aim`` rays per eye go to random points of
        them (a slit's opening, a target behind it), on top of the random ones.
    engine : "embree" (float32) or "exact" (float64, every triangle per ray: small scenes).
    boundary_share : share of the drawn eyes put on the box's faces.
    eyes : optional (e, 3) world eyes to use instead of drawing them.

    Returns
    -------
    RaySample, the seen ids sorted.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    nears = tuple(float(d) for d in nears)
    if not nears or any(not (np.isfinite(d) and d >= 0.0) for d in nears):
        raise ValueError(f"nears must be finite distances >= 0, got {nears}")
    if int(n_dirs) < 1:
        raise ValueError(f"n_dirs must be >= 1, got {n_dirs}")
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    rng = np.random.default_rng(seed)
    centre = 0.5 * (b[0] + b[1])
    world_eyes = draw_eyes(b, n_eyes, rng, boundary_share) if eyes is None else \
        np.asarray(eyes, dtype=np.float64).reshape(-1, 3)
    tri, tri_ids = frame_triangles(scene, centre)
    normals = front_normals(tri, scene)
    caster = EmbreeCaster(tri) if engine == "embree" else ExactCaster(tri)
    aim_local = None
    if aim is not None and int(n_aim) > 0:
        aim_local = np.asarray(aim, dtype=np.float64).reshape(-1, 3, 3) - centre
    n_aim = int(n_aim) if aim_local is not None else 0
    per_eye = int(n_dirs) + n_aim
    cubes = random_rotations(rng, len(world_eyes))
    seen = np.zeros(len(tri), dtype=bool)
    wit_count = np.zeros(len(tri), dtype=np.int64)
    wit: list[tuple[np.ndarray, ...]] = []
    kept = np.ones(len(world_eyes), dtype=bool)
    rays = 0
    group = max(1, BATCH_RAYS // (per_eye * len(nears)))
    for g0 in range(0, len(world_eyes), group):
        g1 = min(len(world_eyes), g0 + group)
        k = g1 - g0
        local = world_eyes[g0:g1] - centre
        dirs = np.empty((k, per_eye, 3))
        for e in range(k):
            dirs[e, :n_dirs] = random_directions(n_dirs, rng)
            if n_aim:
                dirs[e, n_dirs:] = aimed_directions(local[e], aim_local, n_aim, rng)
        orig = np.repeat(local, per_eye, axis=0)
        flat = dirs.reshape(-1, 3)
        # Open space: most random rays of an eye inside a solid hit a back face first.
        zero = np.zeros(len(flat))
        hid, ht = caster.first_hits(orig, flat, zero)
        rays += len(flat)
        back = back_hits(flat, hid, normals).reshape(k, per_eye)[:, :n_dirs]
        inside = back.sum(axis=1) >= INSIDE_SHARE * n_dirs
        kept[g0:g1] = ~inside
        eye_of = np.repeat(np.arange(g0, g1), per_eye)
        for near in nears:
            if near == 0.0:
                ids, t, tmin = hid, ht, zero
            else:
                tmin = np.concatenate([near_clip(dirs[e], cubes[g0 + e], near)
                                       for e in range(k)])
                ids, t = caster.first_hits(orig, flat, tmin)
                rays += len(flat)
            use = (ids >= 0) & kept[eye_of]
            if not use.any():
                continue
            t_use = t[use]
            r_idx = np.flatnonzero(use)
            hit_ids = ids[use]
            seen[hit_ids] = True
            # One new witness per triangle per batch, up to WITNESSES each.
            uniq, first = np.unique(hit_ids, return_index=True)
            want = wit_count[uniq] < WITNESSES
            uniq, first = uniq[want], first[want]
            wit_count[uniq] += 1
            r = r_idx[first]
            wit.append((uniq, world_eyes[eye_of[r]], flat[r], tmin[r], t_use[first]))
    ids = np.sort(tri_ids[seen])
    if wit:
        w_id = tri_ids[np.concatenate([w[0] for w in wit])]
        w_eye, w_dir, w_tmin, w_t = (np.concatenate([w[i] for w in wit]) for i in (1, 2, 3, 4))
    else:
        w_id = np.zeros(0, np.int64)
        w_eye = w_dir = np.zeros((0, 3))
        w_tmin = w_t = np.zeros(0)
    return RaySample(ids, centre, world_eyes[kept], int((~kept).sum()), rays, w_id, w_eye,
                     w_dir, w_tmin, w_t, engine, nears)


def rays_seen(scene: Scene, box: np.ndarray, n_eyes: int = 256, n_dirs: int = 1024,
              seed: int = 0, **kwargs) -> np.ndarray:
    """Sorted int64 ids of the triangles ``ray_reference`` sees (same parameters)."""
    return ray_reference(scene, box, n_eyes, n_dirs, seed, **kwargs).ids


# ------------------------------------------------------------------------------ judging
def confirm(scene: Scene, sample: RaySample, ids: np.ndarray) -> np.ndarray:
    """Sorted ids among ``ids`` that some witness ray of ``sample`` still hits first when cast
    again in float64 over every valid triangle of the scene (``exact_first_hits``, in the
    sample's frame): the misses float32 rounding cannot explain."""
    ids = np.asarray(ids, dtype=np.int64)
    pick = np.flatnonzero(np.isin(sample.witness_id, ids))
    if len(pick) == 0:
        return np.zeros(0, np.int64)
    tri, tri_ids = frame_triangles(scene, sample.centre)
    caster = ExactCaster(tri)
    orig = sample.witness_eye[pick] - sample.centre
    got, _ = caster.first_hits(orig, sample.witness_dir[pick], sample.witness_tmin[pick])
    same = (got >= 0) & (tri_ids[np.maximum(got, 0)] == sample.witness_id[pick])
    return np.unique(sample.witness_id[pick][same])


def describe(scene: Scene, sample: RaySample, ids: np.ndarray, box: np.ndarray,
             limit: int = 8) -> str:
    """Where the triangles ``ids`` are and which ray saw each (for failure messages): its
    centroid relative to the cell centre, its distance from the box, one witness eye (relative
    to the cell centre), direction, near-plane clip and hit distance, metres."""
    ids = np.asarray(ids, dtype=np.int64)
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    lines = []
    for i in ids[:limit]:
        tri = scene.vertices[scene.faces[i]]
        c = tri.mean(axis=0) - sample.centre
        lo, hi = tri.min(axis=0), tri.max(axis=0)
        gap = np.maximum(0.0, np.maximum(lo - b[1], b[0] - hi))
        line = (f"triangle {int(i)}: centroid {np.array2string(c, precision=4)} m from the "
                f"cell centre, {float(np.linalg.norm(gap)):.3g} m from the box")
        w = np.flatnonzero(sample.witness_id == i)
        if len(w):
            k = w[0]
            eye = np.array2string(sample.witness_eye[k] - sample.centre, precision=5)
            line += (f"; seen from eye {eye}"
                     f" along {np.array2string(sample.witness_dir[k], precision=4)}"
                     f" (clip {sample.witness_tmin[k]:.3g} m, hit at {sample.witness_t[k]:.4g} m)")
        lines.append(line)
    if len(ids) > limit:
        lines.append(f"... and {len(ids) - limit} more")
    return "\n".join(lines)
