"""The ``dual_ray`` core: from-region visibility in a dual ray space (Koltun, Chrysanthou,
Cohen-Or 2001), for 2.5D scenes and big cells.

Conservative for eyes in the open air of a 2.5D scene: a kd-tree over the scene (``kdtree``) is
traversed from the root; each node's box is tested against the cell (``dual_space``: the shaft's
ceiling, the dual ray space, a hierarchical conservative raster) among the walls closed
downwards (``fences``); an occluded node ends its recursion. The PVS is the triangles of the
visible leaves, each then tested on its own bounds (clipped to its leaf) the same way.
Everything whose bounds reach over the cell's footprint is visible (the shaft needs a gap),
so a cell that reaches into a building reports that building's triangles around it. What is not
a wall (roofs, terrain, trees), moving triangles (over their swept bounds) and spheres (all
reported) never occlude.

Only for 2.5D scenes: ``requires_2_5d`` makes ``fit`` refuse the others, and ``compute`` on one
raises ``NotTwoPointFiveD`` with the reason (``visibility.scene_analysis``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from visibility.cancel import checkpoint
from visibility.cores.base import Core, CoreParams, Cost, Fit, param, register
from visibility.cores.dual_ray.dual_space import (
    COARSE,
    boxes_visible_among,
    leaf_piece_ids,
    nodes_visible,
)
from visibility.cores.dual_ray.fences import Fences, cell_fences, near_pieces, scene_fences
from visibility.cores.dual_ray.groups import GroupLists
from visibility.cores.dual_ray.kdtree import KdTree, scene_kdtree
from visibility.raster.camera import DEFAULT_NEAR
from visibility.scene import Scene
from visibility.scene_cache import Build, per_scene
from visibility.viewcells import Viewcell

#: The paper's choice (Sec. 6): 128 x 128 for 100 m cells.
DEFAULT_RESOLUTION = 128
#: Nodes (or triangles) tested per parallel batch; a cancellation checkpoint after each.
BATCH = 4096
#: Triangles of a leaf tested together first (``refine_triangles``).
GROUP = 8
#: ``triangle_refine="auto"`` tests every triangle of the visible leaves when they hold at most
#: this many (leaf-triangle entries), else only those of the leaves the raster decided. Every
#: entry costs a triangle-against-shaft test, so the bound keeps the refinement near a second
#: (``python -m benchmarks.bench_dual_ray``; figures in docs/cores/dual_ray.md).
REFINE_ALL_MAX = 150_000
#: Cells from this size up (metres, the larger horizontal side) are what the core is for.
BIG_CELL = 10.0


class NotTwoPointFiveD(ValueError):
    """The scene is not 2.5D, so the dual-ray core cannot answer for it."""


@dataclass
class DualRayParams(CoreParams):
    """Parameters of the dual-ray core.

    resolution : side of the dual ray space raster (pixels); the PVS stays conservative at any
        value, higher costs more and overestimates less. Tested 16 x 16 first, refined where
        needed; rounded up to a multiple of 16.
    triangle_refine : which visible kd leaves have each triangle tested on its own bounds:
        "auto" (the default: "all" when the visible leaves hold at most ``REFINE_ALL_MAX``
        triangle entries, about a second of tests, else "marginal"), "all" (smallest PVS),
        "marginal" (only those the raster had to decide: no probe ray was free; on Lyon's
        40 m cells about half the time for up to twice the PVS) or "none" (whole leaves).
    """

    resolution: int = param(DEFAULT_RESOLUTION, unit="px", ge=8, le=4096,
                            help="side of the dual ray space raster (16 x 16 first, refined)")
    triangle_refine: str = param(
        "auto", choices=("auto", "all", "marginal", "none"),
        help="which visible kd leaves have each triangle tested on its own bounds: auto "
             "(all while that is cheap: at most 150k leaf triangles, else marginal), all "
             "(smallest PVS), marginal (only those no probe ray saw: about half the time, "
             "up to twice the PVS) or none (whole leaves)")


#: Cost model (``estimate_cost``), fitted to ``python -m benchmarks.bench_dual_ray`` on the
#: 2-core development machine (benchmarks/results/dual_ray.md, load average about 1): the time
#: grows about linearly with the scene's triangles and with the cell's side (a bigger cell sees
#: more leaves and tests more triangles, each with a wider shaft), and barely with the
#: resolution (the quadtree refines only along region boundaries). The per-triangle-metre
#: rate is the largest the benchmark's cells showed (figures in docs/cores/dual_ray.md): an
#: upper estimate, as admission wants. Bytes: tree, bounds
#: and fences per triangle, and the raster's lists per pixel of the coarse square.
SECONDS_BASE = 0.02
SECONDS_PER_TRIANGLE_METRE = 6e-8
BYTES_PER_TRIANGLE = 160


@register
class DualRayCore(Core):
    """Koltun et al. 2001: kd-tree traversal, cell-to-node visibility on the shaft's ceiling
    in the dual ray space (conservative, 2.5D scenes only)."""

    name: ClassVar[str] = "dual_ray"
    description: ClassVar[str] = (
        "Dual ray space (Koltun, Chrysanthou, Cohen-Or 2001): kd-tree nodes tested against the "
        "cell on the shaft's ceiling plane, occluding walls rasterized conservatively in the "
        "dual ray space (conservative; 2.5D scenes only, made for big cells)")
    Params: ClassVar[type[CoreParams]] = DualRayParams
    promise: ClassVar[str] = "conservative"
    knob: ClassVar[str] = "resolution"
    knob_levels: ClassVar[tuple[int, ...]] = (16, 32, 64, 128, 256)
    native_segments: ClassVar[bool] = False
    requires_2_5d: ClassVar[bool] = True
    fits: ClassVar[str] = ("2.5D scenes (cities: walls standing on the ground) at big cells, "
                           "10 m to a few hundred metres")
    check_params: ClassVar[dict[str, Any]] = {}
    fn_bound: ClassVar[float] = 0.0
    #: The worst FP ``checks.check_fn_fp_against_sampled_ground_truth`` measures, rounded up
    #: (its failure message prints the rate): on the city blocks, roofs and ground faces that
    #: only roofs could hide (roofs never occlude here) and the far faces of blocks whose boxes
    #: reach past a corner; ``check_fp_bound_can_fail`` checks that reporting every triangle
    #: still exceeds it.
    fp_bound: ClassVar[float] = 0.75

    def fit(self, scene: Scene, cell_size: float | None = None) -> Fit:
        """``Core.fit``; a refusal of a scene whose meta states it is not 2.5D also says what
        its geometry shows (the share under overhangs and where the first one is)."""
        out = super().fit(scene, cell_size)
        if out.ok or "2.5D" not in out.why:
            return out
        return Fit(False, out.score, out.why + _geometry_says(scene))

    def suitability(self, scene: Scene, cell_size: float | None) -> tuple[float, str]:
        # Only called on 2.5D scenes (fit refuses the rest). Big cells are what the core is
        # for: the tree's early termination prunes whole districts at once, and the cost grows
        # slowly with the cell (benchmarks/results/dual_ray.md); small cells are better served
        # by the per-pixel cores, which also use roofs and terrain as occluders.
        if cell_size is not None and cell_size >= BIG_CELL:
            return 6.0, (f"2.5D scene and big cells ({cell_size:g} m >= {BIG_CELL:g} m): "
                         "conservative dual-ray-space visibility, fast on big cells")
        return 0.5, (f"conservative, but made for big cells (>= {BIG_CELL:g} m) of 2.5D "
                     "scenes; smaller cells are better served by per-pixel cores")

    def estimate_cost(self, scene: Scene, cell: Viewcell, params: CoreParams) -> Cost:
        """Linear in the scene's triangles and in the cell's side (at least 20 m), slowly
        growing with the resolution; memory per triangle (tree, fences, bounds) and per
        pixel."""
        r = int(params.resolution)
        size = float(np.max(cell.size[[0, 2]])) if np.all(np.isfinite(cell.size)) else 0.0
        m = scene.n_triangles
        res_factor = (max(r, 16) / 128.0) ** 0.1
        seconds = SECONDS_BASE + m * SECONDS_PER_TRIANGLE_METRE * max(size, 20.0) * res_factor
        peak = m * BYTES_PER_TRIANGLE + 64 * r * r
        return Cost(float(seconds), int(peak), {"triangles": m, "resolution": r,
                                                "cell_size": size})

    def scene_builds(self, scene: Scene) -> list[Build]:
        """The kd-tree and the fences (``scene_kdtree``, ``scene_fences``)."""
        from visibility.cores.dual_ray.fences import build_fences
        from visibility.cores.dual_ray.kdtree import build_kdtree

        return [Build("kdtree", build_kdtree), Build("fences", build_fences)]

    def _compute(
        self, scene: Scene, cell: Viewcell, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, DualRayParams)
        from visibility.scene_analysis import scene_is_2_5d

        flat, how = scene_is_2_5d(scene)
        if not flat:
            raise NotTwoPointFiveD(f"core 'dual_ray' needs a 2.5D scene; {scene.name!r} is "
                                   f"not: {how['reason']}{_geometry_says(scene)}")
        return dual_ray_pvs(scene, np.asarray(cell.box, dtype=np.float64),
                            int(params.resolution), str(params.triangle_refine))


def _geometry_says(scene: Scene) -> str:
    """``"; its geometry: <reason>"`` when the 2.5D answer came from the scene's meta (which
    says only who stated it), else ``""``. The analysis is cached with the scene."""
    from visibility.scene_analysis import analyse_2_5d, stated_2_5d

    if stated_2_5d(scene) is None:
        return ""
    geo, _ = per_scene(scene, "analysis_2_5d", analyse_2_5d)
    return f"; its geometry: {geo.reason}"


def dual_ray_pvs(scene: Scene, box: np.ndarray, resolution: int,
                 triangle_refine: str = "auto",
                 coarse: int = COARSE) -> tuple[np.ndarray, dict[str, Any]]:
    """PVS of a box cell of a 2.5D scene (module docstring).

    Parameters
    ----------
    scene : the scene.
    box : (2, 3) float64 [min, max], metres.
    resolution : side of the dual ray space raster, pixels.
    triangle_refine : which visible leaves have each triangle tested on its own bounds:
        "all", "marginal" (those only the raster found visible: no probe ray was free),
        "none", or "auto" ("all" up to ``REFINE_ALL_MAX`` leaf-triangle entries, else
        "marginal").
    coarse : side of the first raster pass.

    Returns
    -------
    triangle_ids : (k,) int64 visible triangle ids (any order).
    stats : ``near_pieces`` (fence pieces within reach of a client's near plane from the
        cell, which occlude nothing here), ``near_plane`` (the client near plane assumed,
        metres), seconds per phase (``kdtree_seconds`` and ``fence_seconds``: 0 once cached,
        ``traversal_seconds``, ``refine_seconds``), ``nodes_visited``, ``nodes_culled``,
        ``leaves_visible``, ``leaf_triangles`` (their triangle entries), ``triangle_refine``
        (the mode used), ``triangle_tests``, ``triangles_culled``, ``occluders`` (fence
        pieces of the scene), ``occluding_segments`` (summed over the tests),
        ``coarse_pixels_refined``, and ``sphere_ids`` (every sphere: they never occlude).
    """
    t0 = time.perf_counter()
    tree, kd_s = scene_kdtree(scene)
    fences, fence_s = scene_fences(scene)
    alo = np.ascontiguousarray(box[0], dtype=np.float64)
    ahi = np.ascontiguousarray(box[1], dtype=np.float64)
    stats: dict[str, Any] = {
        "kdtree_seconds": kd_s, "fence_seconds": fence_s, "traversal_seconds": 0.0,
        "refine_seconds": 0.0, "nodes_visited": 0, "nodes_culled": 0, "leaves_visible": 0,
        "triangle_tests": 0, "triangles_culled": 0, "occluders": len(fences),
        "occluding_segments": 0, "coarse_pixels_refined": 0, "resolution": int(resolution),
        "kd_nodes": tree.n_nodes, "kd_leaves": tree.n_leaves,
    }
    # Walls a client's near plane can cut from inside the cell hide nothing from it.
    near = near_pieces(fences, alo, ahi)
    stats["near_pieces"] = int(near.sum())
    stats["near_plane"] = DEFAULT_NEAR
    if near.any():
        fences = cell_fences(fences, near)
    t1 = time.perf_counter()
    leaves, decided = traverse(tree, fences, alo, ahi, resolution, coarse, stats)
    t2 = time.perf_counter()
    stats["traversal_seconds"] = t2 - t1
    held = tree.item_start[leaves + 1] - tree.item_start[leaves]
    stats["leaf_triangles"] = int(held.sum())
    if triangle_refine == "auto":
        triangle_refine = "all" if held.sum() <= REFINE_ALL_MAX else "marginal"
    stats["triangle_refine"] = triangle_refine
    if triangle_refine == "all":
        fine = np.ones(len(leaves), dtype=bool)
    elif triangle_refine == "marginal":
        fine = decided == 1
    else:
        fine = np.zeros(len(leaves), dtype=bool)
    whole = [tree.leaf_items(int(n)) for n in leaves[~fine]]
    ids = np.unique(np.concatenate(whole)) if whole else np.zeros(0, np.int64)
    if fine.any():
        tested = refine_triangles(tree, fences, leaves[fine], alo, ahi, resolution, coarse,
                                  stats)
        ids = np.union1d(ids, tested)
    stats["refine_seconds"] = time.perf_counter() - t2
    stats["setup_seconds"] = t1 - t0 - kd_s - fence_s
    stats["sphere_ids"] = np.arange(scene.n_spheres, dtype=np.int32)
    return ids, stats


def _test(fences: Fences, alo: np.ndarray, ahi: np.ndarray, blo: np.ndarray, bhi: np.ndarray,
          resolution: int, coarse: int) -> np.ndarray:
    """``nodes_visible`` over the scene's fences, in batches with a checkpoint between."""
    out = np.zeros((len(blo), 3), dtype=np.int64)
    for s in range(0, len(blo), BATCH):
        checkpoint()
        out[s:s + BATCH] = nodes_visible(
            alo, ahi, np.ascontiguousarray(blo[s:s + BATCH]),
            np.ascontiguousarray(bhi[s:s + BATCH]), fences.pieces, fences.grid,
            int(resolution), int(coarse))
    return out


