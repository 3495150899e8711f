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

from visibility.raster import render_cubemap, render_cubemap_ids
from visibility.raster.camera import DEFAULT_NEAR, random_rotation
from visibility.raster.spheres import draw_spheres_cubemap
from visibility.scene import Scene
from visibility.viewcells import Viewcell


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
    """Cells per axis of a grid over a box of ``size`` with at least ``n`` near-cubic cells."""
    counts = np.ones(3, dtype=np.int64)
    pos = size > 0
    if not pos.any() or n <= 1:
        return counts
    side = (np.prod(size[pos]) / n) ** (1.0 / pos.sum())
    counts[pos] = np.maximum(1, np.floor(size[pos] / side)).astype(np.int64)
    while counts.prod() < n:
        # Split the axis whose cells are longest.
        k = int(np.argmax(np.where(pos, size / counts, -1.0)))
        counts[k] += 1
    return counts


def sample_points(box: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 stratified points in an axis-aligned box (metres).

    The box ``(2, 3)`` [min, max] is cut into a grid of at least ``n`` near-cubic cells (flat
    axes get one cell); ``n`` distinct cells are drawn at random and one point is jittered
    uniformly inside each, so any prefix of the points is also spread over the box.
    """
    b = np.asarray(box, dtype=np.float64).reshape(2, 3)
    if not np.all(np.isfinite(b)) or np.any(b[1] < b[0]):
        raise ValueError(f"box must be finite with max >= min, got {b.tolist()}")
    n = int(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if n == 0:
        return np.zeros((0, 3))
    size = b[1] - b[0]
    if not np.any(size > 0):
        return np.tile(b[0], (n, 1))
    counts = _grid_counts(size, n)
    cells = rng.choice(int(counts.prod()), size=n, replace=False)
    ijk = np.stack(np.unravel_index(cells, tuple(counts)), axis=1)
    u = rng.random((n, 3))
    pts = b[0] + (ijk + u) * (size / counts)
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
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
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
    if n_points < 1:
        raise ValueError(f"n_points must be >= 1, got {n_points}")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    if not 1 <= int(resolution) <= 1 << 14:
        raise ValueError(f"resolution must be in [1, 16384], got {resolution}")


def _union_of_views(scene: Scene, points: np.ndarray, rng: np.random.Generator, resolution: int,
                    batch: int, progress: bool, near: float, t0: float) -> GroundTruth:
    """Cubemap id buffers from ``points`` with random orientations (and times), united."""
    n_points = len(points)
    rotations = [random_rotation(rng) for _ in range(n_points)]
    dynamic = scene.is_dynamic
    if dynamic:
        times = rng.uniform(*scene.time_range(), size=n_points)
    mask = scene.valid_faces
    m = scene.n_triangles
    seen = np.zeros(m + scene.n_spheres, dtype=bool)
    found = 0
    convergence: list[tuple[int, int, int]] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_points, desc="ground truth", unit="view")
    batch_start = found
    for k in range(n_points):
        t = times[k] if dynamic else 0.0
        verts = scene.vertices_at(t)
        if scene.n_spheres:
            depth, ids = render_cubemap(verts, scene.faces, points[k], resolution, rotations[k],
                                        near=near, face_mask=mask)
            draw_spheres_cubemap(scene.sphere_centers_at(t), scene.sphere_radii, points[k],
                                 depth, ids, rotations[k], near, base_id=m)
        else:
            ids = render_cubemap_ids(verts, scene.faces, points[k], resolution, rotations[k],
                                     near=near, face_mask=mask)
        hit = ids[ids >= 0]
        seen[hit] = True
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
