"""Dense sampled ground truth, computed once per (scene, cell, parameters) and cached on disk.

The cache lives under ``benchmarks/results/cache/`` (git-ignored). A key names the scene by its
name and a hash of its geometry (so a regenerated scene with different triangles never reuses a
stale entry), the cell box, the ground-truth parameters (points, resolution, seed) and the
entry format (``FORMAT``: version 2 added the sphere ids).
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from visibility.ground_truth import sample_pvs
from visibility.scene import Scene, scene_fingerprint
from visibility.viewcells import Viewcell

#: Entry format, part of the key: entries of an older format are never read.
FORMAT = 2
#: Default cache folder (git-ignored).
CACHE_DIR = Path(__file__).resolve().parent / "results" / "cache"


def cache_key(scene: Scene, cell: Viewcell, n_points: int, resolution: int, seed: int,
              fingerprint: str | None = None) -> str:
    """The file stem naming one ground truth: scene, geometry hash, cell box and parameters."""
    box = np.asarray(cell.box, dtype=np.float64).reshape(-1)
    box_hash = hashlib.sha1(box.tobytes()).hexdigest()[:12]
    fp = fingerprint or scene_fingerprint(scene)
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in scene.name)[:40]
    return (f"{safe}-{fp}-cell{box_hash}-n{int(n_points)}-r{int(resolution)}-s{int(seed)}"
            f"-v{FORMAT}")


def cached_ground_truth(
    scene: Scene,
    cell: Viewcell,
    n_points: int,
    resolution: int,
    seed: int = 12345,
    cache_dir: str | Path | None = None,
    fingerprint: str | None = None,
) -> tuple[np.ndarray, dict]:
    """Sorted int32 triangle ids of the sampled ground truth of ``cell`` and its record.

    Computes ``visibility.ground_truth.sample_pvs(scene, cell, n_points, resolution, seed)``
    the first time and stores it as ``<key>.npz`` (triangle and sphere ids) plus
    ``<key>.json`` (seconds, convergence, parameters); later calls read the files. The record
    has ``"cached": True`` when it came from disk and ``"sphere_ids"`` (sorted int32 indices
    into the scene's spheres, empty without spheres).
    """
    folder = Path(cache_dir) if cache_dir is not None else CACHE_DIR
    folder.mkdir(parents=True, exist_ok=True)
    key = cache_key(scene, cell, n_points, resolution, seed, fingerprint)
    ids_path, rec_path = folder / f"{key}.npz", folder / f"{key}.json"
    if ids_path.is_file() and rec_path.is_file():
        with np.load(ids_path) as data:
            ids = data["ids"].astype(np.int32)
            sphere_ids = data["sphere_ids"].astype(np.int32)
        rec = json.loads(rec_path.read_text())
        rec["cached"] = True
        rec["sphere_ids"] = sphere_ids
        return ids, rec
    t0 = time.perf_counter()
    gt = sample_pvs(scene, cell, n_points=n_points, resolution=resolution, seed=seed)
    rec = {
        "key": key,
        "scene": scene.name,
        "cell_box": np.asarray(cell.box).tolist(),
        "n_points": int(n_points),
        "resolution": int(resolution),
        "seed": int(seed),
        "seconds": time.perf_counter() - t0,
        "found": int(len(gt.triangle_ids)),
        "found_spheres": int(len(gt.sphere_ids)),
        "convergence": [list(map(int, c)) for c in gt.convergence],
    }
    # Write the ids first and the record last: a record on disk means a complete entry.
    tmp = folder / f"{key}.tmp.npz"
    np.savez_compressed(tmp, ids=gt.triangle_ids, sphere_ids=gt.sphere_ids)
    tmp.replace(ids_path)
    rec_path.write_text(json.dumps(rec))
    rec["cached"] = False
    rec["sphere_ids"] = gt.sphere_ids.astype(np.int32)
    return gt.triangle_ids.astype(np.int32), rec
