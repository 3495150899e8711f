"""One PVS computation as a plain function of its inputs, so it can run wherever a scene is:
in the server's own worker threads or on a remote worker (``server.dask_executor`` ships
``compute_within`` to a Dask cluster).

Nothing here knows where it runs; the caller gives the scene, the core and one region (a
viewcell or a segment). A remote worker gets the scene itself (scattered to it once) or a
``SceneSource``: where to load or generate it and its content hash, which ``scene_from``
checks, loading it once per process.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visibility.cancel import CancelToken
from visibility.cores.base import PVS, Core, CoreParams
from visibility.scene import Scene, scene_fingerprint
from visibility.viewcells import Viewcell


class SceneUnavailable(RuntimeError):
    """A worker could not load the scene a ``SceneSource`` names: no such file there, or one
    whose content hash is not the named one."""


@dataclass(frozen=True)
class SceneSource:
    """Where a worker finds a scene: a file (``path``, the same on every machine) or a
    generator (``generator``, ``triangles``, ``seed``), and its ``scene_fingerprint``."""

    fingerprint: str
    name: str = ""
    path: str | None = None
    generator: str | None = None
    triangles: int | None = None
    seed: int = 0


_LOADED: dict[str, Scene] = {}
_LOADING = threading.Lock()


def scene_from(scene: Scene | SceneSource) -> Scene:
    """``scene`` itself, or the scene its source names, loaded (or generated) once per process
    and checked against its content hash; SceneUnavailable when it cannot be or differs."""
    if isinstance(scene, Scene):
        return scene
    with _LOADING:  # one load per scene, however many jobs ask at once
        found = _LOADED.get(scene.fingerprint)
        if found is not None:
            return found
        try:
            if scene.path is not None:
                from visibility.loaders import load_scene

                found = load_scene(Path(scene.path), name=scene.name or None)
            else:
                from visibility.generators import make_scene

                found = make_scene(str(scene.generator), triangles=scene.triangles,
                                   seed=scene.seed)
        except Exception as exc:  # loaders and generators raise many types
            raise SceneUnavailable(f"scene {scene.name!r} could not be loaded here: "
                                   f"{type(exc).__name__}: {exc}") from None
        got = scene_fingerprint(found)
        if got != scene.fingerprint:
            raise SceneUnavailable(f"scene {scene.name!r} here has content hash {got}, not "
                                   f"{scene.fingerprint}")
        if scene.name:
            found.name = scene.name
        _LOADED[scene.fingerprint] = found
        return found


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


def compute_within(scene: Scene | SceneSource, core: Core, params: CoreParams,
                   cell: Viewcell | None, segment: np.ndarray | None,
                   seconds: float | None) -> PVS:
    """``compute_region`` on ``scene_from(scene)``, stopped at the core's next checkpoint once
    ``seconds`` have passed (None: no limit). The remote form: a deadline travels as seconds
    left, since another machine's monotonic clock does not share the caller's origin."""
    return compute_region(scene_from(scene), core, params, cell, segment,
                          CancelToken.after(seconds))

