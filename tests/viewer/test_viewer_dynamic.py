"""Dynamic scenes in the browser: moving triangles come with their keyframes, spheres with a
centre per keyframe (``protocol.keyframes``); the page draws them at a scene time as the
headless client does (``client.store`` interpolation, ``client.render`` icospheres), so its frame
at two scene times matches pyrender's of the same triangles and spheres (SSIM >= 0.95), and the
two times differ."""

from __future__ import annotations

import numpy as np
import pytest

from client.metrics import ssim
from client.render import OffscreenRenderer, scene_sphere_centers, sphere_triangles
from tests.conftest import serving
from tests.viewer.chromium import console_errors, snapshot, start_chromium, wait_state
from visibility.generators import make_scene

SIZE = 192
SIZES = {"swaying_grass": 4000, "spheres": 64}


@pytest.mark.parametrize("name", sorted(SIZES))
def test_moving_geometry_matches_the_headless_client_at_two_times(settings, name):
    scene = make_scene(name, triangles=SIZES[name], seed=0)
    assert scene.is_dynamic
    with serving(settings, generated=SIZES) as (url, _app):
        driver = start_chromium()
        renderer = OffscreenRenderer(SIZE, SIZE, yfov_deg=90.0)
        try:
            driver.get(f"{url}/viewer?scene={name}&core=sampling&fov=90&aa=0&size={SIZE}x{SIZE}")
            st = wait_state(driver, lambda s: s["cell"] is not None and s["cell"] in s["complete"]
                            and s["framesNonEmpty"] > 3)
            assert st["localErrors"] == [] and st["serverErrors"] == []
            eye, fwd = np.array(st["eye"]), np.array(st["forward"])
            fwd = fwd + [0.0, -0.35, 0.0]  # look down a little: the grass or the spheres
            images = []
            for t in (0.4, 1.3):
                snap = snapshot(driver, eye, fwd, t)
                ids, sids = snap["ids"], snap["spheres"]
                tris, cols = scene.triangles(ids, t=t), scene.colors[ids]
                if len(sids):
                    st_, sc = sphere_triangles(scene_sphere_centers(scene, t)[sids],
                                               scene.sphere_radii[sids], scene.sphere_colors[sids])
                    tris, cols = np.concatenate([tris, st_]), np.concatenate([cols, sc])
                want = renderer.render(tris, cols, eye, fwd)
                score = ssim(snap["image"], want.color)
                differ = int(np.count_nonzero(np.any(snap["image"] != want.color, axis=2)))
                print(f"{name} t={t}: SSIM {score:.4f}, {differ} pixels differ, "
                      f"{len(ids)} triangles, {len(sids)} spheres")
                assert score >= 0.95, (t, score)
                images.append(snap["image"])
            # Something moved between the two times.
            assert np.count_nonzero(np.any(images[0] != images[1], axis=2)) > 50
            assert console_errors(driver) == []
        finally:
            renderer.close()
            driver.quit()
