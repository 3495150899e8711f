"""Frames of independent rays: one ray per pixel of a randomly turned cube, from eyes in a cell.

What a client at an eye of the cell shows in each pixel is the triangle its ray meets first.
Aggressive cores promise a bound on the share of such pixels whose triangle their PVS lacks
(the trim regions paper: 0.005 % of a frame), so that promise is judged here by rays cast
independently of the project's rasterizer and of the cores:

* eyes stratified in the box (``ground_truth.sample_points``), each with a random cube
  orientation (``raster.camera.random_rotations``), so no eye or direction lies on a core's
  grid; an eye inside geometry (most of its rays meet a back face first,
  ``ray_reference.INSIDE_SHARE``) is dropped, as the cores promise what eyes in open space see;
* per face ``resolution``² rays, each through a uniformly random point of its pixel;
* Embree (``embreex``, float32, in a frame centred on the cell) finds the first hits, clipped
  by the frame's near plane along the view axis of the ray's face;
* every pixel a PVS would miss is cast again in float64 over every triangle
  (``ray_reference.exact_first_hits``) before it counts, so float32 cracks between welded
  triangles are not charged to the core.

Conventions: Y-up, right-handed, metres; triangle ids are row indices of ``scene.faces``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from visibility.ground_truth import sample_points
from visibility.raster.camera import random_rotations
from visibility.ray_reference import (
    INSIDE_SHARE,
    EmbreeCaster,
    ExactCaster,
    back_hits,
    frame_triangles,
    front_normals,
    near_clip,
    random_directions,
)
from visibility.scene import Scene
from visibility.viewcells import ViewcellGrid

#: Most missed pixels per frame cast again in float64 (each such ray tests every triangle of
#: the scene); past it the rest count as missed unconfirmed, an upper bound. 26 times the
#: trim regions paper's bound at 256 px (19.7 of 393,216 pixels): a frame past it fails
#: whatever the rest would show.
CONFIRM_PER_FRAME = 512


@dataclass
class RayFrames:
    """First hits of the frames of one cell.

    Attributes
    ----------
    ids : (f, 6 * resolution²) int64 triangle met first by each pixel's ray (-1: nothing).
    eyes : (f, 3) float64 world eyes of the frames kept (in open space), metres.
    cubes : (f, 3, 3) float64 their cube orientations (rows: the face axes).
    states : per frame, the random generator's state its rays were drawn from
        (``directions`` draws them again: storing 12 bytes a ray cost more than casting).
    centre : (3,) float64 the cell centre (the casting frame's origin).
    dropped : eyes dropped as inside geometry.
    resolution : pixels across a face.
    near : the frames' near plane, metres.
    """

    ids: np.ndarray
    eyes: np.ndarray
    cubes: np.ndarray
    states: list[dict]
    centre: np.ndarray
    dropped: int
    resolution: int
    near: float

    @property
    def pixels(self) -> int:
        """Pixels per frame (6 faces)."""
        return int(self.ids.shape[1])

    def directions(self, k: int, pixels: np.ndarray) -> np.ndarray:
        """(n, 3) float32 unit directions of frame ``k``'s rays at ``pixels`` (n,): the rays
        Embree cast (their near clip follows from them and the cube)."""
        rng = np.random.default_rng()
        rng.bit_generator.state = self.states[k]
        d, _ = _cube_rays(self.cubes[k], self.resolution, rng)
        return d[np.asarray(pixels, dtype=np.int64)].astype(np.float32)


def cube_directions(cube: np.ndarray, resolution: int, rng: np.random.Generator
                    ) -> np.ndarray:
    """(6 * resolution², 3) float64 unit directions, one through a uniformly random point of
    each pixel of the six faces of a cube turned by ``cube`` (3, 3) (its rows: the face axes);
    face k looks along ``(-1)^k`` times row ``k // 2``."""
    return _cube_rays(cube, resolution, rng)[0]


def _cube_rays(cube: np.ndarray, resolution: int, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray]:
    """``cube_directions`` and, per ray, 1 / (its component along its face's axis): the
    distance along the ray to view depth 1."""
    r = int(resolution)
    jitter = rng.random((6, r * r, 2))
    out = np.empty((6 * r * r, 3))
    depth1 = np.empty(6 * r * r)
    _fill_cube_rays(np.ascontiguousarray(cube, dtype=np.float64), r, jitter, out, depth1)
    return out, depth1


@njit(cache=True, nogil=True, parallel=True)
def _fill_cube_rays(c, r, jitter, out, depth1):  # pragma: no cover - numba
    for kr in prange(6 * r):
        k = kr // r
        i = kr - k * r
        a = k // 2
        s = 1.0 if k % 2 == 0 else -1.0
        b1 = (a + 1) % 3
        b2 = (a + 2) % 3
        for j in range(r):
            q = i * r + j
            u = (j + jitter[k, q, 0]) * (2.0 / r) - 1.0
            v = (i + jitter[k, q, 1]) * (2.0 / r) - 1.0
            x = s * c[a, 0] + u * c[b1, 0] + v * c[b2, 0]
            y = s * c[a, 1] + u * c[b1, 1] + v * c[b2, 1]
            z = s * c[a, 2] + u * c[b1, 2] + v * c[b2, 2]
            n = np.sqrt(x * x + y * y + z * z)
            o = k * r * r + q
            out[o, 0] = x / n
            out[o, 1] = y / n
            out[o, 2] = z / n
            depth1[o] = n


def ray_frames(scene: Scene, box: np.ndarray, n_eyes: int = 24, resolution: int = 256,
               seed: int = 0, near: float = 1e-3) -> RayFrames:
    """Frames of first hits from ``n_eyes`` eyes stratified in ``box`` (2, 3) [min, max]
    metres, each a cube of ``resolution`` px per face in a random orientation, near plane
    ``near`` metres (module docstring). ``seed`` seeds eyes, orientations and the points
    in the pixels. Static scenes only."""
    if int(resolution) < 1:
        raise ValueError(f"resolution must be >= 1, got {resolution}")
    if not (np.isfinite(near) and near >= 0.0):
        raise ValueError(f"near must be a finite distance >= 0, got {near}")
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    rng = np.random.default_rng(seed)
    eyes = sample_points(b, int(n_eyes), rng)
    cubes = random_rotations(rng, len(eyes))
    centre = 0.5 * (b[0] + b[1])
    tri, tri_ids = frame_triangles(scene, centre)
    normals = front_normals(tri, scene)
    caster = EmbreeCaster(tri)
    n_pix = 6 * int(resolution) ** 2
    ids = np.empty((len(eyes), n_pix), dtype=np.int64)
    kept = np.ones(len(eyes), dtype=bool)
    states = []
    zero = np.zeros(n_pix)
    for k in range(len(eyes)):
        states.append(rng.bit_generator.state)
        d, depth1 = _cube_rays(cubes[k], resolution, rng)
        orig = np.broadcast_to(eyes[k] - centre, d.shape)
        # Open space: from inside a solid nearly every ray meets a back face first.
        hid, ht = caster.first_hits(orig, d, zero)
        kept[k] = np.count_nonzero(back_hits(d, hid, normals)) < INSIDE_SHARE * n_pix
        # The near plane clips at view depth ``near`` along the face's axis.
        t0 = near * depth1
        # Only rays whose first hit lies before the near plane are cast again from it.
        again = np.flatnonzero(ht < t0)
        if len(again):
            hid[again] = caster.first_hits(orig[again], d[again], t0[again])[0]
        _frame_ids(hid, tri_ids, ids[k])
    if not kept.all():
        ids = ids[kept]
    return RayFrames(ids, eyes[kept], cubes[kept], [states[k] for k in np.flatnonzero(kept)],
                     centre, int((~kept).sum()), int(resolution), float(near))


@njit(cache=True, nogil=True)
def _frame_ids(hit, tri_ids, out):  # pragma: no cover - numba
    """Scene triangle ids of the caster's rows ``hit`` (-1: nothing) into ``out``."""
    for r in range(hit.shape[0]):
        out[r] = tri_ids[hit[r]] if hit[r] >= 0 else -1


def missed_pixels(scene: Scene, frames: RayFrames, pvs_ids: np.ndarray,
                  confirm: bool = True) -> np.ndarray:
    """(f,) int64 pixels per frame whose first-hit triangle the PVS ``pvs_ids`` lacks. With
    ``confirm``, each is cast again in float64 over every valid triangle (up to
    ``CONFIRM_PER_FRAME`` a frame; the rest count unconfirmed) and counts only when that
    cast also meets a triangle outside the PVS."""
    return np.array([len(m) for m in _missed(scene, frames, pvs_ids, confirm)],
                    dtype=np.int64)


def missed_triangles(scene: Scene, frames: RayFrames, pvs_ids: np.ndarray) -> np.ndarray:
    """Sorted int64 ids of the triangles outside the PVS ``pvs_ids`` that some pixel of the
    frames shows, each confirmed by the float64 cast of ``missed_pixels`` (past
    ``CONFIRM_PER_FRAME`` a frame, the float32 hit counts unconfirmed): what a core that
    promises no false negatives must never leave out."""
    got = [m for m in _missed(scene, frames, pvs_ids, True) if len(m)]
    return np.unique(np.concatenate(got)) if got else np.zeros(0, dtype=np.int64)


def _missed(scene: Scene, frames: RayFrames, pvs_ids: np.ndarray, confirm: bool
            ) -> list[np.ndarray]:
    """Per frame, the triangle outside the PVS that each missed pixel shows (``confirm``:
    by the float64 cast where it was made), one entry per pixel."""
    in_pvs = np.zeros(scene.n_triangles + 1, dtype=bool)
    in_pvs[np.asarray(pvs_ids, dtype=np.int64)] = True
    out: list[np.ndarray] = []
    caster = None
    tri_ids = None
    for k, row in enumerate(frames.ids):
        miss = np.flatnonzero((row >= 0) & ~in_pvs[np.maximum(row, 0)])
        if not confirm or len(miss) == 0:
            out.append(row[miss])
            continue
        if caster is None:
            tri, tri_ids = frame_triangles(scene, frames.centre)
            caster = ExactCaster(tri)
        check, rest = miss[:CONFIRM_PER_FRAME], miss[CONFIRM_PER_FRAME:]
        d = frames.directions(k, check).astype(np.float64)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        orig = np.broadcast_to(frames.eyes[k] - frames.centre, d.shape)
        got, _ = caster.first_hits(np.ascontiguousarray(orig), d,
                                   near_clip(d, frames.cubes[k], frames.near))
        hit = np.where(got >= 0, tri_ids[np.maximum(got, 0)], -1)
        out.append(np.concatenate([hit[(hit >= 0) & ~in_pvs[np.maximum(hit, 0)]], row[rest]]))
    return out


def in_open_space(scene: Scene, points: np.ndarray, n_dirs: int = 256, seed: int = 0
                  ) -> np.ndarray:
    """(n,) bool: which world ``points`` (n, 3) metres stand in open space, by the test
    ``ray_frames`` drops eyes with: fewer than ``INSIDE_SHARE`` of ``n_dirs`` random rays
    meet a back face first (inside a solid nearly all do). Static scenes only."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    centre = pts.mean(axis=0)
    tri, _ = frame_triangles(scene, centre)
    return open_mask(EmbreeCaster(tri), front_normals(tri, scene), pts - centre, n_dirs, seed)


def open_mask(caster: EmbreeCaster, normals: np.ndarray, points: np.ndarray,
              n_dirs: int = 256, seed: int = 0) -> np.ndarray:
    """``in_open_space`` for ``points`` (n, 3) in the frame of a caster already built over the
    scene's triangles, whose front normals are ``normals`` (``front_normals``)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        return np.zeros(0, dtype=bool)
    d = random_directions(int(n_dirs), np.random.default_rng(seed))
    dirs = np.tile(d, (len(pts), 1))
    hid, _ = caster.first_hits(np.repeat(pts, len(d), axis=0), dirs, np.zeros(len(dirs)))
    back = back_hits(dirs, hid, normals)
    return back.reshape(len(pts), -1).sum(axis=1) < INSIDE_SHARE * len(d)


def first_open_cell(scene: Scene, grid: ViewcellGrid, start: int) -> int:
    """Index of the first cell of ``grid`` from ``start`` on (wrapping round) whose centre
    stands in open space (``in_open_space``): a cell to judge frames from, not one inside a
    solid or in a level's void, where no eye stands. ValueError when there is none."""
    n = len(grid)
    order = [(start + k) % n for k in range(n)]
    for k0 in range(0, n, 64):
        idx = order[k0:k0 + 64]
        ok = in_open_space(scene, np.stack([grid.cell(i).center for i in idx]))
        if ok.any():
            return int(idx[int(np.argmax(ok))])
    raise ValueError(f"no cell of the grid has its centre in open space in {scene.name!r}")


def seen_ids(frames: RayFrames) -> np.ndarray:
    """Sorted int64 ids of every triangle some pixel of the frames shows."""
    ids = np.unique(frames.ids)
    return ids[ids >= 0]
