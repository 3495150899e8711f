"""The viewer's JavaScript mirrors of the headless client, run by node on the same inputs as the
Python they mirror: face shading (``visibility.raster.shading.shade_colors``), the camera basis
(``look_rotation``), the sphere mesh (trimesh's icosphere, as ``client.render`` draws spheres),
the budget's eviction order (``client.budget.choose_evictions``), walkthrough poses
(``client.walkthrough``) and what a token is (``protocol.auth.is_token``, before the page sends
one)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import trimesh

from client.budget import choose_evictions
from client.walkthrough import walkthrough_from_dict
from protocol.auth import is_token
from visibility.raster.camera import look_rotation
from visibility.raster.shading import shade_colors

SCRIPT = Path(__file__).with_name("mirrors.mjs")
#: Tokens and not-tokens: lengths 15, 16, 512 and 513, each allowed character, others.
TOKENS = ["a" * 15, "a" * 16, "b" * 512, "c" * 513, "AZaz09-._~+AZaz09", "A" * 16 + " ",
          "A" * 16 + "\n", "tok/en0123456789ab", "tok=en0123456789ab", "tok%en0123456789ab",
          "é" * 16, ""]


def test_js_mirrors_agree_with_python():
    rng = np.random.default_rng(5)
    tris = rng.uniform(-50, 50, size=(400, 3, 3)) + [1e4, 0, -3e3]
    tris[0] = tris[0, 0]  # a degenerate face: ambient only
    colors = rng.integers(0, 256, size=(400, 3), dtype=np.uint8)
    looks = np.concatenate([rng.normal(size=(40, 3)), [[0, 1, 0], [0, -2, 0], [1e-12, 1, 0]]])
    ids = rng.permutation(1000)[:300]
    cents = rng.uniform(-20, 20, size=(300, 3))
    walk = {"poses": [{"t": float(t), "position": rng.uniform(-5, 5, 3).tolist(),
                       "forward": rng.normal(size=3).tolist()}
                      for t in np.cumsum(rng.uniform(0.05, 0.3, 12))]}
    times = [-1.0, *rng.uniform(0, 3, 20).tolist(), 99.0]
    inputs = {"shade": {"tris": tris.reshape(-1, 9).tolist(), "colors": colors.tolist()},
              "look": looks.tolist(),
              "evict": {"ids": ids.tolist(), "centroids": cents.tolist(),
                        "protect": ids[:120].tolist(), "eye": [1.0, 1.7, -2.0], "budget": 100},
              "walk": {"data": walk, "times": times}, "tokens": TOKENS}
    node = shutil.which("node") or shutil.which("nodejs")
    assert node, "node is not installed (scripts/setup.sh installs nodejs)"
    run = subprocess.run([node, str(SCRIPT)], input=json.dumps(inputs), capture_output=True,
                         text=True, timeout=60, check=True)
    out = json.loads(run.stdout)

    want = shade_colors(tris, colors)
    got = np.array(out["shade"], dtype=np.uint8)
    # Float64 in both; numpy's dot may sum in another order: at most one level, rarely.
    assert np.abs(got.astype(int) - want).max() <= 1
    assert np.mean(np.any(got != want, axis=1)) < 0.01
    for f, rows in zip(looks, out["look"], strict=True):
        assert np.allclose(rows, look_rotation(f), atol=1e-12)
    ico = trimesh.creation.icosphere(subdivisions=2)
    ours = np.array(out["icosphere"]).reshape(-1, 3, 3)
    theirs = np.asarray(ico.vertices)[np.asarray(ico.faces)]
    key = lambda t: sorted(map(tuple, np.round(t, 9)))  # noqa: E731 - same faces, any order
    assert sorted(map(key, ours)) == sorted(map(key, theirs))
    want_evict = choose_evictions(ids, cents, ids[:120], np.array([1.0, 1.7, -2.0]), 100)
    assert out["evict"] == want_evict.tolist()
    w = walkthrough_from_dict(walk)
    for t, (pos, fwd) in zip(times, out["poses"], strict=True):
        p, f = w.pose_at(t)
        assert np.allclose(pos, p, atol=1e-12) and np.allclose(fwd, f, atol=1e-12)
    assert out["isToken"] == [is_token(t) for t in TOKENS]
    assert sum(out["isToken"]) == 3
