"""Sampled ground truth: the triangles seen from many points of a viewcell, in every direction.

The PVS every core is measured against. From ``n_points`` stratified eye positions in the cell,
each with a fresh uniformly random cube orientation (and, for a moving scene, a random time),
six cubemap id buffers are rendered and their ids united; spheres (``Scene.sphere_centers``) are
drawn analytically at the pixel centres and occlude and are occluded like triangles. Sampling can
only miss primitives (a visible sliver between samples), never add invisible ones, so the result
is a subset of the true PVS that grows with the samples; the convergence record shows how close
to saturation it is.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from visibility.cancel import checkpoint
from visibility.raster import render_cubemap, render_cubemap_ids, render_ids
from visibility.raster.camera import (
    DEFAULT_NEAR,
    cube_face_rotations,
    random_rotation,
    random_rotations,
)
from visibility.raster.culling import Coherence
from visibility.raster.hierarchy import ready_hierarchy
from visibility.raster.spheres import draw_spheres_cubemap
from visibility.scene import Scene
from visibility.viewcells import Viewcell

#: Box extents below this (metres) are flat: sampling treats such an axis as one cell, so a
#: box of 1e-300 m is the point it is. A micrometre is far below anything a walker's eye
#: resolves, and far above the rounding of coordinates (float64 spacing at 1e5 m is ~1e-11 m).
MIN_EXTENT = 1e-6
#: Most viewpoints one call samples. Ten times the sampling core's own cap (100 000), and small
#: enough that a grid of n^3 cells still counts in int64 (2^60); the per-viewpoint arrays
#: (position, rotation, time: 104 bytes) stay under 110 MB.
MAX_POINTS = 1 << 20
#: Largest cubemap (6 R^2 pixels) rendered in one pass. Bigger cubemaps render one face at a
#: time, so a request's pixel buffers hold R^2, not 6 R^2, pixels (about 16 bytes each): 6 Mi
#: pixels is ~100 MB, reached at R = 1024; at R = 4096 a face is 16 Mi pixels, ~270 MB.
CUBEMAP_PIXELS_AT_ONCE = 6 << 20
#: Largest cubemap face size (pixels) sampling accepts; one face is then 1 Gi pixels (~16 GB of
#: buffers), which only offline ground truths on big machines ask for. The server's cores stop
#: at 4096 (``CoreParams.MAX_RESOLUTION``); ``estimate_sampling_cost`` prices any request.
MAX_RESOLUTION = 1 << 14


@dataclass
class GroundTruth:
    """Result of ``sample_pvs``.

    Attributes
    ----------
    triangle_ids : sorted unique int32 ids of the triangles seen.
    sphere_ids : sorted unique int32 ids (indices into the scene's spheres) of the spheres seen.
    convergence : (samples so far, total found, new in this batch) after each batch.
    seconds : wall time of the sampling.
    samples : number of viewpoints rendered.
    pixels : number of pixels rendered (samples x 6 x R x R).
    """

    triangle_ids: np.ndarray
    sphere_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    convergence: list[tuple[int, int, int]] = field(default_factory=list)
    seconds: float = 0.0
    samples: int = 0
    pixels: int = 0


def _grid_counts(size: np.ndarray, n: int) -> np.ndarray:
    """(3,) int64 cells per axis of a grid over a box of ``size`` (metres, finite, >= 0) with at
    least ``n`` near-cubic cells; axes shorter than MIN_EXTENT get one cell.

    Terminates for every input: each count is clamped to [1, MAX_POINTS] (so their product fits
    int64), and the refinement loop runs at most 3 n times (each pass adds one to a count below
    n; once any count reaches n there are n cells).
    """
    size = np.asarray(size, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(size)) or np.any(size < 0):
        raise ValueError(f"box size must be finite and >= 0, got {size.tolist()}")
    n = int(n)
    counts = np.ones(3, dtype=np.int64)
    pos = size >= MIN_EXTENT
    k = int(pos.sum())
    if k == 0 or n <= 1:
        return counts
    with np.errstate(over="ignore", under="ignore"):
        prod = float(np.prod(size[pos]))
    if 0.0 < prod < np.inf:
        side = (prod / n) ** (1.0 / k)
        ratio = size[pos] / side
    else:
        # The product left float64 (kilometre by micrometre boxes): the same side in logs.
        logs = np.log(size[pos])
        ratio = np.exp(np.minimum(logs - (logs.sum() - np.log(n)) / k, np.log(MAX_POINTS)))
    counts[pos] = np.clip(np.floor(np.minimum(ratio, MAX_POINTS)), 1, MAX_POINTS).astype(np.int64)
    cell = np.where(pos, size, -1.0)
    for _ in range(3 * n):
        if counts.prod() >= n:
            break
        # Split the axis whose cells are longest, among those still below n cells.
        j = int(np.argmax(np.where(counts < n, cell / counts, -np.inf)))
        counts[j] += 1
    return counts


def sample_points(box: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 stratified points in an axis-aligned box (metres).

    The box ``(2, 3)`` [min, max] is cut into a grid of at least ``n`` near-cubic cells (axes
    shorter than MIN_EXTENT are flat: one cell, so a box that thin is the point, segment or
    rectangle it is); ``n`` distinct cells are drawn at random and one point is jittered
    uniformly inside each, so any prefix of the points is also spread over the box. ValueError
    for a non-finite or inverted box, ``n < 0`` or ``n > MAX_POINTS``.
    """
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
        raise ValueError(f"box must be finite with max >= min, got {b.tolist()}")
    n = int(n)
    if not 0 <= n <= MAX_POINTS:
        raise ValueError(f"n must be in [0, {MAX_POINTS}], got {n}")
    if n == 0:
        return np.zeros((0, 3))
    with np.errstate(over="ignore"):
        size = b[1] - b[0]
    if not np.all(np.isfinite(size)):
        # Wider than float64 holds (corners near +-1.8e308): only ratios matter to the grid.
        size = b[1] * 0.5 - b[0] * 0.5
    if not np.any(size >= MIN_EXTENT):
        return np.tile(b[0], (n, 1))
    counts = _grid_counts(size, n)
    cells = rng.choice(int(counts.prod()), size=n, replace=False)
    ijk = np.stack(np.unravel_index(cells, tuple(counts)), axis=1)
    u = rng.random((n, 3))
    t = (ijk + u) / counts
    with np.errstate(over="ignore", invalid="ignore"):
        pts = b[0] + (ijk + u) * ((b[1] - b[0]) / counts)
    bad = ~np.isfinite(pts)
    if bad.any():
        # The same point as a weighted mean of the corners, which cannot overflow.
        pts = np.where(bad, b[0] * (1.0 - t) + b[1] * t, pts)
    # Keep every point inside the closed box despite rounding.
    return np.clip(pts, b[0], b[1])


def sample_pvs(
    scene: Scene,
    cell: Viewcell,
    n_points: int = 64,
    resolution: int = 256,
    seed: int = 0,
    batch: int = 8,
    progress: bool = False,
    near: float = DEFAULT_NEAR,
) -> GroundTruth:
    """Sampled PVS of ``cell``: union of cubemap id buffers from stratified viewpoints.

    Parameters
    ----------
    scene : the scene; only ``scene.valid_faces`` are drawn, and its spheres. When it moves
        (``scene.is_dynamic``) each viewpoint also draws a time uniform in the keyframe range
        (``scene.time_range()``) and renders the scene at that time (the PVS over all states).
    cell : the viewcell whose box the eye positions are drawn from.
    n_points : number of viewpoints.
    resolution : cubemap face size R in pixels.
    seed : seeds the positions, cube orientations and times (deterministic for a fixed seed).
    batch : viewpoints per convergence record.
    progress : show a tqdm bar.
    near : near-plane distance in metres.
    """
    n_points = int(n_points)
    batch = int(batch)
    _check_sampling(n_points, batch, resolution)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    points = sample_points(cell.box, n_points, rng)
    return _union_of_views(scene, points, rng, int(resolution), batch, progress, near, t0)


def segment_points(p: np.ndarray, q: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 stratified points on the segment p -> q (metres): one point jittered
    uniformly in each of ``n`` equal pieces, in a random order (any prefix spreads out too)."""
    a = np.asarray(p, dtype=np.float64).reshape(3)
    b = np.asarray(q, dtype=np.float64).reshape(3)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError("segment end points must be finite")
    n = int(n)
    if not 0 <= n <= MAX_POINTS:
        raise ValueError(f"n must be in [0, {MAX_POINTS}], got {n}")
    t = (rng.permutation(n) + rng.random(n)) / max(n, 1)
    return a + np.clip(t, 0.0, 1.0)[:, None] * (b - a)


def sample_segment_pvs(
    scene: Scene,
    p: np.ndarray,
    q: np.ndarray,
    n_points: int = 64,
    resolution: int = 256,
    seed: int = 0,
    batch: int = 8,
    progress: bool = False,
    near: float = DEFAULT_NEAR,
) -> GroundTruth:
    """Sampled PVS of the segment p -> q: ``sample_pvs`` with the eye positions stratified
    along the segment (``segment_points``) instead of over a box. Same parameters."""
    n_points = int(n_points)
    _check_sampling(n_points, int(batch), resolution)
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    points = segment_points(p, q, n_points, rng)
    return _union_of_views(scene, points, rng, int(resolution), int(batch), progress, near, t0)


def _check_sampling(n_points: int, batch: int, resolution: int) -> None:
    if not 1 <= n_points <= MAX_POINTS:
        raise ValueError(f"n_points must be in [1, {MAX_POINTS}], got {n_points}")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    if not 1 <= int(resolution) <= MAX_RESOLUTION:
        raise ValueError(f"resolution must be in [1, {MAX_RESOLUTION}], got {resolution}")


@njit(cache=True, nogil=True)
def mark_seen(ids, seen):  # pragma: no cover - numba
    """seen[i] = True for every id i >= 0 in the flat id buffer ``ids`` (no temporaries)."""
    for j in range(ids.shape[0]):
        i = ids[j]
        if i >= 0:
            seen[i] = True


def _whole_cubemap(resolution: int, spheres: bool) -> bool:
    """Whether a view renders its six faces in one pass (else one face at a time). The sphere
    rasterizer composites into all six faces at once, so scenes with spheres always do."""
    return spheres or 6 * resolution * resolution <= CUBEMAP_PIXELS_AT_ONCE


def _union_of_views(scene: Scene, points: np.ndarray, rng: np.random.Generator, resolution: int,
                    batch: int, progress: bool, near: float, t0: float) -> GroundTruth:
    """Cubemap id buffers from ``points`` with random orientations (and times), united.

    Memory: the pixel buffers of one pass (``_whole_cubemap``: 6 R^2 or R^2 pixels), the
    (m + s,) ``seen`` flags and 104 bytes per point; never a buffer per view kept."""
    n_points = len(points)
    # Drawn in this order (all rotations, then all times) so a seed gives the same views as ever.
    rotations = random_rotations(rng, n_points)
    dynamic = scene.is_dynamic
    if dynamic:
        times = rng.uniform(*scene.time_range(), size=n_points)
    mask = scene.valid_faces
    m = scene.n_triangles
    # Culling draws the same images; until the scene's hierarchy is built (in the background,
    # never waited for) every face is drawn.
    hier = ready_hierarchy(scene)
    # The points are close together: each view draws first what the last one saw, and the
    # run stops culling where it does not pay.
    seen_last = Coherence()
    seen = np.zeros(m + scene.n_spheres, dtype=bool)
    whole = _whole_cubemap(resolution, scene.n_spheres > 0)
    found = 0
    convergence: list[tuple[int, int, int]] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_points, desc="ground truth", unit="view")
    batch_start = found
    for k in range(n_points):
        checkpoint()  # a cancelled or late sampling core stops between views
        t = times[k] if dynamic else 0.0
        verts = scene.vertices_at(t)
        if scene.n_spheres:
            depth, ids = render_cubemap(verts, scene.faces, points[k], resolution, rotations[k],
                                        near=near, face_mask=mask,
                                        hierarchy=seen_last.hierarchy_for(hier),
                                        coherence=seen_last)
            draw_spheres_cubemap(scene.sphere_centers_at(t), scene.sphere_radii, points[k],
                                 depth, ids, rotations[k], near, base_id=m)
            mark_seen(ids.reshape(-1), seen)
        elif whole:
            ids = render_cubemap_ids(verts, scene.faces, points[k], resolution, rotations[k],
                                     near=near, face_mask=mask,
                                     hierarchy=seen_last.hierarchy_for(hier),
                                     coherence=seen_last)
            mark_seen(ids.reshape(-1), seen)
        else:
            # The same six views as render_cubemap, one at a time: a sixth of the buffers.
            # Each face's buffers are dropped before the next face renders.
            for rot in cube_face_rotations(rotations[k]):
                checkpoint()
                ids = render_ids(verts, scene.faces, points[k], rot, resolution, resolution,
                                 near=near, face_mask=mask,
                                 hierarchy=seen_last.hierarchy_for(hier))[1]
                mark_seen(ids.reshape(-1), seen)
                del ids
        ids = depth = None
        if bar is not None:
            bar.update(1)
        if (k + 1) % batch == 0 or k + 1 == n_points:
            found = int(np.count_nonzero(seen))
            convergence.append((k + 1, found, found - batch_start))
            batch_start = found
    if bar is not None:
        bar.close()
    ids = np.flatnonzero(seen[:m]).astype(np.int32)
    return GroundTruth(
        triangle_ids=ids,
        sphere_ids=np.flatnonzero(seen[m:]).astype(np.int32),
        convergence=convergence,
        seconds=time.perf_counter() - t0,
        samples=n_points,
        pixels=n_points * 6 * resolution ** 2,
    )


#: Bytes per pixel of one rendering pass: the rasterizer's float64 1/depth and int32 id buffers
#: and the float32 depth it finishes with (``render_ids``, ``render_cubemap``).
_BYTES_PER_PIXEL = 8 + 4 + 4
#: Bytes per triangle held for a whole request: the ``seen`` flag, and per pass the rasterizer's
#: int64 face selection (and its flatnonzero temporary), int32 face ids and, per vertex (at most
#: three a triangle), its int8 home view and two float64 screen coordinates.
_BYTES_PER_TRIANGLE = 1 + 8 + 8 + 4 + 3 * (1 + 16)
#: More per triangle for a moving scene: the interpolated float64 vertices (three a triangle).
_BYTES_PER_MOVING_TRIANGLE = 3 * 24
#: Bytes per triangle of a rasterizer batch (at most ``BATCH`` triangles): cull bits, int32
#: screen box, six views' int64 indices, int32 bounds and the 13-float64 setup record.
_BYTES_PER_BATCH_TRIANGLE = 1 + 16 + 6 * 8 + 16 + 13 * 8
#: Triangles per rasterizer batch (``visibility.raster.triangles.BATCH``).
_RASTER_BATCH = 1 << 18
#: Bytes per viewpoint: position (3 float64), rotation (9 float64) and time (float64).
_BYTES_PER_POINT = (3 + 9 + 1) * 8
#: Seconds per view, per triangle of a view and per pixel, calibrated by timing ``sample_pvs``
#: on generated ``rooms`` scenes (2 000 and 200 000 triangles, R = 32 to 2048) on the 2-core
#: development machine, rounded up: dense scenes overdraw, costing more per pixel.
_SECONDS_PER_VIEW = 3e-4
_SECONDS_PER_TRIANGLE = 50e-9
_SECONDS_PER_PIXEL = 20e-9


def estimate_sampling_cost(n_triangles: int, resolution: int, samples: int, *,
                           spheres: int = 0, dynamic: bool = False) -> tuple[float, int]:
    """(seconds, peak bytes) that ``sample_pvs`` of a scene of ``n_triangles`` is expected to
    take with ``samples`` viewpoints of ``resolution`` px cube faces, for admission control.

    Derived from the buffers ``_union_of_views`` allocates, not measured: one rendering pass
    holds ``_BYTES_PER_PIXEL`` per pixel of 6 R^2 pixels (one pass per view) or R^2 (one pass
    per face, above ``CUBEMAP_PIXELS_AT_ONCE``; scenes with spheres always take 6 R^2); plus
    ``_BYTES_PER_TRIANGLE`` per triangle (more when ``dynamic``), a rasterizer batch of at most
    ``_RASTER_BATCH`` triangles and ``_BYTES_PER_POINT`` per viewpoint. The scene itself is not
    counted (it is loaded once for every request). Seconds: per view a fixed cost plus costs
    per triangle and per pixel, calibrated roughly by timing on the 2-core development machine
    (see the constants); expect a factor of 2 to 3 either way on other scenes and machines.

    Parameters
    ----------
    n_triangles : triangles in the scene (m).
    resolution : cube face size R, pixels.
    samples : number of viewpoints.
    spheres : spheres in the scene (their ids share the ``seen`` flags).
    dynamic : whether the scene moves (vertices are interpolated per view).
    """
    m, r, n = int(n_triangles), int(resolution), int(samples)
    if m < 0 or r < 1 or n < 0 or int(spheres) < 0:
        raise ValueError(f"need n_triangles >= 0, resolution >= 1, samples >= 0, got {m}, {r}, "
                         f"{n}")
    pass_pixels = 6 * r * r if _whole_cubemap(r, int(spheres) > 0) else r * r
    per_tri = _BYTES_PER_TRIANGLE + (_BYTES_PER_MOVING_TRIANGLE if dynamic else 0)
    peak = (pass_pixels * _BYTES_PER_PIXEL + m * per_tri + int(spheres)
            + min(m, _RASTER_BATCH) * _BYTES_PER_BATCH_TRIANGLE + n * _BYTES_PER_POINT)
    per_view = _SECONDS_PER_VIEW + m * _SECONDS_PER_TRIANGLE + 6 * r * r * _SECONDS_PER_PIXEL
    return float(n * per_view), int(peak)


def fn_fp_rates(pvs_ids: np.ndarray, reference_ids: np.ndarray) -> tuple[float, float]:
    """(false-negative rate, false-positive rate) of a PVS against a reference set of ids.

    FN = share of the reference missing from the PVS; FP = share of the PVS not in the
    reference; each is 0 when its denominator set is empty.
    """
    p = np.unique(np.asarray(pvs_ids, dtype=np.int64))
    r = np.unique(np.asarray(reference_ids, dtype=np.int64))
    common = len(np.intersect1d(p, r, assume_unique=True))
    fn = (len(r) - common) / len(r) if len(r) else 0.0
    fp = (len(p) - common) / len(p) if len(p) else 0.0
    return float(fn), float(fp)


# ------------------------------------------------------------ the conservative cores' reference

def boundary_points(box: np.ndarray) -> np.ndarray:
    """(26, 3) corners, edge midpoints and face centres of a box (2, 3)."""
    lo, hi = box
    mid = 0.5 * (lo + hi)
    out = []
    for i in (0, 1, 2):
        for j in (0, 1, 2):
            for k in (0, 1, 2):
                if (i, j, k) == (1, 1, 1):
                    continue
                pick = [(lo, mid, hi)[c] for c in (i, j, k)]
                out.append([pick[0][0], pick[1][1], pick[2][2]])
    return np.array(out)


def dense_reference(scene: Scene, box: np.ndarray, n_points: int = 256, resolution: int = 256,
                    seed: int = 0) -> np.ndarray:
    """Sorted ids of every triangle seen from ``n_points`` stratified eyes in the box and from
    its 26 boundary points, in random orientations, at ``resolution`` px per cube face."""
    gt = sample_pvs(scene, Viewcell(box), n_points=n_points, resolution=resolution, seed=seed)
    seen = np.zeros(scene.n_triangles, dtype=bool)
    seen[gt.triangle_ids] = True
    rng = np.random.default_rng(seed + 7919)
    for p in boundary_points(np.asarray(box, dtype=np.float64)):
        ids = render_cubemap_ids(scene.vertices, scene.faces, p, resolution, random_rotation(rng),
                                 face_mask=scene.valid_faces)
        seen[ids[ids >= 0]] = True
    return np.flatnonzero(seen)


def cell_around(scene: Scene, size: float, index: int = 0, height: float | None = None
                ) -> np.ndarray:
    """(2, 3) a cube cell of side ``size`` centred at eye height over the ``index``-th cell of
    the scene's default viewcell grid (cycled)."""
    from visibility.viewcells import ViewcellGrid

    grid = ViewcellGrid.for_scene(scene)
    c = grid.cell(index % len(grid)).center
    if height is not None:
        c = c.copy()
        c[1] = height
    return np.stack([c - 0.5 * size, c + 0.5 * size])
