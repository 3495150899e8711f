"""``by_layer``: items grouped by layer, in a stable order, as a stable argsort groups them."""

from __future__ import annotations

import numpy as np
import pytest

from visibility.cores.trim_regions.layers import by_layer


@pytest.mark.parametrize("n", [0, 1, 7, 5000])
def test_by_layer_is_a_stable_sort_with_the_layers_and_their_starts(n):
    layer = np.random.default_rng(n).integers(0, 9, n) * 3 + 2  # gaps between the layers
    order, values, starts = by_layer(layer)
    assert np.array_equal(order, np.argsort(layer, kind="stable"))
    assert np.array_equal(values, np.unique(layer))
    assert starts[0] == 0 and starts[-1] == n and len(starts) == len(values) + 1
    for v, a, b in zip(values, starts[:-1], starts[1:], strict=True):
        assert (layer[order[a:b]] == v).all()
