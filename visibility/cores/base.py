"""The core interface: every visibility algorithm is a ``Core`` that turns (scene, cell) into a PVS.

A core is one package in ``visibility/cores/`` (or a module another installed package names in
the ``pvs.cores`` entry-point group) holding a ``Core`` subclass decorated with ``@register``.
Everything the server, the CLI, the benchmarks and the conformance suite need to know about a
core, the core declares here: its parameters with units, ranges and help (``param``), its
promise (``PROMISES``), the knob that trades error for time, whether it solves segments natively,
and how well it fits a scene and cell size (``Core.fit``, which ``choose_core`` weighs for
``auto``). Cores are discovered (``discover``), never listed by hand.

Conventions: Y-up, right-handed, metres; triangle ids are row indices of the scene's face array.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import importlib.metadata
import logging
import pkgutil
import time
import typing
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np

from visibility.cancel import CancelToken, running_under
from visibility.ids import unique_ids
from visibility.scene import Scene
from visibility.scene_cache import Build
from visibility.viewcells import Viewcell

log = logging.getLogger(__name__)

Granularity = Literal["triangle", "object"]

#: What a core can promise about its PVS, from weakest to strongest guarantee against misses.
#: The conformance suite (``visibility.cores.checks``) holds each core to its promise.
PROMISES: dict[str, str] = {
    "aggressive": "reports only what it saw from sampled points; may miss what falls between "
                  "its samples and pixels (false negatives), rarely reports hidden triangles",
    "exact_at_pixel_samples": "exact visibility at one sample per cubemap pixel (its centre, or a "
                              "fixed point jittered inside it) along the cell's sides; misses "
                              "only what falls between samples",
    "conservative": "no false negatives for any eye position in the cell and any view "
                    "direction; over-reports by a measured share",
}
Promise = Literal["aggressive", "exact_at_pixel_samples", "conservative"]

#: The entry-point group through which another installed package registers cores.
ENTRY_POINT_GROUP = "pvs.cores"
#: Largest seed accepted (seeds travel as uint32).
MAX_SEED = 2**32 - 1


# --------------------------------------------------------------------------- parameters
def param(default: Any, *, help: str, unit: str = "", ge: float | None = None,
          le: float | None = None, choices: tuple[Any, ...] | None = None) -> Any:
    """A core parameter: a dataclass field whose metadata says its unit, range and help.

    ``CoreParams.validate`` checks every declared range and choice, so a core's parameters are
    described once, here, for the server's ``/cores`` and ``/docs``, the CLI's help and errors.
    """
    return field(default=default, metadata={"help": help, "unit": unit, "ge": ge, "le": le,
                                             "choices": choices})


@dataclass(frozen=True)
class ParamSpec:
    """What a parameter is: name, JSON type name, default, unit, one-line help, range, choices."""

    name: str
    type: str
    default: Any
    unit: str
    help: str
    minimum: float | None
    maximum: float | None
    choices: tuple[Any, ...] | None

    def as_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["choices"] = None if self.choices is None else list(self.choices)
        return d

    def describe(self) -> str:
        """One line: help, unit, range or choices and default (CLI help, error messages)."""
        bits = [self.help]
        if self.choices is not None:
            bits.append("one of " + ", ".join(map(str, self.choices)))
        elif self.minimum is not None or self.maximum is not None:
            lo = "-inf" if self.minimum is None else _num(self.minimum)
            hi = "inf" if self.maximum is None else _num(self.maximum)
            bits.append(f"{lo}..{hi}" + (f" {self.unit}" if self.unit else ""))
        elif self.unit:
            bits.append(self.unit)
        bits.append(f"default {self.default}")
        return "; ".join(bits)


def _num(x: float) -> str:
    """A bound as people write it: 4294967295, not 4.29497e+09."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _type_name(hint: Any) -> str:
    if typing.get_origin(hint) is Literal:
        return "string"
    return {bool: "boolean", int: "integer", float: "number", str: "string"}.get(hint, "string")


