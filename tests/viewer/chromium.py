"""Headless Chromium for the viewer's tests and its README screenshot: Debian's ``chromium`` and
``chromium-driver`` (``scripts/setup.sh`` installs them) driven by selenium, WebGL on SwiftShader
(software), the browser console kept for the tests to read. Also a walk's data: URL, the page's
state, and the canvas as an image.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import time
from collections.abc import Callable
from typing import Any

import numpy as np

#: Where Debian puts the browser and its driver.
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


def start_chromium(width: int = 900, height: int = 700) -> Any:
    """A headless Chromium (selenium WebDriver) with software WebGL and a device pixel ratio of
    1; AssertionError naming what to install when the browser or its driver is missing."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser = os.environ.get("PVS_CHROMIUM") or shutil.which("chromium") or CHROMIUM
    driver = os.environ.get("PVS_CHROMEDRIVER") or shutil.which("chromedriver") or CHROMEDRIVER
    for path, pkg in ((browser, "chromium"), (driver, "chromium-driver")):
        assert os.path.exists(path), f"{path} missing: install Debian's {pkg} (scripts/setup.sh)"
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                f"--window-size={width},{height}", "--force-device-scale-factor=1",
                "--disable-gpu-sandbox", "--mute-audio", "--no-first-run"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    # An explicit driver path: selenium then never tries to download one.
    return webdriver.Chrome(options=opts, service=Service(driver))


def console_errors(driver: Any) -> list[str]:
    """The browser console's errors since the last call (SEVERE entries)."""
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def walk_data_url(walk: Any) -> str:
    """A ``data:`` URL holding a ``client.walkthrough.Walkthrough`` as its JSON file."""
    text = json.dumps(walk.to_dict())
    return "data:application/json;base64," + base64.b64encode(text.encode()).decode()


def state(driver: Any) -> dict | None:
    """``window.pvsViewer.state()``, or None before the viewer exists."""
    return driver.execute_script("return window.pvsViewer ? window.pvsViewer.state() : null")


def wait_state(driver: Any, pred: Callable[[dict], bool], timeout: float = 120.0) -> dict:
    """Poll the page's state until ``pred(state)``; AssertionError with the last state (and
    the console's errors) after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    st = None
    while time.monotonic() < deadline:
        st = state(driver)
        if st is not None and pred(st):
            return st
        time.sleep(0.2)
    raise AssertionError(f"viewer state not reached in {timeout} s: {st}; console: "
                         f"{console_errors(driver)}")


def snapshot(driver: Any, position: Any, forward: Any, t: float | None = None) -> dict:
    """Freeze the page and draw one frame at a pose (and scene time ``t``, seconds):
    {"image": (H, W, 3) uint8, "ids": held triangle ids, "spheres": held sphere ids, "cell"}."""
    from PIL import Image

    args = [[float(x) for x in position], [float(x) for x in forward]]
    if t is not None:
        args.append(float(t))
    snap = driver.execute_script(
        "return window.pvsViewer.snapshot(...arguments)", *args)
    png = base64.b64decode(snap["png"].split(",", 1)[1])
    return {"image": np.array(Image.open(io.BytesIO(png)).convert("RGB")),
            "ids": np.asarray(snap["ids"], dtype=np.int64),
            "spheres": np.asarray(snap["spheres"], dtype=np.int64), "cell": snap["cell"]}
