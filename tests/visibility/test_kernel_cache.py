"""The kernel cache is keyed by the kernels' sources: an edit to any of them starts a new one."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from visibility import kernel_cache
from visibility.kernel_cache import KEEP, source_digest

ROOT = Path(__file__).resolve().parents[2]


def _tree(root: Path, body: str) -> None:
    for pkg in kernel_cache.PACKAGES:
        (root / pkg / "sub").mkdir(parents=True, exist_ok=True)
        (root / pkg / "__init__.py").write_text("")
    (root / "visibility" / "sub" / "callee.py").write_text(body)


def test_digest_follows_every_source_file(tmp_path):
    _tree(tmp_path, "def f():\n    return 1\n")
    d0 = source_digest(tmp_path)
    assert source_digest(tmp_path) == d0
    # An edit to a callee alone (the case numba's own check misses) changes the key.
    _tree(tmp_path, "def f():\n    return 2\n")
    d1 = source_digest(tmp_path)
    assert d1 != d0
    # So does a new file, and a file's move; files outside the packages do not count.
    (tmp_path / "client" / "new.py").write_text("")
    d2 = source_digest(tmp_path)
    assert d2 != d1
    (tmp_path / "client" / "new.py").rename(tmp_path / "client" / "sub" / "new.py")
    assert source_digest(tmp_path) != d2
    (tmp_path / "README.md").write_text("x")
    (tmp_path / "client" / "sub" / "new.py").rename(tmp_path / "client" / "new.py")
    assert source_digest(tmp_path) == d2


def _cache_dir_in_child(base: Path) -> str:
    code = "import visibility, numba; print(numba.config.CACHE_DIR)"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(base), "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, check=True,
                         capture_output=True, text=True, timeout=120)
    return out.stdout.strip()


def test_a_process_caches_under_the_digest_and_old_folders_are_pruned(tmp_path):
    stale = [tmp_path / f"src-{k:016x}" for k in range(KEEP + 2)]
    for k, p in enumerate(stale):
        p.mkdir()
        os.utime(p, (1_000_000 + k, 1_000_000 + k))
    other = tmp_path / "not-a-digest"
    other.mkdir()
    got = _cache_dir_in_child(tmp_path)
    assert got == str(tmp_path / f"src-{source_digest()}")
    left = sorted(p.name for p in tmp_path.iterdir())
    # The folder in use and the KEEP - 1 newest others stay; what is not ours is left alone.
    assert left == sorted([Path(got).name, "not-a-digest"] + [p.name for p in stale[-(KEEP - 1):]])


def test_without_numba_cache_dir_numba_keeps_its_default(tmp_path):
    code = "import visibility, numba; print(repr(numba.config.CACHE_DIR))"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, check=True,
                         capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "''"


def test_cached_kernels_counts_numba_index_files(tmp_path):
    folder = tmp_path / "src-0000000000000000"
    folder.mkdir()
    assert kernel_cache.cached_kernels(folder) == 0
    (folder / "core_abc").mkdir()
    (folder / "core_abc" / "raster.f-12.py311.nbi").write_bytes(b"")
    (folder / "core_abc" / "raster.f-12.py311.1.nbc").write_bytes(b"")
    assert kernel_cache.cached_kernels(folder) == 1
    assert kernel_cache.cached_kernels(tmp_path / "missing") == 0