def param_specs(params_cls: type[CoreParams]) -> list[ParamSpec]:
    """The ``ParamSpec`` of every field of a ``CoreParams`` class, in declaration order."""
    return list(_param_specs(params_cls))


@functools.cache
def _param_specs(params_cls: type[CoreParams]) -> tuple[ParamSpec, ...]:
    # Type hints are resolved once per class: validate() runs on every request.
    hints = typing.get_type_hints(params_cls)
    out = []
    for f in dataclasses.fields(params_cls):
        md = f.metadata
        hint = hints.get(f.name, str)
        choices = md.get("choices")
        if choices is None and typing.get_origin(hint) is Literal:
            choices = typing.get_args(hint)
        out.append(ParamSpec(f.name, _type_name(hint), f.default, md.get("unit", ""),
                             md.get("help", ""), md.get("ge"), md.get("le"),
                             None if choices is None else tuple(choices)))
    return tuple(out)


@dataclass
class CoreParams:
    """Parameters every core understands. Cores extend this with their own ``param`` fields."""

    resolution: int = param(256, unit="px", ge=8, le=4096,
                            help="side of each cube face the core renders or rasterizes")
    granularity: Granularity = param(
        "triangle", choices=("triangle", "object"),
        help="triangle: the visible triangles; object: every triangle of each visible object")
    seed: int = param(0, ge=0, le=MAX_SEED, help="random seed: equal seeds give equal answers")

    def validate(self) -> None:
        """Raise ValueError naming the parameter when a value is outside its declared range,
        not one of its choices, not finite, or not an integer where one is declared."""
        for spec in param_specs(type(self)):
            value = getattr(self, spec.name)
            if spec.choices is not None:
                if value not in spec.choices:
                    raise ValueError(f"{spec.name} must be one of {list(spec.choices)}, "
                                     f"got {value!r}")
                continue
            if spec.type in ("integer", "number"):
                if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
                    raise ValueError(f"{spec.name} must be a number, got {value!r}")
                # Integers are finite; np.isfinite cannot even take one past int64 (a seed of
                # 2**64 must read as out of range, not as a numpy type error).
                if not isinstance(value, (int, np.integer)) and not np.isfinite(value):
                    raise ValueError(f"{spec.name} must be finite, got {value!r}")
                if spec.type == "integer" and int(value) != value:
                    raise ValueError(f"{spec.name} must be an integer, got {value!r}")
                lo, hi = spec.minimum, spec.maximum
                if (lo is not None and value < lo) or (hi is not None and value > hi):
                    raise ValueError(f"{spec.name} must be in [{_num(lo)}, {_num(hi)}]"
                                     f"{' ' + spec.unit if spec.unit else ''}, got {value!r}")

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def cache_key(self) -> str:
        """A stable string naming these parameters, for caches."""
        return ",".join(f"{k}={v}" for k, v in sorted(self.as_dict().items()))


# --------------------------------------------------------------------------- results
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


@dataclass(frozen=True)
class Fit:
    """How well a core fits a scene and cell size: ``ok`` (may it be used at all), ``score``
    (higher is a better choice for ``auto``; meaningful when ok) and ``why`` (one sentence)."""

    ok: bool
    score: float
    why: str


@dataclass(frozen=True)
class Cost:
    """What one computation is expected to take, for admission control.

    ``seconds``: wall time on one worker of the 2-core development machine (expect a factor of 2
    to 3 either way elsewhere: ``benchmarks/bench_admission.py`` prints estimate against
    measurement); ``peak_bytes``: scratch memory beyond the loaded scene, bytes; ``detail``:
    the quantities the estimate was made from (views, pixels, triangles...), for error answers.
    """

    seconds: float
    peak_bytes: int
    detail: dict[str, Any] = field(default_factory=dict, compare=False)

    def as_dict(self) -> dict[str, Any]:
        return {"seconds": float(self.seconds), "peak_bytes": int(self.peak_bytes),
                **self.detail}


