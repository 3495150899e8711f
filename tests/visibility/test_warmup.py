"""``pvs warmup``: every core is compiled, and a warm cache makes it quick."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from visibility.cores.base import available_cores
from visibility.warmup import groups

ROOT = Path(__file__).resolve().parents[2]


def test_every_registered_core_is_in_a_group():
    names = [n for g in groups() for n in g]
    assert set(available_cores()) <= set(names)
    assert len(names) == len(set(names))  # none compiled twice


def test_the_command_runs_every_group_on_the_suites_cache():
    # The test command ran it before pytest, so here every kernel loads from the cache.
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-m", "pvs_cli", "warmup"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    for g in groups():
        assert "+".join(g) in out.stdout
    assert "total (wall)" in out.stdout
