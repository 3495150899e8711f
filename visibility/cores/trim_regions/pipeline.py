"""One PVS computation of the trim region method: spheres covering the cell, six adapted
frusta per sphere, octree layers front to back (P0), geometry generation (P1), rasterization
into the k-buffers (P2), per-pixel resolve (P3) and the gather (P4) (paper Fig. 8)."""

from __future__ import annotations

import contextvars
import queue
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numba
import numpy as np

from visibility.cancel import checkpoint, stop_flag
from visibility.cores.trim_regions.cache import SceneData, faced_out_for
from visibility.cores.trim_regions.crew import Crew
from visibility.cores.trim_regions.filters import (
    grazing_boxes,
    grazing_mask,
    plane_holds_box,
    planes_near,
)
from visibility.cores.trim_regions.frustum import View, cover_box, sphere_views
from visibility.cores.trim_regions.hulls import (
    BOX_FACES,
    hulls_in_front,
    near_sphere,
    small_in_front,
    touching_in_front,
    touching_samples,
)
from visibility.cores.trim_regions.kbuffer import K, KBuffer
from visibility.cores.trim_regions.layers import (
    LeafFrame,
    by_layer,
    drawn_leaves,
    in_view,
    leaf_frame,
    leaf_layers,
)
from visibility.cores.trim_regions.octree import Octree
from visibility.cores.trim_regions.once import Once
from visibility.cores.trim_regions.quality import FRAME_NEAR
from visibility.cores.trim_regions.raster import (
    Camera,
    SetUp,
    boxes_to_camera,
    raster_surfaces,
    raster_trims,
    setup_triangles,
    to_camera,
)
from visibility.cores.trim_regions.resolve import DEPTH_TOL, Reach, resolve_layer
from visibility.cores.trim_regions.samples import open_depth
from visibility.cores.trim_regions.silhouettes import (
    AMBIGUOUS,
    TRIM_MARGIN_PX,
    silhouette_trims,
)
from visibility.cores.trim_regions.view_masks import drawn_edges, drawn_instances, drawn_rows
from visibility.cores.trim_regions.warm import GATHER_SCRATCH, WARM
from visibility.ground_truth import MAX_RESOLUTION, mark_seen, sample_pvs
from visibility.raster.hierarchy import MIN_TRIANGLES, Hierarchy, ready_hierarchy, scene_hierarchy
from visibility.raster.render import render_ids
from visibility.scene import Scene
from visibility.scratch import Scratch
from visibility.viewcells import Viewcell

#: Sample points per pixel side of the depth the conservative occludee test compares with.
SUPERSAMPLE = 4
#: How many of a pixel's samples must see a depth for the occludee test to use it.
OPEN_SAMPLES = 3
#: Widest pixel box (pixels) of the triangles also tested against v*'s samples one by one
#: (``hulls.touching_samples``): a larger triangle meets the samples themselves.
SMALL_BOX_PX = 8
#: How small triangles behind trimmed occluders are rasterized (``small`` of ``trim_pvs``):
#: at pixel centres (the paper) or conservatively, at every pixel they touch.
SMALL_RASTERS = ("centres", "conservative")
#: With ``small="conservative"``: the width (pixels, twice the area over the longest edge)
#: up to which a triangle is tested at every pixel it touches (``hulls.small_in_front``);
#: a wider one meets pixel centres.
THIN_PX = 1.0
#: Roll of the second grid the gather samples from v*, radians (atan 1/2: no scene axis of a
#: cube face lies along its rows or columns or their diagonals).
ROLL = float(np.arctan(0.5))
#: Samples per pixel side of that rolled grid.
ROLLED_SAMPLES = 2
#: Eyes inside the cell whose views (``SUPERSAMPLE``² samples per pixel) the sampling add-on
#: adds when asked for (``gather_eyes``; off by default: it is from-point sampling inside the
#: answer, not the method), and the seed that places and turns them (fixed: the same cell gets
#: the same answer).
GATHER_EYES = 8
GATHER_SEED = 104729
#: Share of a sphere's drawn items above which its leading view's gather from v* is made
#: aside, by a worker with no view left (``_Gather``).
ASIDE_SHARE = 0.5
#: Bytes of one k-buffer entry (depth, umbra, far float64; id int64; kind int8).
ENTRY_BYTES = 33
PHASES = ("p0_layers", "p1_geometry", "p2_raster", "p3_resolve", "p4_gather")


