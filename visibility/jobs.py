"""One PVS computation as a plain function of its inputs, so it can run wherever a scene is:
in the server's own worker threads or on a remote worker (``server.dask_executor`` ships
``compute_within`` to a Dask cluster, with the scene scattered to the workers once).

Nothing here knows where it runs; the caller gives the scene, the core and one region (a
viewcell or a segment).
"""

from __future__ import annotations

import numpy as np

from visibility.cancel import CancelToken
from visibility.cores.base import PVS, Core, CoreParams
from visibility.scene import Scene
from visibility.viewcells import Viewcell


def compute_region(scene: Scene, core: Core, params: CoreParams, cell: Viewcell | None = None,
                   segment: np.ndarray | None = None, token: CancelToken | None = None) -> PVS:
    """The PVS of viewcell ``cell`` or of ``segment`` ((2, 3) [p, q], metres,
    ``Core.compute_segment``) in ``scene`` with ``core`` at ``params``; exactly one of the two.

    ``token``: stops the core at its next checkpoint (``ComputationCancelled``)."""
    if (cell is None) == (segment is None):
        raise ValueError("give exactly one of cell and segment")
    if segment is not None:
        seg = np.asarray(segment, dtype=np.float64).reshape(2, 3)
        return core.compute_segment(scene, seg[0], seg[1], params, token=token)
    return core.compute(scene, cell, params, token=token)


def compute_within(scene: Scene, core: Core, params: CoreParams, cell: Viewcell | None,
                   segment: np.ndarray | None, seconds: float | None) -> PVS:
    """``compute_region`` stopped at the core's next checkpoint once ``seconds`` have passed
    (None: no limit). The remote form: a deadline travels as seconds left, since another
    machine's monotonic clock does not share the caller's origin."""
    return compute_region(scene, core, params, cell, segment, CancelToken.after(seconds))
