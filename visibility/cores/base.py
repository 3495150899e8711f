"""The core interface: every visibility algorithm is a ``Core`` that turns (scene, cell) into a PVS.

A core is one module that subclasses ``Core``, declares a ``Params`` dataclass, and registers
itself with ``@register``. The server, the CLI, the benchmarks and the conformance suite find
cores only through the registry, so a new core needs nothing beyond its own module.
"""

from __future__ import annotations

import dataclasses
import importlib
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from visibility.ids import unique_ids
from visibility.scene import Scene
from visibility.viewcells import Viewcell

Granularity = Literal["triangle", "object"]


@dataclass
class CoreParams:
    """Parameters every core understands. Cores extend this with their own fields."""

    resolution: int = 256
    granularity: Granularity = "triangle"
    seed: int = 0

    #: Bounds that keep a request from exhausting the machine (checked by ``validate``).
    MAX_RESOLUTION: ClassVar[int] = 4096

    def validate(self) -> None:
        """Raise ValueError when a parameter is out of its allowed range."""
        if not (8 <= int(self.resolution) <= self.MAX_RESOLUTION):
            raise ValueError(
                f"resolution must be in [8, {self.MAX_RESOLUTION}], got {self.resolution}"
            )
        if self.granularity not in ("triangle", "object"):
            raise ValueError(
                f"granularity must be 'triangle' or 'object', got {self.granularity!r}"
            )

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def cache_key(self) -> str:
        """A stable string naming these parameters, for caches."""
        return ",".join(f"{k}={v}" for k, v in sorted(self.as_dict().items()))


@dataclass
class PVS:
    """A potentially visible set.

    ``triangle_ids`` is sorted, unique int32 rows of the scene's face array. With object
    granularity it holds every triangle of each visible object; ``object_ids`` lists them.
    """

    triangle_ids: np.ndarray
    granularity: Granularity = "triangle"
    object_ids: np.ndarray | None = None
    sphere_ids: np.ndarray | None = None
    stats: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.triangle_ids = unique_ids(self.triangle_ids, np.int32)
        if self.sphere_ids is not None:
            self.sphere_ids = unique_ids(self.sphere_ids, np.int32)

    def __len__(self) -> int:
        return int(len(self.triangle_ids))

    @property
    def seconds(self) -> float:
        return float(self.stats.get("seconds", 0.0))


