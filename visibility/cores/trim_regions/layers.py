"""Per view: which octree leaves are drawn, in which layer, and the draw lists sorted by layer
(paper Sec. 5.2 and phase P0)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from visibility.cores.trim_regions.frustum import View, in_frustum, layers
from visibility.cores.trim_regions.octree import Octree


@dataclass
class LeafFrame:
    """The octree's leaves in a computation's frame (metres relative to its centre).

    Attributes
    ----------
    lo, hi : (L, 3) float64 leaf boxes.
    grid_origin : (3,) the fine grid's origin.
    item_leaf : (k,) int64 leaf of each entry of ``octree.tri_items``.
    """

    lo: np.ndarray
    hi: np.ndarray
    grid_origin: np.ndarray
    item_leaf: np.ndarray


def leaf_frame(octree: Octree, centre: np.ndarray) -> LeafFrame:
    """The leaves of ``octree`` relative to ``centre`` (3,) metres."""
    boxes = octree.leaf_boxes()
    shift = octree.origin - np.asarray(centre, dtype=np.float64)
    counts = np.diff(octree.tri_start)
    return LeafFrame(np.ascontiguousarray(boxes[:, 0] + shift),
                     np.ascontiguousarray(boxes[:, 1] + shift), shift,
                     np.repeat(np.arange(len(octree), dtype=np.int64), counts))


@njit(cache=True, nogil=True, parallel=True)
def in_view(lo, hi, vstar, rot, tan, near):  # pragma: no cover - numba
    """(k,) bool: whether each box [lo, hi] (k, 3) metres may meet the frustum at v*
    (``frustum.in_frustum``)."""
    n = lo.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for k in prange(n):
        out[k] = in_frustum(lo[k], hi[k], vstar, rot, tan, near)
    return out


def drawn_leaves(frame: LeafFrame, view: View) -> np.ndarray:
    """(L,) bool: the leaves that meet the frustum at v* (those ``view`` draws)."""
    return in_view(frame.lo, frame.hi, view.vstar, view.rot, view.tan, view.near)


def leaf_layers(octree: Octree, frame: LeafFrame, view: View,
                drawn: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(layer (L,) int64, drawn (L,) bool) of every leaf for ``view``: layers from the
    dependency queue at v*, drawn where the leaf meets the frustum at v* (``drawn_leaves``,
    unless the caller has it already)."""
    lay = layers(frame.lo, frame.hi, octree.nbr_start, octree.nbr_items, octree.nbr_face,
                 view.vstar)
    return lay, drawn_leaves(frame, view) if drawn is None else drawn


def by_layer(layer: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order of items by layer (stable), the distinct layers and their start offsets.

    Returns
    -------
    order : (k,) int64 item indices sorted by layer.
    values : (l,) int64 distinct layers, ascending.
    starts : (l + 1,) int64 offsets into ``order`` of each layer's items.
    """
    layer = np.ascontiguousarray(layer, dtype=np.int64)
    if not len(layer):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), \
            np.zeros(1, dtype=np.int64)
    lo = int(layer.min())
    # A counting sort: a view's layers are a few hundred at most, its items a million.
    return _count_sort(layer, lo, int(layer.max()) - lo + 1)


@njit(cache=True, nogil=True)
def _count_sort(layer, lo, span):  # pragma: no cover - numba
    """``by_layer`` for layers in [lo, lo + span)."""
    count = np.zeros(span + 1, dtype=np.int64)
    for i in range(layer.shape[0]):
        count[layer[i] - lo + 1] += 1
    n_values = 0
    for v in range(span):
        if count[v + 1] > 0:
            n_values += 1
        count[v + 1] += count[v]
    values = np.empty(n_values, dtype=np.int64)
    starts = np.empty(n_values + 1, dtype=np.int64)
    j = 0
    for v in range(span):
        if count[v + 1] > count[v]:
            values[j] = lo + v
            starts[j] = count[v]
            j += 1
    starts[n_values] = layer.shape[0]
    order = np.empty(layer.shape[0], dtype=np.int64)
    for i in range(layer.shape[0]):
        k = layer[i] - lo
        order[count[k]] = i
        count[k] += 1
    return order, values, starts
