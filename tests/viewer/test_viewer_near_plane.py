"""The viewer draws with the near plane the welcome states (``welcome.near_plane``, the one the
server's answers assume), in a real browser: headless Chromium opening ``/viewer`` of the real
server on loopback, whose default core is ``from_segment`` with its own near plane (12.5 cm,
not the viewer's built-in 5 cm), so only a page that reads the welcome draws with it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.conftest import serving
from tests.viewer.chromium import console_errors, start_chromium, wait_state

NEAR = 0.125


@pytest.fixture(scope="module")
def server(settings) -> Iterator[str]:
    with serving(settings, core="from_segment", core_params={"near": NEAR}) as (url, _app):
        yield url


def test_the_page_draws_with_the_welcomes_near_plane(server):
    driver = start_chromium()
    try:
        driver.get(f"{server}/viewer?scene=rooms&size=64x64")
        st = wait_state(driver, lambda s: s["connected"] and s["core"] is not None)
        assert st["core"] == "from_segment"
        near, stated, cube = driver.execute_script(
            "const v = window.pvsViewer; return [v.renderer.camera.near, v.welcome.near_plane,"
            " v.renderer.camera.projectionMatrix.elements[14]]")
        assert stated == NEAR and near == NEAR
        # The projection was rebuilt with it: -2 n f / (f - n) for three's perspective.
        far = driver.execute_script("return window.pvsViewer.renderer.camera.far")
        assert cube == pytest.approx(-2.0 * NEAR * far / (far - NEAR), rel=1e-6)
        assert console_errors(driver) == []
    finally:
        driver.quit()
