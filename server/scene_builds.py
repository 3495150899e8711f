"""Per-scene builds started when a scene loads, in the background: the spatial hierarchy that
every rasterizing path culls with (``visibility.raster.hierarchy``), and what the cores this
server's sessions use build once per scene (``Core.scene_builds``: ``dual_ray``'s kd-tree and
fences). Nothing waits for them: a walker's first request is answered without the hierarchy
(drawing every triangle) and a core that needs its structure builds it then, sharing the
background build if one is under way (``visibility.scene_cache.per_scene``'s lock).
Finished builds are kept on disk by the scene's content hash under ``settings.cache_dir``
(``visibility.scene_cache.set_store``), so a restart reads them instead of building again.
"""

from __future__ import annotations

import logging
import threading

from server.catalog import LoadedScene
from server.settings import Settings
from visibility.cores.base import AUTO_CORE, choose_core, get_core
from visibility.raster import hierarchy
from visibility.scene_cache import Build, build_in_background

log = logging.getLogger(__name__)


def builds_for(loaded: LoadedScene, settings: Settings) -> list[Build]:
    """What to build for ``loaded``: the hierarchy (scenes of at least
    ``hierarchy.MIN_TRIANGLES`` triangles), then the per-scene structures of the session
    core (``auto``: the core its declared fits pick) and the first answers' core, when they fit
    the scene."""
    scene = loaded.scene
    out: list[Build] = []
    if scene.n_triangles >= hierarchy.MIN_TRIANGLES:
        out.append(hierarchy.BUILD)
    names = [settings.core, settings.first_core]
    if settings.core == AUTO_CORE:
        try:
            names[0] = choose_core(scene, float(loaded.grid.cell_size))[0]
        except LookupError:
            names = names[1:]
    seen = {b.kind for b in out}
    for name in dict.fromkeys(names):
        try:
            core = get_core(name)
        except KeyError:
            continue
        if not core.fit(scene, float(loaded.grid.cell_size)).ok:
            continue
        for b in core.scene_builds(scene):
            if b.kind not in seen:
                seen.add(b.kind)
                out.append(b)
    return out


def prepare_scene(loaded: LoadedScene, settings: Settings) -> threading.Thread | None:
    """Start ``builds_for(loaded)`` on a background thread (``settings.worker_nice`` nicer);
    each finished build's seconds land in ``loaded.info["builds"]`` (``GET /scenes/{name}``).
    None when there is nothing to build."""
    builds = builds_for(loaded, settings)
    if not builds:
        return None
    loaded.info["builds"] = {}

    def finished(kind: str, seconds: float) -> None:
        # A new dict each time: a request may be serializing the old one on another thread.
        loaded.info["builds"] = {**loaded.info["builds"], kind: round(seconds, 3)}
        log.info("scene %r: %s ready in %.2f s", loaded.name, kind, seconds)

    log.info("scene %r: building %s in the background", loaded.name,
             ", ".join(b.kind for b in builds))
    return build_in_background(loaded.scene, builds, nice=settings.worker_nice,
                               on_done=finished)
