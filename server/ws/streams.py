"""The streamer task of a session: which cell streams next, its PVS, and its messages.

The streamer picks the next job (the current cell first, then the neighbours ahead in order),
gets its PVS from the shared compute service (cache, in-flight sharing, priority pool; prefetch
work no walker wants any more is skipped), and queues ``cell_begin``, the triangles the client
lacks as geometry frames, the cubemap (near-far), ``cell_end``. A prefetch stream yields to the
current cell's between chunks, and when the walker needs another cell its queued frames are cut
(``server.sendqueue``: ``cell_end.partial``). When a client's triangle ``budget`` would be
exceeded, a ``drop`` message first names the held triangles it must drop (outside the current
and prefetched cells' PVS first, farthest first).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from protocol.codes import ErrorCode, is_fatal
from protocol.frames import chunk_count, encode_geometry, triangles_per_frame
from protocol.messages import CellBegin, CellEnd, Drop, Error
from server.admission import Refused
from server.catalog import wire_origin
from server.errors import error_code, error_message
from server.region import PVSResult
from server.sendqueue import StreamTag
from server.ws.transport import SessionOver
from visibility.cancel import ComputationCancelled
from visibility.cores.base import PVS

if TYPE_CHECKING:
    from server.state import Session

log = logging.getLogger(__name__)

#: Seconds a cell not in memory waits for a shared cache (Redis) that is up before a
#: progressive first answer is started for it: a Redis hit lands in about a millisecond, and a
#: first answer started for a cell Redis then answers is computed for nothing.
SHARED_CACHE_GRACE_S = 0.02
#: Known neighbours that make a known answer on their own (``Streamer._known_answer``): with
#: fewer, the union misses much of what the cell itself sees close by (the benchmark's image
#: error says how much: docs/streaming.md).
KNOWN_MIN = 3


class Streamer:
    """Streams the cells a session's walker needs, in order; ``run`` is the task."""

    def __init__(self, session: Session) -> None:
        self.s = session

    # ----------------------------------------------------------------------------- jobs
    def next_job(self) -> tuple[int, bool, int, bool] | None:
        """(cell, prefetch?, rank, refinement?) of the next stream: the current cell first, then
        refinements that are ready (the current cell's, then those ahead), then prefetch
        order."""
        s = self.s
        c, done = s.cell, s.inventory.done
        if c is not None and (c not in done or c != s.announced) and c not in s.skip:
            return c, False, 0, False
        self._drop_unwanted_refinements()
        ready = [n for n, (fut, _) in s.refining.items() if fut.done()]
        if c in ready:
            return c, False, 0, True
        for rank, n in enumerate(s.want):
            if n in ready:
                return n, True, rank, True
        for rank, n in enumerate(s.want):
            if n not in done and n not in s.skip and n != c:
                return n, True, rank, False
        return None

    # ----------------------------------------------------------------------------- refinements
    def _drop_unwanted_refinements(self) -> None:
        """Give up the refinements of cells the walker left (neither current nor ahead): the
        computation stops unless another walker wants it, and the cell counts as not done, so
        coming back streams it again (what it lacks, then its refinement)."""
        s = self.s
        for n in [n for n in s.refining if n != s.cell and n not in s.want_set]:
            cf, _ = s.refining.pop(n)
            s.provisional.pop(n, None)
            s.state.compute.release(cf, "the walker left the cell before its refinement")
            s.inventory.done.discard(n)
            s.state.counters["refinements_dropped"] += 1

    def release_refinements(self) -> None:
        """The session ends: give up every pending refinement."""
        s = self.s
        for cf, _ in s.refining.values():
            s.state.compute.release(cf, "the walker left")
        s.refining.clear()
        s.provisional.clear()

    async def refine(self, cell: int, prefetch: bool) -> None:
        """Stream what the session core's answer adds to ``cell``'s first answer."""
        s = self.s
        cf, seq = s.refining.pop(cell)
        s.provisional.pop(cell, None)
        if cf.cancelled():
            s.inventory.done.discard(cell)
            return
        exc = cf.exception()
        if exc is not None:
            code = error_code(exc)
            msg = error_message(exc) if code is not None else (
                f"refinement of cell {cell} failed: {type(exc).__name__}: {exc}")
            if code is None:
                log.error("session %s: refinement of %s cell %d failed: %r", s.id,
                          s.loaded.name, cell, exc)
            s.state.counters["refinements_failed"] += 1
            await self._job_failed(cell, prefetch, msg, seq, code)
            return
        s.state.counters["refinements"] += 1
        await self.stream_cell(cell, cf.result(), prefetch, answer="refined")

    def current_pending(self, streaming: int) -> bool:
        """Whether the walker's cell, not ``streaming``, waits for its stream."""
        s = self.s
        c = s.cell
        return (c is not None and c != streaming and c not in s.inventory.done
                and c not in s.skip)

    async def run(self) -> None:
        """Stream until the session ends; a failure ends with an ``internal`` error."""
        s = self.s
        try:
            while True:
                job = self.next_job()
                if job is None:
                    s.wake.clear()
                    await s.wake.wait()
                    continue
                cell, prefetch, rank, refinement = job
                if refinement:
                    await self.refine(cell, prefetch)
                    continue
                got = await self.get_pvs(cell, prefetch, rank)
                if got is not None:
                    await self.stream_cell(cell, got[0], prefetch, answer=got[1])
        except SessionOver:
            pass
        except Exception:
            log.exception("session %s: streaming failed", s.id)
            try:
                await s.error(ErrorCode.INTERNAL, "internal server error while streaming")
            except SessionOver:
                pass

    # ----------------------------------------------------------------------------- PVS
    def _ready(self, cell: int, ids: np.ndarray, stats: dict | None = None) -> PVSResult:
        """A PVS the session has without computing (as if cached)."""
        s = self.s
        box = s.loaded.grid.boxes[cell].copy()
        pvs = PVS(ids) if stats is None else PVS(ids, stats=stats)
        return PVSResult(s.loaded.name, cell, box, s.core.name, s.params, pvs, True)

    async def get_pvs(self, cell: int, prefetch: bool,
                      rank: int) -> tuple[PVSResult, str] | None:
        """The PVS of ``cell`` and which answer it is (``protocol.messages.ANSWERS``), or None
        when the job was superseded (the walker moved on: the computation goes on in the pool
        and lands in the cache) or failed (error sent).

        Progressive (``Session.progressive``): for the walker's cell, when the session core's
        answer is not ready at once, the cheap first answer (``_submit_first``) is returned as
        soon as it is there, and the core's computation goes on as the cell's refinement
        (``refine``)."""
        s = self.s
        name = s.loaded.name
        known = s.inventory.pvs_of.get(cell)
        if known is not None and cell in s.inventory.done:
            # A cell whose refinement is still under way holds its first answer.
            if cell in s.refining:
                return self._ready(cell, known), s.provisional.get(cell, "first")
            return self._ready(cell, known), "full"
        if s.send_all:
            return self._ready(
                cell, np.flatnonzero(s.loaded.scene.valid_faces).astype(np.int32)), "full"
        near = await s.nearfar.near_region_if_it_fits(cell, s.inventory.budget)
        if near is not None:
            s.state.counters["cells_sent_whole"] += 1
            return self._ready(cell, near, stats={
                "skipped": "the near region fits the client's budget: sent whole"}), "full"
        compute = s.state.compute
        key = s.key_of(cell)
        seq = s.cell_seq if not prefetch else None
        # Ranked across walkers by expected arrival (``docs/scheduling.md``).
        priority, since = s.rank_of(cell)
        try:
            cf = compute.submit(name, s.core, s.params, cell=cell, priority=priority,
                                since=since, walker=True,
                                wanted=(lambda: s.state.wanted(key)) if prefetch else None)
        except (LookupError, Refused) as exc:
            # Refused: over a server limit (the walker's cell) or a full queue (prefetch only).
            await self._job_failed(cell, prefetch, error_message(exc), seq, error_code(exc))
            return None
        fut = asyncio.wrap_future(cf)
        fut.add_done_callback(lambda f: f.cancelled() or f.exception())
        shared = s.progressive and compute.cache.shared_up
        if shared and not prefetch and not cf.done():
            await asyncio.wait({fut}, timeout=SHARED_CACHE_GRACE_S)
        known = None
        if not prefetch and s.progressive and not cf.done():
            known = await self._known_answer(cell)
            if known is not None and known.pvs.stats["enough"] and not cf.done():
                # No first answer to compute: the core goes on, its answer refines this one.
                s.refining[cell] = (cf, seq)
                s.provisional[cell] = "known"
                fut.add_done_callback(lambda f: s.wake.set())
                s.state.counters["known_answers"] += 1
                return known, "known"
        first = self._first_answer(cell, cf) if not prefetch else None
        if prefetch and s.progressive and not cf.done():
            # Should the walker get there before the core's answer, its first answer is
            # then ready at once: computed now, after the first answers walkers wait for.
            def warm() -> None:
                if cf.done():
                    return
                try:
                    self._submit_first(cell, priority=priority)
                except Exception:  # noqa: BLE001 - a warm-up only; ``_first_answer`` reports
                    pass

            if shared:
                asyncio.get_running_loop().call_later(SHARED_CACHE_GRACE_S, warm)
            else:
                warm()
        job = (cell, prefetch)
        try:
            while not fut.done():
                if first is not None and first.done():
                    if not first.cancelled() and first.exception() is None:
                        # The core goes on computing; its answer refines this one.
                        s.refining[cell] = (cf, seq)
                        s.provisional[cell] = "first"
                        fut.add_done_callback(lambda f: s.wake.set())
                        s.state.counters["first_answers"] += 1
                        return self._with_known(first.result(), known), "first"
                    first = None  # no first answer: wait for the core's
                s.wake.clear()
                waker = asyncio.ensure_future(s.wake.wait())
                await asyncio.wait({fut, waker} | ({first} if first is not None else set()),
                                   return_when=asyncio.FIRST_COMPLETED)
                waker.cancel()
                nxt = self.next_job()
                if not fut.done() and (nxt is None or nxt[:2] != job):
                    # Superseded: the walker moved on. The computation goes on only if some
                    # walker still wants the cell (prefetch lists); else it is cancelled.
                    if not prefetch:
                        compute.release(cf, "the walker moved on")
                    return None
        except asyncio.CancelledError:
            if not prefetch:
                compute.release(cf, "the walker left")
            raise
        finally:
            if first is not None and not first.done():
                first.cancel()  # releases the first answer's job (``_first_answer``)
        if fut.cancelled():
            return None
        exc = fut.exception()
        if exc is None:
            return fut.result(), "full"
        if prefetch and isinstance(exc, ComputationCancelled) and cell not in s.want_set:
            # Cancelled as no walker wanted it any more (``ComputeService.want``): not a
            # failure, so the cell is not skipped should the walker head for it again. (A
            # wanted cell's cancellation, a deadline, is skipped below: never retried at once.)
            return None
        code = error_code(exc)
        if code is not None:
            msg = error_message(exc)
        else:
            log.error("session %s: PVS of %s cell %d failed: %r", s.id, name, cell, exc)
            msg = f"PVS of cell {cell} failed: {type(exc).__name__}: {exc}"
        await self._job_failed(cell, prefetch, msg, seq, code)
        return None

    @staticmethod
    def _with_known(first: PVSResult, known: PVSResult | None) -> PVSResult:
        """The computed first answer joined by what is known around the cell (too little to
        answer alone, but what the neighbours see is mostly what the walker holds already)."""
        if known is None:
            return first
        ids = np.union1d(first.pvs.triangle_ids, known.pvs.triangle_ids).astype(np.int32)
        sph = [p.sphere_ids for p in (first.pvs, known.pvs) if p.sphere_ids is not None]
        pvs = PVS(ids, sphere_ids=np.unique(np.concatenate(sph)).astype(np.int32) if sph
                  else None, stats={**first.pvs.stats, "known_from": known.pvs.stats["known_from"]})
        return dataclasses.replace(first, pvs=pvs)

    async def _known_answer(self, cell: int) -> PVSResult | None:
        """The union of the session core's PVS of the neighbouring cells where it is known
        (this session's own streams, then the cache's memory and shared tiers:
        ``TieredCache.peek_async``, never a computation); None when none is known or
        ``settings.known_answers`` is off. Its ``stats["enough"]``: at least ``KNOWN_MIN`` of
        the neighbours (all when there are fewer) are known, so it answers alone, costing
        nothing; with fewer it misses much of what only the cell itself sees nearby, and joins
        a computed first answer instead."""
        s = self.s
        if not s.settings.known_answers:
            return None
        nbrs = s.loaded.grid.neighbours(cell)
        parts: list[PVS] = []
        ask = []
        for n in nbrs:
            held = s.inventory.pvs_of.get(n)
            if held is not None and n in s.inventory.done and n not in s.refining:
                parts.append(PVS(held))
            else:
                ask.append(n)
        if ask:
            cache = s.state.compute.cache
            n_tri = s.loaded.scene.n_triangles
            found = await asyncio.gather(*(cache.peek_async(s.key_of(n), n_tri) for n in ask))
            parts.extend(p for p in found if p is not None)
        if not parts:
            return None
        ids = np.unique(np.concatenate([p.triangle_ids for p in parts])).astype(np.int32)
        spheres = [p.sphere_ids for p in parts if p.sphere_ids is not None]
        pvs = PVS(ids, sphere_ids=np.unique(np.concatenate(spheres)).astype(np.int32)
                  if spheres else None,
                  stats={"known_from": len(parts), "neighbours": len(nbrs),
                         "enough": len(parts) >= min(KNOWN_MIN, len(nbrs))})
        box = s.loaded.grid.boxes[cell].copy()
        return PVSResult(s.loaded.name, cell, box, s.core.name, s.params, pvs, True)

    def _first_answer(self, cell: int, cf: Any) -> asyncio.Future | None:
        """The first answer's future for the walker's ``cell`` whose core future ``cf`` is not
        done, or None when the session is not progressive or it cannot be had (a bad
        ``first_core`` setting is logged once per session, never an error to the walker)."""
        s = self.s
        if not s.progressive or cf.done():
            return None
        compute = s.state.compute
        try:
            ff = self._submit_first(cell)
        except Exception as exc:
            if not s.first_failed:
                s.first_failed = True
                log.warning("session %s: no first answers: %s", s.id, exc)
            return None
        first = asyncio.wrap_future(ff)
        first.add_done_callback(lambda f: f.cancelled() or f.exception())
        # Cancelling the asyncio future leaves ``ff`` to the service: release the job so the
        # computation stops when no one else waits for it.
        first.add_done_callback(lambda f: f.cancelled() and compute.release(ff, "not needed"))
        return first

    def _submit_first(self, cell: int, priority: float = 0.0) -> Any:
        """The compute service's future of the cheap first answer for ``cell``
        (``Resolver.first``), on the first answers' worker (lowest ``priority`` first: 0 for
        the cell the walker stands in); cached like any PVS."""
        s = self.s
        first = s.state.resolver.first()
        return s.state.compute.submit(s.loaded.name, first.core, first.params, cell=cell,
                                      priority=priority, lane="first")

    async def _job_failed(self, cell: int, prefetch: bool, msg: str, seq: int | None,
                          code: ErrorCode | None = None) -> None:
        self.s.skip.add(cell)
        if not prefetch:
            if code is None or is_fatal(code):
                # The session goes on with its other cells: a failed cell is never fatal.
                code = ErrorCode.COMPUTE_FAILED
            await self.s.error(code, msg, seq)

    # ----------------------------------------------------------------------------- budget
    async def _over_budget(self, message: str, seq: int, stream: StreamTag | None) -> None:
        await self.s.outbox.put(Error(code=ErrorCode.OVER_BUDGET, seq=seq, message=message),
                                stream)
        self.s.state.counters["errors_sent"] += 1

    async def _make_room(self, cell: int, ids: np.ndarray, new: np.ndarray,
                         prefetch: bool, seq: int, stream: StreamTag | None = None) -> bool:
        """Drop held triangles so ``new`` fits the budget; False when a prefetch cannot fit
        without touching the current cell's PVS (the prefetch is then skipped)."""
        s, inv = self.s, self.s.inventory
        need = inv.over_budget(new)
        if need <= 0:
            return True
        box = s.loaded.grid.boxes[s.cell if s.cell is not None else cell]
        drops = inv.choose_drops(need, ids, s.cell, s.want, prefetch,
                                 s.state.centroids(s.loaded), box.mean(axis=0))
        if len(drops) < need:
            if prefetch:
                s.skip.add(cell)
                return False
            await self._over_budget(
                f"PVS of cell {cell} holds {len(ids)} triangles; with the current cell's it "
                f"exceeds the budget of {inv.budget}", seq, stream)
        if len(drops):
            gone = inv.drop(drops)
            s.state.counters["triangles_dropped"] += len(drops)
            await s.outbox.put(Drop(ids=np.sort(drops).tolist(), cells=gone), stream)
        return True

    def yield_prefetch(self) -> None:
        """Cut the queued prefetch streams (but the current cell's) so the current cell's
        messages go next: their unsent triangles count as not held, their cells as not done
        (a later stream sends what is missing)."""
        s = self.s
        removed, cut = s.outbox.cut_ahead(s.cell)
        unsent = [item.ids for item in removed if item.ids is not None]
        if unsent:
            # A triangle a queued frame still carries stays held (it was dropped and re-sent).
            s.inventory.release(np.setdiff1d(np.concatenate(unsent), s.outbox.queued_ids()))
        for item in removed:
            if item.kind == "cubemap":
                s.nearfar.cubemaps_sent.discard(s.nearfar.anchor(item.stream.cell))
        for tag in cut:
            s.inventory.done.discard(tag.cell)
        c = s.state.counters
        c["prefetch_yields"] += len(cut)
        c["prefetch_frames_cut"] += len(unsent)

    # ----------------------------------------------------------------------------- one cell
    async def stream_cell(self, cell: int, result: PVSResult, prefetch: bool,
                          answer: str = "full") -> None:
        """Queue ``cell``'s stream: ``cell_begin``, the triangles the client lacks as geometry
        frames, the cubemap (near-far), ``cell_end``. A current cell's stream first cuts the
        queued prefetch streams; a prefetch stream stops (cut) when the walker needs another
        cell. ``answer``: which answer ``result`` is (``cell_begin.answer``)."""
        s, inv, out = self.s, self.s.inventory, self.s.outbox
        seq = s.cell_seq
        t0 = s.cell_t0 if not prefetch else time.perf_counter()
        if not prefetch:
            s.announced = cell
            self.yield_prefetch()
        tag = StreamTag(cell, prefetch, seq, t0, result.seconds, result.cached)
        ids, near_far, cube = await s.nearfar.geometry(cell, result.pvs.triangle_ids)
        inv.remember(cell, ids, keep=(s.cell, *s.want))
        new = inv.missing(ids)
        if not prefetch and inv.budget is not None and len(ids) > inv.budget:
            await self._over_budget(f"PVS of cell {cell} holds {len(ids)} triangles, over the "
                                    f"budget of {inv.budget}", seq, tag)
        if not await self._make_room(cell, ids, new, prefetch, seq, tag):
            return
        max_bytes = s.settings.max_frame_bytes
        count = chunk_count(len(new), max_bytes)
        begin = CellBegin(cell=cell, seq=seq, triangles=len(ids), new=len(new), chunks=count,
                          prefetch=prefetch, near_far=near_far, answer=answer)
        if not await out.put(begin, tag):
            self.yield_prefetch()  # a prefetch stream waited for room: the walker moved on
            return
        spheres = result.pvs.sphere_ids
        if not await s.dynamic.queue(lambda d: d.spheres_for(spheres, cell, seq, tag), tag):
            self.yield_prefetch()
            return
        per = triangles_per_frame(max_bytes)
        scene = s.loaded.scene
        for i in range(count):
            if prefetch and self.current_pending(cell):
                self.yield_prefetch()  # the walker needs another cell now
                return
            part = new[i * per:(i + 1) * per]
            # A moving triangle's keyframes go just before its geometry (``server.dynamic``).
            if not await s.dynamic.queue(lambda d, p=part: d.keyframes_for(p, cell, seq), tag):
                self.yield_prefetch()
                return
            # Encoding a full frame takes milliseconds: do it off the loop.
            frame = await asyncio.to_thread(
                lambda p=part, k=i: encode_geometry(
                    p, scene.triangles(p), scene.colors[p], cell=cell, seq=seq, index=k,
                    count=count, origin=wire_origin(scene),
                )
            )
            if not await out.put(frame, tag, ids=part):
                self.yield_prefetch()
                return
            inv.add(part)
        if cube is not None:
            if not await out.put(cube, tag, cubemap=True):
                self.yield_prefetch()
                return
            s.nearfar.cubemaps_sent.add(s.nearfar.anchor(cell))
        end = CellEnd(cell=cell, seq=seq, seconds=time.perf_counter() - t0,
                      compute_seconds=result.seconds, cached=result.cached, prefetch=prefetch,
                      partial=False, answer=answer)
        if not await out.put(end, tag):
            self.yield_prefetch()
            return
        inv.done.add(cell)
