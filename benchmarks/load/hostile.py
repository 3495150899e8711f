"""The hostile client of the load benchmark's abuse mode (``--hostile``): a flood of expensive
HTTP PVS requests (``POST /scenes/{scene}/pvs``, every box different so nothing is shared
through the cache, parameters far above the defaults), from its own process and from another
loopback address than the walkers', so a per-client cap keyed by address applies to it and not
to them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import multiprocessing
import random
from collections.abc import Callable, Iterator

import httpx
import numpy as np

#: Expensive parameters of the hostile client's requests, per core (``--hostile-params``): far
#: above the defaults, within each parameter's declared range so they pass validation.
HOSTILE_PARAMS: dict[str, dict] = {"sampling": {"resolution": 2048, "samples": 100_000},
                                   "from_segment": {"resolution": 2048},
                                   "cos": {"resolution": 2048}}
#: The hostile client's source address: another loopback address than the walkers' 127.0.0.1.
HOSTILE_ADDRESS = "127.0.0.2"
#: The statuses the hostile's answers are counted by; anything else counts as "other".
HOSTILE_STATUSES = (200, 422, 429, 503)


def hostile_box(cells: np.ndarray, rng: random.Random) -> list[list[float]]:
    """A random box near a random cell of ``cells`` ((k, 2, 3) [min, max]): shifted by up to
    half the cell and shrunk by up to half, so no two requests ask the same question."""
    lo, hi = cells[rng.randrange(len(cells))]
    size = hi - lo
    shift = np.array([rng.uniform(-0.5, 0.5) for _ in range(3)]) * size * np.array([1, 0, 1])
    scale = rng.uniform(0.5, 1.0)
    centre = 0.5 * (lo + hi) + shift
    half = 0.5 * size * scale
    return [(centre - half).tolist(), (centre + half).tolist()]


async def hostile_flood(url: str, scene: str, core: str, params: dict, cells: np.ndarray,
                        concurrency: int, timeout: float, pause: float, seed: int,
                        stop: Callable[[], bool], started: Callable[[], None]) -> dict:
    """Flood ``POST /scenes/{scene}/pvs`` with expensive ad-hoc boxes from ``HOSTILE_ADDRESS``
    until ``stop()``: ``concurrency`` requests at once, each abandoned after ``timeout`` s and
    replaced by a new one; after a refused connection or a 429/503 a loop waits ``pause`` s
    and sends again. Returns the answers counted by status and what went unanswered."""
    counts: dict = {"sent": 0, **{str(c): 0 for c in HOSTILE_STATUSES}, "other": 0,
                    "refused": 0, "timeout": 0, "unfinished": 0, "other_statuses": {}}
    inflight = [0]
    rng = random.Random(seed)
    transport = httpx.AsyncHTTPTransport(local_address=HOSTILE_ADDRESS)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    async with httpx.AsyncClient(base_url=url, transport=transport, timeout=timeout,
                                 limits=limits) as http:
        async def loop() -> None:
            while True:
                body = {"box": hostile_box(cells, rng), "core": core, "params": params}
                counts["sent"] += 1
                inflight[0] += 1
                try:
                    r = await http.post(f"/scenes/{scene}/pvs", json=body)
                except httpx.TimeoutException:
                    counts["timeout"] += 1
                    continue
                except httpx.TransportError:
                    counts["refused"] += 1
                    await asyncio.sleep(pause)
                    continue
                finally:
                    inflight[0] -= 1
                if r.status_code in HOSTILE_STATUSES:
                    counts[str(r.status_code)] += 1
                else:
                    counts["other"] += 1
                    other = counts["other_statuses"]
                    other[str(r.status_code)] = other.get(str(r.status_code), 0) + 1
                if r.status_code in (429, 503):
                    await asyncio.sleep(pause)

        tasks = [asyncio.create_task(loop()) for _ in range(concurrency)]
        started()
        while not stop():
            await asyncio.sleep(0.1)
        counts["unfinished"] = inflight[0]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    return counts


def _hostile_main(url: str, scene: str, core: str, params: dict, cells: np.ndarray,
                  concurrency: int, timeout: float, pause: float, seed: int, stop_ev: object,
                  started_ev: object, out: object) -> None:
    """The hostile client's process: flood until ``stop_ev`` is set, put the counts on
    ``out``."""
    out.put(asyncio.run(hostile_flood(url, scene, core, params, cells, concurrency, timeout,
                                      pause, seed, stop_ev.is_set, started_ev.set)))


@contextlib.contextmanager
def hostile_client(url: str, scene: str, core: str, params: dict, cells: np.ndarray,
                   concurrency: int, timeout: float, pause: float, seed: int) -> Iterator[dict]:
    """Run ``hostile_flood`` (its own process, ``spawn``: this process runs threads) for the
    ``with`` block, over the cell boxes ``cells`` ((k, 2, 3) metres); the dict it yields holds
    its counts once the block has ended."""
    ctx = multiprocessing.get_context("spawn")
    stop_ev, started_ev, out = ctx.Event(), ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_hostile_main, daemon=True, args=(
        url, scene, core, params, np.ascontiguousarray(cells), concurrency, timeout, pause,
        seed, stop_ev, started_ev, out))
    proc.start()
    counts: dict = {}
    try:
        if not started_ev.wait(120):
            raise RuntimeError("the hostile client did not start")
        yield counts
    finally:
        stop_ev.set()
        try:
            counts.update(out.get(timeout=60))
        except Exception as exc:  # a lost count must not lose the walkers' numbers
            counts["error"] = f"{type(exc).__name__}: {exc}"
        proc.join(10)
        if proc.is_alive():
            proc.kill()


def hostile_answers_text(h: dict) -> str:
    """The hostile's answers by status, one line."""
    if "error" in h and "sent" not in h:
        return f"not counted: {h['error']}"
    bits = [f"{c}: {h.get(str(c), 0)}" for c in HOSTILE_STATUSES]
    other = h.get("other_statuses") or {}
    bits.append(f"other: {h.get('other', 0)}" + (f" ({json.dumps(other)})" if other else ""))
    bits += [f"refused: {h.get('refused', 0)}", f"gave up: {h.get('timeout', 0)}",
             f"unanswered at stop: {h.get('unfinished', 0)}"]
    return ", ".join(bits)
