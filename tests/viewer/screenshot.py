"""A screenshot of the browser viewer on a scene, as a person sees it (the README's).

Starts the real server (``pvs serve``) on a free port, opens ``/viewer`` in headless Chromium
(``tests/viewer/chromium.py``, the viewer tests' harness: Debian's chromium and
chromium-driver, software WebGL), waits until the eye's cell has streamed and drawn, optionally
moves the eye, and saves the window::

    python -m tests.viewer.screenshot --scene lavaducts --out docs/viewer_lavaducts.png \\
        --eye 10.6,1.7,-7.1 --forward 1,-0.1,0.3
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from pvs_cli import DEFAULT_SCENES_DIR, _free_port, wait_until_healthy
from tests.viewer.chromium import console_errors, start_chromium, wait_state

REPO = Path(__file__).resolve().parents[2]


def _vec(text: str) -> list[float]:
    vals = [float(x) for x in text.split(",")]
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,z, got {text!r}")
    return vals


def _cell_point(url: str, scene: str, cell: str) -> list[float]:
    """The walk point of ``cell`` (an id, or "middle") of ``scene`` on the server at ``url``."""
    import httpx

    listing = httpx.get(f"{url}/scenes/{scene}/cells", timeout=600).json()
    cells = listing["cells"]
    if cell == "middle":
        (x0, _, z0), (x1, _, z1) = listing["grid"]["bounds"]
        mid = ((x0 + x1) / 2, (z0 + z1) / 2)
        return min(cells, key=lambda c: (c["walk"][0] - mid[0]) ** 2
                   + (c["walk"][2] - mid[1]) ** 2)["walk"]
    return next(c for c in cells if c["id"] == int(cell))["walk"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="lavaducts")
    ap.add_argument("--core", default="sampling")
    ap.add_argument("--scenes", default=str(DEFAULT_SCENES_DIR), help="folder of scene files")
    ap.add_argument("--out", default="docs/viewer.png")
    ap.add_argument("--cell", help="start in this cell (an id, or 'middle': the one nearest the "
                                   "grid's centre) instead of the first")
    ap.add_argument("--eye", type=_vec, help="eye position x,y,z (default: the page's start)")
    ap.add_argument("--forward", type=_vec, help="view direction x,y,z")
    ap.add_argument("--size", default="1280x720", help="window size WxH")
    ap.add_argument("--fov", type=float, default=70.0)
    args = ap.parse_args(argv)

    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    server = subprocess.Popen([sys.executable, "-m", "pvs_cli", "serve", "--port", str(port),
                               "--scenes", args.scenes], cwd=REPO, stdout=subprocess.DEVNULL,
                              stderr=subprocess.STDOUT)
    width, height = (int(v) for v in args.size.split("x"))
    driver = None
    try:
        if not wait_until_healthy(url, server):
            raise SystemExit("the server did not start")
        driver = start_chromium(width, height)
        driver.get(f"{url}/viewer?scene={args.scene}&core={args.core}&fov={args.fov}")
        here = lambda s: s["cell"] is not None and s["cell"] in s["complete"]  # noqa: E731
        wait_state(driver, here, timeout=600)
        eye = args.eye
        if args.cell is not None:
            eye = _cell_point(url, args.scene, args.cell)
        if eye:
            forward = args.forward or [0.0, 0.0, 1.0]
            driver.execute_script("window.pvsViewer.controls.set(arguments[0], arguments[1])",
                                  eye, forward)
            time.sleep(0.5)
            wait_state(driver, here, timeout=600)
        time.sleep(1.5)  # a few frames, and the overlay's refresh
        st = wait_state(driver, lambda s: s["framesNonEmpty"] > 5)
        driver.save_screenshot(args.out)
        print(f"{args.out}: {args.scene}, cell {st['cell']}, {st['held']} triangles held, "
              f"{st['bytes']} bytes received; console errors: {console_errors(driver)}")
    finally:
        if driver is not None:
            driver.quit()
        server.terminate()
        server.wait(20)
    return 0


if __name__ == "__main__":
    sys.exit(main())
