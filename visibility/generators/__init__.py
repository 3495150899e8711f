"""Deterministic procedural scenes, by name.

``make_scene(name, triangles, seed)`` builds one; ``GENERATORS`` maps each name to its
``"module:function"``, imported only when used, so a generator whose module is missing (or
fails to import) is simply unavailable: ``available_generators()`` leaves it out and
``make_scene`` raises KeyError for it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from visibility.scene import Scene

GENERATORS: dict[str, str] = {
    "city": "visibility.generators.city:generate",
    "village": "visibility.generators.village:generate",
    "rooms": "visibility.generators.rooms:generate",
    "stress": "visibility.generators.stress:generate",
    "grass": "visibility.generators.grass:generate",
    "swaying_grass": "visibility.generators.grass:generate_swaying",
    "spheres": "visibility.generators.spheres:generate",
}

#: Default size (triangles) per generator: what the server serves. For "spheres" the value is
#: passed on as that generator's ``triangles`` argument like any other.
DEFAULT_TRIANGLES: dict[str, int] = {
    "city": 100_000,
    "village": 100_000,
    "rooms": 100_000,
    "stress": 10_000,
    "grass": 200_000,
    "swaying_grass": 100_000,
    "spheres": 2_000,
}


def _resolve(name: str) -> Callable[..., Scene]:
    """The generator function for ``name``; KeyError when unknown or not importable."""
    if not isinstance(name, str) or name not in GENERATORS:
        raise KeyError(f"unknown generator {name!r}; known: {sorted(GENERATORS)}")
    module_name, _, func_name = GENERATORS[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise KeyError(f"generator {name!r} is unavailable: cannot import {module_name} "
                       f"({exc})") from exc
    func = getattr(module, func_name, None)
    if not callable(func):
        raise KeyError(f"generator {name!r} is unavailable: {module_name} has no {func_name}()")
    return func


def available_generators() -> list[str]:
    """Names of the generators whose module imports and defines its function, sorted."""
    out = []
    for name in GENERATORS:
        try:
            _resolve(name)
        except KeyError:
            continue
        out.append(name)
    return sorted(out)


def make_scene(name: str, triangles: int | None = None, seed: int = 0, **kw) -> Scene:
    """Build the generated scene ``name``.

    Parameters
    ----------
    name : a key of GENERATORS.
    triangles : the triangle budget; None uses the generator's own default.
    seed : random seed; the same arguments give bit-identical arrays.
    **kw : passed to the generator (``floors=2`` for "rooms", ``offset=`` for "stress").

    Raises KeyError for an unknown or unavailable name, ValueError for bad arguments.
    """
    func = _resolve(name)
    if triangles is None:
        return func(seed=seed, **kw)
    return func(triangles=triangles, seed=seed, **kw)
