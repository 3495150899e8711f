"""Reading v*'s supersampled renders: the open depth per pixel."""

from __future__ import annotations

import numpy as np

from visibility.cores.trim_regions.samples import open_depth


def test_open_depth_is_the_kth_smallest_sample_of_each_pixel():
    rng = np.random.default_rng(3)
    res, s = 7, 4
    depth = rng.uniform(0.5, 9.0, (res * s, res * s)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = np.inf  # samples that see nothing
    samples = depth.astype(np.float64).reshape(res, s, res, s).transpose(0, 2, 1, 3)
    samples = samples.reshape(res * res, s * s)
    for k in (0, 5, s * s - 3, s * s - 1):
        out = np.empty(res * res)
        open_depth(depth, res, s, k, out, np.empty(0))
        np.testing.assert_array_equal(out, np.sort(samples, axis=1)[:, k])



def test_open_depth_gives_the_farthest_sample_in_the_same_pass():
    rng = np.random.default_rng(4)
    res, s = 5, 4
    # float32, as the supersampled render is (the kernel's one specialization).
    depth = rng.uniform(0.5, 9.0, (res * s, res * s)).astype(np.float32)
    out = np.empty(res * res)
    far = np.empty(res * res)
    open_depth(depth, res, s, 2, out, far)
    blocks = depth.reshape(res, s, res, s).transpose(0, 2, 1, 3).reshape(res * res, s * s)
    np.testing.assert_array_equal(far, blocks.max(axis=1).astype(np.float64))
    np.testing.assert_array_equal(out, np.sort(blocks, axis=1)[:, 2].astype(np.float64))