def expand_to_objects(scene: Scene, triangle_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(triangle ids, object ids): every valid triangle of each object that has a visible one."""
    objs = unique_ids(scene.object_ids[np.asarray(triangle_ids, dtype=np.int64)])
    mask = np.isin(scene.object_ids, objs) & scene.valid_faces
    return np.nonzero(mask)[0].astype(np.int32), objs.astype(np.int32)


class SegmentNotSupported(ValueError):
    """A core was asked for the PVS of a segment it cannot describe (a diagonal segment for a
    core that only solves boxes)."""


class Core(ABC):
    """A from-region visibility algorithm.

    Subclasses set ``name``, ``Params`` (a ``CoreParams`` subclass), ``description`` and
    implement ``_compute``; ``compute`` adds timing, memory, validation and granularity.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    Params: ClassVar[type[CoreParams]] = CoreParams
    #: True when the core only fits 2.5D scenes (heightfield-like occluders).
    requires_2_5d: ClassVar[bool] = False
    #: Upper bound on the false-negative rate against the sampled ground truth that the
    #: conformance suite holds this core to, at its default parameters.
    fn_bound: ClassVar[float] = 0.05
    #: Upper bound on the false-positive rate (share of the PVS that the sampled ground truth
    #: did not see) that the conformance suite holds this core to, at its default parameters.
    #: The sampled ground truth is itself aggressive (it misses what falls between its samples
    #: and pixels), so an FP there is either a hidden triangle reported (over-conservative or
    #: wrong) or a visible one the reference missed (slivers, grazing views from the cell's
    #: boundary): a bound that catches gross over-inclusion, not a proof of exactness. The
    #: default is loose for conservative cores; each core states its own measured one.
    fp_bound: ClassVar[float] = 0.25

    def make_params(self, **overrides: Any) -> CoreParams:
        """This core's parameter object with the given fields changed; unknown names raise."""
        known = {f.name for f in dataclasses.fields(self.Params)}
        unknown = set(overrides) - known
        if unknown:
            raise ValueError(f"unknown parameters for core {self.name!r}: {sorted(unknown)}")
        params = self.Params(**overrides)
        params.validate()
        return params

    def supports(self, scene: Scene) -> tuple[bool, str]:
        """Whether this core fits the scene, and why not when it does not."""
        return True, ""

    def compute(self, scene: Scene, cell: Viewcell, params: CoreParams | None = None) -> PVS:
        """The PVS of ``cell``: triangles visible from some point of the box (and stats)."""
        params = params or self.make_params()
        params.validate()
        t0 = time.perf_counter()
        ids, stats = self._compute(scene, cell, params)
        return self._finish(scene, params, ids, stats, time.perf_counter() - t0)

    def compute_segment(
        self, scene: Scene, p: np.ndarray, q: np.ndarray, params: CoreParams | None = None
    ) -> PVS:
        """The PVS of the segment p -> q (metres): triangles visible from some point of it.

        Cores that solve segments natively override ``_compute_segment``; the default answers
        a segment along a coordinate axis as the (degenerate) box it is, and raises
        ``SegmentNotSupported`` for a diagonal one, which no box describes.
        """
        a = np.asarray(p, dtype=np.float64).reshape(3)
        b = np.asarray(q, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise ValueError("segment end points must be finite")
        params = params or self.make_params()
        params.validate()
        t0 = time.perf_counter()
        ids, stats = self._compute_segment(scene, a, b, params)
        return self._finish(scene, params, ids, stats, time.perf_counter() - t0)

    def _compute_segment(
        self, scene: Scene, p: np.ndarray, q: np.ndarray, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Return (visible triangle ids, stats) for the segment p -> q; see ``compute_segment``."""
        if np.count_nonzero(p != q) > 1:
            raise SegmentNotSupported(
                f"core {self.name!r} computes boxes only; a diagonal segment has no box "
                f"(ask a core with native segments: {segment_cores()})")
        return self._compute(scene, Viewcell(np.stack([np.minimum(p, q), np.maximum(p, q)])),
                             params)

    def _finish(self, scene: Scene, params: CoreParams, ids: np.ndarray, stats: dict[str, Any],
                seconds: float) -> PVS:
        ids = np.asarray(ids, dtype=np.int64)
        ids = ids[(ids >= 0) & (ids < scene.n_triangles)]
        ids = ids[scene.valid_faces[ids]]
        object_ids = None
        if params.granularity == "object":
            ids, object_ids = expand_to_objects(scene, ids)
        stats = dict(stats)
        stats["seconds"] = seconds
        sphere_ids = stats.pop("sphere_ids", None)
        return PVS(ids, params.granularity, object_ids, sphere_ids, stats)

    @abstractmethod
    def _compute(
        self, scene: Scene, cell: Viewcell, params: CoreParams
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Return (visible triangle ids in any order, stats dict)."""


_REGISTRY: dict[str, type[Core]] = {}


def unregister(name: str) -> None:
    """Remove a core from the registry (tests that register throwaway cores use it)."""
    _REGISTRY.pop(name, None)

#: Modules that hold the built-in cores; importing one registers its core.
BUILTIN_CORE_MODULES = ("visibility.cores.sampling", "visibility.cores.from_segment",
                        "visibility.cores.cos")


def register(cls: type[Core]) -> type[Core]:
    """Class decorator: make a core available by its ``name``."""
    if not cls.name:
        raise ValueError("a core needs a name")
    _REGISTRY[cls.name] = cls
    return cls


def _load_builtins() -> None:
    for mod in BUILTIN_CORE_MODULES:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            # A built-in core still under construction is simply absent.
            if exc.name != mod:
                raise


def segment_cores() -> list[str]:
    """Names of the registered cores that solve arbitrary segments natively, sorted."""
    _load_builtins()
    return sorted(n for n, c in _REGISTRY.items()
                  if c._compute_segment is not Core._compute_segment)


def available_cores() -> list[str]:
    """Names of every registered core, sorted."""
    _load_builtins()
    return sorted(_REGISTRY)


def get_core(name: str) -> Core:
    """An instance of the core registered under ``name``; KeyError with the choices otherwise."""
    _load_builtins()
    try:
        return _REGISTRY[name]()
    except KeyError:
        raise KeyError(f"unknown core {name!r}; available: {sorted(_REGISTRY)}") from None