def traverse(tree: KdTree, fences: Fences, alo: np.ndarray, ahi: np.ndarray, resolution: int,
             coarse: int, stats: dict[str, Any]) -> np.ndarray:
    """Visible leaves (int64 node ids) and how each was found visible (``node_visible``: 1 by
    the raster, 2 by a free probe ray, 3 over the cell's footprint): the tree from the root, a
    level at a time (each level's nodes tested in parallel); an occluded node ends its
    recursion."""
    if tree.n_nodes == 0 or len(tree.items) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    frontier = np.array([0], dtype=np.int64)
    leaves: list[np.ndarray] = []
    how: list[np.ndarray] = []
    while len(frontier):
        res = _test(fences, alo, ahi, tree.lo[frontier], tree.hi[frontier], resolution, coarse)
        stats["nodes_visited"] += len(frontier)
        stats["occluding_segments"] += int(res[:, 1].sum())
        stats["coarse_pixels_refined"] += int(res[:, 2].sum())
        seen = res[:, 0] > 0
        vis = frontier[seen]
        stats["nodes_culled"] += int(len(frontier) - len(vis))
        is_leaf = tree.child[vis, 0] < 0
        leaves.append(vis[is_leaf])
        how.append(res[seen, 0][is_leaf])
        inner = vis[~is_leaf]
        frontier = tree.child[inner].reshape(-1)
        frontier = frontier[frontier >= 0]
    out = np.concatenate(leaves)
    decided = np.concatenate(how)
    keep = tree.item_start[out + 1] > tree.item_start[out]
    out, decided = out[keep], decided[keep]
    stats["leaves_visible"] = int(len(out))
    stats["leaves_by_raster"] = int(np.count_nonzero(decided == 1))
    return out, decided


