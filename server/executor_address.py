"""The ``executor`` setting's two forms, parsed: ``local`` or ``dask://HOST:PORT[?scenes=load]``.

A leaf (nothing of the server imported), so ``server.settings`` validates the setting and
``server.executor`` makes the executor from the same parse without importing each other.
"""

from __future__ import annotations

import re

LOCAL = "local"
_DASK = re.compile(r"^dask://(?P<host>[A-Za-z0-9_.\-]+|\[[0-9A-Fa-f:.]+\]):(?P<port>\d{1,5})/?"
                   r"(\?scenes=(?P<scenes>scatter|load))?$")


def _parse(executor: str) -> re.Match | None:
    text = executor.strip()
    if text == LOCAL:
        return None
    m = _DASK.match(text)
    if m is None or not 0 < int(m["port"]) <= 65535:
        raise ValueError(f"executor must be 'local' or 'dask://HOST:PORT' (optionally "
                         f"'?scenes=load'), got {executor!r}")
    return m


def scheduler_address(executor: str) -> str | None:
    """The Dask scheduler address (``tcp://host:port``) an ``executor`` setting names, or None
    for ``"local"``; ValueError for anything else."""
    m = _parse(executor)
    return None if m is None else f"tcp://{m['host']}:{int(m['port'])}"


def workers_load_scenes(executor: str) -> bool:
    """Whether a ``dask://...?scenes=load`` setting asks the workers to load each scene
    themselves (the same scene file path on every machine, or the same generator) instead of
    receiving it scattered from the server."""
    m = _parse(executor)
    return m is not None and m["scenes"] == "load"
