"""The established ray-caster peer: from-point sampling with Intel Embree (via embreex/trimesh).

Same method as the ``sampling`` core, with a different visibility engine: from stratified points
of the cell (``visibility.ground_truth.sample_points``), rays through the pixel centres of the
six faces of a randomly rotated cube (``visibility.camera`` conventions), united first-hit
triangle ids. It is not a registered core (the server never serves it); the benchmark runs it as
a peer, either with a fixed number of points or with a time budget ("equal time").

Precision: Embree works in float32, so vertices and ray origins are taken relative to the cell
centre (in float64) before the conversion. Embree has no near plane: rays start at the eye.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from visibility.camera import cube_face_rotations, pixel_rays, random_rotation
from visibility.ground_truth import sample_points
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
    """Union of Embree first hits from ``samples`` points of ``cell`` (6 R x R rays each).

    Parameters
    ----------
    scene : the scene; only ``scene.valid_faces`` take part.
    cell : the viewcell the points are drawn from.
    samples : number of viewpoints (an upper bound when ``time_budget`` is set).
    resolution : cube face size R; each viewpoint casts 6 R^2 rays.
    seed : seeds points and cube orientations.
    time_budget : seconds; when set, stop after the first viewpoint that ends past it (the
        BVH build counts against the budget).

    Returns
    -------
    PeerResult with the ids, seconds, and stats (samples used, rays cast, build seconds).
    """
    from trimesh import Trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    samples, resolution = int(samples), int(resolution)
    if samples < 1 or resolution < 1:
        raise ValueError(f"samples and resolution must be >= 1, got {samples}, {resolution}")
    t0 = time.perf_counter()
    valid = np.flatnonzero(scene.valid_faces)
    rng = np.random.default_rng(seed)
    points = sample_points(cell.box, samples, rng)
    if len(valid) == 0:
        return PeerResult(np.zeros(0, np.int32), time.perf_counter() - t0, {"samples": 0})
    origin = np.asarray(cell.box, dtype=np.float64).mean(axis=0)
    used_v, local_f = np.unique(scene.faces[valid], return_inverse=True)
    verts = scene.vertices[used_v] - origin
    mesh = Trimesh(verts, local_f.reshape(-1, 3), process=False, validate=False)
    caster = RayMeshIntersector(mesh)
    caster.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))  # builds the BVH
    build = time.perf_counter() - t0
    rays_cam = pixel_rays(resolution, resolution).reshape(-1, 3)
    seen = np.zeros(len(valid), dtype=bool)
    done = 0
    for k in range(samples):
        rots = cube_face_rotations(random_rotation(rng))  # world-to-camera, rows r, u, back
        # Camera-to-world is R^T: world dir = rays_cam @ R for each face.
        dirs = np.concatenate([rays_cam @ r for r in rots])
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        origins = np.broadcast_to(points[k] - origin, dirs.shape)
        hit = caster.intersects_first(origins, dirs)
        seen[hit[hit >= 0]] = True
        done = k + 1
        if time_budget is not None and time.perf_counter() - t0 >= time_budget:
            break
    ids = valid[seen].astype(np.int32)
    seconds = time.perf_counter() - t0
    return PeerResult(ids, seconds, {"samples": done, "rays": done * 6 * resolution**2,
                                     "build_seconds": build})
