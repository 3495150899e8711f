"""Entry points of the triangle rasterizer: depth and id buffers of one view or a cubemap.

Each checks its inputs and draws either every face (``visibility.raster.triangles``) or, given
the scene's ``Hierarchy``, through frustum and occlusion culling
(``visibility.raster.culling``): the same image either way. Conventions as in
``visibility.raster.camera`` (Y-up, right-handed, metres; ``-z_cam`` depth).
"""

from __future__ import annotations

import numba
import numpy as np

from visibility.raster.camera import DEFAULT_NEAR, cube_face_rotations
from visibility.raster.culling import Coherence, render_views_culled
from visibility.raster.hierarchy import Hierarchy
from visibility.raster.triangles import (
    PARALLEL_MIN_PIXELS,
    PARALLEL_MIN_TRIANGLES,
    _render_views_on,
)

__all__ = ["DEFAULT_NEAR", "render_ids", "render_cubemap", "render_cubemap_ids"]


def _check_inputs(vertices, faces, face_mask, face_ids, need_sel=True):
    """Checked (vertices float64, faces int32, selected face rows int64, ids int32: empty for
    the row index). ``need_sel`` False leaves the selection empty (culled renders walk the
    hierarchy instead)."""
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (n, 3), got shape {v.shape}")
    f = np.ascontiguousarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (m, 3), got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must hold integers, got {f.dtype}")
    if f.dtype != np.int32:
        # Indices that do not fit int32 are out of range anyway: mark them so they are skipped.
        f = np.where((f < 0) | (f > np.iinfo(np.int32).max), -1, f).astype(np.int32)
    f = np.ascontiguousarray(f, dtype=np.int32)
    m = len(f)
    if face_mask is None:
        sel = np.arange(m if need_sel else 0, dtype=np.int64)
    else:
        mask = np.asarray(face_mask)
        if mask.dtype != np.bool_ or mask.shape != (m,):
            raise ValueError(
                f"face_mask must be a ({m},) bool array, got {mask.dtype} {mask.shape}"
            )
        sel = np.flatnonzero(mask).astype(np.int64, copy=False) if need_sel else \
            np.zeros(0, np.int64)
    if face_ids is None:
        ids = np.zeros(0, dtype=np.int32)
    else:
        ids = np.ascontiguousarray(face_ids)
        if ids.shape != (m,) or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(
                f"face_ids must be a ({m},) integer array, got {ids.dtype} {ids.shape}"
            )
        if m and (ids.min() < 0 or ids.max() > np.iinfo(np.int32).max):
            raise ValueError("face_ids must be in [0, 2**31 - 1] (-1 marks empty pixels)")
        ids = ids.astype(np.int32)
    return v, f, sel, ids


def _check_view(eye, width, height, tan_x, tan_y, near):
    e = np.asarray(eye, dtype=np.float64).reshape(-1)
    if e.shape != (3,) or not np.all(np.isfinite(e)):
        raise ValueError(f"eye must be a finite 3-vector, got {eye!r}")
    for name, val in (("width", width), ("height", height)):
        if int(val) != val or not 1 <= int(val) <= 1 << 14:
            raise ValueError(f"{name} must be an integer in [1, 16384], got {val!r}")
    for name, val in (("tan_x", tan_x), ("tan_y", tan_y), ("near", near)):
        if not (np.isfinite(val) and val > 0):
            raise ValueError(f"{name} must be a finite positive number, got {val!r}")
    return e


def _check_rotation(rotation):
    r = np.ascontiguousarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError("rotation must be a finite (3, 3) matrix")
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
        raise ValueError("rotation must be orthonormal (rows = right, up, back)")
    return r


