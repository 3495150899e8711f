"""The ``cos`` core: the camera offset space PVS (Hladky, Seidel, Steinberger 2019).

Conservative: no false negatives for any eye position in the box and any viewing direction, at
any resolution. The cell is solved from its six side planes (``planes``), each seen through five
cube frusta covering its outer half-space; per view, per-pixel lists of every primitive that can
cover the pixel under some offset and some direction inside the pixel (``lists``) are resolved
front to back in the COS with occluder fusion (``resolve``). What lies in the box itself is added
directly (``prims.inside_box``). Moving triangles and spheres take part as swept boxes that never
occlude (``prims``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, ClassVar

import numba
import numpy as np

from visibility.cancel import checkpoint, stop_flag
from visibility.cores.base import Core, CoreParams, Cost, param, register
from visibility.cores.cos.cull import Tree, cell_tree, view_planes, views_positions
from visibility.cores.cos.fusion import scene_welded_ids
from visibility.cores.cos.groups import Marks, PrimArrays, Screen, TileLists
from visibility.cores.cos.lists import TILE, bin_tiles, fill_lists, footprints
from visibility.cores.cos.planes import View, side_plane_views
from visibility.cores.cos.prims import (
    TRIANGLE,
    Prims,
    build_prims,
    distance_order,
    face_reach,
    inside_box,
    prim_bounds,
    run_boxes,
    solid_mask,
)
from visibility.cores.cos.resolve import (
    CYCLE_PART0,
    CYCLE_PARTS,
    FRONT_PARTS,
    N_COUNTERS,
    REFINE_LEVELS,
    TIME_STRIDE,
    WALK0,
    resolve_tiles,
)
from visibility.raster.camera import DEFAULT_NEAR
from visibility.raster.hierarchy import (
    MIN_TRIANGLES,
    ready_hierarchy,
    scene_hierarchy,
)
from visibility.scene import Scene
from visibility.scene_cache import Build
from visibility.tjunctions import scene_t_split
from visibility.topology import CLOSED_BUILD, NEAR_CLEARANCE, unseen_back_faces
from visibility.viewcells import Viewcell

#: Default pixels across a 90 degree frustum.
DEFAULT_RESOLUTION = 128


#: Items (primitives whose footprint meets it) from which a tile is busy (``CosParams``):
#: clutter; 100k city and village cells at 0.3 m have no such tile.
BUSY_MIN_ITEMS = 8192
#: Pixels listing at least this many entries test leaf boxes (``CosParams.leaf_list``):
#: only clutter's lists are that long. In shorter ones a box spares few entries, and the
#: entries it spares no longer close their neighbours' silhouettes, so the answer grows
#: (docs/cores/cos.md).
LEAF_LIST = 2048
#: Triangles of a leaf for that test: a run of consecutive ids (``_leaf_boxes``).
LEAF_SIZE = 16
#: The coarse pass (``CosParams.coarse_items``): off by default, since busy tiles' samples
#: resolved down to single pixels cost less without it (benchmarks/results/cos.md).
COARSE_ITEMS = 0
#: Pixels per side of the samples in busy tiles (``CosParams``), where their lists may reach
#: ``BUSY_BLOCK_MIN`` entries per pixel on average (the tile's ``bin_tiles`` bound): below
#: that (the 4 m city cell's busy tiles) 2 x 2 samples without sub-samples loosened the answer
#: and gained no time (docs/cores/cos.md).
BUSY_BLOCK = 4
BUSY_BLOCK_MIN = 1024
#: The values it may take: divisors of ``lists.TILE``.
BUSY_BLOCKS = (1, 2, 4, 8)
#: Levels of 2 x 2 sub-pixels an occludee no group hides over a whole pixel is tested at
#: (``CosParams.refine``), by default and at most (``resolve.REFINE_STACK`` holds the walk).
REFINE = 0
REFINE_MAX = REFINE_LEVELS

#: The cover tests (``CosParams.cover``).
COVERS = ("strict", "relaxed")
#: How occluders join to hide (``CosParams.fusion``).
FUSIONS = ("edges", "groups")


@dataclass
class CosParams(CoreParams):
    """Parameters of the COS core.

    resolution : pixels across each 90 degree frustum of a side plane (side frusta have half the
        rows); the PVS stays conservative at any value, higher costs more and overestimates less.
    list_budget_mb : most memory (MiB) the per-pixel lists of one view may take at once; a view
        whose lists are longer is resolved in runs of screen tiles.
    busy_items : a screen tile of ``lists.TILE`` x ``TILE`` pixels whose footprints list at
        least this many primitives (at the default resolution and above; scaled by the
        tile's solid angle below it) is busy: clutter; 0: none is.
    busy_block : busy tiles whose lists may reach ``BUSY_BLOCK_MIN`` entries per pixel are
        resolved with one sample per ``busy_block`` x ``busy_block`` pixels (at their
        centre, covering all their directions, so still conservative) where the others
        sample every pixel: in clutter their lists are long and mostly the same from pixel
        to pixel. An entry a sample's test leaves unhidden is tested again at its 2 x 2
        sub-samples, down to single pixels (``refine``'s walk, ``log2(busy_block)`` levels
        before ``refine``'s own, ``REFINE_MAX`` levels in all at most). 1 samples every pixel
        there too.
    coarse_items : the coarse pass (``cos_pvs``): each busy tile whose footprints list at
        least this many primitives (scaled as ``busy_items``) is first resolved as one pixel
        of the tile's width, and what that finds hidden for the whole tile is left out of
        the tile's per-pixel lists; 0 (the default) turns it off.
    subcells : the cell is solved as ``subcells`` x ``subcells`` boxes splitting its x and z
        sides (its height, the eye range, stays whole), and the PVS is their union
        (``cos_subcells``): still conservative, tighter where the offsets of the whole cell
        leave no single occluder covering what the sub-cells' do.
    cover : the cover test an occludee must pass behind an occluder group. ``strict`` (the
        paper's): no silhouette edge of the group comes near the occludee's whole offset
        region K. ``relaxed``: where the strict test hides it behind no group, edges that
        meet K may still pass when they provably never cross the offsets whose rays meet the
        occludee (``resolve._covers_q``); still conservative, tighter at large cells, dearer
        (``docs/cores/cos.md``).
    fusion : how occluders join to hide an occludee. ``edges`` (the paper's): only triangles
        sharing edges, so one group must cover its whole offset region. ``groups``: where no
        group does alone, separate groups each in front of it may cover the region together
        (``resolve._fused_hide``: two walls one behind the other, buildings side by side),
        and with ``refine`` at each sub-pixel too (``resolve._fused_sub``); the scene is
        solved with its T-junctions cut (``visibility.tjunctions``), so that surfaces
        meeting along a seam with no vertex pair in common fuse; still conservative,
        tighter at large cells, dearer (``docs/cores/cos.md``).
    refine : where no occluder group hides an occludee over a whole pixel, it is tested
        again at the pixel's 2 x 2 sub-pixels, each split again where none hides it, down to
        ``refine`` levels (``resolve._refined_hide``): hidden when hidden at each. A far
        occludee next to a near silhouette fails a pixel's test by the pixel's width times
        their depth difference; a sub-pixel's test is that much finer. Conservative at any
        level; 0 (none) is the paper's.
    """

    resolution: int = param(DEFAULT_RESOLUTION, unit="px", ge=8, le=4096,
                            help="pixels across each 90 degree frustum of a side plane")
    list_budget_mb: int = param(256, unit="MiB", ge=1, le=1 << 16,
                                help="most memory the per-pixel lists of one view take at once")
    busy_items: int = param(BUSY_MIN_ITEMS, unit="primitives", ge=0, le=1 << 30,
                            help="screen tiles meeting this many primitives are busy, "
                                 "sampled per busy_block pixels (0: none)")
    busy_block: int = param(BUSY_BLOCK, unit="px", choices=BUSY_BLOCKS,
                            help="pixels per side of one sample in busy tiles, tested again "
                                 "down to single pixels where it sees an entry (1: every "
                                 "pixel)")
    coarse_items: int = param(COARSE_ITEMS, unit="primitives", ge=0, le=1 << 30,
                              help="busy tiles meeting this many primitives are resolved as "
                                   "one pixel first, and what that hides leaves their "
                                   "per-pixel lists (0: never, the default)")
    subcells: int = param(1, unit="per side", ge=1, le=16,
                          help="solve the cell as n x n sub-cells across the ground (x, z) "
                               "and join their answers: tighter at large cells, for up to n² "
                               "the time")
    cover: str = param("strict", choices=COVERS,
                       help="the occluder cover test: strict (the paper's) or relaxed "
                            "(tighter at large cells, for more time)")
    refine: int = param(REFINE, unit="levels", ge=0, le=REFINE_MAX,
                        help="levels of 2 x 2 sub-pixels an occludee no occluder hides over "
                             "a whole pixel is tested at (0: none): tighter where far "
                             "occludees pass near silhouettes, for more time")
    fusion: str = param("edges", choices=FUSIONS,
                        help="occluders that hide together: edges (the paper's: triangles "
                             "sharing edges) or groups (separate surfaces too, at sub-pixels "
                             "with refine, and seams at T-junctions cut: tighter at large "
                             "cells, for more time)")
    leaf_list: int = param(LEAF_LIST, unit="entries", ge=0, le=1 << 30,
                           help="at pixels listing at least this many entries, once an "
                                "occludee is hidden, the box of its leaf (16 consecutive "
                                "triangle ids) is tested against what hid it, and the leaf's "
                                "other triangles skip the pixel where it is hidden (faster in "
                                "clutter, a few more triangles; 0: never)")


#: Cost model (``estimate_cost``): per pixel of the views, per triangle and side plane: a
#: least-squares fit of the time per pixel over 4 m cells of a 20k village and a 100k city at
#: 64, 128 and 256 px (the per-triangle term fits near zero there), the per-triangle term
#: bounded by a 0.3 m cell of the 100k city at 64 px (mostly the per-triangle sort and
#: footprints). ``python -m benchmarks.bench_admission`` (benchmarks/results/admission.md)
#: checks it on 4 m cells; 0.3 m cells cost less than this says (benchmarks/results/cos.md).
#: List lengths, and so the resolution's true cost, depend on the
#: depth complexity around the cell, which no cheap estimate sees: dense clutter costs far
#: more (the 1M kitchen, 20k rooms at 4 m: benchmarks/results/cos.md), and the deadline
#: stops what the estimate lets through. Bytes: per triangle (the primitives, their order,
#: box distance, bounds, face subsets, footprints and tile bins, at the peak), per
#: pixel (list starts and counts of a run), and the lists themselves up to ``list_budget_mb``
#: (a cap, so the estimate is an upper bound; the benchmark measures how loose).
#: Not counted: each thread's working set for its current tile, which grows with the longest
#: list there (``resolve._share_scratch``).
SECONDS_PER_PIXEL = 2e-6
SECONDS_PER_PLANE_TRIANGLE = 1e-7
BYTES_PER_TRIANGLE = 320
BYTES_PER_PIXEL = 24


@register
class CosCore(Core):
    """Camera offset space PVS from the six side planes of the cell (conservative)."""

    name: ClassVar[str] = "cos"
    description: ClassVar[str] = (
        "Camera offset space (Hladky et al. 2019): per-pixel COS visibility with occluder "
        "fusion from the cell's six side planes, 180 degrees each (conservative: any eye in "
        "the box, any direction)")
    Params: ClassVar[type[CoreParams]] = CosParams
    promise: ClassVar[str] = "conservative"
    knob: ClassVar[str] = "resolution"
    knob_levels: ClassVar[tuple[int, ...]] = (64, 128, 256)
    # Busy tiles and the coarse pass: only clutter reaches them at the default thresholds.
    warm_params: ClassVar[tuple[dict[str, Any], ...]] = (
        {"busy_items": 1, "coarse_items": 1, "leaf_list": 1},)
    native_segments: ClassVar[bool] = False
    # Orders of magnitude only: the measured times live in benchmarks/results/cos.md.
    fits: ClassVar[str] = ("small cells (up to about 1 m) of scenes up to a few 100k triangles "
                           "(a 0.3 m cell of a 100k city in 0.1-0.3 s); 4 m cells under a second "
                           "(a city) to several seconds (interiors), a 0.3 m cell of clutter "
                           "(a 1M-triangle kitchen) about ten seconds: docs/cores/cos.md")
    check_params: ClassVar[dict[str, Any]] = {}
    fn_bound: ClassVar[float] = 0.0
    #: The worst FP ``checks.check_fn_fp_against_sampled_ground_truth`` measures on the
    #: designed scenes (tests/visibility/cores/designed_scenes.py) at 64, 128 and 256 px,
    #: rounded up (its failure message prints the rate): on two rooms and a door, the hidden
    #: faces of the dividing-wall slabs and the box, flush against floor, ceiling and walls,
    #: whose edges lie on the occluders' silhouettes; on the stiff cases the 1e6-aspect sliver
    #: pair the reference cannot sample and the closed room's hidden faces.
    fp_bound: ClassVar[float] = 0.5

    def scene_builds(self, scene: Scene) -> list[Build]:
        """The closed parts (``topology.CLOSED_BUILD``) whose back faces it leaves out."""
        return [CLOSED_BUILD]

    def suitability(self, scene: Scene, cell_size: float | None) -> tuple[float, str]:
        # benchmarks/results/cos.md (2 cores): small cells of moderate scenes cost a fraction
        # of a second and are worth picking automatically; 4 m cells of interiors and dense
        # clutter cost seconds to minutes, so only on request.
        small = cell_size is not None and cell_size <= 0.5
        if small and scene.n_triangles <= 200_000:
            return 5.0, ("small cells: conservative camera-offset-space visibility, no false "
                         "negatives")
        return 0.1, ("conservative but slow here: cells above 0.5 m or scenes above 200k "
                     "triangles cost seconds (4 m cells) to minutes (dense clutter)")

    def estimate_cost(self, scene: Scene, cell: Viewcell, params: CoreParams) -> Cost:
        """Six side planes of five frusta each, priced per pixel and per triangle and plane;
        memory bounded by ``list_budget_mb`` plus the per-triangle and per-pixel arrays."""
        assert isinstance(params, CosParams)
        r = int(params.resolution)
        # Five frusta per plane: the front one whole, the four side ones with half the rows.
        pixels_per_plane = r * r + 4 * r * (r // 2)
        m = scene.n_triangles + scene.n_spheres
        seconds = (6 * pixels_per_plane * SECONDS_PER_PIXEL + 6 * m * SECONDS_PER_PLANE_TRIANGLE
                   ) * int(params.subcells) ** 2
        peak = (m * BYTES_PER_TRIANGLE + pixels_per_plane * BYTES_PER_PIXEL
                + int(params.list_budget_mb) * (1 << 20))
        return Cost(seconds, int(peak), {"views": 30 * int(params.subcells) ** 2,
                                         "pixels": 6 * pixels_per_plane,
                                         "triangles": scene.n_triangles})

    def _compute(
        self, scene: Scene, cell: Viewcell, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, CosParams)
        box = np.asarray(cell.box, dtype=np.float64)
        if int(params.subcells) > 1:
            return cos_subcells(scene, box, int(params.subcells), int(params.resolution),
                                float(params.list_budget_mb), int(params.coarse_items),
                                cover=str(params.cover), fusion=str(params.fusion),
                                busy_block=int(params.busy_block), refine=int(params.refine),
                                busy_items=int(params.busy_items),
                                leaf_list=int(params.leaf_list))
        return cos_pvs(scene, box, int(params.resolution), float(params.list_budget_mb),
                       int(params.coarse_items), cover=str(params.cover),
                       fusion=str(params.fusion), busy_block=int(params.busy_block),
                       refine=int(params.refine), busy_items=int(params.busy_items),
                       leaf_list=int(params.leaf_list))


def sub_boxes(box: np.ndarray, n: int) -> np.ndarray:
    """(n², 2, 3) the boxes splitting ``box`` (2, 3) [min, max] into n x n equal parts along
    x and z (y, the eye range, whole), row by row, so consecutive ones are neighbours."""
    xs = np.linspace(box[0, 0], box[1, 0], n + 1)
    zs = np.linspace(box[0, 2], box[1, 2], n + 1)
    out = np.repeat(np.asarray(box, dtype=np.float64)[None], n * n, axis=0)
    for i in range(n):
        for k in range(n):
            # Snake order: each box shares a side with the one before.
            kk = k if i % 2 == 0 else n - 1 - k
            b = out[i * n + k]
            b[0, 0], b[1, 0] = xs[i], xs[i + 1]
            b[0, 2], b[1, 2] = zs[kk], zs[kk + 1]
    return out


def cos_subcells(scene: Scene, box: np.ndarray, n: int, resolution: int,
                 list_budget_mb: float = 256.0, coarse_items: int = COARSE_ITEMS,
                 cover: str = "strict", fusion: str = "edges", busy_block: int = BUSY_BLOCK,
                 refine: int = REFINE, busy_items: int = BUSY_MIN_ITEMS,
                 leaf_list: int = LEAF_LIST) -> tuple[np.ndarray, dict[str, Any]]:
    """PVS of a box cell as the union of ``cos_pvs`` over its n x n sub-cells (``sub_boxes``):
    each is conservative for its eyes, so the union is for the cell's. What one sub-cell finds
    visible is passed on as known to the next (``cos_pvs``'s ``known``: in the answer already,
    tested no more, still an occluder), which changes the time, not the answer. Stats: each
    count and time summed over the sub-cells (``longest_list``: the longest), ``subcells``
    n, ``union_sizes`` the answer's size after each sub-cell."""
    m = scene.n_triangles
    known = np.zeros(m + scene.n_spheres, dtype=bool)
    total: dict[str, Any] = {}
    sizes = []
    for b in sub_boxes(box, n):
        ids, st = cos_pvs(scene, b, resolution, list_budget_mb, coarse_items, known=known,
                          cover=cover, fusion=fusion, busy_block=busy_block, refine=refine,
                          busy_items=busy_items, leaf_list=leaf_list)
        known[ids] = True
        known[m + st["sphere_ids"].astype(np.int64)] = True
        sizes.append(int(known.sum()))
        for k, v in st.items():
            if k == "longest_list":
                total[k] = max(total.get(k, 0), v)
            elif k == "costliest_view":
                if v["seconds"] > total.get(k, {"seconds": -1.0})["seconds"]:
                    total[k] = v
            elif isinstance(v, (int, float)) and not isinstance(v, bool) and k not in (
                    "resolution", "near_plane", "near_clearance", "tjunction_cut"):
                total[k] = total.get(k, 0) + v
            else:
                total[k] = v
    ids = np.flatnonzero(known[:m]).astype(np.int64)
    total["sphere_ids"] = np.flatnonzero(known[m:]).astype(np.int32)
    total["subcells"] = int(n)
    total["union_sizes"] = sizes
    return ids, total


def cos_pvs(scene: Scene, box: np.ndarray, resolution: int,
            list_budget_mb: float = 256.0,
            coarse_items: int = COARSE_ITEMS, known: np.ndarray | None = None,
            cover: str = "strict", fusion: str = "edges", busy_block: int = BUSY_BLOCK,
            refine: int = REFINE, busy_items: int = BUSY_MIN_ITEMS, leaf_list: int = LEAF_LIST
            ) -> tuple[np.ndarray, dict[str, Any]]:
    """PVS of a box cell (``_cos_pvs``, whose docstring has the parameters and stats). With
    ``fusion="groups"`` the scene is solved with its T-junctions cut
    (``visibility.tjunctions``, once per scene), so that surfaces meeting along a seam fuse,
    and the answer is given in the scene's own triangle ids; ``stats`` adds
    ``tjunction_cut`` (triangles cut) and ``tjunction_seconds`` (cutting them, 0 once
    cached)."""
    if fusion != "groups":
        return _cos_pvs(scene, box, resolution, list_budget_mb, coarse_items, known, cover,
                        fusion, busy_block, refine, busy_items, leaf_list)
    split, split_s = scene_t_split(scene)
    if split.source is None:
        ids, stats = _cos_pvs(scene, box, resolution, list_budget_mb, coarse_items, known,
                              cover, fusion, busy_block, refine, busy_items, leaf_list)
    else:
        if known is not None:
            known = np.asarray(known, dtype=bool)
            m = scene.n_triangles
            known = np.concatenate([known[:m][split.source], known[m:]])
        ids, stats = _cos_pvs(split.scene, box, resolution, list_budget_mb, coarse_items,
                              known, cover, fusion, busy_block, refine, busy_items, leaf_list)
        ids = np.unique(split.source[ids])
    stats["tjunction_cut"] = split.cut
    stats["tjunction_seconds"] = split_s
    return ids, stats


def _cos_pvs(scene: Scene, box: np.ndarray, resolution: int,
             list_budget_mb: float = 256.0,
             coarse_items: int = COARSE_ITEMS, known: np.ndarray | None = None,
             cover: str = "strict", fusion: str = "edges", busy_block: int = BUSY_BLOCK,
             refine: int = REFINE, busy_items: int = BUSY_MIN_ITEMS, leaf_list: int = LEAF_LIST
             ) -> tuple[np.ndarray, dict[str, Any]]:
    """PVS of a box cell, solved on ``scene`` as it is.

    Parameters
    ----------
    scene : the scene (static or keyframed; spheres are reported in ``stats["sphere_ids"]``).
    box : (2, 3) float64 [min, max], metres.
    resolution : pixels across a 90 degree frustum.
    list_budget_mb : list memory per run of tiles, MiB.
    coarse_items : busy screen tiles whose footprints list at least this many primitives are
        resolved as one pixel first (``_coarse_pass``), and what that hides for the whole tile
        leaves the tile's per-pixel lists; 0: never.
    known : optional (n_triangles + n_spheres,) bool, ids already in the answer (another
        cell's PVS, ``cos_subcells``): reported, tested no more, still occluders.
    cover : ``strict`` or ``relaxed``, the occluder cover test (``CosParams.cover``).
    fusion : ``edges`` or ``groups``, how occluders join (``CosParams.fusion``).
    busy_block : pixels per side of a sample in busy tiles (``CosParams.busy_block``).
    refine : levels of 2 x 2 sub-pixels an occludee is tested at where no group hides it
        over the whole pixel (``CosParams.refine``).
    busy_items : screen tiles whose footprints list at least this many primitives are busy
        (``CosParams.busy_items``); 0: none.
    leaf_list : pixels listing at least this many entries test a hidden occludee's leaf box
        (``CosParams.leaf_list``, ``resolve._leaf_hidden``, ``_leaf_boxes``); 0: none.

    Returns
    -------
    triangle_ids : (k,) int64 visible triangle ids.
    stats : seconds per phase (``weld_seconds``, ``topology_seconds`` (closed surfaces: built
        once per scene, then the per-cell test), ``sort_seconds``, ``list_seconds`` (of
        which ``footprint_seconds``, ``bin_seconds`` and ``fill_seconds``: each primitive's
        pixel box per view (the hierarchy walk, ``walk_seconds``, included), binning the
        boxes into tiles, filling the per-pixel lists),
        ``resolve_seconds``), ``list_entries``, ``tile_items`` (the (primitive, screen
        tile) pairs the lists are filled from: ``list_entries / tile_items`` is how many
        pixels of a tile list an item on average, what state shared across a tile's pixels
        could save), ``longest_list``, ``tested``, ``occluded``,
        ``occluder_triangles``, ``early_z_cut`` (list entries skipped behind a coverall
        occluder's depth), ``fill_cut`` (pixels of primitives' boxes left out of the lists
        while they are filled, behind a triangle that alone holds the pixel's offsets),
        ``silhouette_edges`` and ``plane_tests`` (the resolution's work: occluder
        silhouette edges walked by the cover tests, occluder triangles put through the
        depth test), ``cycles_resolve`` (CPU cycles in the resolution's tiles, all threads)
        and estimates (one entry in ``TIME_STRIDE`` timed) of the parts of it spent testing
        entries (``cycles_test``: K, the cover and depth
        tests), turning entries into occluders (``cycles_insert``: set-up, fusion along
        shared edges, merges) and checking whether a group now covers the pixel
        (``cycles_coverall``); the rest is each entry's projection and early z. The
        test's and the insertion's parts (``resolve.CYCLE_PARTS``): ``cycles_test_region``
        (K), ``cycles_test_groups`` (cover and depth tests against single groups),
        ``cycles_test_subpixels`` (separate groups together, sub-pixels and the busy
        tiles' sub-samples),
        ``cycles_test_leaf`` (leaf boxes), ``cycles_insert_setup``,
        ``cycles_insert_slots`` (edge slots, at an item's first insertion in a tile) and
        ``cycles_insert_fusion`` (fusion along shared edges, merges);
        ``unseen_back_faces`` (triangles of closed surfaces that face away
        from the whole cell, left out before the lists), ``inside_box``, ``views``,
        ``pixels``, ``sphere_ids``, ``coarse_seconds``, ``coarse_entries`` and
        ``coarse_dropped`` (the coarse pass's list entries and those it left out of the
        per-pixel lists), ``coarse_tested``, ``coarse_silhouette_edges``,
        ``coarse_plane_tests`` and ``coarse_cycles_*`` (its work, counted as the pixels'
        ``tested``, ``silhouette_edges``, ``plane_tests`` and ``cycles_*`` are),
        ``block_tiles`` (tiles sampled per ``busy_block`` pixels) and ``block_cycles``,
        ``block_tested`` (the resolution's CPU cycles and entries tested in them: where
        clutter's time goes), ``leaf_seconds`` (the
        leaf boxes, part of the set-up), ``leaf_tests``, ``leaf_hidden`` and
        ``leaf_skipped`` (leaf boxes tested, found hidden, and the list entries that skipped
        a pixel for it: ``leaf_list``) and
        ``costliest_view`` (the side plane and frustum that
        took longest, its seconds, list entries and longest list), ``tree`` (whether the
        scene's hierarchy was there to cull with), ``tree_seconds`` (where the cell's
        primitives sit in it; a small scene's hierarchy is built then, once), ``projected``
        and ``culled`` (footprints projected over the 30 views, and those the hierarchy walk
        spared: primitives no ray of the view meets), ``fusion`` (the one used) and
        ``fused`` (entries hidden by separate groups together, ``fusion="groups"``),
        ``front_parts`` (entries hidden by the part of a group in front of them, where the
        whole group failed the depth test: ``fusion="groups"``),
        ``refined`` and ``subpixels`` (entries hidden at sub-pixels, and sub-pixels
        resolved: ``refine``, and the busy tiles' sub-samples), ``walks_seen`` and
        ``subpixels_seen`` (the entries whose sub-pixel walk ended with them seen, and the
        sub-pixels those walks resolved: at least one a level; the other walks are the
        ``refined`` entries).
    """
    if cover not in COVERS:
        raise ValueError(f"cover must be one of {COVERS}, not {cover!r}")
    if fusion not in FUSIONS:
        raise ValueError(f"fusion must be one of {FUSIONS}, not {fusion!r}")
    if not 0 <= int(refine) <= REFINE_MAX:
        raise ValueError(f"refine must be 0 to {REFINE_MAX}, not {refine!r}")
    fuse = fusion == "groups"
    t0 = time.perf_counter()
    lo, hi = box[0], box[1]
    centre = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    welded, weld_s = scene_welded_ids(scene)
    t1 = time.perf_counter()
    # Back faces of closed surfaces that face away from the whole cell are never seen from it:
    # they leave the lists (in dense clutter about a quarter of the triangles, the ones every
    # pixel had to prove hidden) and can hide nothing their surface's front does not.
    unseen = unseen_back_faces(scene, box)
    t1b = time.perf_counter()
    prims = build_prims(scene, centre, welded, unseen)
    bounds = prim_bounds(prims)
    order, gap = distance_order(prims, half, bounds)
    t2 = time.perf_counter()
    # The scene's hierarchy culls each view's primitives before their footprints are projected
    # (``cull``). Like every culling path it is never waited for: a large scene's is built in
    # the background (as a server does when the scene loads), and until it is there every
    # primitive is projected, for the same answer; a small scene's costs milliseconds.
    hier = ready_hierarchy(scene)
    if hier is None and scene.n_triangles < MIN_TRIANGLES:
        hier = scene_hierarchy(scene)
    tree = None if hier is None else cell_tree(hier, prims, order, scene.n_triangles, centre)
    t2b = time.perf_counter()
    inbox = inside_box(prims, half, bounds)
    solid = solid_mask(prims, half)
    vis = inbox.astype(np.uint8)
    if known is not None:
        vis[np.asarray(known, dtype=bool)[prims.out_id]] = 1
    views = side_plane_views(box, resolution)
    plane_tol = prims.plane_tol
    stats: dict[str, Any] = {
        "weld_seconds": weld_s, "topology_seconds": t1b - t1, "sort_seconds": t2 - t1b,
        "tree_seconds": t2b - t2, "culled": 0, "projected": 0, "tree": tree is not None,
        "list_seconds": 0.0, "footprint_seconds": 0.0, "walk_seconds": 0.0,
        "bin_seconds": 0.0, "fill_seconds": 0.0,
        "resolve_seconds": 0.0, "list_entries": 0, "longest_list": 0, "tested": 0,
        "occluded": 0, "occluder_triangles": 0, "inside_box": int(inbox.sum()),
        "views": len(views), "pixels": int(sum(v.n_pixels for v in views)),
        "resolution": int(resolution), "list_runs": 0, "early_z_cut": 0,
        "silhouette_edges": 0, "plane_tests": 0, "fill_cut": 0, "fused": 0, "front_parts": 0,
        "refined": 0, "subpixels": 0, "walks_seen": 0, "subpixels_seen": 0,
        "leaf_skipped": 0, "leaf_tests": 0, "leaf_hidden": 0,
        "fusion": "groups" if fuse else "edges",
        "cycles_test": 0, "cycles_insert": 0, "cycles_coverall": 0, "cycles_resolve": 0,
        "coarse_seconds": 0.0, "coarse_entries": 0, "coarse_dropped": 0, "coarse_tiles": 0,
        "coarse_tested": 0, "coarse_silhouette_edges": 0, "coarse_plane_tests": 0,
        "coarse_cycles_test": 0, "coarse_cycles_insert": 0, "coarse_cycles_coverall": 0,
        "coarse_cycles_resolve": 0,
        **{f"{pre}cycles_{name}": 0 for pre in ("", "coarse_") for name in CYCLE_PARTS},
        "block_tiles": 0, "block_cycles": 0, "block_tested": 0,
        "tile_items": 0,
        "unseen_back_faces": int(unseen.sum()),
        "near_plane": DEFAULT_NEAR, "near_clearance": NEAR_CLEARANCE,
        "near_triangles": int(np.count_nonzero((solid == 0) & (prims.kind == TRIANGLE))),
    }
    budget = max(1, int(float(list_budget_mb) * (1 << 20) / 4))
    leaves = _Leaves(prims)
    stats["leaf_seconds"] = 0.0
    if len(prims):
        sel = _face_subsets(bounds, order, half, views, plane_tol)
        # Pixel boxes by position; each view writes (and reads) only the rows it projects.
        rng = np.empty((len(order), 4), dtype=np.int32)
        positions = None if tree is None else _view_positions(tree, sel, views, plane_tol, stats)
        if positions is None:
            per_face = {face: int(np.count_nonzero(s)) for face, s in sel.items()}
            counts = [per_face[v.face] for v in views]
        else:
            counts = [len(p) for p in positions]
        worst = -1.0
        for k in view_order(counts):
            view = views[k]
            tv, entries0 = time.perf_counter(), stats["list_entries"]
            # int32 either way: one kernel specialization, whether the hierarchy was ready.
            listed = (np.flatnonzero(sel[view.face]).astype(np.int32) if positions is None
                      else positions[k])
            longest = _solve_view(prims, solid, order, listed, gap, view, plane_tol, vis, budget,
                                  stats, coarse_items, rng, cover, fuse, busy_block,
                                  refine, busy_items, leaves, leaf_list)
            seconds = time.perf_counter() - tv
            if seconds > worst:
                # Dense clutter is rarely spread evenly: say which view the time went to.
                worst = seconds
                axis, sgn = view.face
                stats["costliest_view"] = {
                    "plane": f"{'+' if sgn > 0 else '-'}{'xyz'[axis]}", "frustum": view.kind,
                    "seconds": seconds, "list_entries": stats["list_entries"] - entries0,
                    "longest_list": longest}
    m = scene.n_triangles
    ids = prims.out_id[vis != 0]
    stats["sphere_ids"] = (ids[ids >= m] - m).astype(np.int32)
    stats["setup_seconds"] = time.perf_counter() - t0 - stats["list_seconds"] \
        - stats["resolve_seconds"] - stats["sort_seconds"] - stats["weld_seconds"] \
        - stats["topology_seconds"] - stats["coarse_seconds"] - stats["tree_seconds"]
    return ids[ids < m], stats


def view_order(listed: list[int]) -> list[int]:
    """Indices of the views in the order they are solved: fewest listed positions first
    (``listed``: per view), ties in the given order. Dense clutter in one direction fills the
    lists of every view that looks that way (the front frustum of one side plane and the
    half frusta of four others); solved last, the costliest of them finds more of its
    triangles already known visible from the others, and known ones are not tested again."""
    return sorted(range(len(listed)), key=lambda k: listed[k])


def _face_subsets(bounds: np.ndarray, order: np.ndarray, half: np.ndarray, views: list[View],
                  plane_tol: float) -> dict[tuple[int, int], np.ndarray]:
    """Per side plane F, (n,) bool over the positions t (into ``order``), True for the
    primitives its views can list: those reaching beyond F's plane (a front frustum skips what
    lies wholly behind it), or, for a side frustum, into its near box, which reaches
    ``-near_box[2]`` behind the plane (what stays further behind projects to rows below the
    view)."""
    faces = sorted({v.face for v in views})
    assert len(faces) <= 8, "face_reach keeps a byte of bits per primitive"
    axes = np.array([axis for axis, _ in faces], dtype=np.int64)
    upper = np.array([sgn > 0 for _, sgn in faces], dtype=np.bool_)
    thresholds = np.empty(len(faces))
    for f, (axis, sgn) in enumerate(faces):
        margin = max(0.0 if v.kind == "front" else float(-v.near_box[2])
                     for v in views if v.face == (axis, sgn))
        reach = float(half[axis]) - margin - plane_tol
        thresholds[f] = reach if sgn > 0 else -reach
    out = np.empty((len(faces), len(order)), dtype=np.bool_)
    if len(order):
        face_reach(bounds, order, axes, upper, thresholds, out)
    return {face: out[f] for f, face in enumerate(faces)}


def _view_positions(tree: Tree, keep: dict[tuple[int, int], np.ndarray], views: list[View],
                    plane_tol: float, stats: dict[str, Any]) -> list[np.ndarray]:
    """Per view, the positions t (increasing, int32) that its side plane can list (``keep``,
    ``_face_subsets``) and that the ``tree`` walk finds among its rays. One parallel walk for
    all the views: a walk per view, in turn, ran on one thread."""
    t0 = time.perf_counter()
    faces = sorted(keep)
    keep_all = np.stack([keep[f] for f in faces])
    keep_of = np.array([faces.index(v.face) for v in views], dtype=np.int64)
    planes = np.stack([view_planes(v.corners, float(v.x_lo), float(v.y_lo), int(v.nx), int(v.ny),
                                   float(v.pw), 4.0 * plane_tol) for v in views])
    off = np.zeros(len(views) + 1, dtype=np.int64)
    np.cumsum(np.count_nonzero(keep_all, axis=1)[keep_of], out=off[1:])
    out = np.empty(int(off[-1]), dtype=np.int32)
    counts = np.zeros(len(views), dtype=np.int64)
    views_positions(tree, keep_all, keep_of, np.stack([v.origin for v in views]),
                    np.stack([v.perm for v in views]), np.stack([v.sign for v in views]),
                    planes, off, out, counts)
    stats["culled"] += int(off[-1] - counts.sum())
    seconds = time.perf_counter() - t0
    stats["walk_seconds"] += seconds
    stats["footprint_seconds"] += seconds
    stats["list_seconds"] += seconds
    return [out[off[v]:off[v] + counts[v]] for v in range(len(views))]


def _tile_work(pcount: np.ndarray, n_tiles: int) -> np.ndarray:
    """Resolution cost estimate per tile: the sum of its squared list lengths (dense clutter
    makes it about quadratic in list length)."""
    return (pcount.reshape(n_tiles, -1).astype(np.float64) ** 2).sum(axis=1)


def _balanced_order(work: np.ndarray, t0: int, t1: int) -> np.ndarray:
    """Tiles [t0, t1) ordered so that the threads' contiguous shares of a parallel loop (its
    static schedule) get a like mix of the costs ``work`` (t1 - t0,), which vary by orders of
    magnitude in dense clutter: ranked costliest first, dealt round-robin to the shares."""
    ranked = np.argsort(-work, kind="stable")
    k = max(1, min(numba.get_num_threads(), t1 - t0))
    return (t0 + np.concatenate([ranked[b::k] for b in range(k)])).astype(np.int64)


def _leaf_boxes(prims: Prims) -> tuple[np.ndarray, np.ndarray]:
    """Leaves of the cell's triangles for the leaf-box test (``resolve._leaf_hidden``): runs
    of ``LEAF_SIZE`` consecutive ids of the scene's face array (a mesh's triangles come in
    order, so a run is a patch of it), the same whatever else is built for the scene, so the
    answer never depends on what is ready. Per primitive (n,) int64 its leaf (-1: a hull),
    and (8 L, 3) float64 each leaf's box corners: the box of its triangles that are
    primitives here, in their frame (cell-centred metres). Linear in the primitives."""
    n = len(prims)
    lf = np.full(n, -1, dtype=np.int64)
    m = int(np.count_nonzero(prims.kind == TRIANGLE))
    if m == 0:
        return lf, np.zeros((0, 3))
    # The triangles come first, in ascending id order (``prims.build_prims``).
    run = prims.out_id[:m] // LEAF_SIZE
    starts = np.flatnonzero(np.concatenate(([True], run[1:] != run[:-1])))
    corners = np.empty((8 * len(starts), 3))
    run_boxes(prims.pts, starts, m, lf, corners)
    return lf, corners


class _Leaves:
    """The cell's leaf boxes (``_leaf_boxes``), built at their first use (``_solve_view``:
    the first run of tiles with a pixel list of ``leaf_list`` entries or more, where the
    kernel tests them), so that open scenes, whose lists stay shorter, never pay for them."""

    def __init__(self, prims: Prims) -> None:
        self.prims = prims
        self.built: tuple[np.ndarray, np.ndarray] | None = None
        #: No leaves, for views that need none: made once per cell.
        self.none = _no_leaves(len(prims))

    def get(self, stats: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """The leaves, built once (their time added to ``stats["leaf_seconds"]``)."""
        if self.built is None:
            tl = time.perf_counter()
            self.built = _leaf_boxes(self.prims)
            stats["leaf_seconds"] += time.perf_counter() - tl
        return self.built


def _no_leaves(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``_leaf_boxes``' arrays for n primitives in no leaf: every leaf -1, no box."""
    return np.full(n, -1, dtype=np.int64), np.zeros((0, 3))


def _prim_arrays(prims: Prims, solid: np.ndarray, gap: np.ndarray,
                 leaves: tuple | None = None) -> PrimArrays:
    """The kernels' view of the primitives (``leaves``: ``_leaf_boxes``'s, or none)."""
    if leaves is None:
        leaves = _no_leaves(len(prims))
    return PrimArrays(prims.pts, prims.start, prims.npts, prims.kind, prims.vid, solid, gap,
                      leaves[0], leaves[1])


def _screen(view: View, plane_tol: float, cover: str, fuse: bool = False,
            refine: int = 0, leaf_list: int = 0) -> Screen:
    """The kernels' view of a view's camera and pixel grid."""
    return Screen(view.origin, view.perm, view.sign, view.corners, int(view.nx), int(view.ny),
                  float(view.x_lo), float(view.y_lo), float(view.pw), float(plane_tol),
                  cover == "relaxed", bool(fuse), int(refine), int(leaf_list))



def _coarse_pass(parrays: PrimArrays, screen: Screen, tiles_x: int, tiles_y: int,
                 items: np.ndarray, tile_off: np.ndarray, tile_items: np.ndarray,
                 tiles: np.ndarray, known: np.ndarray, stats: dict[str, Any]) -> np.ndarray:
    """Which of each tile's items (``tile_items``, ``bin_tiles``) are hidden for the whole
    tile: (len(tile_items),) uint8, 1 where hidden.

    Each tile is resolved as one pixel of the tile's width, over all its items (each of its
    pixels' lists is a subset, in the same front-to-back order). A tile's directions hold
    every direction of each of its pixels, so an item Alg. 1 finds hidden (or not seen) there
    is hidden at every pixel of the tile, and leaving it out of their lists loses nothing
    they would report. What it costs is tightness: a left-out item no longer occludes nor
    closes silhouettes at the pixels, whose tests can only fail more often. What the coarse
    pass finds visible is not the answer (its pixels are wide): it goes to a scratch array.
    Only the ``tiles`` (tiles_x * tiles_y,) bool take part; items ``known`` visible are not
    tested (they are in the answer already). ``screen`` is the view's pixel grid; ``items``
    the primitive ids of ``tile_items`` (``TileLists.items``)."""
    n_tiles = tiles_x * tiles_y
    pstart = tile_off[:-1].astype(np.int64)
    pcount = np.diff(tile_off).astype(np.int64)
    # Each tile's one list holds all its items, in order.
    entries = (np.arange(len(tile_items), dtype=np.int64)
               - np.repeat(pstart, pcount)).astype(np.int32)
    pcount[~tiles] = 0
    hid = np.zeros(len(entries), dtype=np.uint8)
    if not pcount.any():
        return hid
    counters = np.zeros((n_tiles, N_COUNTERS), dtype=np.int64)
    scratch = np.zeros_like(known)
    lists = TileLists(entries, pstart, pcount, 0, n_tiles,
                      _balanced_order(pcount.astype(np.float64) ** 2, 0, n_tiles), tiles_x, 1,
                      numba.get_num_threads(), items, tile_off,
                      np.ones(n_tiles, dtype=np.int64))
    # One pixel per tile, as wide as the tile; the strict cover test only: at a tile's width
    # the relaxed one drops next to nothing more and costs far more (docs/cores/cos.md).
    # Nor separate groups together: in clutter that costs the pass more than it drops.
    wide = screen._replace(nx=tiles_x, ny=tiles_y, pw=screen.pw * TILE, relaxed=False,
                           fuse=False, refine=0)
    resolve_tiles(parrays, lists, wide, Marks(known, scratch, hid, counters, stop_flag()))
    checkpoint()
    stats["coarse_entries"] += int(pcount.sum())
    stats["coarse_dropped"] += int(hid.sum())
    _add_work(stats, counters, "coarse_")
    return hid


def _add_work(stats: dict[str, Any], counters: np.ndarray, prefix: str = "") -> None:
    """Add a resolution's work counters (``resolve_tiles``'s (tiles, ``N_COUNTERS``)) to
    ``stats`` under ``prefix``: entries tested, silhouette edges walked, plane tests and the
    CPU cycles of each step (timed at one entry in ``TIME_STRIDE``: scaled up, an estimate)."""
    for name, col in (("tested", 0), ("silhouette_edges", 4), ("plane_tests", 5)):
        stats[prefix + name] += int(counters[:, col].sum())
    for name, col, scale in (("test", 6, TIME_STRIDE), ("insert", 7, TIME_STRIDE),
                             ("coverall", 8, TIME_STRIDE), ("resolve", 9, 1)):
        stats[f"{prefix}cycles_{name}"] += scale * int(counters[:, col].sum())
    for c, name in enumerate(CYCLE_PARTS):
        stats[f"{prefix}cycles_{name}"] += TIME_STRIDE * int(counters[:, CYCLE_PART0 + c].sum())


def _solve_view(prims: Prims, solid: np.ndarray, order: np.ndarray, sel: np.ndarray,
                gap: np.ndarray, view: View, plane_tol: float, vis: np.ndarray, budget: int,
                stats: dict[str, Any], coarse_items: int, rng: np.ndarray,
                cover: str = "strict", fuse: bool = False, busy_block: int = 1,
                refine: int = 0, busy_items: int = 0, leaves: _Leaves | None = None,
                leaf_list: int = 0) -> int:
    """Lists and resolution of one view (over the positions ``sel``, increasing: those its side
    plane can list, less those the hierarchy walk finds no ray of the view meets,
    ``_view_positions``; only the ``solid`` primitives occlude); sets ``vis`` for what it finds
    visible, adds to ``stats`` and returns the view's longest list. Tiles listing at least
    ``busy_items`` primitives (0: none) are busy: sampled per ``busy_block`` pixels where
    their lists are long, and, listing ``coarse_items`` (0: never), first take the coarse
    pass (``_coarse_pass``). ``rng`` (n, 4) int32 is scratch for the pixel boxes
    (``footprints``); ``cover`` the cover test (``CosParams.cover``); ``fuse`` whether
    separate groups hide together."""
    t0 = time.perf_counter()
    stats["projected"] += len(sel)
    known = vis.copy()
    footprints(prims.pts, prims.start, prims.npts, prims.kind, order, sel, view.origin,
               view.perm, view.sign, view.corners, view.near_box, view.near_w, view.nx,
               view.ny, view.x_lo, view.y_lo, view.pw, plane_tol, rng)
    tiles_x = -(-view.nx // TILE)
    tiles_y = -(-view.ny // TILE)
    n_tiles = tiles_x * tiles_y
    npix = TILE * TILE
    t0b = time.perf_counter()
    tile_off, tile_items, bound = bin_tiles(rng, sel, tiles_x, tiles_y)
    t0c = time.perf_counter()
    stats["footprint_seconds"] += t0b - t0
    stats["bin_seconds"] += t0c - t0b
    stats["tile_items"] += int(tile_off[-1])
    stats["list_seconds"] += t0c - t0
    n_items = np.diff(tile_off)
    # The leaf boxes only where a pixel lists ``leaf_list`` entries or more (built at the
    # first such run of tiles): a pixel lists items of its tile, so a view whose tiles hold
    # fewer never needs them.
    if leaves is None:
        leaves = _Leaves(prims)
    could = 0 < leaf_list <= int(n_items.max(initial=0))
    parrays = _prim_arrays(prims, solid, gap, leaves.none)
    screen = _screen(view, plane_tol, cover, fuse, refine, 0)

    def with_leaves() -> tuple[PrimArrays, Screen]:
        leaf, leaf_pts = leaves.get(stats)
        return (parrays._replace(leaf=leaf, leaf_pts=leaf_pts),
                screen._replace(leaf_list=leaf_list))
    # The tiles' items as primitive ids: lists name them by their place in their tile.
    items = order[tile_items].astype(np.int32)
    drop = np.empty(0, dtype=np.uint8)
    # The threshold holds for tiles at the default resolution; below it a tile spans more
    # solid angle and meets more items with no longer lists (at 64 px, 8 px tiles took the
    # pass on 100k city cells and cost more than they saved), so it grows with that angle.
    scale = max(1.0, (float(view.pw) * DEFAULT_RESOLUTION / 2.0) ** 2)
    busy = (n_items >= max(busy_items, 1) * scale) & (busy_items > 0)
    coarse = busy & (n_items >= max(coarse_items, 1) * scale) & (coarse_items > 0)
    if coarse.any():
        # Clutter: the coarse pass on the tiles with that many items; their lists are then
        # filled without what it found hidden for the whole tile.
        tc = time.perf_counter()
        drop = _coarse_pass(*(with_leaves() if could else (parrays, screen)), tiles_x, tiles_y,
                            items, tile_off, tile_items, coarse, known, stats)
        stats["coarse_seconds"] += time.perf_counter() - tc
        stats["coarse_tiles"] += int(coarse.sum())
    # Clutter's tiles are sampled more coarsely (``CosParams.busy_block``).
    block = np.where(busy & (bound >= BUSY_BLOCK_MIN * npix), busy_block, 1).astype(np.int64)
    stats["block_tiles"] += int(np.count_nonzero(block > 1))
    counters = np.zeros((n_tiles, N_COUNTERS), dtype=np.int64)
    longest = 0
    stop = stop_flag()
    t = 0
    while t < n_tiles:
        # A run of tiles whose list slots (bounded by their footprint pixels) fit the budget
        # (at least one tile).
        t1 = t + 1
        size = int(bound[t])
        while t1 < n_tiles and size + bound[t1] <= budget:
            size += int(bound[t1])
            t1 += 1
        stats["list_runs"] += 1
        if size == 0:
            t = t1
            continue
        checkpoint()  # a cancelled or late computation stops between runs of tiles
        ta = time.perf_counter()
        slot = np.zeros(t1 - t + 1, dtype=np.int64)
        np.cumsum(bound[t:t1], out=slot[1:])
        entries = np.empty(size, dtype=np.int32)
        pstart = np.empty((t1 - t) * npix, dtype=np.int64)
        pcount = np.empty((t1 - t) * npix, dtype=np.int64)
        lists = TileLists(entries, pstart, pcount, t, t1,
                          _balanced_order(bound[t:t1].astype(np.float64), t, t1), tiles_x, TILE,
                          numba.get_num_threads(), items, tile_off, block)
        fill_cut = np.zeros(t1 - t, dtype=np.int64)
        fill_lists(parrays, screen, order, rng, tile_off, tile_items, drop, slot, lists,
                   fill_cut)
        stats["fill_cut"] += int(fill_cut.sum())
        stats["fill_seconds"] += time.perf_counter() - ta
        stats["list_entries"] += int(pcount.sum())
        longest = max(longest, int(pcount.max(initial=0)))
        stats["longest_list"] = max(stats["longest_list"], longest)
        tb = time.perf_counter()
        lists = lists._replace(torder=_balanced_order(_tile_work(pcount, t1 - t), t, t1))
        run_arrays, run_screen = (with_leaves() if could and int(pcount.max(initial=0)) >= leaf_list
                                  else (parrays, screen))
        resolve_tiles(run_arrays, lists, run_screen,
                      Marks(known, vis, np.empty(0, dtype=np.uint8), counters, stop))
        checkpoint()  # the kernel returns early, with vis incomplete, once stop is set
        stats["list_seconds"] += tb - ta
        stats["resolve_seconds"] += time.perf_counter() - tb
        t = t1
    _add_work(stats, counters)
    sampled = block > 1
    stats["block_cycles"] += int(counters[sampled, 9].sum())
    stats["block_tested"] += int(counters[sampled, 0].sum())
    for name, col in (("occluded", 1), ("occluder_triangles", 2), ("early_z_cut", 3),
                      ("fused", 10), ("front_parts", FRONT_PARTS), ("refined", 11),
                      ("subpixels", 12),
                      ("leaf_skipped", 13), ("leaf_tests", 14), ("leaf_hidden", 15),
                      ("walks_seen", WALK0), ("subpixels_seen", WALK0 + 1)):
        stats[name] += int(counters[:, col].sum())
    return longest
