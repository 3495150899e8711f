"""The ``sampling`` core: the PVS as the union of cubemap id buffers from points of the cell.

Aggressive (it can miss triangles seen only between its samples, never reports hidden ones) and
exact in what it reports; its cost grows linearly with ``samples``. Same method as the sampled
ground truth (``visibility.ground_truth``), at a lighter default budget.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from visibility.cores.base import Core, CoreParams, Cost, param, register
from visibility.ground_truth import (
    GroundTruth,
    estimate_sampling_cost,
    sample_pvs,
    sample_segment_pvs,
)
from visibility.scene import Scene
from visibility.viewcells import Viewcell

#: Upper bound on ``SamplingParams.samples`` (keeps one request from hogging the machine).
MAX_SAMPLES = 100_000


@dataclass
class SamplingParams(CoreParams):
    """``samples`` viewpoints in the cell, convergence recorded every ``batch`` of them."""

    samples: int = param(32, ge=1, le=MAX_SAMPLES, unit="viewpoints",
                         help="stratified viewpoints in the cell, each rendering a cubemap")
    batch: int = param(8, ge=1, le=MAX_SAMPLES, unit="viewpoints",
                       help="the convergence curve records the PVS size every batch samples")


@register
class SamplingCore(Core):
    """Union of the triangle ids seen in cubemaps from stratified points of the cell."""

    name: ClassVar[str] = "sampling"
    description: ClassVar[str] = (
        "Cubemap id buffers from stratified random viewpoints in the cell, united "
        "(aggressive: may miss thin slivers seen between samples)."
    )
    Params: ClassVar[type[CoreParams]] = SamplingParams
    promise = "aggressive"
    fits = "any scene (static, dynamic, spheres), any cell size: the general fallback"
    knob = "samples"
    knob_levels = (8, 32, 128)
    native_segments = True
    check_params: ClassVar[dict[str, Any]] = {"samples": 16}
    #: Holds on the conformance scenes (``check_core`` measures it there). Open scenes with many
    #: sub-pixel triangles miss more, and more samples or pixels buy it back: what is missed is
    #: resolution-bound (figures and their commands: docs/cores/sampling.md).
    fn_bound: ClassVar[float] = 0.05
    #: It samples like the reference, so it reports little the reference does not see
    #: (``check_core`` measures it on every conformance scene).
    fp_bound: ClassVar[float] = 0.05

    def suitability(self, scene: Scene, cell_size: float | None) -> tuple[float, str]:
        # The fallback: it fits everything, so any core made for the scene outranks it.
        kind = "dynamic scene" if scene.states is not None else "static scene"
        return 1.0, (f"{kind}: from-point sampling is the general fallback (aggressive: may "
                     "miss what falls between its samples)")

    def estimate_cost(self, scene: Scene, cell: Viewcell, params: CoreParams) -> Cost:
        """``samples`` cubemaps of ``resolution`` px over every triangle
        (``visibility.ground_truth.estimate_sampling_cost``)."""
        assert isinstance(params, SamplingParams)
        seconds, peak = estimate_sampling_cost(
            scene.n_triangles, int(params.resolution), int(params.samples),
            spheres=scene.n_spheres, dynamic=scene.states is not None)
        return Cost(seconds, peak, {"views": int(params.samples),
                                    "pixels": 6 * int(params.resolution) ** 2,
                                    "triangles": scene.n_triangles})

    def _compute(
        self, scene: Scene, cell: Viewcell, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, SamplingParams)
        gt = sample_pvs(
            scene,
            cell,
            n_points=int(params.samples),
            resolution=int(params.resolution),
            seed=int(params.seed),
            batch=int(params.batch),
        )
        return gt.triangle_ids, _stats(gt, params)

    def _compute_segment(
        self, scene: Scene, p: np.ndarray, q: np.ndarray, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        assert isinstance(params, SamplingParams)
        gt = sample_segment_pvs(scene, p, q, n_points=int(params.samples),
                                resolution=int(params.resolution), seed=int(params.seed),
                                batch=int(params.batch))
        return gt.triangle_ids, _stats(gt, params)


def _stats(gt: GroundTruth, params: SamplingParams) -> dict[str, Any]:
    stats: dict[str, Any] = {
        "samples": gt.samples,
        "resolution": int(params.resolution),
        "convergence": [list(c) for c in gt.convergence],
        "pixels_rendered": gt.pixels,
    }
    if gt.sphere_ids is not None and len(gt.sphere_ids):
        # The base class moves these onto ``PVS.sphere_ids``; without them a client of the
        # sampling core would never receive the spheres it sees.
        stats["sphere_ids"] = gt.sphere_ids
    return stats
