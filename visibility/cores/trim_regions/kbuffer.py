"""Fixed-size per-pixel k-buffers and the stencils of the trim region algorithm (paper Sec. 4,
Table 1).

One buffer per view holds, per pixel, up to ``K`` entries of the pixel's trim sequence: front
faces (depth, triangle id), back faces (depth, id) and trim fragments (depth of the silhouette,
umbra depth). Entries stay from layer to layer until the pixel is resolved: the residual
sequence of Sec. 4.3. A full buffer makes room by merging two trim fragments into one that
spans both their depths with the nearer umbra (``raster._insert``): every interval either one
validates, the merged one validates, hiding no deeper, so the merge only reveals more. A
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
#: Hidden depth spans [front face, umbra] of validated intervals kept per pixel for the hull
#: test (more are dropped: a dropped span only makes hulls more visible).
SPANS = 4


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

    Attributes
    ----------
    depth : (n, K) float64, depth from v* along the view axis, metres.
    kind : (n, K) int8, FRONT, BACK or TRIM.
    ident : (n, K) int32, triangle id (FRONT, BACK) or -1.
    umbra : (n, K) float64, umbra depth of a TRIM entry, metres (inf: unbounded).
    far : (n, K) float64, far end of a TRIM entry's depth range, metres: its own depth, or
        the deepest of the fragments merged into it (``depth`` holds the nearest).
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
        return cls(np.zeros((n, K)), np.zeros((n, K), dtype=np.int8),
                   np.full((n, K), -1, dtype=np.int32), np.zeros((n, K)), np.zeros((n, K)),
                   np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int8),
                   np.zeros(n, dtype=np.uint8), np.zeros(n, dtype=np.uint8), np.zeros(n),
                   np.full(n, np.inf), np.zeros((n, SPANS, 2)), np.zeros(n, dtype=np.int64),
                   np.full(n, np.inf), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64),
                   np.zeros(bands, dtype=np.int64), np.zeros(bands, dtype=np.int64))

    @property
    def allocated_bytes(self) -> int:
        """Bytes of the k-buffers (Table 2's allocated memory)."""
        return int(self.depth.nbytes + self.kind.nbytes + self.ident.nbytes + self.umbra.nbytes
                   + self.far.nbytes)
