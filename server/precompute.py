"""Computing a scene's cell PVS ahead of time, so a server starts with its cache warm.

The load benchmark shows computation, not streaming, bounds how many walkers a machine serves
(``benchmarks/results/load.md``): with every cell computed beforehand, 50 walkers stream on two
cores without a stall. ``precompute`` runs the cells through the same ``ComputeService`` the
server uses, so the results land under the keys sessions and HTTP queries look up; with an
on-disk cache (``Settings.cache_dir``) they survive until a server starts on that folder; with a
Redis cache (``Settings.cache``) they land where every replica reads them. Cells already on disk
or in Redis are read, not recomputed, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import as_completed
from dataclasses import dataclass, field
from typing import Any

from server.compute import ComputeService
from server.region import UnknownCellError, cell_key
from server.resolve import Resolver
from visibility.cores.base import AUTO_CORE


@dataclass
class PrecomputeReport:
    """What a ``precompute`` run did: cells computed now, found cached (memory or disk), and
    failed ({cell: message}); ``compute_seconds`` sums the computations' own times, ``wall``
    is the run's wall time (seconds); ``why`` how the core was chosen (``Resolver.resolve``)."""

    scene: str
    core: str
    params: dict[str, Any]
    cells: int
    computed: int = 0
    cached: int = 0
    failed: dict[int, str] = field(default_factory=dict)
    compute_seconds: float = 0.0
    wall: float = 0.0
    why: str = ""

    def summary(self) -> str:
        """One line for people."""
        # Only the auto choice has a reason worth printing; a named core was simply asked for.
        chosen = f" (auto: {self.why})" if self.why not in ("", "requested",
                                                            "server default") else ""
        return (f"{self.scene}: {self.cells} cells with {self.core}{chosen} {self.params}: "
                f"{self.computed} computed ({self.compute_seconds:.1f} s of computation), "
                f"{self.cached} already cached, {len(self.failed)} failed, "
                f"{self.wall:.1f} s wall")


def parse_cells(text: str, n_cells: int) -> list[int]:
    """Cell ids from ``"0-99,120,130-131"`` (inclusive ranges), sorted and unique; ValueError
    for malformed text or ids outside ``0..n_cells-1``."""
    out: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        try:
            a, b = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f"cells: {part!r} is not an id or a range a-b") from None
        if a > b or a < 0 or b >= n_cells:
            raise ValueError(f"cells: {part!r} outside 0..{n_cells - 1}")
        out.update(range(a, b + 1))
    if not out:
        raise ValueError("cells: no cell named")
    return sorted(out)


def precompute(service: ComputeService, scene: str, core: str | None = None,
               params: Mapping[str, Any] | None = None, cells: Sequence[int] | None = None,
               progress: bool = True, resolver: Resolver | None = None) -> PrecomputeReport:
    """Compute the PVS of ``cells`` (default: every cell of the scene's grid) of catalogue
    scene ``scene`` with ``core`` (default and ``"auto"`` as the server resolves them:
    ``resolver``, default one of the service's settings) and ``params``, on the service's
    worker pool; results go to its caches (memory, and disk when configured, and Redis when
    ``settings.cache`` names one). A cell that fails is reported, not raised: its computation
    failed or its entry is not valid afterwards in the on-disk cache (``DiskPVSCache.check``)
    or in Redis (a Redis that is down fails the cells it misses). Raises UnknownSceneError,
    UnknownCoreError, ValueError (bad parameters) and UnknownCellError (ids outside the grid)
    before computing anything."""
    resolver = resolver or Resolver(service.settings)
    loaded = service.catalog.get(scene)
    n = len(loaded.grid)
    ids = list(range(n)) if cells is None else sorted({int(c) for c in cells})
    bad = [c for c in ids if not 0 <= c < n]
    if bad:
        raise UnknownCellError(f"scene {scene!r} has no cell {bad[0]} (cells 0..{n - 1})")
    if (core or service.settings.core) == AUTO_CORE and service.settings.calibrate:
        # ``auto`` picks by measurement: calibrate now (kept in the cache folder with the
        # scene's content hash, so the server finds it), then resolve.
        resolver.calibration.calibration(
            loaded.scene, float(loaded.grid.cell_size), wait=True,
            progress=(lambda line: print("calibration: " + line)) if progress else None)
    choice = resolver.resolve(core, params, loaded)
    report = PrecomputeReport(scene, choice.core.name, dataclasses.asdict(choice.params),
                              len(ids), why=choice.why)
    t0 = time.perf_counter()
    futures = {service.submit(scene, choice.core, choice.params, cell=c): c for c in ids}
    done = as_completed(futures)
    if progress:
        from tqdm import tqdm

        done = tqdm(done, total=len(futures), desc=f"precompute {scene}", unit="cell")
    for fut in done:
        cell = futures[fut]
        try:
            result = fut.result()
        except Exception as exc:  # one cell's failure must not lose the others
            report.failed[cell] = f"{type(exc).__name__}: {exc}"
            continue
        # The point of the run is the entry a server will read: one that is not there, or
        # would be rejected, is a failure however the computation went.
        key = cell_key(loaded, cell, choice.core, choice.params)
        missing = service.cache.missing(key, loaded.scene.n_triangles)
        if missing:
            where = "on-disk cache" if "disk" in missing else "Redis"
            report.failed[cell] = f"its {where} entry could not be written"
            continue
        if result.cached:
            report.cached += 1
        else:
            report.computed += 1
            report.compute_seconds += result.seconds
    report.wall = time.perf_counter() - t0
    return report
