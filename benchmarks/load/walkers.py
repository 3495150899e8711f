"""The walkers of a load run: protocol clients (``client.session.Session``: receiving and
accounting, not rendering) replaying their walkthroughs at real-time pacing.

Per frame a walker records whether the pose's cell was complete one frame interval after the
pose was sent (else a stall), the delivery latency, and the answer its cell held when drawn
(``cell_begin.answer``, one of ``protocol.messages.ANSWERS``; ``STALLED`` for a stall,
``NO_CELL`` for a pose in no cell). Every
``sample_every``-th frame of each answer (the first one included) keeps the eye, the view and
the triangle ids the walker held, to be drawn after the run (``benchmarks.load.frames``).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

import numpy as np

from benchmarks.common import rss_bytes
from benchmarks.load.scenes import walk_velocities
from client.session import Session, SessionError
from client.walkthrough import Walkthrough

#: The answer of a frame whose cell was not complete one frame interval after its pose.
STALLED = "stalled"
#: The answer of a frame whose pose lies in no cell (a walk kept off the ground).
NO_CELL = "no_cell"


@dataclass
class Sample:
    """A frame kept for drawing: eye (3,) and forward (3,) in metres, the ids the walker held
    as a packed bit mask over the scene's triangles (``np.packbits``), and its answer."""

    eye: np.ndarray
    forward: np.ndarray
    held: np.ndarray
    answer: str


@dataclass
class ClientStats:
    """What one walker saw over a run."""

    frames: int = 0
    stalls: int = 0
    latencies: list[float] = field(default_factory=list)
    bytes: int = 0
    duplicates: int = 0
    dropped: int = 0
    first_cell_timeouts: int = 0
    #: Triangles the walker received (``Session.triangles_received``) and held at the end.
    triangles_received: int = 0
    triangles_held: int = 0
    #: Triangles received by the answer of the stream that brought them.
    triangles_by_answer: dict[str, int] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    #: Frames by the answer their cell held when drawn (``STALLED`` when none in time).
    answers: dict[str, int] = field(default_factory=dict)
    samples: list[Sample] = field(default_factory=list)


def held_mask(ids: np.ndarray, n: int) -> np.ndarray:
    """The ids ``ids`` (k,) over ``n`` triangles as a packed bit mask (ceil(n / 8) uint8)."""
    m = np.zeros(n, dtype=bool)
    m[np.asarray(ids, dtype=np.int64)] = True
    return np.packbits(m)


async def one_client(url: str, scene: str, core: str, params: dict, walk: Walkthrough,
                     cell_of: list[int | None], stats: ClientStats, *, budget: int | None,
                     progressive: bool | None, first_cell_timeout: float, grace: float,
                     fps: float, sample_every: int) -> None:
    """Walk ``walk`` (its poses' cells ``cell_of``) on the server at ``url`` at real-time
    pacing, recording into ``stats``. The first cell is waited for before the clock starts
    (up to ``first_cell_timeout`` s; then the walker walks anyway and it is counted); stalled
    frames' cells are awaited ``grace`` s after the walk, then count as never delivered."""
    pos, t, fwd = walk.positions, walk.t, walk.forwards
    vel = walk_velocities(walk)
    pending: list[asyncio.Task] = []
    per_answer: dict[str, int] = {}
    try:
        s = await Session.connect(url, scene, core, params, budget=budget, timeout=120,
                                  progressive=progressive)
    except (SessionError, OSError, TimeoutError) as exc:
        stats.errors.append(f"connect: {exc}")
        return
    n_tri = s.welcome.scene.triangles
    try:
        await s.send_pose(0, 0.0, pos[0], fwd[0], vel[0])
        if cell_of[0] is not None:
            try:
                await s.wait_cell(cell_of[0], first_cell_timeout)
            except TimeoutError:
                # A flooded server may never get to it: walk anyway, so the frames still count.
                stats.first_cell_timeouts += 1
        t0 = time.perf_counter()
        frame = 1.0 / fps

        async def late(cell: int, sent: float) -> None:
            try:
                await s.wait_cell(cell, None)
                stats.latencies.append(time.perf_counter() - sent)
            except SessionError:
                stats.latencies.append(float("inf"))

        for i in range(1, len(walk)):
            await asyncio.sleep(max(0.0, t0 + t[i] - t[0] - time.perf_counter()))
            sent = time.perf_counter()
            await s.send_pose(i, float(t[i]), pos[i], fwd[i], vel[i])
            stats.frames += 1
            cell = cell_of[i]
            if cell is None or s.is_complete(cell):
                stats.latencies.append(0.0)
            else:
                try:
                    await s.wait_cell(cell, frame)
                    stats.latencies.append(time.perf_counter() - sent)
                except TimeoutError:
                    stats.stalls += 1
                    pending.append(asyncio.create_task(late(cell, sent)))
            if cell is None:
                answer = NO_CELL
            else:
                held = s.cells.get(cell) if s.is_complete(cell) else None
                answer = (held.answer if held is not None else None) or STALLED
            stats.answers[answer] = stats.answers.get(answer, 0) + 1
            k = per_answer.get(answer, 0)
            per_answer[answer] = k + 1
            if sample_every > 0 and k % sample_every == 0:
                stats.samples.append(Sample(pos[i].copy(), fwd[i].copy(),
                                            held_mask(s.store.ids, n_tri), answer))
        if pending:
            # A cell the walker has left may never come (the server drops prefetch work no
            # walker is heading for): after a grace period it counts as never delivered.
            _, late_ones = await asyncio.wait(pending, timeout=grace)
            for task in late_ones:
                task.cancel()
            stats.latencies += [float("inf")] * len(late_ones)
    except SessionError as exc:
        stats.errors.append(str(exc))
    finally:
        stats.bytes = s.bytes_received
        stats.duplicates = s.duplicates
        stats.dropped = s.dropped
        stats.triangles_received = s.triangles_received
        stats.triangles_by_answer = dict(s.triangles_by_answer)
        stats.triangles_held = s.held
        stats.errors += [f"{e.code}: {e.message}" for e in s.errors]
        stats.errors += s.local_errors
        await s.close()


async def run_clients(urls: list[str], pids: list[int], scene: str, core: str, params: dict,
                      walks: list[Walkthrough], *, budget: int | None,
                      progressive: bool | None, first_cell_timeout: float, grace: float,
                      fps: float, sample_every: int
                      ) -> tuple[list[ClientStats], int, float]:
    """One walker per walk (walker i on ``urls[i % len(urls)]``), their starts staggered over a
    second as real clients arrive: their stats, the servers' peak RSS (bytes, summed over
    ``pids``, sampled every 0.25 s) and the wall time, seconds."""
    stats = [ClientStats() for _ in walks]
    peak = [sum(rss_bytes(p) for p in pids)]

    async def sample_rss() -> None:
        while True:
            peak[0] = max(peak[0], sum(rss_bytes(p) for p in pids))
            await asyncio.sleep(0.25)

    sampler = asyncio.create_task(sample_rss())
    t0 = time.perf_counter()

    async def delayed(i: int) -> None:
        await asyncio.sleep(i / max(1, len(walks)))
        await one_client(urls[i % len(urls)], scene, core, params, walks[i],
                         walks[i].meta["cells"], stats[i], budget=budget,
                         progressive=progressive, first_cell_timeout=first_cell_timeout,
                         grace=grace, fps=fps, sample_every=sample_every)

    try:
        await asyncio.gather(*(delayed(i) for i in range(len(walks))))
    finally:
        sampler.cancel()
    return stats, peak[0], time.perf_counter() - t0
