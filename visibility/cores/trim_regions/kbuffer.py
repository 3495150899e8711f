"""Fixed-size per-pixel k-buffers and the stencils of the trim region algorithm (paper Sec. 4,
Table 1).

One buffer per view holds, per pixel, up to ``K`` entries of the pixel's trim sequence: front
faces (depth, triangle id), back faces (depth, id) and trim fragments (depth of the silhouette,
umbra depth). Entries stay from layer to layer until the pixel is resolved: the residual
sequence of Sec. 4.3. A full buffer makes room by merging two trim fragments into one that
spans both their depths with the nearer umbra (``raster._insert``): every interval either one
validates, the merged one validates, hiding no deeper, so the merge only reveals more; trims
of different pieces merge into one that carries the set of their pieces (``piece_bits``). A
pixel whose buffer is full with fewer than two trim fragments gives up occlusion for the rest
of the view: what it holds and everything still to come there is reported (conservative).

The trim region stencil is UNTRIMMED, TRIMMED or SEALED; the active stencil marks pixels that got
new surface entries in the current layer.
"""

from __future__ import annotations

from math import gcd
from typing import NamedTuple

import numpy as np
from numba import njit

#: Entry kinds, in the order ties in depth are sorted (a front face before a trim fragment at
#: its own depth before a back face).
FRONT = 0
TRIM = 1
BACK = 2
#: Trim region stencil states.
UNTRIMMED = 0
TRIMMED = 1
SEALED = 2
#: Entries per pixel.
K = 48
#: A pixel's entries lie in blocks of ``LANES`` (``KBuffer``): entry q of pixel p at
#: [q >> LANE_BITS, p, q & LANE_MASK].
LANE_BITS = 3
LANES = 1 << LANE_BITS
LANE_MASK = LANES - 1
#: Hidden depth spans [front face, umbra] of validated intervals kept per pixel for the
#: footprint tests of small triangles and hulls (more are dropped: a dropped span only makes
#: them more visible). A pixel looking through a row of rooms validates a wall's interval per
#: door frame it passes, more than 4 of them (docs/cores/trim_regions.md).
SPANS = 8
#: Bits of the piece set a merged trim fragment carries (``piece_bits``), and that set with
#: every bit: a trim of any piece.
PIECE_SET_BITS = 62
ANY_PIECE = -((1 << PIECE_SET_BITS) - 1)


