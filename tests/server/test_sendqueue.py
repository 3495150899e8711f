"""The session's prioritised send queue (``server.sendqueue``): the current cell's stream goes
before prefetch streams, a cell stream's bracketing (``cell_begin`` ... ``cell_end``) is never
broken, messages without a stream are never lost, and the queue stays bounded."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from server.sendqueue import Outgoing, SendQueue, StreamTag


def _stream(q: SendQueue, tag: StreamTag, frames: int, size: int = 100) -> None:
    """Queue a whole stream of ``tag``: begin, ``frames`` frames of ``size`` bytes, end."""
    ahead = tag.prefetch
    q.put_nowait(Outgoing(f"begin {tag.cell}", "begin", tag), ahead)
    for k in range(frames):
        ids = np.arange(k * 10, k * 10 + 10, dtype=np.int32) + 1000 * tag.cell
        q.put_nowait(Outgoing(b"x" * size, "frame", tag, ids), ahead)
    q.put_nowait(Outgoing(f"end {tag.cell}", "end", tag), ahead)


def _partial(tag: StreamTag) -> Outgoing:
    return Outgoing(f"partial {tag.cell}", "end", tag, partial=True)


async def _drain(q: SendQueue) -> list[Outgoing]:
    out = []
    while len(q):
        out.append(await asyncio.wait_for(q.get(), 2.0))
    return out


def _bracketing_ok(items: list[Outgoing]) -> bool:
    """Every frame lies between its own stream's begin and end; streams never interleave."""
    open_ = None
    for it in items:
        if it.kind == "begin":
            if open_ is not None:
                return False
            open_ = it.stream
        elif it.kind in ("frame", "cubemap"):
            if it.stream is not open_:
                return False
        elif it.kind == "end":
            if it.stream is not open_:
                return False
            open_ = None
    return open_ is None


def test_current_cell_goes_before_queued_prefetch():
    async def main():
        q = SendQueue(max_items=100, max_bytes=10**6)
        pre = StreamTag(cell=7, prefetch=True)
        _stream(q, pre, frames=16)  # prefetch already queued: 18 items
        cur = StreamTag(cell=3, prefetch=False)
        _stream(q, cur, frames=2)
        return await _drain(q)

    items = asyncio.run(main())
    # Nothing of the prefetch stream went out: the whole current stream comes first.
    assert [it.stream.cell for it in items[:4]] == [3, 3, 3, 3]
    assert items[3].kind == "end"
    assert _bracketing_ok(items)


def test_open_prefetch_stream_is_cut_with_a_partial_end():
    async def main():
        q = SendQueue(max_items=100, max_bytes=10**6)
        pre = StreamTag(cell=7, prefetch=True)
        _stream(q, pre, frames=16)
        first = [await q.get(), await q.get()]  # cell_begin and one frame are out
        removed, cut = q.cut_ahead(keep=3, partial_end=_partial)
        cur = StreamTag(cell=3, prefetch=False)
        _stream(q, cur, frames=2)
        return first, removed, cut, pre, await _drain(q)

    first, removed, cut, pre, rest = asyncio.run(main())
    assert [it.kind for it in first] == ["begin", "frame"]
    # 15 unsent frames and the end were removed; the stream is marked cut.
    assert len(removed) == 16 and cut == [pre] and pre.cut
    # The partial end closes the open stream first (one item), then the current cell.
    assert rest[0].kind == "end" and rest[0].partial and rest[0].stream is pre
    assert [it.stream.cell for it in rest[1:]] == [3] * 4
    assert _bracketing_ok(first + rest)


def test_cut_keeps_messages_without_a_stream_and_the_current_cells_prefetch():
    async def main():
        q = SendQueue(max_items=100, max_bytes=10**6)
        a = StreamTag(cell=5, prefetch=True)
        _stream(q, a, frames=2)
        q.put_nowait(Outgoing('{"type":"drop"}'), True)  # a drop made room for prefetch
        b = StreamTag(cell=6, prefetch=True)
        _stream(q, b, frames=2)
        removed, cut = q.cut_ahead(keep=6, partial_end=_partial)  # walker entered cell 6
        # The next prefetch stream, queued after the cut, waits for cell 6's (moved) stream.
        _stream(q, StreamTag(cell=7, prefetch=True), frames=1)
        return removed, cut, await asyncio.wait_for(_drain(q), 2.0)

    removed, cut, items = asyncio.run(main())
    assert cut[0].cell == 5 and len(cut) == 1 and len(removed) == 4
    # The drop and cell 6's whole stream survive, in their order, then cell 7.
    assert [it.kind for it in items[:5]] == ["message", "begin", "frame", "frame", "end"]
    assert [it.stream.cell for it in items[1:]] == [6] * 4 + [7] * 3
    assert _bracketing_ok(items)


def test_bounded_in_items_and_bytes():
    async def main():
        q = SendQueue(max_items=4, max_bytes=250)
        tag = StreamTag(cell=1, prefetch=False)
        assert q.has_room(10_000)  # one large message fits an empty queue
        await q.put(Outgoing(b"x" * 100, "frame", tag), ahead=False)
        await q.put(Outgoing(b"x" * 100, "frame", tag), ahead=False)
        assert not q.has_room(100) and q.has_room(50)
        # A producer waits (backpressure) until the consumer takes something.
        blocked = asyncio.create_task(q.put(Outgoing(b"y" * 100, "frame", tag), ahead=True))
        await asyncio.sleep(0.01)
        assert not blocked.done() and q.nbytes == 200
        got = await q.get()
        await asyncio.wait_for(blocked, 1.0)
        return got, q.nbytes, q.lanes()

    got, nbytes, lanes = asyncio.run(main())
    assert got.data == b"x" * 100 and nbytes == 200 and lanes == (1, 1)


def test_queued_ids_follow_what_is_queued():
    async def main():
        q = SendQueue(max_items=100, max_bytes=10**6)
        _stream(q, StreamTag(cell=2, prefetch=True), frames=3)
        before = q.queued_ids()
        q.cut_ahead(keep=None, partial_end=_partial)
        return before, q.queued_ids()

    before, after = asyncio.run(main())
    assert len(before) == 30 and len(after) == 0


@pytest.mark.parametrize("keep", [None, 9])
def test_random_interleavings_keep_bracketing(keep):
    """Random producer/consumer/cut interleavings never break a stream's bracketing."""
    rng = np.random.default_rng(keep or 0)

    async def main():
        q = SendQueue(max_items=1000, max_bytes=10**8)
        sent: list[Outgoing] = []
        for _step in range(200):
            r = rng.random()
            if r < 0.25:
                _stream(q, StreamTag(int(rng.integers(0, 12)), bool(rng.random() < 0.7)),
                        frames=int(rng.integers(0, 4)))
            elif r < 0.35:
                q.cut_ahead(keep=keep, partial_end=_partial)
            elif len(q):
                sent.append(await q.get())
        sent += await asyncio.wait_for(_drain(q), 5.0)
        return sent

    sent = asyncio.run(main())
    assert _bracketing_ok(sent)
