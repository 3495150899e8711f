"""The ``trim_regions`` core: from-region PVS by trim regions (Voglreiter et al. 2023).

Per sphere covering the cell and per cube face, the scene octree is peeled in layers front to
back from the moved-back viewpoint v*; each layer's front and back faces, trim region quads at
the silhouettes and their umbrae go into fixed-size per-pixel k-buffers, and every pixel's trim
sequence is resolved into occlusion intervals, validated where a trim fragment lies inside,
with early termination at the first untrimmed occluder. The PVS is what the pixels found and
what v* sees between them. A sampling add-on (``gather_eyes``, off by default) also adds what
eyes stratified inside the cell see at 16 samples per pixel: v* stands outside the cell and
meets small triangles behind trimmed occluders at no pixel centre; that is from-point sampling
inside the answer, not the method.

Aggressive: rasterization at pixel centres can miss what covers no pixel centre (thin or far
triangles), and a trim region is local to its silhouette, so an eye near the edge of a large
sphere may see past a silhouette the trims do not model (the paper's residual false negatives,
Table 3 and Fig. 16). Made for small cells: Δ of 5-30 cm.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from visibility.cores.base import Core, CoreParams, Cost, param, register
from visibility.cores.trim_regions.cache import scene_data
from visibility.cores.trim_regions.frustum import cover_box
from visibility.cores.trim_regions.kbuffer import K
from visibility.cores.trim_regions.pipeline import (
    ENTRY_BYTES,
    GATHER_EYES,
    SMALL_RASTERS,
    SUPERSAMPLE,
    trim_pvs,
)
from visibility.scene import Scene
from visibility.scene_cache import Build
from visibility.topology import CLOSED_BUILD, unseen_back_faces
from visibility.viewcells import Viewcell

#: Default pixels across each cube face.
DEFAULT_RESOLUTION = 256
#: Default largest sphere radius, metres (``TrimRegionsParams.max_delta``).
DEFAULT_MAX_DELTA = 0.41


@dataclass
class TrimRegionsParams(CoreParams):
    """Parameters of the trim region core.

    resolution : pixels across each (slightly widened) cube face of every sphere.
    max_delta : the cell is covered by spheres of at most this radius Δ (metres); smaller
        spheres trim less and cost one computation each. The default, 0.41 m, is the
        radius that covers the server's 1 m cell (1 m across the ground, the grid's 0.4 m eye
        range high) with 2 x 2 spheres and a 1 m cube with 12 (at the paper's largest Δ,
        0.3 m: 12 and 27); the paper's bound is measured there (docs/cores/trim_regions.md).
    max_prims : most triangles per octree node (the octree is cached per value).
    gather_eyes : a sampling add-on, 0 (off) by default: eyes stratified in the cell whose
        supersampled views join the answer (from-point sampling, not the method; 8 is the
        count measured). They catch the small triangles v*, outside the cell, sees under no
        pixel centre behind trimmed occluders.
    small : how those triangles are found by the method itself (``pipeline.SMALL_RASTERS``):
        ``conservative`` (the default: every triangle under a pixel wide touching a pixel
        whose centre would have found it visible; holds the paper's pixel bound where centres
        do not, for a larger PVS) or ``centres`` (the paper's pixel centres: not at all).
    """

    resolution: int = param(DEFAULT_RESOLUTION, unit="px", ge=8, le=4096,
                            help="pixels across each cube face of every sphere")
    max_delta: float = param(DEFAULT_MAX_DELTA, unit="m", ge=1e-4, le=1e4,
                             help="largest sphere radius the cell is covered with")
    max_prims: int = param(256, ge=8, le=1 << 20, help="most triangles per octree node")
    gather_eyes: int = param(0, ge=0, le=256,
                             help="sampling add-on (off: 0): eyes in the cell whose "
                                  f"supersampled views join the answer ({GATHER_EYES} measured)")
    small: str = param("conservative", choices=SMALL_RASTERS,
                       help="triangles behind trimmed occluders that cover no pixel centre: "
                            "conservative (every one under a pixel wide touching a pixel its "
                            "centre leaves open) or centres (the paper: not found; a smaller "
                            "PVS, more missed pixels)")


#: Cost model (``estimate_cost``), fitted on the 2-core development machine with
#: ``python -m benchmarks.bench_trim_regions`` (benchmarks/results/trim_regions.md): per pixel
#: of the views and per triangle and view (set-up, silhouettes, instances). Bytes: the
#: k-buffers of one view (``K`` entries per pixel) and the per-triangle arrays of a view.
SECONDS_PER_PIXEL = 1.5e-6
SECONDS_PER_VIEW_TRIANGLE = 1.5e-7
#: The eyes' gather, per pixel rendered (6 faces of SUPERSAMPLE x the resolution per eye):
#: fitted to P4's growth when the gather came (``python -m benchmarks.bench_trim_regions``,
#: benchmarks/results/trim_regions.md; figures in docs/cores/trim_regions.md), rounded up.
SECONDS_PER_GATHER_PIXEL = 1e-8
BYTES_PER_TRIANGLE = 160


@register
class TrimRegionsCore(Core):
    """Trim regions from spheres covering the cell (aggressive; small cells)."""

    name: ClassVar[str] = "trim_regions"
    description: ClassVar[str] = (
        "Trim regions (Voglreiter et al. 2023): octree layers peeled front to back, silhouette "
        "trim regions and umbrae in fixed-size per-pixel k-buffers, per-pixel trim sequences "
        "resolved with early termination; the cell covered by spheres of radius <= max_delta, "
        "six widened cube faces each (aggressive: rare pixel-level misses)")
    Params: ClassVar[type[CoreParams]] = TrimRegionsParams
    promise: ClassVar[str] = "aggressive"
    knob: ClassVar[str] = "resolution"
    knob_levels: ClassVar[tuple[int, ...]] = (128, 256, 512)
    native_segments: ClassVar[bool] = False
    # Orders of magnitude only: the measured figures live in benchmarks/results/trim_regions.md.
    fits: ClassVar[str] = ("cells of 5 cm to 1 m (spheres of at most 0.41 m: one for a 0.3 m "
                           "cube, 4 for the server's 1 m cell) of arbitrary, non-manifold "
                           "scenes, in a fraction of a second (about a second on a 1M-triangle "
                           "kitchen); misses within the paper's 0.005 % of a frame's pixels, "
                           "a PVS several times what is seen, more in clutter: "
                           "docs/cores/trim_regions.md")
    check_params: ClassVar[dict[str, Any]] = {}
    #: What ``checks.check_fn_fp_against_sampled_ground_truth`` measures on the designed
    #: scenes at 64, 128 and 256 px, by the method alone and with the sampling add-on alike
    #: (its failure message prints the rates; docs/cores/trim_regions.md): no FN, and the worst
    #: FP (two rooms and a door: hidden faces of the wall slabs and boxes flush against floor
    #: and walls, the trims' price) rounded up, so a regression fails; the method stays
    #: aggressive elsewhere (benchmarks/results/trim_regions.md: pixel-level misses on real
    #: scenes).
    fn_bound: ClassVar[float] = 0.0
    fp_bound: ClassVar[float] = 0.44

    def scene_builds(self, scene: Scene) -> list[Build]:
        """The closed parts (``topology.CLOSED_BUILD``) whose back faces it leaves out."""
        return [CLOSED_BUILD]

    def suitability(self, scene: Scene, cell_size: float | None) -> tuple[float, str]:
        small = cell_size is not None and cell_size <= 0.5
        if small:
            return 3.0, ("small cells: a tight trim-region PVS in about a second, with rare "
                         "pixel-level misses (aggressive)")
        return 0.05, ("made for small cells: a larger one is covered by many spheres of "
                      f"at most {DEFAULT_MAX_DELTA} m, each a computation of its own")

    def estimate_cost(self, scene: Scene, cell: Viewcell, params: CoreParams) -> Cost:
        """Six views per covering sphere, priced per pixel and per triangle and view;
        memory: one view's k-buffers and per-triangle arrays."""
        assert isinstance(params, TrimRegionsParams)
        r = int(params.resolution)
        centres, _ = cover_box(np.asarray(cell.box, float), float(params.max_delta))
        views = 6 * len(centres)
        m = scene.n_triangles + scene.n_spheres
        seconds = views * (r * r * SECONDS_PER_PIXEL + m * SECONDS_PER_VIEW_TRIANGLE)
        seconds += int(params.gather_eyes) * 6 * (SUPERSAMPLE * r) ** 2 * SECONDS_PER_GATHER_PIXEL
        peak = r * r * K * ENTRY_BYTES + m * BYTES_PER_TRIANGLE
        return Cost(seconds, int(peak), {"views": views, "pixels": views * r * r,
                                         "triangles": scene.n_triangles})

    def _compute(
        self, scene: Scene, cell: Viewcell, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, TrimRegionsParams)
        data, built = scene_data(scene, int(params.max_prims))
        box = np.asarray(cell.box, dtype=np.float64)
        ids, stats = trim_pvs(scene, data, box, int(params.resolution),
                              float(params.max_delta), gather_eyes=int(params.gather_eyes),
                              small=str(params.small))
        # Back faces of closed surfaces facing away from the whole cell are never seen from
        # it: what the interval rules let through of them leaves the answer.
        unseen = unseen_back_faces(scene, box)[ids]
        stats["unseen_back_faces"] = int(unseen.sum())
        ids = ids[~unseen]
        stats["octree_build_seconds"] = data.build_seconds if built else 0.0
        stats["octree_leaves"] = len(data.octree)
        return ids, stats
