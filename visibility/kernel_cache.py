"""numba's on-disk kernel cache, keyed by the source of every kernel it may hold.

numba checks a cached kernel against its own file's time stamp only, yet a kernel's machine
code holds every njit function it calls, inlined or linked, from other files too: after an edit
to a callee alone (``from_segment/envelope.py`` under ``raster.py``'s pixel loop) the caller
would load its old code from the cache and run it. So the cache lives in a folder named for a
digest of the kernels' packages' sources (``visibility/`` and ``client/``), and any edit starts
a fresh one. Only when ``NUMBA_CACHE_DIR`` is set (``scripts/env.sh`` sets it; without it numba
caches beside each source file, and this module leaves that alone); the ``KEEP`` folders used
last stay, older ones are removed.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
from pathlib import Path

#: Digest folders kept under ``NUMBA_CACHE_DIR``: the ones used most recently.
KEEP = 4
#: Packages whose ``.py`` files hold numba kernels or what they call.
PACKAGES = ("visibility", "client")
_PREFIX = "src-"

_keyed: str | None = None
log = logging.getLogger(__name__)


def source_digest(root: Path | None = None) -> str:
    """Hex digest (16 characters) of the path and bytes of every ``.py`` file of ``PACKAGES``
    under ``root`` (the repository root by default)."""
    root = root or Path(__file__).resolve().parent.parent
    h = hashlib.blake2b(digest_size=8)
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode())
            h.update(b"\0")
            h.update(path.read_bytes())
    return h.hexdigest()


def key_numba_cache() -> str | None:
    """Point numba's cache at ``$NUMBA_CACHE_DIR/src-<digest>`` (before any kernel is
    decorated) and prune digest folders beyond the ``KEEP`` latest. Returns that folder, or
    None when ``NUMBA_CACHE_DIR`` is not set. Idempotent within a process; child processes
    key themselves from the same environment."""
    global _keyed
    base = os.environ.get("NUMBA_CACHE_DIR")
    if not base:
        return None
    if _keyed is None:
        import numba

        folder = Path(base) / f"{_PREFIX}{source_digest()}"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            os.utime(folder)
        except OSError:
            # A read-only cache (a mounted image layer) still serves what it holds; where numba
            # cannot write it falls back to its own locations.
            log.warning("numba cache %s is not writable", folder)
        numba.config.CACHE_DIR = str(folder)
        _keyed = str(folder)
        _prune(Path(base))
    return _keyed


def cached_kernels(folder: str | Path | None = None) -> int | None:
    """How many kernels the keyed cache folder (``folder``, by default this process's) holds
    (numba's index files), or None when numba caches beside the sources (no
    ``NUMBA_CACHE_DIR``). 0 after an edit to the kernels' sources until ``pvs warmup`` or
    first use compiles them."""
    folder = folder if folder is not None else key_numba_cache()
    if folder is None:
        return None
    try:
        return sum(1 for _ in Path(folder).rglob("*.nbi"))
    except OSError:
        return 0


def _prune(base: Path) -> None:
    """Remove digest folders under ``base`` beyond the ``KEEP`` most recently used."""
    try:
        old = sorted((p for p in base.iterdir() if p.is_dir() and p.name.startswith(_PREFIX)),
                     key=lambda p: p.stat().st_mtime, reverse=True)[KEEP:]
    except OSError:
        return
    for p in old:
        shutil.rmtree(p, ignore_errors=True)