def _render_views(v, eye, faces, sel, ids, rots, base, width, height, tan_x, tan_y, near,
                  stats, want_depth=True, hierarchy=None, face_mask=None, coherence=None,
                  out=None):
    """Depth (F, H, W) float32 and ids (F, H, W) int32 of F views sharing an eye: one view, or
    the six cube faces of ``base`` (then ``rots`` = ``cube_face_rotations(base)``); written
    into ``out`` (depth or None, ids) when given."""
    if hierarchy is not None:
        return _render_culled(v, eye, faces, ids, rots, base, width, height, tan_x, tan_y, near,
                              stats, want_depth, hierarchy, face_mask, coherence, out)
    n_views = len(rots)
    small = (len(sel) * n_views < PARALLEL_MIN_TRIANGLES
             and n_views * width * height < PARALLEL_MIN_PIXELS)
    if not small:
        return _render_views_on(v, eye, faces, sel, ids, rots, base, width, height, tan_x, tan_y,
                                near, stats, want_depth, out)
    # Small jobs run on the calling thread alone: starting the pool for a few thousand
    # triangles costs more than it saves, much more when other processes hold the cores.
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        return _render_views_on(v, eye, faces, sel, ids, rots, base, width, height, tan_x, tan_y,
                                near, stats, want_depth, out)
    finally:
        numba.set_num_threads(threads)


def _render_culled(v, eye, faces, ids, rots, base, width, height, tan_x, tan_y, near, stats,
                   want_depth, hierarchy, face_mask, coherence=None, out=None):
    """``_render_views`` through the hierarchy (``visibility.raster.culling``)."""

    m = len(faces)
    if hierarchy.n_faces != m:
        raise ValueError(f"the hierarchy was built for {hierarchy.n_faces} faces, not {m}")
    if not hierarchy.matches(v):
        raise ValueError("the hierarchy was built for other vertex positions (another scene, "
                         "or these are in another frame)")
    mask = np.ones(m, dtype=bool) if face_mask is None else np.asarray(face_mask, dtype=bool)
    loose = hierarchy.loose[mask[hierarchy.loose]] if len(hierarchy.loose) else None
    if coherence is not None and len(ids):
        raise ValueError("coherence needs the faces' rows as ids (face_ids None)")
    return render_views_culled(v, eye, faces, hierarchy, mask, ids, rots, base, width, height,
                               tan_x, tan_y, near, stats, want_depth, loose, coherence, out)


def render_ids(
    vertices: np.ndarray,
    faces: np.ndarray,
    eye: np.ndarray,
    rotation: np.ndarray,
    width: int,
    height: int,
    tan_x: float = 1.0,
    tan_y: float = 1.0,
    near: float = DEFAULT_NEAR,
    face_mask: np.ndarray | None = None,
    face_ids: np.ndarray | None = None,
    stats: dict | None = None,
    hierarchy: Hierarchy | None = None,
    coherence: Coherence | None = None,
    out: tuple[np.ndarray | None, np.ndarray] | None = None,
) -> tuple[np.ndarray | None, np.ndarray]:
    """Depth and triangle-id buffers of one perspective view.

    Parameters
    ----------
    vertices : (n, 3) float64 world positions, metres.
    faces : (m, 3) int32 vertex indices.
    eye : (3,) camera position, metres.
    rotation : (3, 3) world-to-camera rotation (rows right, up, back; ``visibility.raster.camera``).
    width, height : image size in pixels.
    tan_x, tan_y : tangents of the half field of view.
    near : near-plane distance, metres (no far plane).
    face_mask : (m,) bool, faces to draw (None = all). Faces with out-of-range indices,
        non-finite corners or no area are skipped whatever the mask says.
    face_ids : (m,) int32, the id written for each face (default: its row index).
    stats : optional dict to which ``triangles``, ``pixels``, ``pixel_tests`` (pixel centres
        tested) and ``band_pairs`` (triangle x row-band pairs rasterized) are added.
    hierarchy : the faces' ``visibility.raster.hierarchy.Hierarchy``: draw through frustum and
        occlusion culling (``visibility.raster.culling``; the same image, at a cost that follows
        what the view sees). None draws every face.
    coherence : with ``hierarchy``, a ``visibility.raster.culling.Coherence`` shared by a run
        of views from nearby eyes: each draws first what the previous one saw (the same image;
        less drawn). Needs ``face_ids`` None.
    out : (depth, ids) buffers to render into, returned (as views) instead of new ones: C-contiguous
        (height, width) float32 and int32 (a caller rendering view after view keeps one pair:
        fresh pages cost their first-touch faults). A None depth skips the depth pass and
        returns None for it.

    Returns
    -------
    depth : (height, width) float32, ``-z_cam`` in metres, +inf where nothing is drawn.
    ids : (height, width) int32, the id of the nearest face (ties: smaller id), -1 where empty.
    """
    v, f, sel, ids = _check_inputs(vertices, faces, face_mask, face_ids, hierarchy is None)
    e = _check_view(eye, width, height, tan_x, tan_y, near)
    r = _check_rotation(rotation)
    bufs = None if out is None else _check_out(out, int(width), int(height))
    depth, idbuf = _render_views(v, e, f, sel, ids, r[None], None, int(width), int(height),
                                 tan_x, tan_y, near, stats, bufs is None or bufs[0] is not None,
                                 hierarchy, face_mask, coherence, bufs)
    return (None if depth is None else depth[0]), idbuf[0]


