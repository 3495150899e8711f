"""A bad server message or a dropped connection: the page says so and reconnects, never hangs.

A WebSocket relay (real sockets, ``websockets``) sits between headless Chromium and the real
server's ``/ws`` and spoils the page's first session once it is streaming: it sends a frame
that is no frame, or cuts the TCP connection without a close. Later sessions pass untouched.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator

import pytest
import websockets
from websockets.asyncio.client import connect
from websockets.asyncio.server import serve

from client.walkthrough import generate_walkthrough
from tests.conftest import SMALL_GENERATED_TRIANGLES, serving
from tests.viewer.chromium import console_errors, start_chromium, state, wait_state, walk_data_url
from visibility.generators import make_scene
from visibility.viewcells import ViewcellGrid

#: Binary frames relayed before the first session is spoiled.
SPOIL_AFTER = 5


class FaultyRelay:
    """Relays ``ws://127.0.0.1:PORT/ws`` to ``upstream``; its first session gets ``fault``
    ("bad_frame" or "drop") after ``SPOIL_AFTER`` binary frames. Runs on its own loop thread."""

    def __init__(self, upstream: str, fault: str, on_demand: bool = False) -> None:
        self.upstream = upstream
        self.fault = fault
        #: The first session is cut when the test calls :meth:`drop`, not after frames.
        self.on_demand = on_demand
        self._first_page = None
        self.sessions = 0
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._run, name="faulty-relay", daemon=True)

    def __enter__(self) -> FaultyRelay:
        self.thread.start()
        assert self.ready.wait(10), "the relay did not start"
        return self

    def __exit__(self, *exc: object) -> None:
        self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(10)

    def drop(self) -> None:
        """Cuts the first session's TCP connection without a close frame, now."""
        assert self._first_page is not None, "no session to drop"
        self.loop.call_soon_threadsafe(self._first_page.transport.abort)

    def _run(self) -> None:
        self.loop.run_until_complete(self._main())

    async def _main(self) -> None:
        self.stop = asyncio.Event()
        async with serve(self._session, "127.0.0.1", 0, compression=None) as server:
            self.port = server.sockets[0].getsockname()[1]
            self.ready.set()
            await self.stop.wait()

    async def _session(self, page) -> None:
        self.sessions += 1
        spoil = self.sessions == 1
        if spoil and self.on_demand:
            self._first_page = page
            spoil = False
        async with connect(self.upstream, compression=None, max_size=None) as up:

            async def to_server() -> None:
                async for msg in page:
                    await up.send(msg)

            async def to_page() -> None:
                frames = 0
                async for msg in up:
                    await page.send(msg)
                    frames += isinstance(msg, bytes)
                    if spoil and frames == SPOIL_AFTER:
                        if self.fault == "bad_frame":
                            await page.send(b"not a PVS frame, though as long as a header" * 2)
                        else:
                            page.transport.abort()  # no close frame: the page sees 1006
                            return

            tasks = [asyncio.ensure_future(t()) for t in (to_server, to_page)]
            try:
                await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            except websockets.ConnectionClosed:
                pass
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)


@pytest.fixture(scope="module")
def server(settings) -> Iterator[str]:
    with serving(settings) as (url, _app):
        yield url


@pytest.mark.parametrize("fault, says", [
    ("bad_frame", "bad message from the server: bad magic"),
    ("drop", "connection lost (close 1006)"),
])
def test_page_reports_the_fault_and_reconnects(server, fault, says):
    upstream = server.replace("http://", "ws://") + "/ws"
    with FaultyRelay(upstream, fault) as relay:
        driver = start_chromium()
        try:
            driver.get(f"{server}/viewer?scene=rooms&core=sampling&size=160x120"
                       f"&ws=ws://127.0.0.1:{relay.port}/ws")
            # The message is on screen, then a second session streams the eye's cell again.
            st = wait_state(driver, lambda s: s["connections"] >= 2 and s["connected"]
                            and s["cell"] is not None and s["cell"] in s["complete"], 120)
            errors = [h for h in st["history"] if h.startswith("error:")]
            assert errors and says in errors[0] and "reconnecting in 1 s" in errors[0]
            assert relay.sessions == 2 and st["connections"] == 2
            assert st["status"].startswith("connected") and st["held"] > 0
            drawn = st["framesNonEmpty"]
            wait_state(driver, lambda s: s["framesNonEmpty"] > drawn + 5, 30)
            # The browser's own note of the aborted socket is the only console error allowed.
            assert [e for e in console_errors(driver) if "WebSocket" not in e] == []
        finally:
            driver.quit()


def test_page_says_when_its_modules_do_not_load(settings, tmp_path):
    """An incomplete three.js install (its module there, the core it imports not) leaves no
    page at "loading": the page says what is missing."""
    (tmp_path / "three.module.js").write_text("export * from './three.core.js';\n")
    with serving(settings, viewer_three_dir=tmp_path) as (url, _app):
        driver = start_chromium()
        try:
            driver.get(f"{url}/viewer?scene=rooms")
            status = driver.find_element("id", "status")
            deadline = time.monotonic() + 30
            while "did not load" not in status.text and time.monotonic() < deadline:
                time.sleep(0.1)
            assert "the viewer's modules did not load" in status.text
            assert "npm ci" in status.text
        finally:
            driver.quit()


def test_a_replay_cut_by_a_dropped_connection_resumes_where_it_was(server):
    """The walkthrough's clock does not go back to its first pose after a reconnect: the
    second session starts at the pose the first one had reached. The connection is cut once
    the page's replay clock has run a second, however long the first cell took (busy CI)."""
    grid = ViewcellGrid.for_scene(make_scene("rooms", triangles=SMALL_GENERATED_TRIANGLES,
                                             seed=0))
    walk = generate_walkthrough(grid, duration=8.0, fps=10, seed=4)
    upstream = server.replace("http://", "ws://") + "/ws"
    with FaultyRelay(upstream, "drop", on_demand=True) as relay:
        driver = start_chromium()
        try:
            driver.get(f"{server}/viewer?scene=rooms&core=sampling&size=160x120"
                       f"&ws=ws://127.0.0.1:{relay.port}/ws&walk={walk_data_url(walk)}")
            samples: list[tuple[int, float]] = []
            dropped = False
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                st = state(driver)
                if st is not None and st["replayAt"] is not None:
                    samples.append((st["connections"], st["replayAt"]))
                    if not dropped and st["replayAt"] > 1.0:
                        relay.drop()
                        dropped = True
                    if st["connections"] >= 2 and st["replayDone"]:
                        break
                time.sleep(0.05)
            first = [t for c, t in samples if c == 1]
            second = [t for c, t in samples if c >= 2]
            assert relay.sessions == 2 and first and second, samples[-5:]
            assert max(first) > 0.5, "the drop must come after the replay's clock started"
            assert min(second) >= max(first) - 0.05, (max(first), min(second))
            assert second[-1] >= 8.0 - 1e-6  # and it plays to the end
        finally:
            driver.quit()