def refine_triangles(tree: KdTree, fences: Fences, leaves: np.ndarray, alo: np.ndarray,
                     ahi: np.ndarray, resolution: int, coarse: int,
                     stats: dict[str, Any]) -> np.ndarray:
    """Triangles of the visible ``leaves`` whose own bounds, clipped to the visible leaves'
    regions, are visible from the cell. A triangle is tested once: over the box of its parts in
    the visible leaves."""
    counts = tree.item_start[leaves + 1] - tree.item_start[leaves]
    leaf_of = np.repeat(leaves, counts)
    group = np.repeat(np.arange(len(leaves), dtype=np.int64), counts)
    tri = np.concatenate([tree.leaf_items(int(n)) for n in leaves])
    blo = tree.tri_lo[tri].copy()
    bhi = tree.tri_hi[tri].copy()
    # Clip to the leaf's box (its region, which holds the triangle's part there).
    for c in (0, 1, 2):
        blo[:, c] = np.maximum(blo[:, c], tree.lo[leaf_of, c])
        bhi[:, c] = np.minimum(bhi[:, c], tree.hi[leaf_of, c])
    bhi = np.maximum(bhi, blo)
    # One box per triangle: the union of its parts in the visible leaves.
    order = np.argsort(tri, kind="stable")
    tri, blo, bhi, group = tri[order], blo[order], bhi[order], group[order]
    first = np.flatnonzero(np.r_[True, tri[1:] != tri[:-1]])
    n_parts = np.diff(np.r_[first, len(tri)])
    ubox_lo = np.minimum.reduceat(blo, first, axis=0)
    ubox_hi = np.maximum.reduceat(bhi, first, axis=0)
    utri = tri[first]
    ugroup = group[first]
    # Each triangle draws its occluders from the list of one of its visible leaves: that
    # leaf's shaft and footprint (``shaft_piece_ids``), gathered once per leaf. For a triangle
    # in that leaf alone and sharing its axis, these are its own shaft's; otherwise a subset
    # (parts in other leaves, mostly the same footprint at other heights, may have occluders
    # the list lacks): conservative either way.
    checkpoint()
    t_lists = time.perf_counter()
    start, ids, ok = leaf_piece_ids(alo, ahi, np.ascontiguousarray(tree.lo[leaves]),
                                    np.ascontiguousarray(tree.hi[leaves]), fences.seg,
                                    fences.top, fences.bot, fences.lean, fences.grid_lo,
                                    fences.grid_step, fences.grid_n, fences.cell_start,
                                    fences.cell_items)
    t_tests = time.perf_counter()
    stats["occluder_list_seconds"] = t_tests - t_lists
    lists = (start, ids, ok)
    # Small groups of neighbouring triangles of one leaf are tested first, on the box of the
    # group: a hidden box hides every triangle in it, which then needs no test of its own.
    order = np.lexsort((ubox_lo[:, 2] + ubox_hi[:, 2], ubox_lo[:, 0] + ubox_hi[:, 0],
                        ubox_lo[:, 1], ugroup))
    new_group = np.r_[True, ugroup[order][1:] != ugroup[order][:-1]]
    rank = np.arange(len(order)) - np.maximum.accumulate(np.where(new_group,
                                                                   np.arange(len(order)), 0))
    first = new_group | (rank % GROUP == 0)
    gstart = np.flatnonzero(first)
    glo = np.minimum.reduceat(ubox_lo[order], gstart, axis=0)
    ghi = np.maximum.reduceat(ubox_hi[order], gstart, axis=0)
    gres = _test_among(fences, alo, ahi, glo, ghi, ugroup[order][gstart], lists, resolution,
                       coarse)
    member_of = np.repeat(np.arange(len(gstart)), np.diff(np.r_[gstart, len(order)]))
    open_ = np.zeros(len(utri), dtype=bool)
    open_[order] = gres[member_of, 0] == 1
    res = np.zeros((len(utri), 3), dtype=np.int64)
    sel = np.flatnonzero(open_)
    res[sel] = _test_among(fences, alo, ahi, ubox_lo[sel], ubox_hi[sel], ugroup[sel], lists,
                           resolution, coarse)
    stats["group_tests"] = int(len(gstart))
    stats["groups_culled"] = int(np.count_nonzero(gres[:, 0] == 0))
    stats["triangle_test_seconds"] = time.perf_counter() - t_tests
    stats["candidate_pieces"] = int(np.sum((start[1:] - start[:-1])[ugroup[sel]]))
    stats["multi_leaf_triangles"] = int(np.count_nonzero(n_parts > 1))
    stats["triangle_tests"] = int(len(sel))
    stats["occluding_segments"] += int(res[:, 1].sum() + gres[:, 1].sum())
    stats["coarse_pixels_refined"] += int(res[:, 2].sum())
    vis = utri[res[:, 0] == 1]
    stats["triangles_culled"] = int(len(utri) - len(vis))
    return vis


def _test_among(fences: Fences, alo: np.ndarray, ahi: np.ndarray, blo: np.ndarray,
                bhi: np.ndarray, group: np.ndarray, lists: tuple[np.ndarray, ...],
                resolution: int, coarse: int) -> np.ndarray:
    """``boxes_visible_among`` in batches with a checkpoint between: (n, 3) int64."""
    start, ids, ok = lists
    out = np.zeros((len(blo), 3), dtype=np.int64)
    for s in range(0, len(blo), BATCH):
        checkpoint()
        out[s:s + BATCH] = boxes_visible_among(
            alo, ahi, np.ascontiguousarray(blo[s:s + BATCH]),
            np.ascontiguousarray(bhi[s:s + BATCH]),
            GroupLists(np.ascontiguousarray(group[s:s + BATCH]), start, ids, ok), fences.pieces,
            fences.grid, int(resolution), int(coarse))
    return out
