"""``knn.unique_keys``: the voxel hash's mark-and-rank path (a frame's cull: the key range a
few times the keys) gives exactly ``np.unique(..., return_inverse=True)``, and so does the sort
path it falls back to for sparse key ranges."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.lifting.knn import VoxelGrid, unique_keys


@pytest.mark.parametrize("n, cells", [(1, 1), (50, 50), (20_000, 30_000), (20_000, 10**9), (0, 7)])
def test_unique_keys_equals_numpy_unique(n, cells):
    rng = np.random.default_rng(n)
    key = rng.integers(0, cells, n)
    if n > 2:
        key[:2] = [0, cells - 1]  # the range's ends
    keys, inverse = unique_keys(key, cells)
    ref_keys, ref_inverse = np.unique(key, return_inverse=True)
    assert np.array_equal(keys, ref_keys) and keys.dtype == ref_keys.dtype
    assert np.array_equal(inverse, ref_inverse.reshape(-1)) and inverse.dtype == np.int64
    assert np.array_equal(keys[inverse], key)


def test_voxel_grid_keys_and_neighbours_are_those_of_the_sorted_hash():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 12, (5_000, 3)).astype(np.float32)
    g = VoxelGrid(xyz, 0.7, pad=2)
    q = np.floor((xyz - xyz.min(axis=0)) / 0.7).astype(np.int64) + 2
    key = (q[:, 0] * g.dims[1] + q[:, 1]) * g.dims[2] + q[:, 2]
    ref_keys, ref_inverse = np.unique(key, return_inverse=True)
    assert np.array_equal(g.keys, ref_keys) and np.array_equal(g.inverse, ref_inverse.reshape(-1))
    nb = g.neighbour(np.arange(g.n_voxels), 1, 0, 0)
    hit = nb >= 0
    assert hit.any() and np.array_equal(g.keys[nb[hit]], g.keys[hit] + g.offset_key(1, 0, 0))
