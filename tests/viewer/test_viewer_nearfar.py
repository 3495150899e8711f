"""Near-far streams in the browser: the real server with ``near_far`` on streams the small
generated ``city`` (radii of 15 and 30 m, so that much of it is far) as near geometry plus a
far cubemap with per-pixel range per cell; the page
composes them as ``client.compose.compose_frame`` does (the cubemap behind, depth-tested by its
range, the intermediate band morphed toward the cubemap centre), and at two poses of a walk its
frame matches the Python composition of the same triangles and cubemap (SSIM >= 0.95).

What differs by design: the viewer morphs per vertex on the GPU (float32) and shades a face
from its unmorphed corners; the Python composition morphs in float64, shades the morphed face
and, by default, splits long triangles in the band first (``max_edge``: 0 here, as the viewer
does not split)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from client.compose import compose_frame
from client.metrics import ssim
from client.render import OffscreenRenderer
from client.walkthrough import generate_walkthrough
from protocol.cubemap import decode_cubemap, encode_cubemap
from tests.conftest import SMALL_GENERATED_TRIANGLES, serving
from tests.viewer.chromium import (
    console_errors,
    snapshot,
    start_chromium,
    wait_state,
    walk_data_url,
)
from visibility import nearfar
from visibility.generators import make_scene
from visibility.raster.shading import BACKGROUND
from visibility.viewcells import ViewcellGrid

SCENE, SIZE = "city", 256


@pytest.fixture(scope="module")
def city():
    scene = make_scene(SCENE, triangles=SMALL_GENERATED_TRIANGLES, seed=0)
    return scene, ViewcellGrid.for_scene(scene)


@pytest.fixture(scope="module")
def walked(settings, city) -> Iterator[tuple]:
    _, grid = city
    walk = generate_walkthrough(grid, duration=3.0, fps=10, seed=2)
    cells = [grid.cell_of(p) for p in walk.positions]
    with serving(settings, near_far=True, near_far_r1=15.0, near_far_r2=30.0) as (url, app):
        driver = start_chromium()
        try:
            driver.get(f"{url}/viewer?scene={SCENE}&core=sampling&fov=90&aa=0"
                       f"&size={SIZE}x{SIZE}&walk={walk_data_url(walk)}")
            st = wait_state(driver, lambda s: s["replayDone"] and set(cells) <= set(s["complete"]))
            yield driver, st, walk, cells, app.state.server.settings.near_far_config()
        finally:
            driver.quit()


def test_composed_frames_match_the_python_composition(walked, city):
    driver, st, walk, cells, cfg = walked
    scene, grid = city
    assert st["localErrors"] == [] and st["serverErrors"] == []
    renderer = OffscreenRenderer(SIZE, SIZE, yfov_deg=90.0)
    try:
        ids = np.asarray(driver.execute_script(
            "return Array.from(window.pvsViewer.store.heldIds())"), dtype=np.int64)
        for i in (0, len(walk) - 1):
            pos = walk.positions[i]
            # The cubemap the server baked for the cell, through the wire's range encoding.
            centre = grid.boxes[cells[i]].mean(axis=0)
            cube = nearfar.bake_cubemap(scene, centre, cfg)
            cube = decode_cubemap(encode_cubemap(cells[i], cube.center, cube.colors,
                                                 cube.ranges, cfg.r1, cfg.r2))

            def composed(fwd, ids, pos=pos, cube=cube):
                return compose_frame(renderer, scene.triangles(ids), scene.colors[ids], cube,
                                     pos, fwd, cfg.r1, cfg.r2, morph=True, points=False,
                                     max_edge=0)

            # Of eight level views, the one that sees most of the far field (down a street).
            views = [np.array([np.sin(a), 0.0, np.cos(a)]) for a in np.arange(8) * np.pi / 4]
            fwd = max(views, key=lambda f: np.mean(composed(f, ids).source == 2))
            snap = snapshot(driver, pos, fwd)
            image = snap["image"]
            # The same triangles as the page held when it drew (prefetched cells may arrive).
            assert snap["cell"] == cells[i]
            ids = snap["ids"]
            want = composed(fwd, ids)
            # The far field is there: the cubemap fills what the near geometry leaves.
            sky = np.all(want.color == BACKGROUND, axis=2)
            from_cube = np.mean(want.source == 2)
            assert from_cube > 0.05, from_cube
            score = ssim(image, want.color)
            differ = int(np.count_nonzero(np.any(image != want.color, axis=2)))
            gap = np.abs(image.astype(int) - want.color).max(axis=2)
            print(f"pose {i}: SSIM {score:.4f}, {differ} pixels differ ({np.sum(gap > 8)} by "
                  f"more than 8 levels), "
                  f"{from_cube:.0%} from the cubemap, {sky.mean():.0%} sky")
            assert score >= 0.95, (i, score)
            # Without its cubemap the page's frame would not match.
            bare = renderer.render(scene.triangles(ids), scene.colors[ids], pos, fwd)
            assert ssim(image, bare.color) < score
    finally:
        renderer.close()
    assert console_errors(driver) == []
