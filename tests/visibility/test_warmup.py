"""``pvs warmup``: every core is compiled, and a warm cache makes it quick."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.visibility.real_scenes import SHARED_SCENES
from visibility.cores.base import available_cores
from visibility.warmup import groups

ROOT = Path(__file__).resolve().parents[2]


def test_every_registered_core_is_in_a_group():
    names = [n for g in groups() for n in g]
    assert set(available_cores()) <= set(names)
    assert len(names) == len(set(names))  # none compiled twice


def test_the_command_runs_every_group_on_the_suites_cache():
    # The test command (scripts/test.sh) ran it before pytest and kept its report
    # (PVS_WARMUP_REPORT): read that one. Outside it, run the command (every kernel loads
    # from the cache then).
    report = os.environ.get("PVS_WARMUP_REPORT")
    if report and Path(report).is_file():
        stdout = Path(report).read_text()
    else:
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        out = subprocess.run([sys.executable, "-m", "pvs_cli", "warmup"], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr
        stdout = out.stdout
    for g in groups():
        assert "+".join(g) in stdout
    assert "total (wall)" in stdout


def test_the_warm_up_takes_the_large_scene_paths_and_the_coarse_pass():
    from visibility.cores.base import get_core
    from visibility.raster.hierarchy import MIN_TRIANGLES
    from visibility.viewcells import Viewcell
    from visibility.warmup import _scenes

    scenes = _scenes(dynamic=False)
    assert any(s.n_triangles >= MIN_TRIANGLES for s, _ in scenes)
    cos = get_core("cos")
    city, box = scenes[0]
    for extra in cos.warm_params:
        pvs = cos.compute(city, Viewcell(box), cos.make_params(resolution=64, **extra))
        assert pvs.stats["coarse_tiles"] > 0


#: Run in a fresh process: each core (the built-in ones: no test registers its own there) once
#: on a real scene's cell, then the kernels numba had to compile (not load from the cache the
#: warm-up filled).
_COMPILED_ON_A_REAL_SCENE = """
import gc, sys, numpy as np
from numba.core.registry import CPUDispatcher
from visibility.cores.base import available_cores, get_core
from visibility.loaders import load_scene
from visibility.viewcells import Viewcell, ViewcellGrid
scene = load_scene(sys.argv[1])
grid = ViewcellGrid.for_scene(scene)
c = grid.cell(len(grid) // 2).center
for name in available_cores():
    core = get_core(name)
    knob = {core.knob: min(core.knob_levels)} if core.knob else {}
    core.compute(scene, Viewcell(np.stack([c - 0.15, c + 0.15])), core.make_params(**knob))
print(sorted(f"{d.py_func.__module__}.{d.py_func.__qualname__}" for d in gc.get_objects()
             if isinstance(d, CPUDispatcher) and d.py_func.__module__.startswith("visibility")
             and sum(d._cache_misses.values())))
"""


def test_after_the_warm_up_a_real_scene_compiles_no_kernel():
    # A kernel compiled at its first real use holds the GIL for seconds to minutes: a server
    # stalls every walker meanwhile. Lyon: a loaded file (its own array types) over the scene
    # hierarchy's threshold.
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", _COMPILED_ON_A_REAL_SCENE,
                          str(SHARED_SCENES / "lyon_vilo3d.glb")],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"
