"""What a PVS is computed for (``Region``: a grid cell, an ad-hoc box or a segment of a loaded
scene), its cache key, and what comes back (``PVSResult``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.cache.key import PVSKey
from server.catalog import LoadedScene
from visibility.cores.base import PVS, Core, CoreParams
from visibility.viewcells import Viewcell


class UnknownCellError(LookupError):
    """A cell id outside the scene's grid."""


class UnsupportedSceneError(ValueError):
    """The core does not fit the scene (``Core.fit`` said no)."""


@dataclass(frozen=True)
class Region:
    """Where the eyes are: ``viewcell`` (its box (2, 3) [min, max], metres; its ``id`` the grid
    cell's, -1 for an ad-hoc box or a segment's bounding box) and, for a segment, ``segment``
    (2, 3) [p, q], metres. ``cell``: the grid cell id, else None."""

    cell: int | None
    viewcell: Viewcell
    segment: np.ndarray | None = None

    @property
    def box(self) -> np.ndarray:
        """(2, 3) the viewcell box (a segment's bounding box), metres."""
        return self.viewcell.box

    def key(self, fingerprint: str, core: Core, params: CoreParams) -> PVSKey:
        """The cache key of this region's PVS in the scene of ``fingerprint`` (a grid cell's
        and an ad-hoc box's alike: cores see only the box)."""
        if self.segment is not None:
            return PVSKey.of(fingerprint, "segment", self.segment, core.name, params.cache_key())
        return PVSKey.of(fingerprint, "box", self.viewcell.box, core.name, params.cache_key())


def region_of(loaded: LoadedScene, cell: int | None = None, box: np.ndarray | None = None,
              segment: np.ndarray | None = None) -> Region:
    """The region of exactly one of grid ``cell``, ``box`` (2, 3) [min, max] and ``segment``
    (2, 3) [p, q] (metres) in ``loaded``. Raises ValueError (not exactly one; an inverted box;
    NaN or inf), UnknownCellError (a cell outside the grid)."""
    if sum(x is not None for x in (cell, box, segment)) != 1:
        raise ValueError("give exactly one of cell, box and segment")
    if cell is not None:
        try:
            return Region(int(cell), loaded.grid.cell(cell))
        except IndexError:
            raise UnknownCellError(f"scene {loaded.name!r} has no cell {cell} (cells "
                                   f"0..{len(loaded.grid) - 1})") from None
    if segment is not None:
        seg = np.asarray(segment, dtype=np.float64).reshape(2, 3)
        if not np.all(np.isfinite(seg)):
            raise ValueError("segment end points must be finite")
        return Region(None, Viewcell(np.stack([seg.min(axis=0), seg.max(axis=0)])), seg)
    return Region(None, Viewcell(box))


def cell_key(loaded: LoadedScene, cell: int, core: Core, params: CoreParams) -> PVSKey:
    """The cache key of grid cell ``cell``'s PVS by ``core`` with ``params`` (UnknownCellError
    outside the grid)."""
    return region_of(loaded, cell=cell).key(loaded.fingerprint, core, params)


@dataclass(frozen=True)
class PVSResult:
    """A computed (or cached) PVS with what it was computed for.

    ``box`` is the (2, 3) viewcell box, metres; ``seconds`` the computation time (of the
    original computation for cached results); ``cached`` whether it came from a cache.
    """

    scene: str
    cell: int | None
    box: np.ndarray
    core: str
    params: CoreParams
    pvs: PVS
    cached: bool

    @property
    def seconds(self) -> float:
        """The computation's time, seconds."""
        return self.pvs.seconds
