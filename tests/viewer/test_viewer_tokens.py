"""The viewer against a server with tokens, in headless Chromium (the real server on loopback,
as ``test_viewer_browser``): the page and its modules load without a token; a token in the URL
fragment leaves the address bar and the page walks and draws with it (``Authorization`` on its
HTTP calls, the ``pvs.bearer.`` subprotocol on ``/ws``); without a token the page asks for one
and uses the one typed; a wrong token is refused in words on the page. The server's log,
captured at DEBUG throughout, never holds a token.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from client.metrics import ssim
from client.render import OffscreenRenderer
from tests.conftest import serving
from tests.viewer.chromium import (
    console_errors,
    snapshot,
    start_chromium,
    state,
    wait_state,
    walk_data_url,
)
from tests.viewer.fixed_walk import SCENE, SIZE
from visibility.raster.shading import BACKGROUND

#: The server's token: "+" and "~" too, which a careless reading of the fragment would mangle
#: ("+" read as a space).
TOKEN = "viewer+token~0123456789.abc_-"
#: A token of the right form that the server does not know.
WRONG = "wrong-viewer-token-0123456789"
#: Loggers of the server's side whose lines are captured (the ones ``test_auth`` checks).
SERVER_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access", "websockets.server", "server")
#: Loggers of this test's own clients, which are not the server's log.
CLIENT_LOGGERS = ("selenium", "urllib3", "httpx", "httpcore", "websockets.client")
TIMEOUT = 120.0


class LogLines(logging.Handler):
    """Every record reaching it, as ``name message`` lines."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if not record.name.startswith(CLIENT_LOGGERS):
            self.lines.append(f"{record.name} {record.getMessage()}")

    def text(self) -> str:
        """All lines so far."""
        return "\n".join(self.lines)


@pytest.fixture(scope="module")
def served(settings) -> Iterator[tuple[str, LogLines]]:
    """The real server with one token, its log at DEBUG captured: (base URL, the log)."""
    with serving(settings, tokens=[TOKEN], log_level="debug") as (url, _app):
        # After uvicorn's logging set-up (the server's construction), which replaces handlers.
        log = LogLines()
        levels = {name: logging.getLogger(name).level for name in SERVER_LOGGERS}
        hosts = [logging.getLogger(n) for n in ("", "uvicorn", "uvicorn.access")]
        for name in SERVER_LOGGERS:
            logging.getLogger(name).setLevel(logging.DEBUG)
        for logger in hosts:  # uvicorn's loggers do not propagate to the root
            logger.addHandler(log)
        try:
            yield url, log
        finally:
            for logger in hosts:
                logger.removeHandler(log)
            for name, level in levels.items():
                logging.getLogger(name).setLevel(level)


@pytest.fixture
def driver() -> Iterator:
    d = start_chromium()
    try:
        yield d
    finally:
        d.quit()


def wait_for(what: str, probe: Callable[[], bool], timeout: float = TIMEOUT) -> None:
    """Poll ``probe`` until true; AssertionError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if probe():
            return
        time.sleep(0.2)
    raise AssertionError(f"{what}: not reached in {timeout} s")


def token_form(driver) -> tuple[bool, str]:
    """(whether the token form shows, what it says)."""
    form = driver.find_element("id", "token-form")
    return form.is_displayed(), driver.find_element("id", "token-why").text


def held_token(driver) -> str | None:
    """The token the page keeps (sessionStorage)."""
    return driver.execute_script("return sessionStorage.getItem('pvs.token')")


def assert_no_token_logged(log: LogLines) -> None:
    """The server logged requests, and neither token."""
    text = log.text()
    assert "GET /viewer/" in text and "GET /viewer/main.js" in text, text[-2000:]
    for token in (TOKEN, WRONG):
        assert token not in text


def test_token_in_the_fragment_walks_and_draws(served, walk, rooms, driver):
    """``/viewer?...#token=``: the fragment survives the redirect to ``/viewer/``, the token
    leaves the address bar, and the page walks the whole walk and draws what the headless
    client draws at its last pose."""
    url, log = served
    w, cells = walk
    driver.get(f"{url}/viewer?scene={SCENE}&core=sampling&fov=90&aa=0&size={SIZE}x{SIZE}"
               f"&walk={walk_data_url(w)}#token={TOKEN}")
    st = wait_state(driver, lambda s: s["replayDone"] and cells[-1] in s["complete"],
                    timeout=TIMEOUT)
    assert "token" not in driver.current_url and held_token(driver) == TOKEN
    assert st["connected"] and st["connections"] == 1 and st["core"] == "sampling"
    assert st["localErrors"] == [] and st["serverErrors"] == []
    assert st["framesNonEmpty"] > 10 and st["bytes"] > 0 and st["held"] > 0
    done = set(cells) & set(st["complete"])
    assert cells[-1] in done and len(done) >= 2, (cells, st["complete"])
    assert not token_form(driver)[0]
    pos, fwd = w.positions[-1], w.forwards[-1]
    snap = snapshot(driver, pos, fwd)
    assert snap["cell"] == cells[-1]
    assert np.mean(np.any(snap["image"] != BACKGROUND, axis=2)) > 0.5
    renderer = OffscreenRenderer(SIZE, SIZE, yfov_deg=90.0)
    try:
        ids = snap["ids"]
        frame = renderer.render(rooms.triangles(ids), rooms.colors[ids], pos, fwd)
    finally:
        renderer.close()
    assert ssim(snap["image"], frame.color) >= 0.95
    assert console_errors(driver) == []
    assert "WebSocket /ws" in log.text()  # the page's session is in the log, its token not
    assert_no_token_logged(log)


def test_without_a_token_the_page_asks_for_one_and_uses_it(served, driver):
    """No token: the page shows the form (the scene listing answered 401), and nothing
    starts; the token typed there is kept and the page walks with it."""
    url, log = served
    driver.get(f"{url}/viewer/?scene={SCENE}&core=sampling&size=160x120")
    wait_for("the token form", lambda: token_form(driver)[0])
    assert "needs a token" in token_form(driver)[1]
    assert "needs a token" in driver.find_element("id", "status").text
    assert state(driver) is None and held_token(driver) is None
    # The browser reports the refused request (and nothing else) on its console.
    assert all("401" in e for e in console_errors(driver))
    driver.find_element("id", "token-input").send_keys(TOKEN)
    driver.find_element("css selector", "#token-form button").click()
    st = wait_state(driver, lambda s: s["cell"] is not None and s["cell"] in s["complete"],
                    timeout=TIMEOUT)
    assert st["connected"] and st["serverErrors"] == [] and held_token(driver) == TOKEN
    assert not token_form(driver)[0] and "token" not in driver.current_url
    assert_no_token_logged(log)


def test_a_wrong_token_is_refused_in_words(served, driver):
    """A token the server does not know: the page says it was refused, forgets it and asks
    for another; the address bar no longer holds it."""
    url, log = served
    driver.get(f"{url}/viewer/?scene={SCENE}#token={WRONG}")
    wait_for("the token form", lambda: token_form(driver)[0])
    shown, why = token_form(driver)
    assert "refused this token" in why and "401" in why
    assert "refused this token" in driver.find_element("id", "status").text
    assert state(driver) is None and held_token(driver) is None
    assert WRONG not in driver.current_url and "token" not in driver.current_url
    # A typed non-token is caught on the page, before any request.
    driver.find_element("id", "token-input").send_keys("short")
    driver.find_element("css selector", "#token-form button").click()
    wait_for("the form's complaint", lambda: "not a token" in token_form(driver)[1])
    assert held_token(driver) is None
    assert_no_token_logged(log)