@njit(cache=True, nogil=True, inline="always")
def piece_bits(piece: int) -> int:
    """The bits that stand for connected piece ``piece`` in a merged trim fragment's piece
    set: two of ``PIECE_SET_BITS`` picked by an integer hash (a Bloom filter: a set
    holding the piece has both; a set of others has both only by chance, and then the trim
    counts for the piece, which only reveals more). 0 for no piece (``piece`` < 0): every
    set holds it."""
    if piece < 0:
        return 0
    # A 32-bit integer mix (consecutive pieces, as labelling gives neighbours, spread).
    h = piece + 1
    h = ((h ^ (h >> 16)) * 0x45D9F3B) & 0xFFFFFFFF
    h = ((h ^ (h >> 16)) * 0x45D9F3B) & 0xFFFFFFFF
    h ^= h >> 16
    return (1 << (h % PIECE_SET_BITS)) | (1 << ((h // PIECE_SET_BITS) % PIECE_SET_BITS))


@njit(cache=True, nogil=True, inline="always")
def trim_holds(ident: int, piece: int) -> bool:
    """Whether a trim entry's ``ident`` (a piece >= 0, or minus a merged piece set) may hold
    connected piece ``piece`` (``piece_bits``)."""
    if ident >= 0:
        return ident == piece
    m = piece_bits(piece)
    return (-ident) & m == m


@njit(cache=True, nogil=True, inline="always")
def joined_pieces(a: int, b: int) -> int:
    """The ``ident`` of a trim merged from trims of idents a and b: the piece when both are
    of one, else minus the union of their piece sets (``piece_bits``)."""
    if a == b:
        return a
    ma = -a if a < 0 else piece_bits(a)
    mb = -b if b < 0 else piece_bits(b)
    return -(ma | mb)


@njit(cache=True, nogil=True)
def band_stride(n_bands: int) -> int:
    """A stride coprime with ``n_bands`` near ``n_bands`` / golden ratio squared: the kernels
    that run over bands of rows visit band ``(j * stride) % n_bands`` at step ``j``.

    Numba splits a ``prange`` into one contiguous run of steps per thread, and a view's work
    lies in a few rows (the floor and clutter below the horizon); a contiguous run of steps
    spread this way over the frame gives each thread a share of every part of it.
    """
    s = max(1, int(round(n_bands * 0.381966)))
    while gcd(s, n_bands) != 1:
        s += 1
    return s


class KBuffer(NamedTuple):
    """The per-pixel state of one view of ``n`` pixels (a named group the kernels take
    whole: ``resolve.resolve_layer``).

    The entries are stored in blocks: entry q of pixel p lies at [q >> LANE_BITS, p,
    q & LANE_MASK] of the (K / LANES, n, LANES) arrays below. A pixel's first ``LANES``
    entries share a cache line per field, as in a (n, K) layout, but the planes of later
    blocks are touched only where some pixel holds that many: most pixels hold a few entries,
    so most of the buffer's pages are never faulted in (in a (n, K) layout every page holds
    the first entry of some pixel).

    Attributes
    ----------
    depth : (K / LANES, n, LANES) float64, depth from v* along the view axis, metres.
    kind : (K / LANES, n, LANES) int8, FRONT, BACK or TRIM.
    ident : (K / LANES, n, LANES) int64, triangle id (FRONT, BACK); of a TRIM entry, the
        connected piece of its edge (``topology.connected_pieces``), or of a trim merged
        from several pieces minus their piece set (``piece_bits``; ``ANY_PIECE``: all).
    umbra : (K / LANES, n, LANES) float64, umbra depth of a TRIM entry, metres (inf:
        unbounded).
    far : (K / LANES, n, LANES) float64, far end of a TRIM entry's depth range, metres: its
        own depth, or the deepest of the fragments merged into it (``depth`` holds the
        nearest).
    count : (n,) int64 entries held.
    stencil : (n,) int8 trim region stencil.
    active : (n,) uint8, new surface entries this layer.
    overflow : (n,) uint8, 1 once the pixel overflowed.
    cover : (n,) float64, depth up to which earlier validated intervals' umbrae hide (metres).
    seal : (n,) float64, depth of the terminator face of a sealed pixel (inf otherwise).
    spans : (n, SPANS, 2) float64, hidden depth spans of the pixel's validated intervals;
        ``n_spans`` (n,) int64 how many are held.
    first : (n,) float64, depth of the first surface the pixel resolved (inf: none).
    hid : (n,) int64, 1 + the closed part (``SceneData.closed``) of the front face that hid in
        an umbra since the last front face seen, 0 for none or a face of no closed part.
    queue : (n,) int64, the pixels marked active this layer, per band of 8 rows: band b's
        list starts at its first pixel, b * 8 * res, and is ``queued[b]`` long (a layer
        resolves those, not the whole frame).
    queued : (bands,) int64, the length of each band's list.
    held_entries : (bands,) int64, the entries each band holds (the k-buffers' use, without
        a full-frame pass per layer).
    """

    depth: np.ndarray
    kind: np.ndarray
    ident: np.ndarray
    umbra: np.ndarray
    far: np.ndarray
    count: np.ndarray
    stencil: np.ndarray
    active: np.ndarray
    overflow: np.ndarray
    cover: np.ndarray
    seal: np.ndarray
    spans: np.ndarray
    n_spans: np.ndarray
    first: np.ndarray
    hid: np.ndarray
    queue: np.ndarray
    queued: np.ndarray
    held_entries: np.ndarray

    @classmethod
    def empty(cls, n: int) -> KBuffer:
        """A cleared buffer of ``n`` pixels (a square view: res * res)."""
        bands = (int(round(np.sqrt(n))) + 7) // 8 + 1
        # Zeroed, not filled: untouched pages stay unmapped (an entry beyond ``count`` is
        # never read).
        shape = (K // LANES, n, LANES)
        return cls(np.zeros(shape), np.zeros(shape, dtype=np.int8),
                   np.zeros(shape, dtype=np.int64), np.zeros(shape), np.zeros(shape),
                   np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int8),
                   np.zeros(n, dtype=np.uint8), np.zeros(n, dtype=np.uint8), np.zeros(n),
                   np.full(n, np.inf), np.zeros((n, SPANS, 2)), np.zeros(n, dtype=np.int64),
                   np.full(n, np.inf), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64),
                   np.zeros(bands, dtype=np.int64), np.zeros(bands, dtype=np.int64))

    def entries(self, p: int) -> tuple[np.ndarray, ...]:
        """Pixel p's held entries as (kind, depth, ident, umbra, far), each (count,) (copies,
        in slot order); umbra and far mean something for TRIM entries only (a surface's are
        neither written nor read by the kernels)."""
        c = int(self.count[p])
        return tuple(np.asarray(a[:, p, :]).reshape(-1)[:c].copy()
                     for a in (self.kind, self.depth, self.ident, self.umbra, self.far))

    def put(self, p: int, q: int, kind: int, depth: float, ident: int, umbra: float,
            far: float | None = None) -> None:
        """Write entry q of pixel p (``far`` defaults to ``depth``); ``count`` is the
        caller's."""
        i, j = q >> LANE_BITS, q & LANE_MASK
        self.kind[i, p, j], self.depth[i, p, j], self.ident[i, p, j] = kind, depth, ident
        self.umbra[i, p, j] = umbra
        self.far[i, p, j] = depth if far is None else far

    @property
    def allocated_bytes(self) -> int:
        """Bytes of the k-buffers (Table 2's allocated memory)."""
        return int(self.depth.nbytes + self.kind.nbytes + self.ident.nbytes + self.umbra.nbytes
                   + self.far.nbytes)
