"""How good a PVS is, as the paper measures it (Secs. 6.3-6.4): false-negative pixels in
frames drawn from eyes and orientations inside the cell, and the false-negative and
false-positive primitive rates against the sampled ground truth, with and without unreliable
primitives (Table 3's FN / FN*, Fig. 15's FP / FP*).

A false-negative pixel is a pixel whose nearest triangle in the full scene is missing from the
PVS (the frame drawn from the PVS differs there). The frames are cast by independent rays
(``visibility.ray_frames``: Embree, one ray through a random point of each pixel, misses
confirmed in float64), never by the rasterizer the cores share. The ground truth is the
union of the triangles those frames show (the paper: 200 samples of the viewcell).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from visibility.ray_frames import RayFrames, missed_pixels, ray_frames, seen_ids
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
                 resolution: int = 256, seed: int = 0, near: float = FRAME_NEAR,
                 frames: RayFrames | None = None) -> dict[str, Any]:
    """False-negative pixels and primitive rates of a PVS over a box cell, judged by
    independent rays (``visibility.ray_frames``: Embree, misses confirmed in float64), not by
    the project's rasterizer.

    Parameters
    ----------
    scene : a static scene (its vertices at rest are cast against).
    pvs_ids : (k,) triangle ids of the PVS.
    box : (2, 3) float64 cell [min, max], metres.
    n_points : eyes drawn stratified in the box, each with a random orientation of the cube
        (those inside geometry are dropped).
    resolution : pixels per cube face of the frames (one ray through a random point of each).
    seed : seeds the eyes, orientations and points in the pixels.
    near : near plane of the frames, metres (``FRAME_NEAR``).
    frames : the cell's frames (``ray_frames.ray_frames``) when already cast; the four
        parameters above are then theirs.

    Returns
    -------
    dict with ``fn_pixels_max`` and ``fn_pixels_mean`` (per frame of 6 faces),
    ``fn_pixel_rate_max`` (share of a frame's pixels, the paper's bound is 5e-5), ``pixels``
    per frame, ``frames`` (kept), ``gt`` (triangles the frames show), ``pvs``, ``fn``, ``fp``
    (FN / GTC and FP / GTC as Table 3 and Fig. 15 define them), ``fn_star``, ``fp_star``
    (unreliable triangles left out) and ``missed`` (ids of the ground truth missing from the
    PVS).
    """
    if frames is None:
        frames = ray_frames(scene, box, n_points, resolution, seed, near)
    m = scene.n_triangles
    fn_pix = missed_pixels(scene, frames, pvs_ids)
    pixels = frames.pixels
    gt = seen_ids(frames)
    pvs = np.unique(np.asarray(pvs_ids, dtype=np.int64))
    pvs = pvs[(pvs >= 0) & (pvs < m)]
    centre = 0.5 * (np.asarray(box)[0] + np.asarray(box)[1])
    ok = ~unreliable_triangles(scene, centre, frames.resolution)
    missed = np.setdiff1d(gt, pvs)
    extra = np.setdiff1d(pvs, gt)
    gt_star = gt[ok[gt]]

    def rate(num: np.ndarray, den: np.ndarray) -> float:
        return float(len(num) / len(den)) if len(den) else 0.0

    n = len(fn_pix)
    return {
        "fn_pixels_max": int(fn_pix.max(initial=0)), "fn_pixels_mean": float(fn_pix.mean())
        if n else 0.0, "fn_pixel_rate_max": float(fn_pix.max(initial=0) / pixels),
        "pixels": pixels, "frames": n, "gt": len(gt), "pvs": len(pvs),
        "fn": rate(missed, gt), "fp": rate(extra, gt),
        "fn_star": rate(missed[ok[missed]], gt_star),
        "fp_star": rate(extra[ok[extra]], gt_star), "missed": missed,
    }