# --------------------------------------------------------------------------- the core
class Core(ABC):
    """A from-region visibility algorithm.

    Subclasses set ``name``, ``Params`` (a ``CoreParams`` subclass of ``param`` fields),
    ``description`` and the declarations below, and implement ``_compute``; ``compute`` adds
    timing, validation and granularity.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    Params: ClassVar[type[CoreParams]] = CoreParams
    #: What the core guarantees about misses: a key of ``PROMISES``.
    promise: ClassVar[Promise] = "aggressive"
    #: The scenes and cell sizes the core is made for, one line (``/cores``, the README).
    fits: ClassVar[str] = "any triangle scene, any cell size"
    #: The parameter that trades error for time, and its levels in ascending cost (``pvs bench``).
    knob: ClassVar[str | None] = None
    knob_levels: ClassVar[tuple[Any, ...]] = ()
    #: Parameter sets besides the cheapest knob level that ``visibility.warmup`` runs too:
    #: code paths the small warm-up scenes reach only with them (each kernel specialization
    #: compiles at its first call, holding the GIL, and a server would stall on it).
    warm_params: ClassVar[tuple[dict[str, Any], ...]] = ()
    #: True when ``_compute_segment`` solves arbitrary segments, not only boxes.
    native_segments: ClassVar[bool] = False
    #: True when the core only fits 2.5D scenes (heightfield-like occluders).
    requires_2_5d: ClassVar[bool] = False
    #: Parameters that keep the conformance checks quick (``visibility.cores.checks``).
    check_params: ClassVar[dict[str, Any]] = {}
    #: Upper bound on the false-negative rate against the sampled ground truth that the
    #: conformance suite holds this core to, at ``check_params`` (conservative cores: 0).
    fn_bound: ClassVar[float] = 0.05
    #: Upper bound on the false-positive rate (share of the PVS that the sampled ground truth
    #: did not see) that the conformance suite holds this core to, at ``check_params``. The
    #: sampled ground truth is itself aggressive (it misses what falls between its samples and
    #: pixels), so an FP there is either a hidden triangle reported or a visible one the
    #: reference missed: a bound that catches gross over-inclusion, not a proof of exactness.
    fp_bound: ClassVar[float] = 0.25

    def make_params(self, **overrides: Any) -> CoreParams:
        """This core's parameter object with the given fields changed; unknown names raise."""
        known = {f.name for f in dataclasses.fields(self.Params)}
        unknown = set(overrides) - known
        if unknown:
            raise ValueError(f"unknown parameters for core {self.name!r}: {sorted(unknown)}; "
                             f"known: {sorted(known)}")
        params = self.Params(**overrides)
        params.validate()
        return params

    @classmethod
    def param_specs(cls) -> list[ParamSpec]:
        """What each parameter is (``ParamSpec``), in declaration order."""
        return param_specs(cls.Params)

    def supports(self, scene: Scene) -> tuple[bool, str]:
        """Whether this core can compute on the scene at all, and why not when it cannot."""
        return True, ""

    def scene_builds(self, scene: Scene) -> list[Build]:
        """The per-scene structures this core builds once per scene (``visibility.scene_cache
        .Build``), so a server can build them in the background when the scene loads instead
        of on a walker's first request. Default: none."""
        return []

    def suitability(self, scene: Scene, cell_size: float | None) -> tuple[float, str]:
        """(score, why) of choosing this core for ``scene`` at viewcells of ``cell_size``
        metres (None: unknown), given it fits. ``auto`` takes the highest score. By default a
        core made for 2.5D scenes (``requires_2_5d``) outranks general ones on the scenes it
        fits; cores that know their costs override this."""
        if self.requires_2_5d:
            from visibility.scene_analysis import scene_is_2_5d

            how = scene_is_2_5d(scene)[1]
            return 4.0, (f"2.5D scene ({how['source']}: {how['reason']}): a core made for "
                         "heightfield-like occluders")
        return 1.0, self.fits

    def fit(self, scene: Scene, cell_size: float | None = None) -> Fit:
        """Whether the core may be used on ``scene`` (``supports``; 2.5D-only cores only on
        2.5D scenes) and how well it suits it (``suitability``). Never raises: a failing
        check is a no with its reason."""
        try:
            if self.requires_2_5d:
                from visibility.scene_analysis import scene_is_2_5d

                flat, how = scene_is_2_5d(scene)
                if not flat:
                    return Fit(False, 0.0, f"needs a 2.5D scene; this one is not: "
                                           f"{how['reason']}")
            ok, why = self.supports(scene)
            if not ok:
                return Fit(False, 0.0, why)
            score, why = self.suitability(scene, cell_size)
            return Fit(True, float(score), why)
        except Exception as exc:  # a core's own check must not take a request down
            return Fit(False, 0.0, f"fit check failed: {type(exc).__name__}: {exc}")

    def estimate_cost(self, scene: Scene, cell: Viewcell, params: CoreParams) -> Cost:
        """The expected time and scratch memory of ``compute(scene, cell, params)`` (``Cost``),
        from the scene's size and the parameters only: cheap, never runs the core. This
        default prices one cubemap of ``params.resolution`` px faces rendered over every
        triangle (``visibility.ground_truth.estimate_sampling_cost`` with one viewpoint); cores
        override it with their own structure (views, segments, lists)."""
        from visibility.ground_truth import estimate_sampling_cost

        seconds, peak = estimate_sampling_cost(scene.n_triangles, params.resolution, 1)
        return Cost(seconds, peak, {"views": 1, "triangles": scene.n_triangles})

    @classmethod
    def describe(cls) -> dict[str, Any]:
        """Everything the core declares, as JSON-ready values (``GET /cores``)."""
        return {
            "name": cls.name, "description": cls.description, "promise": cls.promise,
            "promise_means": PROMISES[cls.promise], "fits": cls.fits,
            "params": [s.as_dict() for s in cls.param_specs()], "knob": cls.knob,
            "knob_levels": list(cls.knob_levels), "native_segments": cls.native_segments,
            "requires_2_5d": cls.requires_2_5d, "fn_bound": cls.fn_bound,
            "fp_bound": cls.fp_bound,
        }

    def compute(self, scene: Scene, cell: Viewcell, params: CoreParams | None = None, *,
                token: CancelToken | None = None) -> PVS:
        """The PVS of ``cell``: triangles visible from some point of the box (and stats).
        With ``token`` the computation stops at the core's next ``checkpoint()`` once it is
        cancelled or past its deadline (``ComputationCancelled``)."""
        params = params or self.make_params()
        params.validate()
        t0 = time.perf_counter()
        with running_under(token):
            ids, stats = self._compute(scene, cell, params)
        return self._finish(scene, params, ids, stats, time.perf_counter() - t0)

    def compute_segment(
        self, scene: Scene, p: np.ndarray, q: np.ndarray, params: CoreParams | None = None, *,
        token: CancelToken | None = None,
    ) -> PVS:
        """The PVS of the segment p -> q (metres): triangles visible from some point of it.

        Cores with ``native_segments`` solve it; the others answer a segment along a coordinate
        axis as the (degenerate) box it is, and raise ``SegmentNotSupported`` for a diagonal
        one, which no box describes.
        """
        a = np.asarray(p, dtype=np.float64).reshape(3)
        b = np.asarray(q, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise ValueError("segment end points must be finite")
        params = params or self.make_params()
        params.validate()
        t0 = time.perf_counter()
        with running_under(token):
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


# --------------------------------------------------------------------------- registry
_REGISTRY: dict[str, type[Core]] = {}
_discovered = False


class CoreImportError(ImportError):
    """A core package or entry point failed to import: never silently absent."""


def register(cls: type[Core]) -> type[Core]:
    """Class decorator: make a core available by its ``name``; checks its declarations."""
    if not cls.name:
        raise ValueError("a core needs a name")
    if cls.promise not in PROMISES:
        raise ValueError(f"core {cls.name!r}: promise must be one of {list(PROMISES)}, "
                         f"got {cls.promise!r}")
    names = {f.name for f in dataclasses.fields(cls.Params)}
    if cls.knob is not None and cls.knob not in names:
        raise ValueError(f"core {cls.name!r}: knob {cls.knob!r} is not one of its parameters")
    _REGISTRY[cls.name] = cls
    return cls


def unregister(name: str) -> None:
    """Remove a core from the registry (tests that register throwaway cores use it)."""
    _REGISTRY.pop(name, None)


def discover(refresh: bool = False) -> None:
    """Import every core: each subpackage of ``visibility.cores`` and each ``pvs.cores`` entry
    point (a module, or a ``Core`` subclass, which is then registered). Runs once unless
    ``refresh``. Raises ``CoreImportError`` naming the core and the cause when one fails."""
    global _discovered
    if _discovered and not refresh:
        return
    import visibility.cores as pkg

    for info in pkgutil.iter_modules(pkg.__path__):
        if not info.ispkg:
            continue
        modname = f"{pkg.__name__}.{info.name}"
        try:
            importlib.import_module(modname)
        except Exception as exc:
            raise CoreImportError(f"core package {info.name!r} ({modname}) failed to import: "
                                  f"{type(exc).__name__}: {exc}") from exc
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:
            raise CoreImportError(f"core entry point {ep.name!r} ({ep.value}) failed to "
                                  f"import: {type(exc).__name__}: {exc}") from exc
        if isinstance(obj, type) and issubclass(obj, Core) and obj.name not in _REGISTRY:
            register(obj)
    _discovered = True


def available_cores() -> list[str]:
    """Names of every registered core, sorted."""
    discover()
    return sorted(_REGISTRY)


def segment_cores() -> list[str]:
    """Names of the registered cores that solve arbitrary segments natively, sorted."""
    discover()
    return sorted(n for n, c in _REGISTRY.items() if c.native_segments)


def get_core(name: str) -> Core:
    """An instance of the core registered under ``name``; KeyError with the choices otherwise."""
    discover()
    try:
        return _REGISTRY[name]()
    except KeyError:
        raise KeyError(f"unknown core {name!r}; available: {sorted(_REGISTRY)}") from None


def describe_cores() -> list[dict[str, Any]]:
    """``Core.describe()`` of every registered core, sorted by name."""
    return [get_core(n).describe() for n in available_cores()]


# --------------------------------------------------------------------------- auto
#: The core name that asks for a core chosen per scene and cell size.
AUTO_CORE = "auto"


def all_fits(scene: Scene, cell_size: float | None = None) -> dict[str, Fit]:
    """``Core.fit`` of every registered core for ``scene`` at ``cell_size`` metres."""
    return {n: get_core(n).fit(scene, cell_size) for n in available_cores()}


def choose_core(scene: Scene, cell_size: float | None = None) -> tuple[str, str]:
    """The ``auto`` core for ``scene`` at viewcells of ``cell_size`` metres, and why: every
    core is asked (``Core.fit``) and the best-scoring one that fits wins (ties: by name).
    Raises LookupError when no registered core fits."""
    fits = all_fits(scene, cell_size)
    ok = sorted(((f.score, n) for n, f in fits.items() if f.ok), key=lambda t: (-t[0], t[1]))
    if not ok:
        raise LookupError(f"no registered core fits scene {scene.name!r}: " + "; ".join(
            f"{n}: {f.why}" for n, f in fits.items()))
    best = ok[0][1]
    others = ", ".join(f"{n} {s:g}" for s, n in ok[1:])
    why = f"{fits[best].why} (score {fits[best].score:g}" + (
        f"; others: {others})" if others else ")")
    return best, why


def core_fit_report(scene: Scene, cell_size: float | None = None) -> dict[str, Any]:
    """Every core's fit for ``scene`` and the ``auto`` choice, JSON-ready (``GET /cores``)."""
    fits = all_fits(scene, cell_size)
    try:
        name, why = choose_core(scene, cell_size)
        auto: dict[str, Any] | None = {"core": name, "why": why}
    except LookupError:
        auto = None
    return {"cell_size": cell_size,
            "cores": [{"core": n, "ok": f.ok, "score": f.score, "why": f.why}
                      for n, f in fits.items()],
            "auto": auto}