def _check_out(out, width, height):
    """``render_ids``'s ``out`` as (1, H, W) views, checked."""
    if not isinstance(out, tuple) or len(out) != 2:
        raise ValueError("out must be a (depth or None, ids) pair")
    bufs = []
    for name, arr, dtype in (("depth", out[0], np.float32), ("ids", out[1], np.int32)):
        if arr is None and name == "depth":
            bufs.append(None)
            continue
        if not isinstance(arr, np.ndarray) or arr.dtype != dtype or \
                arr.shape != (height, width) or not arr.flags.c_contiguous or \
                not arr.flags.writeable:
            raise ValueError(f"out's {name} must be a writeable C-contiguous ({height}, {width}) "
                             f"{np.dtype(dtype).name} array")
        bufs.append(arr.reshape(1, height, width))
    return bufs[0], bufs[1]


def render_cubemap(
    vertices: np.ndarray,
    faces: np.ndarray,
    eye: np.ndarray,
    resolution: int,
    base_rotation: np.ndarray | None = None,
    near: float = DEFAULT_NEAR,
    face_mask: np.ndarray | None = None,
    face_ids: np.ndarray | None = None,
    stats: dict | None = None,
    hierarchy: Hierarchy | None = None,
    coherence: Coherence | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and id buffers of the six cube faces around ``eye``.

    Faces come in ``camera.cube_face_rotations(base_rotation)`` order (+X, -X, +Y, -Y, +Z, -Z of
    the rotated cube), each a 90-degree square view of ``resolution`` pixels. Other parameters
    as in ``render_ids``.

    Returns
    -------
    depth : (6, R, R) float32 metres (+inf where empty); ids : (6, R, R) int32 (-1 where empty).
    """
    return _cubemap(vertices, faces, eye, resolution, base_rotation, near, face_mask, face_ids,
                    stats, True, hierarchy, coherence)


def render_cubemap_ids(
    vertices: np.ndarray,
    faces: np.ndarray,
    eye: np.ndarray,
    resolution: int,
    base_rotation: np.ndarray | None = None,
    near: float = DEFAULT_NEAR,
    face_mask: np.ndarray | None = None,
    face_ids: np.ndarray | None = None,
    stats: dict | None = None,
    hierarchy: Hierarchy | None = None,
    coherence: Coherence | None = None,
) -> np.ndarray:
    """(6, R, R) int32 id buffers of ``render_cubemap`` (identical), without the depth pass."""
    return _cubemap(vertices, faces, eye, resolution, base_rotation, near, face_mask, face_ids,
                    stats, False, hierarchy, coherence)[1]


def _cubemap(vertices, faces, eye, resolution, base_rotation, near, face_mask, face_ids, stats,
             want_depth, hierarchy=None, coherence=None):
    v, f, sel, ids = _check_inputs(vertices, faces, face_mask, face_ids, hierarchy is None)
    e = _check_view(eye, resolution, resolution, 1.0, 1.0, near)
    base = np.eye(3) if base_rotation is None else _check_rotation(base_rotation)
    rots = cube_face_rotations(base)
    res = int(resolution)
    return _render_views(v, e, f, sel, ids, rots, base, res, res, 1.0, 1.0, near, stats,
                         want_depth, hierarchy, face_mask, coherence)
