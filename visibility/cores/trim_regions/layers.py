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


def leaf_layers(octree: Octree, frame: LeafFrame, view: View) -> tuple[np.ndarray, np.ndarray]:
    """(layer (L,) int64, drawn (L,) bool) of every leaf for ``view``: layers from the
    dependency queue at v*, drawn where the leaf meets the frustum at v*."""
    lay = layers(frame.lo, frame.hi, octree.nbr_start, octree.nbr_items, octree.nbr_face,
                 view.vstar)
    return lay, in_view(frame.lo, frame.hi, view.vstar, view.rot, view.tan, view.near)


def by_layer(layer: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order of items by layer (stable), the distinct layers and their start offsets.

    Returns
    -------
    order : (k,) int64 item indices sorted by layer.
    values : (l,) int64 distinct layers, ascending.
    starts : (l + 1,) int64 offsets into ``order`` of each layer's items.
    """
    order = np.argsort(layer, kind="stable")
    ordered = layer[order]
    # Sorted already: the layers start where the value changes (no second sort or hash).
    first = np.flatnonzero(np.diff(ordered)) + 1
    starts = np.concatenate([[0], first, [len(ordered)]]).astype(np.int64) if len(ordered) \
        else np.zeros(1, dtype=np.int64)
    return order.astype(np.int64), ordered[starts[:-1]].astype(np.int64), starts
