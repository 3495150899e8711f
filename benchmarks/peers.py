"""The established ray-caster peer: from-point sampling with Intel Embree (via embreex/trimesh).

Same method as the ``sampling`` core, with a different visibility engine: from stratified points
of the cell (``visibility.ground_truth.sample_points``), rays through the pixel centres of the
six faces of a randomly rotated cube (``visibility.raster.camera`` conventions), united first-hit
triangle ids. It is not a registered core (the server never serves it); the benchmark runs it as
a peer, either with a fixed number of points, with a time budget ("equal time") or until it has
found a share of a reference set ("equal completeness"). ``from_point_pvs`` runs the same loop
with either engine: ``"embree"`` or ``"raster"`` (our rasterizer, i.e. the ``sampling`` core's
method, which has no budget or target of its own).

Precision: Embree works in float32, so vertices and ray origins are taken relative to the cell
centre (in float64) before the conversion. Embree has no near plane: rays start at the eye.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from visibility.ground_truth import sample_points
from visibility.raster import render_cubemap_ids
from visibility.raster.camera import cube_face_rotations, pixel_rays, random_rotation
from visibility.scene import Scene
from visibility.viewcells import Viewcell

NAME = "embree_rays"
DESCRIPTION = "from-point sampling with Intel Embree rays (embreex via trimesh), cube pixel centres"


def available() -> bool:
    """Whether embreex (and so trimesh's Embree ray backend) is importable."""
    try:
        import embreex  # noqa: F401
        from trimesh.ray import ray_pyembree  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class PeerResult:
    """What the peer found: sorted int32 triangle ids, wall seconds and stats."""

    triangle_ids: np.ndarray
    seconds: float
    stats: dict = field(default_factory=dict)


def embree_pvs(
    scene: Scene,
    cell: Viewcell,
    samples: int = 32,
    resolution: int = 128,
    seed: int = 0,
    time_budget: float | None = None,
) -> PeerResult:
    """Union of Embree first hits from ``samples`` points of ``cell`` (6 R x R rays each);
    ``from_point_pvs`` with ``engine="embree"`` (see there)."""
    return from_point_pvs(scene, cell, "embree", samples, resolution, seed, time_budget)


def from_point_pvs(
    scene: Scene,
    cell: Viewcell,
    engine: str = "embree",
    samples: int = 32,
    resolution: int = 128,
    seed: int = 0,
    time_budget: float | None = None,
    target_ids: np.ndarray | None = None,
    target_share: float | None = None,
) -> PeerResult:
    """Union of the triangles seen from stratified points of ``cell``, one cube per point.

    Parameters
    ----------
    scene : the scene; only ``scene.valid_faces`` take part.
    cell : the viewcell the points are drawn from (``sample_points``, seeded).
    engine : ``"embree"`` (rays through the cube's pixel centres, first hits) or ``"raster"``
        (``render_cubemap_ids``: the ``sampling`` core's method).
    samples : number of viewpoints (an upper bound when a budget or target is set).
    resolution : cube face size R (6 R^2 pixels or rays per viewpoint).
    seed : seeds points and cube orientations.
    time_budget : seconds; when set, stop after the first viewpoint that ends past it (the
        Embree BVH build counts against the budget).
    target_ids, target_share : when set, stop as soon as the union holds at least
        ``target_share`` of ``target_ids`` (equal completeness); ``stats["reached"]`` says
        whether it did within ``samples`` / ``time_budget``.

    Returns
    -------
    PeerResult with the ids, seconds, and stats (samples used, rays cast, build seconds).
    """
    samples, resolution = int(samples), int(resolution)
    if samples < 1 or resolution < 1:
        raise ValueError(f"samples and resolution must be >= 1, got {samples}, {resolution}")
    if engine not in ("embree", "raster"):
        raise ValueError(f"engine must be 'embree' or 'raster', got {engine!r}")
    t0 = time.perf_counter()
    valid = np.flatnonzero(scene.valid_faces)
    rng = np.random.default_rng(seed)
    points = sample_points(cell.box, samples, rng)
    if len(valid) == 0:
        return PeerResult(np.zeros(0, np.int32), time.perf_counter() - t0, {"samples": 0})
    want = None
    if target_ids is not None and target_share is not None:
        want = np.zeros(scene.n_triangles, dtype=bool)
        want[np.asarray(target_ids, dtype=np.int64)] = True
        need = int(np.ceil(float(target_share) * want.sum() - 1e-9))
    seen = np.zeros(scene.n_triangles, dtype=bool)
    if engine == "embree":
        view = embree_views(scene, valid, cell, resolution)
    else:
        def view(eye, rot):
            ids = render_cubemap_ids(scene.vertices, scene.faces, eye, resolution, rot,
                                     face_mask=scene.valid_faces)
            return ids[ids >= 0]
    build = time.perf_counter() - t0
    done, reached = 0, want is None
    for k in range(samples):
        seen[view(points[k], random_rotation(rng))] = True
        done = k + 1
        if want is not None and np.count_nonzero(seen & want) >= need:
            reached = True
            break
        if time_budget is not None and time.perf_counter() - t0 >= time_budget:
            break
    ids = np.flatnonzero(seen).astype(np.int32)
    seconds = time.perf_counter() - t0
    return PeerResult(ids, seconds, {"samples": done, "rays": done * 6 * resolution**2,
                                     "build_seconds": build, "reached": reached,
                                     "engine": engine})


def embree_views(scene: Scene, valid: np.ndarray, cell: Viewcell, resolution: int):
    """A function (eye, cube rotation) -> triangle ids hit by the cube's pixel-centre rays."""
    from trimesh import Trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    # float32 inside Embree: work relative to the cell centre.
    origin = np.asarray(cell.box, dtype=np.float64).mean(axis=0)
    used_v, local_f = np.unique(scene.faces[valid], return_inverse=True)
    verts = scene.vertices[used_v] - origin
    mesh = Trimesh(verts, local_f.reshape(-1, 3), process=False, validate=False)
    caster = RayMeshIntersector(mesh)
    caster.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))  # builds the BVH
    rays_cam = pixel_rays(resolution, resolution).reshape(-1, 3)

    def view(eye: np.ndarray, rot: np.ndarray) -> np.ndarray:
        rots = cube_face_rotations(rot)  # world-to-camera, rows r, u, back
        # Camera-to-world is R^T: world dir = rays_cam @ R for each face.
        dirs = np.concatenate([rays_cam @ r for r in rots])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        hit = caster.intersects_first(np.broadcast_to(eye - origin, dirs.shape), dirs)
        return valid[hit[hit >= 0]]

    return view
