"""A request's core and parameters, resolved once: name -> core, ``auto`` -> the decision
(``server.calibration``), raw values -> validated ``CoreParams``; a ``CoreChoice`` from then on.

HTTP routes, WebSocket handshakes and ``precompute`` call ``Resolver.resolve`` before loading
the scene (a named core is resolved there, so a bad name or parameter never loads a scene) and,
for ``auto`` only, once more with the loaded scene. Nothing downstream converts or checks the
parameters again.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from pydantic import ConfigDict, TypeAdapter, ValidationError

from server.calibration import AutoCalibration
from server.catalog import LoadedScene
from server.settings import Settings
from visibility.cores.base import AUTO_CORE, Core, CoreParams, get_core
from visibility.cores.base import all_fits as registry_fits
from visibility.cores.base import choose_core as registry_choose_core
from visibility.scene import Scene


class UnknownCoreError(LookupError):
    """No core registered under this name (or none fits, for ``auto``)."""


@dataclass(frozen=True)
class CoreChoice:
    """A request's core, its validated parameters and why that core ("requested", "server
    default" or the ``auto`` decision's reason)."""

    core: Core
    params: CoreParams
    why: str


@lru_cache(maxsize=256)
def _adapter(hint: Any) -> TypeAdapter:
    return TypeAdapter(hint, config=ConfigDict(allow_inf_nan=False))


def resolve_core(name: str) -> Core:
    """The core registered as ``name``; UnknownCoreError otherwise."""
    try:
        return get_core(name)
    except KeyError as exc:
        raise UnknownCoreError(exc.args[0] if exc.args else f"unknown core {name!r}") from None


def coerce_params(core: Core, raw: Mapping[str, Any]) -> CoreParams:
    """``core``'s parameters from loosely typed values (query strings, JSON), validated.

    Each value is converted to its dataclass field's type ("32" -> 32, "true" -> True; NaN and
    fractional ints rejected), then ``core.make_params`` checks names and ranges. Raises
    ValueError with a readable message.
    """
    fields = {f.name for f in dataclasses.fields(core.Params)}
    unknown = sorted(set(raw) - fields)
    if unknown:
        raise ValueError(f"unknown parameters for core {core.name!r}: {unknown}; known: "
                         f"{sorted(fields)}")
    hints = typing.get_type_hints(core.Params)
    values = {}
    for k, v in raw.items():
        try:
            values[k] = _adapter(hints[k]).validate_python(v)
        except ValidationError as exc:
            msg = exc.errors(include_url=False)[0]["msg"]
            raise ValueError(f"parameter {k}={v!r}: {msg}") from None
    try:
        return core.make_params(**values)
    except TypeError as exc:
        raise ValueError(str(exc)) from None


# What fits and what ``auto`` picks without a calibration is the cores' own declaration
# (``Core.fit``, ``visibility.cores.base.choose_core``); these wrappers give the server's errors.
def core_fits(core: Core, scene: Scene, cell_size: float | None = None) -> tuple[bool, str]:
    """Whether ``core`` may be used on ``scene`` and why not (``Core.fit``)."""
    fit = core.fit(scene, cell_size)
    return fit.ok, fit.why


def offered_cores(scene: Scene, cell_size: float | None = None) -> list[str]:
    """Registered cores that fit ``scene`` (``Core.fit``), sorted."""
    return sorted(n for n, f in registry_fits(scene, cell_size).items() if f.ok)


def choose_core(scene: Scene, cell_size: float | None = None) -> tuple[str, str]:
    """The best declared fit for ``scene`` at ``cell_size`` metres and why
    (``visibility.cores.base.choose_core``); UnknownCoreError when none fits. ``auto`` itself
    decides with ``server.calibration.decide_auto``, which falls back on this."""
    try:
        return registry_choose_core(scene, cell_size)
    except LookupError as exc:
        raise UnknownCoreError(str(exc)) from None


class Resolver:
    """Resolves requests' cores and parameters for one server (``settings.core``,
    ``core_params``, ``first_core``, ``first_params``; ``auto`` through ``calibration``)."""

    def __init__(self, settings: Settings, calibration: AutoCalibration | None = None) -> None:
        self.settings = settings
        self.calibration = calibration or AutoCalibration(settings)
        self._first: CoreChoice | None = None

    def named(self, core_name: str | None = None,
              params: Mapping[str, Any] | None = None) -> CoreChoice:
        """A named core (default ``settings.core``) and its validated parameters; requests
        for the default core start from ``settings.core_params``. Raises UnknownCoreError
        (also for ``auto``, which needs a scene), ValueError (bad parameters)."""
        name = core_name or self.settings.core
        if name == AUTO_CORE:
            raise UnknownCoreError("the auto core is chosen per scene: resolve it with the "
                                   "loaded scene")
        return self._choice(name, params, "requested" if core_name else "server default")

    def resolve(self, core_name: str | None, params: Mapping[str, Any] | None = None,
                loaded: LoadedScene | None = None) -> CoreChoice | None:
        """The request's choice: a named core at once (``named``); ``auto`` decided for
        ``loaded`` at its grid's cell size (``AutoCalibration.decide``), None while ``loaded``
        is None. Raises UnknownCoreError, ValueError."""
        if (core_name or self.settings.core) != AUTO_CORE:
            return self.named(core_name, params)
        if loaded is None:
            return None
        decision = self.calibration.decide(loaded.scene, float(loaded.grid.cell_size))
        if decision.core is None:
            raise UnknownCoreError(decision.why)
        return self._choice(decision.core, {**decision.params, **(params or {})}, decision.why)

    def first(self) -> CoreChoice:
        """The core and parameters of first answers (``settings.first_core``,
        ``first_params``), resolved once; raises UnknownCoreError, ValueError for bad
        settings."""
        if self._first is None:
            core = resolve_core(self.settings.first_core)
            self._first = CoreChoice(core, coerce_params(core, self.settings.first_params),
                                     "first answers")
        return self._first

    def _choice(self, name: str, params: Mapping[str, Any] | None, why: str) -> CoreChoice:
        core = resolve_core(name)
        raw = dict(self.settings.core_params) if name == self.settings.core else {}
        raw.update(params or {})
        return CoreChoice(core, coerce_params(core, raw), why)