def _hulls(scene: Scene, data: SceneData, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (k, 2, 3) (relative to ``centre``) of the moving triangles and spheres over the
    keyframes, and the id each reports (a triangle id, or ``n_triangles + sphere index``)."""
    lo, hi, ids = [], [], []
    if len(data.moving):
        corners = scene.states[:, scene.faces[data.moving].astype(np.int64)]  # (k, t, 3, 3)
        lo.append(corners.min(axis=(0, 2)))
        hi.append(corners.max(axis=(0, 2)))
        ids.append(data.moving)
    if scene.n_spheres:
        r = scene.sphere_radii[:, None]
        lo.append(scene.sphere_centers.min(axis=0) - r)
        hi.append(scene.sphere_centers.max(axis=0) + r)
        ids.append(scene.n_triangles + np.arange(scene.n_spheres, dtype=np.int64))
    if not lo:
        return np.zeros((0, 2, 3)), np.zeros(0, dtype=np.int64)
    lo_a, hi_a, id_a = np.concatenate(lo), np.concatenate(hi), np.concatenate(ids)
    ok = np.all(np.isfinite(lo_a) & np.isfinite(hi_a), axis=1)
    boxes = np.stack([lo_a[ok], hi_a[ok]], axis=1) - centre
    return boxes, id_a[ok]


def trim_pvs(scene: Scene, data: SceneData, box: np.ndarray, resolution: int,
             max_delta: float, margin_px: float = TRIM_MARGIN_PX, footprints: bool = True,
             gather_eyes: int = 0,
             small: str = "conservative") -> tuple[np.ndarray, dict[str, Any]]:
    """PVS of a box cell by trim regions.

    Parameters
    ----------
    scene : the scene; ``data`` its cached structures (``cache.scene_data``).
    box : (2, 3) float64 [min, max] of the cell, metres.
    resolution : pixels across each cube face.
    max_delta : largest sphere radius Δ the box is covered with, metres.
    margin_px : safety margin added to every trim width, pixels (0 only for tests that compare
        Δ = 0 with from-point visibility at pixel centres).
    footprints : also report what pixel centres miss: every triangle v* sees at 16 samples
        per pixel or on a rolled grid (``_sample_from_vstar``), and every triangle whose pixel
        footprint (conservative) lies in front of the farthest surface sampled in that pixel
        (``hulls.touching_in_front``), or whose footprint touches a sample of that render
        with its nearest point in front of the samples around it (``hulls.touching_samples``:
        small triangles v* sees between its samples). False only for tests of pixel-centre
        visibility.
    gather_eyes : a sampling add-on, off (0) by default: with ``footprints``, also report
        every triangle and sphere seen from this many eyes stratified in the box (random cube
        orientations, ``SUPERSAMPLE`` times the resolution, ``ground_truth.sample_pvs``;
        ``GATHER_EYES`` is the count measured). v* stands outside the cell, and a triangle it
        sees behind a trimmed occluder under no pixel centre (the clutter of the 1M kitchen,
        each under a pixel or so) is often in plain view of an eye inside. 0: the paper's
        gather from v* alone, the method.
    small : how triangles behind trimmed occluders that cover no pixel centre are found
        (``SMALL_RASTERS``; with ``footprints``): ``"conservative"`` (the default), every
        triangle under ``THIN_PX`` wide touching a pixel in front of its seal and outside its
        hidden spans (``hulls.small_in_front``), what the pixel's centre would have found had
        the triangle covered it, or ``"centres"``, never (the paper's pixel centres).

    Returns
    -------
    ids : (k,) int64 triangle ids found potentially visible (any order).
    stats : seconds per phase (``p0_layers`` ... ``p4_gather``; summed over the views, which
        run ``view_workers`` at a time on their own threads, so they can add up to more than
        the wall time), ``view_workers``, ``spheres``, ``delta``,
        ``views``, ``layers`` (drawn, summed over views), ``buffers_reused`` (view workers
        that took the buffers a computation before left, ``warm``), ``kbuffer_allocated_bytes``,
        ``kbuffer_used_bytes`` (most entries held at once), ``active_pixels`` (pixels that
        held a trim sequence, summed over views), ``mean_sequence_length`` (entries per pixel
        resolve), ``trimmed_pixels``, ``sealed_pixels``, ``overflow_pixels``,
        ``silhouette_trims``, ``validated_intervals``, ``terminators``, ``single_sided_trims``,
        ``instances`` ((triangle, leaf) pairs drawn), ``culled_instances`` and ``culled_trims``
        (those and trim rows left out where every pixel they could reach was sealed),
        ``near_eye`` (triangles reported for lying within Δ of a sphere's centre),
        ``grazing`` (triangles whose plane passes within Δ of a sphere centre, also tested as
        hulls), ``gathers_aside`` (views whose gather from v* another worker made,
        ``ASIDE_SHARE``), ``eye_gathered`` (triangles only the eyes' views added),
        ``sphere_ids`` (the spheres of the scene found visible).
    """
    if small not in SMALL_RASTERS:
        raise ValueError(f"small must be one of {list(SMALL_RASTERS)}, got {small!r}")
    box = np.asarray(box, dtype=np.float64)
    # Closed parts wound inside out face out for this cell (its eyes stand outside them).
    data = faced_out_for(scene, data, box)
    centre = 0.5 * (box[0] + box[1])
    centres, delta = cover_box(box, max_delta)
    centres = centres - centre
    m = scene.n_triangles
    vis = np.zeros(m, dtype=np.uint8)
    # What the views add up (``VIEW_STATS``) starts at zero.
    stats: dict[str, Any] = {k: 0.0 if k in PHASES else 0 for k in VIEW_STATS}
    stats.update(spheres=len(centres), delta=float(delta), resolution=int(resolution),
                 gathers_aside=0)
    hull_boxes, hull_ids = _hulls(scene, data, centre)
    graze, graze_rows = _grazing(scene, data, centres + centre, delta, int(resolution))
    if len(graze):
        # A slab along the normal, thick enough for a few pixels at its distance (at most Δ).
        gbox = np.empty((len(graze), 2, 3))
        grazing_boxes(scene.vertices, scene.faces, graze, data.normals, graze_rows, centre,
                      float(delta), float(resolution), gbox)
        hull_boxes = np.concatenate([hull_boxes, gbox])
        hull_ids = np.concatenate([hull_ids, graze])
    stats["grazing"] = len(graze)
    seen_hull = np.zeros(len(hull_ids), dtype=np.uint8)
    if not len(data.static) and not len(hull_ids):
        stats.update(kbuffer_allocated_bytes=0, mean_sequence_length=0.0, near_eye=0,
                     sphere_ids=np.zeros(0, dtype=np.int32))
        return np.zeros(0, dtype=np.int64), stats
    t0 = time.perf_counter()
    verts = np.ascontiguousarray(scene.vertices - centre)
    frame = leaf_frame(data.octree, centre)
    row_of = np.full(m, -1, dtype=np.int64)
    row_of[data.static] = np.arange(len(data.static))
    item_rows = row_of[data.octree.tri_items]
    # Grazing triangles are static: they count only where they lie in front of the first
    # surface a pixel sees (moving hulls are tested against seals and hidden spans).
    open_only = (hull_ids < m) & ~np.isin(hull_ids, data.moving)
    # Static triangles whose plane passes through the box (tested per sphere below).
    through_box = np.empty(len(data.plane), dtype=np.bool_)
    planes_near(data.normals, data.plane, centre, 0.5 * (box[1] - box[0]), 0.0, through_box)
    near_plane = np.empty_like(through_box)
    # v*'s renders (``_sample_from_vstar``) draw through the scene's hierarchy, frustum and
    # occlusion culled, when it is there (a small scene's is built now, as cos does).
    hier = ready_hierarchy(scene)
    if hier is None and 0 < scene.n_triangles < MIN_TRIANGLES:
        hier = scene_hierarchy(scene)
    workers = _view_workers()
    free: queue.SimpleQueue[tuple[KBuffer, Scratch]] = queue.SimpleQueue()
    # Buffers of the previous computation when it ended moments ago (``warm``): fresh ones
    # cost their first-touch page faults.
    pairs, stats["buffers_reused"] = WARM.take(int(resolution) ** 2, workers)
    for pair in pairs:
        free.put(pair)
    stats["kbuffer_allocated_bytes"] = sum(kb.allocated_bytes for kb, _ in pairs)
    stats["near_eye"] = 0
    stats["view_workers"] = workers
    stats["p1_geometry"] += time.perf_counter() - t0
    # Views run ``workers`` at a time, each thread with its own k-buffer and one numba thread
    # (the per-layer kernels are too short to keep two threads busy): the views only add to
    # ``vis`` and ``seen_hull`` (writes of 1, in any order), so the answer does not depend on
    # the order they finish in. What lies near a sphere joins ``vis`` once no view runs.
    near_all = np.zeros(m, dtype=np.uint8)
    hulls = (open_only, seen_hull, np.ascontiguousarray(hull_boxes[:, 0]),
             np.ascontiguousarray(hull_boxes[:, 1])) if len(hull_ids) else None
    shared = (scene, verts, data, frame, item_rows, vis, margin_px, footprints, centre, hier,
              small)
    pool = ThreadPoolExecutor(workers, initializer=numba.set_num_threads, initargs=(1,)) \
        if workers > 1 else None
    crew = Crew(workers) if pool is not None else None
    counts = np.diff(data.octree.tri_start)
    in_flight: deque[list[Future[dict[str, Any]]]] = deque()
    try:
        for v0 in centres:
            t = time.perf_counter()
            # What passes through the sphere is beside some eye and in front of others:
            # reported, and never an occluder for this sphere (the erosion theorem needs
            # occluders outside the viewcell).
            near = np.zeros(m, dtype=np.uint8)
            near_sphere(verts, data.faces, _rows_near(data.octree, frame, v0, delta), v0,
                        delta, near)
            near_all |= near
            stats["near_eye"] += int(np.count_nonzero(near))
            # Planes through the eyes this sphere answers for: those of the sphere in the box.
            planes_near(data.normals, data.plane, v0 + centre, np.zeros(3), delta, near_plane)
            ambiguous = data.static[through_box & near_plane]
            hit = np.all((hull_boxes[:, 0] <= v0 + delta) & (hull_boxes[:, 1] >= v0 - delta),
                         axis=1)
            seen_hull[hit] = 1
            stats["p1_geometry"] += time.perf_counter() - t
            views = sphere_views(v0, delta, int(resolution))
            if pool is None:
                for view in views:
                    _merge(stats, _view_task(view, near, ambiguous, shared, hulls, free))
                continue
            # The views with most to draw first: the last to finish then gets the threads
            # of the workers that ran out of views (``crew``).
            drawn = [drawn_leaves(frame, v) for v in views]
            load = [int(counts[d].sum()) for d in drawn]
            order = sorted(range(len(views)), key=lambda k: -load[k])
            # A view that draws most of the sphere's items (the one into a dense room) has
            # its gather from v* (P4) made aside, as a task queued right behind it: a worker
            # with no view left makes it while the view rasterizes, and the view makes it
            # itself if it gets there first (``_Gather``). Where the views weigh alike
            # (open scenes) the task only cost time.
            renders: list[_Gather | None] = [None] * len(views)
            lead = order[0]
            if footprints and load[lead] > ASIDE_SHARE * sum(load):
                renders[lead] = _Gather(scene, data, verts, views[lead], centre, hier, vis)
            crew.queue(len(views) + sum(r is not None for r in renders))
            # Two spheres in flight at most: each holds its ``near`` marks (one byte per
            # triangle) until its views are done.
            while len(in_flight) >= 2:
                for f in in_flight.popleft():
                    _merge(stats, f.result())
            tasks = []
            for k in order:
                tasks.append(pool.submit(contextvars.copy_context().run, _view_task,
                                         views[k], near, ambiguous, shared, hulls, free, crew,
                                         drawn[k], renders[k]))
                if renders[k] is not None:
                    tasks.append(pool.submit(contextvars.copy_context().run, _render_task,
                                             renders[k], crew))
            in_flight.append(tasks)
        while in_flight:
            for f in in_flight.popleft():
                _merge(stats, f.result())
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        WARM.give(pairs)
    checkpoint()
    vis |= near_all
    t = time.perf_counter()
    gathered_spheres = np.zeros(0, dtype=np.int32)
    stats["eye_gathered"] = 0
    if footprints and gather_eyes > 0:
        checkpoint()
        g = sample_pvs(scene, Viewcell(box), n_points=int(gather_eyes),
                       resolution=min(SUPERSAMPLE * int(resolution), MAX_RESOLUTION),
                       seed=GATHER_SEED, near=FRAME_NEAR)
        stats["eye_gathered"] = int(np.count_nonzero(vis[g.triangle_ids] == 0))
        vis[g.triangle_ids] = 1
        gathered_spheres = g.sphere_ids.astype(np.int32)
    seen = hull_ids[seen_hull != 0]
    vis[seen[seen < m]] = 1
    ids = _not_edge_on(scene, np.flatnonzero(vis).astype(np.int64), box)
    stats["sphere_ids"] = np.union1d((seen[seen >= m] - m).astype(np.int32),
                                     gathered_spheres).astype(np.int32)
    stats["p4_gather"] += time.perf_counter() - t
    n = max(stats.pop("pixel_resolves"), 1)
    stats["mean_sequence_length"] = float(stats.pop("entries_resolved") / n)
    return ids, stats


#: Stats a view adds to (``_view_task``); ``kbuffer_used_bytes`` is a maximum, the rest sums.
VIEW_STATS = ("p0_layers", "p1_geometry", "p2_raster", "p3_resolve", "p4_gather",
              "silhouette_trims", "layers", "views", "kbuffer_used_bytes", "pixel_resolves",
              "validated_intervals", "terminators", "entries_resolved", "single_sided_trims",
              "active_pixels", "trimmed_pixels", "sealed_pixels", "overflow_pixels",
              "instances", "culled_instances", "culled_trims")


def _view_workers() -> int:
    """Views solved at once: the numba threads this computation may use (a pool worker
    limited to one thread solves them in turn)."""
    return max(1, int(numba.get_num_threads()))


def _view_task(view: View, near: np.ndarray, ambiguous: np.ndarray, shared: tuple,
               hulls: tuple | None, free: queue.SimpleQueue,
               crew: Crew | None = None, drawn: np.ndarray | None = None,
               render: _Gather | None = None) -> dict[str, Any]:
    """Solve one view with a k-buffer taken from ``free`` (and given back); returns the
    stats it adds (``VIEW_STATS``). With a ``crew`` (views on worker threads), the view
    takes the numba threads it lends between layers; ``drawn``: its leaves in the frustum
    (``layers.drawn_leaves``), when the caller has them; ``render``: its gather from v*
    (``_Gather``), which another worker may make (``_render_task``)."""
    scene, verts, data, frame, item_rows, vis, margin_px, footprints, centre, hier, small = shared
    st: dict[str, Any] = {k: 0.0 if k in PHASES else 0 for k in VIEW_STATS}
    kb, scratch = free.get()
    if crew is not None:
        crew.start()
    try:
        checkpoint()
        _solve_view(scene, view, verts, data, frame, item_rows, near, ambiguous, kb, vis, st,
                    margin_px, footprints, centre, hier, small, crew, scratch, drawn, render)
        if hulls is not None:
            t = time.perf_counter()
            _test_hulls(view, *hulls, kb, scratch)
            st["p4_gather"] += time.perf_counter() - t
    finally:
        if render is not None:
            # Also when the view never began (a cancel): its gather must not wait for it.
            render.end()
        if crew is not None:
            crew.finish()
        free.put((kb, scratch))
    return st


def _render_task(render: _Gather, crew: Crew) -> dict[str, Any]:
    """Make a view's gather from v* on this worker unless the view has begun it itself;
    returns the stats it adds (``p4_gather``, its seconds, when it made it)."""
    crew.start()
    try:
        if render.once.run():
            return {"p4_gather": render.seconds, "gathers_aside": 1}
        return {}
    finally:
        crew.finish()


class _Gather:
    """A view's gather from v* (P4 but what needs its seals): the renders
    (``_sample_from_vstar``) and the footprint tests against them
    (``hulls.touching_in_front``, ``hulls.touching_samples``), which need only the view's
    set-up polygons (``set_up``), not its layers; run once (``once``) by the worker that
    claims it first. ``seconds``: its work, waiting left out."""

    def __init__(self, scene: Scene, data: SceneData, verts: np.ndarray, view: View,
                 centre: np.ndarray | None, hierarchy: Hierarchy | None,
                 vis: np.ndarray) -> None:
        self._args = (scene, data, verts, view, centre, hierarchy, vis)
        self._ready = threading.Event()
        self._polys: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.seconds = 0.0
        self.once: Once[None] = Once(self._run)

    def set_up(self, poly: np.ndarray, npoly: np.ndarray, pbox: np.ndarray) -> None:
        """The view's set-up polygons are ready (``raster.setup_triangles``)."""
        self._polys = (poly, npoly, pbox)
        self._ready.set()

    def end(self) -> None:
        """The view is done (or failed): a gather not begun never runs, one running is
        waited for, so the view may hand its polygons on."""
        self._ready.set()
        self.once.close()

    def _run(self) -> None:
        scene, data, verts, view, centre, hierarchy, vis = self._args
        t = time.perf_counter()
        bufs = GATHER_SCRATCH.take()
        try:
            self._gather(scene, data, verts, view, centre, hierarchy, vis, bufs, t)
        finally:
            GATHER_SCRATCH.give(bufs)

    def _gather(self, scene: Scene, data: SceneData, verts: np.ndarray, view: View,
                centre: np.ndarray | None, hierarchy: Hierarchy | None, vis: np.ndarray,
                bufs: Scratch, t: float) -> None:
        """``_run``'s work, its renders made into ``bufs``; ``t``: when it began."""
        first, seen, depth, far = _sample_from_vstar(scene, data.static_mask, verts, view,
                                                     centre, hierarchy, bufs)
        work = time.perf_counter() - t
        self._ready.wait()
        if self._polys is not None:
            t = time.perf_counter()
            poly, npoly, pbox = self._polys
            vis[seen] = 1
            touching_in_front(poly, npoly, pbox, data.static, first, view.res, vis)
            # Small triangles v* sees between the samples, which the pixels' open depth
            # (above) can hide: tested against the samples around them.
            touching_samples(poly, npoly, pbox, data.static, depth, far, view.res, SUPERSAMPLE,
                             SMALL_BOX_PX, vis)
            work += time.perf_counter() - t
        self.seconds = work


def _merge(stats: dict[str, Any], part: dict[str, Any]) -> None:
    """Add one view's stats (``_view_task``) into the computation's."""
    for k, v in part.items():
        stats[k] = max(stats[k], v) if k == "kbuffer_used_bytes" else stats[k] + v


def _rows_near(octree: Octree, frame: LeafFrame, centre: np.ndarray,
               radius: float) -> np.ndarray:
    """(k,) int64 static triangle ids (repeats possible) of the octree's leaves that meet the
    cube of half side ``radius`` (metres) around ``centre`` (``frame``'s coordinates), grown
    by a hundredth of a fine cell against rounding: every static triangle within ``radius``
    of ``centre`` is among them, as a triangle sits in every leaf its bounding box meets."""
    g = radius + 0.01 * octree.cell
    hit = np.flatnonzero(np.all((frame.lo <= centre + g) & (frame.hi >= centre - g), axis=1))
    parts = [octree.tri_items[octree.tri_start[k]:octree.tri_start[k + 1]] for k in hit]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


def _grazing(scene: Scene, data: SceneData, centres: np.ndarray, delta: float,
             resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(ids, their rows in ``data.static``) of the static triangles whose plane passes
    within Δ of a sphere centre (world ``centres``
    (k, 3)) and which that centre sees thinner than a pixel: an eye of the sphere may see them
    at a steeper angle than v*, which samples them at no pixel centre, so they are also tested
    as hulls (their box grown along the normal).

    Thin means either the plane's line lies within a pixel of the centre (the triangle is seen
    edge-on) or the triangle's extent across that line is under a pixel: its corners, at
    distances d_i from the centre, rise off / d_i radians off the plane's line, so a triangle
    reaching in depth but not across (a door jamb 4 m off, 4 cm beside the eye) spans
    off (1 / d_min - 1 / d_max) radians however far its line lies from the centre."""
    ids = data.static
    if not len(ids):
        return ids, np.zeros(0, dtype=np.int64)
    close = np.zeros(len(ids), dtype=np.bool_)
    # A face's centre has the fewest pixels per radian: 0.5 * resolution.
    grazing_mask(scene.vertices, scene.faces, ids.astype(np.int64, copy=False), data.normals,
                 data.plane, np.ascontiguousarray(centres, dtype=np.float64), float(delta),
                 0.5 * resolution, close)
    rows = np.flatnonzero(close)
    return ids[rows], rows


def _not_edge_on(scene: Scene, ids: np.ndarray, box: np.ndarray) -> np.ndarray:
    """``ids`` without the triangles whose plane holds the whole cell: they have no area from
    any eye of the cell, only from the spheres' and v*'s extra eye positions."""
    if not len(ids):
        return ids
    holds = np.zeros(len(ids), dtype=np.bool_)
    plane_holds_box(scene.vertices, scene.faces, ids, np.asarray(box, dtype=np.float64), holds)
    return ids[~holds]


def _solve_view(scene: Scene, view: View, verts: np.ndarray, data: SceneData,
                frame: LeafFrame, item_rows: np.ndarray, near: np.ndarray,
                ambiguous: np.ndarray, kb: KBuffer, vis: np.ndarray,
                stats: dict[str, Any], margin_px: float, footprints: bool,
                centre: np.ndarray | None = None, hierarchy: Hierarchy | None = None,
                small: str = "centres", crew: Crew | None = None,
                scratch: Scratch | None = None, drawn: np.ndarray | None = None,
                render: _Gather | None = None) -> None:
    """Layers, geometry, rasterization and resolve of one adapted frustum; adds what it finds
    to ``vis`` and its counters to ``stats``; leaves the seal depths in ``kb.seal``.
    ``centre`` (the computation's centre, world metres) and the scene's ``hierarchy`` serve
    v*'s renders (``_sample_from_vstar``); ``render``, the view's gather from v*
    (``_Gather``), may be made by another worker (one only this view sees is made here when
    not given; the caller ends a shared one, ``_Gather.end``)."""
    if footprints and render is None:
        render = _Gather(scene, data, verts, view, centre, hierarchy, vis)
    stop = stop_flag()
    res = view.res
    faces = data.faces
    t0 = time.perf_counter()
    octree = data.octree
    layer, drawn = leaf_layers(octree, frame, view, drawn)
    t1 = time.perf_counter()
    cam = to_camera(verts, view.vstar, view.rot)
    s = len(data.static)
    # setup_triangles writes every row of these (no polygon outside the drawn leaves).
    scratch = Scratch() if scratch is None else scratch
    facing = scratch.array("facing", s, np.int8)
    poly = scratch.array("poly", (s, 4, 3))
    npoly = scratch.array("npoly", s, np.int64)
    pbox = scratch.array("pbox", (s, 4), np.int64)
    # Polygons only for the triangles of the leaves this view draws (the others lie outside
    # its frustum); facing for every triangle, as silhouettes need it.
    need = scratch.array("need", s, np.bool_)
    drawn_rows(drawn, frame.item_leaf, item_rows, need)
    setup_triangles(cam, faces, data.static, need, view.near, view.tan, res, facing, poly, npoly,
                    pbox)
    if render is not None:
        render.set_up(poly, npoly, pbox)
    e = data.edges
    # A triangle whose plane passes through the sphere faces some of its eyes and turns its
    # back on others: its edges may be silhouettes for them though not for v* (an eye
    # behind one wall of a corner sees past the other wall's end). Silhouettes only where
    # the view draws: an edge with a triangle in a drawn leaf.
    facing_of = scratch.array("facing_of", len(vis), np.int8)
    edge_on = scratch.array("edge_on", len(e.face), np.bool_)
    drawn_edges(data.static, need, facing, ambiguous, AMBIGUOUS, e.face, facing_of, edge_on)
    reach = Reach(data.normal_of, np.ascontiguousarray(view.rot, dtype=np.float64),
                  float(view.tan), int(res), float(view.delta + view.back), cam, data.faces,
                  float(view.back), float(view.delta), facing_of)
    trims, trim_layer = silhouette_trims(
        cam, e.vert, e.face, e.opp, e.many, facing_of, edge_on, view.near, view.tan, res,
        view.delta, view.back, margin_px, view.vstar, view.rot, frame.grid_origin, octree.cell,
        octree.leaf_of_cell, layer, data.piece)
    inst = scratch.array("inst", len(item_rows), np.int64)
    inst_layer = scratch.array("inst_layer", len(item_rows), np.int64)
    k = drawn_instances(drawn, frame.item_leaf, item_rows, data.octree.tri_items, npoly, near,
                        layer, inst, inst_layer)
    inst_order, inst_layers, inst_starts = by_layer(inst_layer[:k])
    inst = inst[:k][inst_order]
    inst_row = np.ascontiguousarray(item_rows[inst])
    inst_leaf = np.ascontiguousarray(frame.item_leaf[inst])
    trim_order, trim_layers, trim_starts = by_layer(trim_layer)
    trims = np.ascontiguousarray(trims[trim_order])
    all_layers = np.union1d(inst_layers, trim_layers)
    _reset(kb)
    tris = SetUp(data.static, facing, poly, npoly, pbox)
    camera = Camera(view.vstar, view.rot, float(view.tan), int(res))
    margin = margin_px * 2.0 * view.tan / res
    n_bands = (res + 7) // 8
    counters = np.zeros((n_bands, 4), dtype=np.int64)
    t2 = time.perf_counter()
    stats["p0_layers"] += t1 - t0
    stats["p1_geometry"] += t2 - t1
    stats["silhouette_trims"] += len(trims)
    stats["layers"] += len(all_layers)
    stats["instances"] += len(inst)
    stats["views"] += 1
    held = scratch.array("held", res * res, np.uint8)
    held[:] = 0
    tally = np.zeros((n_bands, 2), dtype=np.int64)
    for lay in all_layers:
        checkpoint()
        if crew is not None:
            crew.lend()
        ta = time.perf_counter()
        k = np.searchsorted(trim_layers, lay)
        if k < len(trim_layers) and trim_layers[k] == lay:
            stats["culled_trims"] += raster_trims(trims[trim_starts[k]:trim_starts[k + 1]], res,
                                                  view.tan, margin, kb, vis, stop)
        k = np.searchsorted(inst_layers, lay)
        if k < len(inst_layers) and inst_layers[k] == lay:
            sl = slice(inst_starts[k], inst_starts[k + 1])
            stats["culled_instances"] += raster_surfaces(inst_row[sl], inst_leaf[sl], tris,
                                                         frame.lo, frame.hi, camera, kb, vis,
                                                         stop)
        tb = time.perf_counter()
        tally[:] = 0
        _resolve(kb, res, False, vis, counters, stop, data, reach, held, tally)
        stats["kbuffer_used_bytes"] = max(stats["kbuffer_used_bytes"],
                                          int(tally[:, 0].sum()) * ENTRY_BYTES)
        stats["pixel_resolves"] += int(tally[:, 1].sum())
        stats["p2_raster"] += tb - ta
        stats["p3_resolve"] += time.perf_counter() - tb
    checkpoint()
    tb = time.perf_counter()
    stats["pixel_resolves"] += int(np.count_nonzero((kb.count > 0) & (kb.stencil != 2)))
    _resolve(kb, res, True, vis, counters, stop, data, reach, held, tally)
    checkpoint()
    stats["p3_resolve"] += time.perf_counter() - tb
    if footprints:
        if crew is not None:
            crew.lend()
        assert render is not None
        if render.once.run():
            stats["p4_gather"] += render.seconds
        # Made here or by another worker (which counts its seconds): waited for.
        render.once.get()
        if small == "conservative":
            tc = time.perf_counter()
            small_in_front(poly, npoly, pbox, data.static, kb.seal, kb.spans, kb.n_spans, res,
                           THIN_PX, DEPTH_TOL, vis)
            stats["p4_gather"] += time.perf_counter() - tc
    stats["validated_intervals"] += int(counters[:, 0].sum())
    stats["terminators"] += int(counters[:, 1].sum())
    stats["entries_resolved"] += int(counters[:, 2].sum())
    stats["single_sided_trims"] += int(counters[:, 3].sum())
    stats["active_pixels"] += int(held.sum())
    stats["trimmed_pixels"] += int(np.count_nonzero(kb.stencil == 1))
    stats["sealed_pixels"] += int(np.count_nonzero(kb.stencil == 2))
    stats["overflow_pixels"] += int(kb.overflow.sum())


def _sample_from_vstar(scene: Scene, static_mask: np.ndarray, verts: np.ndarray,
                       view: View, centre: np.ndarray | None = None,
                       hierarchy: Hierarchy | None = None, bufs: Scratch | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What v* sees between the pixel centres of a view (``visibility.raster.triangles
    .render_ids``, static triangles only), in the frame of ``verts``; with the scene's
    ``hierarchy`` and the frame's world ``centre``, drawn in the scene's own frame through
    the hierarchy (frustum and occlusion culled: the same images, less drawn). The renders
    are made into ``bufs`` (fresh ones when None); ``depth`` is then its buffer, valid until
    its next use.

    Returns
    -------
    first : (res * res,) the farthest nearest-surface depth that ``OPEN_SAMPLES`` of the
        ``SUPERSAMPLE``² sample points in each pixel's square see: where an occluder's edge
        crosses a pixel, the part of the square it leaves open shows here.
    seen : (k,) int64 ids of the triangles nearest at any of those samples or at the samples
        of a second grid, rolled by ``ROLL`` with ``ROLLED_SAMPLES`` per pixel side.
    depth : (res * SUPERSAMPLE, res * SUPERSAMPLE) the supersampled render's depths.
    far : (res * res,) the farthest of each pixel's ``SUPERSAMPLE``² sample depths.
    """
    res = view.res
    ss = SUPERSAMPLE * res
    eye = view.vstar
    if hierarchy is not None and centre is not None:
        verts = scene.vertices
        eye = view.vstar + centre
    bufs = Scratch() if bufs is None else bufs
    depth, ids = render_ids(verts, scene.faces, eye, view.rot, ss, ss, view.tan, view.tan,
                            near=view.near, face_mask=static_mask, hierarchy=hierarchy,
                            out=(bufs.array("depth", (ss, ss), np.float32),
                                 bufs.array("ids", (ss, ss), np.int32)))
    # Not the farthest sample but the OPEN_SAMPLES-th farthest: a crack between the triangles
    # of a mesh that is not watertight opens one or two samples onto the far side, and would
    # let everything behind the mesh through (most of the 1M kitchen).
    first = np.empty(res * res)
    far = np.empty(res * res)
    open_depth(depth, res, SUPERSAMPLE, SUPERSAMPLE * SUPERSAMPLE - OPEN_SAMPLES, first, far)
    # A sliver lying along a row or column of the face's grid (wall edges, cabinet bevels: the
    # scene's axes are often the cube's) can run between two rows of samples for its whole
    # length; on a rolled grid covering the same frustum it crosses them.
    c, s = np.cos(ROLL), np.sin(ROLL)
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    reach = view.tan * (c + s)
    n_rolled = int(np.ceil(ROLLED_SAMPLES * res * (c + s)))
    _, rolled = render_ids(verts, scene.faces, eye, roll @ view.rot, n_rolled, n_rolled, reach,
                           reach, near=view.near, face_mask=static_mask, hierarchy=hierarchy,
                           out=(None, bufs.array("rolled", (n_rolled, n_rolled), np.int32)))
    # Marks, not np.unique: a million samples per view, most of them repeats.
    mark = np.zeros(scene.n_triangles, dtype=bool)
    mark_seen(ids.reshape(-1), mark)
    mark_seen(rolled.reshape(-1), mark)
    return first, np.flatnonzero(mark), depth, far


def _resolve(kb: KBuffer, res: int, final: bool, vis: np.ndarray, counters: np.ndarray,
             stop: np.ndarray, data: SceneData, reach: Reach, held: np.ndarray,
             tally: np.ndarray) -> None:
    resolve_layer(kb, data.closed, data.piece, reach, res, final, vis, counters, stop, held,
                  tally)


def _reset(kb: KBuffer) -> None:
    kb.count[:] = 0
    kb.stencil[:] = 0
    kb.active[:] = 0
    kb.overflow[:] = 0
    kb.cover[:] = 0.0
    kb.seal[:] = np.inf
    kb.n_spans[:] = 0
    kb.first[:] = np.inf
    kb.hid[:] = 0
    kb.queued[:] = 0
    kb.held_entries[:] = 0


def _test_hulls(view: View, open_only: np.ndarray, seen: np.ndarray, lo: np.ndarray,
                hi: np.ndarray, kb: KBuffer, scratch: Scratch | None = None) -> None:
    """Mark in ``seen`` the hulls (boxes [lo, hi] (k, 3)) not yet seen that meet the view's
    frustum and have a pixel in front of its seal depths and outside its hidden spans."""
    sel = np.flatnonzero(in_view(lo, hi, view.vstar, view.rot, view.tan, view.near)
                         & (seen == 0))
    if not len(sel):
        return
    # Corners of the boxes this view tests only (all of them, made once, cost more).
    cam = boxes_to_camera(lo, hi, sel, view.vstar, view.rot)
    faces = (np.arange(len(sel))[:, None, None] * 8 + BOX_FACES[None]).reshape(-1, 3)
    owner = np.repeat(sel, len(BOX_FACES))
    n = len(faces)
    # The set-up writes every row it is given.
    scratch = Scratch() if scratch is None else scratch
    facing = scratch.array("hull_facing", n, np.int8)
    poly = scratch.array("hull_poly", (n, 4, 3))
    npoly = scratch.array("hull_npoly", n, np.int64)
    pbox = scratch.array("hull_pbox", (n, 4), np.int64)
    setup_triangles(cam, faces, np.arange(n, dtype=np.int64), np.ones(n, dtype=np.bool_),
                    view.near, view.tan, view.res,
                    facing, poly, npoly, pbox)
    hulls_in_front(poly, npoly, pbox, owner, open_only, kb.seal, kb.spans, kb.n_spans,
                   kb.first, view.res, seen)


__all__ = ["K", "PHASES", "trim_pvs"]
