"""The perf map of the project's numba kernels (``benchmarks.perf_kernels``): every compiled
kernel named at its entry point, ranges in address order; a clear refusal without perf."""

from __future__ import annotations

import numpy as np

import benchmarks.perf_kernels as pk
from visibility.raster.pyramid import PyramidLayout, build_pyramid


def test_the_map_names_a_compiled_kernel_at_its_entry_point(tmp_path):
    lay = PyramidLayout.of(4, 4)
    invd = np.ones((1, 4, 4))
    build_pyramid(invd, lay.heights, lay.widths, lay.offsets, lay.empty(1))
    path = pk.write_perf_map(tmp_path / "perf.map")
    rows = [ln.split(" ", 2) for ln in path.read_text().splitlines()]
    starts = [int(a, 16) for a, _, _ in rows]
    sizes = [int(s, 16) for _, s, _ in rows]
    assert starts == sorted(starts) and all(s > 0 for s in sizes)
    named = {name for _, _, name in rows}
    assert "pyramid.build_pyramid" in named
    addresses = {addr for addr, name in pk.kernel_symbols() if name == "pyramid.build_pyramid"}
    assert addresses and addresses <= set(starts)


def test_without_perf_it_says_what_to_install(monkeypatch, capsys):
    monkeypatch.setattr(pk.shutil, "which", lambda _: None)
    assert pk.main(["--scene", "village", "--triangles", "2000"]) == 2
    assert "linux-perf" in capsys.readouterr().err
