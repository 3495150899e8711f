"""How good a PVS is, as the paper measures it (Secs. 6.3-6.4): false-negative pixels in
frames drawn from eyes and orientations inside the cell, and the false-negative and
false-positive primitive rates against the sampled ground truth, with and without unreliable
primitives (Table 3's FN / FN*, Fig. 15's FP / FP*).

A false-negative pixel is a pixel whose nearest triangle in the full scene is missing from the
PVS (the frame drawn from the PVS differs there). The ground truth is the union of the
triangles those frames show (the paper: 200 samples of the viewcell).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from visibility.ground_truth import sample_points
from visibility.raster.camera import random_rotations
from visibility.raster.triangles import render_cubemap_ids
from visibility.scene import Scene

#: Near plane of the frames, metres. The cores compute which triangles an eye can see, with
#: every occluder solid however close; a frame's near plane at the projection's default 5 cm
#: cuts a wall 7 cm from the eye where the cube face's corner rays meet it (view depth 4 cm)
#: and shows what lies behind it, which no occlusion method reports (lavaducts).
FRAME_NEAR = 1e-3


def unreliable_triangles(scene: Scene, eye: np.ndarray, resolution: int) -> np.ndarray:
    """(m,) bool: triangles with an edge shorter than one pixel seen from ``eye`` (3,) at
    ``resolution`` px per 90 degrees (the paper's FP* / FN* criterion: such triangles often
    cover no pixel centre)."""
    v = scene.vertices - np.asarray(eye, dtype=np.float64)
    n = np.linalg.norm(v, axis=1, keepdims=True)
    d = v / np.where(n > 0, n, 1.0)
    f = scene.faces.astype(np.int64)
    px = 0.5 * resolution  # pixels per radian near the face centre (tan ~ angle)
    short = np.zeros(scene.n_triangles, dtype=bool)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        cosang = np.clip(np.einsum("ij,ij->i", d[f[:, a]], d[f[:, b]]), -1.0, 1.0)
        short |= np.arccos(cosang) * px < 1.0
    return short


def frame_errors(scene: Scene, pvs_ids: np.ndarray, box: np.ndarray, n_points: int = 64,
                 resolution: int = 256, seed: int = 0, near: float = FRAME_NEAR
                 ) -> dict[str, Any]:
    """False-negative pixels and primitive rates of a PVS over a box cell.

    Parameters
    ----------
    scene : a static scene (its vertices at rest are drawn).
    pvs_ids : (k,) triangle ids of the PVS.
    box : (2, 3) float64 cell [min, max], metres.
    n_points : eyes drawn stratified in the box, each with a random orientation of the cube.
    resolution : pixels per cube face of the frames.
    seed : seeds the eyes and orientations.
    near : near plane of the frames, metres (``FRAME_NEAR``).

    Returns
    -------
    dict with ``fn_pixels_max`` and ``fn_pixels_mean`` (per frame of 6 faces),
    ``fn_pixel_rate_max`` (share of a frame's pixels, the paper's bound is 5e-5), ``pixels``
    per frame, ``gt`` (triangles the frames show), ``pvs``, ``fn``, ``fp`` (FN / GTC and
    FP / GTC as Table 3 and Fig. 15 define them), ``fn_star``, ``fp_star`` (unreliable
    triangles left out) and ``missed`` (ids of the ground truth missing from the PVS).
    """
    m = scene.n_triangles
    in_pvs = np.zeros(m + 1, dtype=bool)
    in_pvs[np.asarray(pvs_ids, dtype=np.int64)] = True
    rng = np.random.default_rng(seed)
    pts = sample_points(np.asarray(box, dtype=np.float64), n_points, rng)
    rots = random_rotations(rng, n_points)
    seen = np.zeros(m, dtype=bool)
    fn_pix = np.zeros(n_points, dtype=np.int64)
    for k in range(n_points):
        ids = render_cubemap_ids(scene.vertices, scene.faces, pts[k], resolution, rots[k],
                                 near=near, face_mask=scene.valid_faces).reshape(-1)
        drawn = ids[ids >= 0]
        fn_pix[k] = int(np.count_nonzero(~in_pvs[drawn]))
        seen[drawn] = True
    pixels = 6 * resolution * resolution
    gt = np.flatnonzero(seen)
    pvs = np.flatnonzero(in_pvs[:m])
    centre = 0.5 * (np.asarray(box)[0] + np.asarray(box)[1])
    ok = ~unreliable_triangles(scene, centre, resolution)
    missed = np.setdiff1d(gt, pvs)
    extra = np.setdiff1d(pvs, gt)
    gt_star = gt[ok[gt]]

    def rate(num: np.ndarray, den: np.ndarray) -> float:
        return float(len(num) / len(den)) if len(den) else 0.0

    return {
        "fn_pixels_max": int(fn_pix.max(initial=0)), "fn_pixels_mean": float(fn_pix.mean())
        if n_points else 0.0, "fn_pixel_rate_max": float(fn_pix.max(initial=0) / pixels),
        "pixels": pixels, "gt": len(gt), "pvs": len(pvs), "fn": rate(missed, gt),
        "fp": rate(extra, gt), "fn_star": rate(missed[ok[missed]], gt_star),
        "fp_star": rate(extra[ok[extra]], gt_star), "missed": missed,
    }
