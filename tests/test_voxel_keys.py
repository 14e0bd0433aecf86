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


def _numpy_lattice(xyz, edge, pad, origin=None):
    """The lattice as VoxelGrid computed it with numpy before the compiled keys."""
    mn = (xyz.min(axis=0) if origin is None else np.asarray(origin)).astype(np.float64)
    q = np.floor((xyz - mn) / edge).astype(np.int64) + pad
    dims = q.max(axis=0) + pad + 1
    return mn, dims, (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("origin", [None, "below", "inside"])
def test_compiled_lattice_equals_numpy(dtype, origin, tmp_path):
    from occufly.lifting.blockknn import voxel_keys

    rng = np.random.default_rng(7)
    xyz = (rng.normal(0, 40, (30_000, 3)) + [300.0, -20.0, 5.0]).astype(dtype)
    # points exactly on voxel faces, where float rounding decides the cell
    xyz[:500] = (np.round(xyz[:500] / 0.35) * 0.35).astype(dtype)
    org = {None: None, "below": xyz.min(axis=0) - 3.3, "inside": np.median(xyz, axis=0)}[origin]
    for edge, pad in ((0.35, 1), (1.0, 2), (2.5, 0)):
        mn, dims, key = voxel_keys(xyz, edge, pad, org)
        rmn, rdims, rkey = _numpy_lattice(xyz, edge, pad, org)
        assert np.array_equal(mn, rmn) and mn.dtype == np.float64
        assert np.array_equal(dims, rdims)
        assert np.array_equal(key, rkey) and key.dtype == np.int64
    # a file map and a strided view give the same as the array
    m = np.lib.format.open_memmap(tmp_path / "x.npy", mode="w+", dtype=dtype, shape=xyz.shape)
    m[:] = xyz
    assert np.array_equal(voxel_keys(m, 0.5, 1)[2], voxel_keys(xyz, 0.5, 1)[2])
    wide = np.zeros((len(xyz), 4), dtype)
    wide[:, :3] = xyz
    assert np.array_equal(voxel_keys(wide[:, :3], 0.5, 1)[2], _numpy_lattice(xyz, 0.5, 1)[2])


def test_compiled_lattice_refuses_no_points():
    from occufly.lifting.blockknn import voxel_keys

    with pytest.raises(ValueError, match="n >= 1"):
        voxel_keys(np.zeros((0, 3), np.float32), 1.0, 1)


def test_points_in_box_equals_the_gathered_comparison():
    from occufly.lifting.blockknn import points_in_box

    rng = np.random.default_rng(11)
    xyz = rng.uniform(-5, 5, (20_000, 3)).astype(np.float32)
    ids = np.sort(rng.choice(len(xyz), 9_000, replace=False))
    lo, hi = np.array([-1.0, -2.0, float(xyz[ids[3], 2])]), np.array([2.5, 1.0, 4.0])
    ref = np.all((xyz[ids] >= lo) & (xyz[ids] <= hi), axis=1)
    got = points_in_box(xyz, ids, lo, hi)
    assert got.dtype == bool and np.array_equal(got, ref) and 0 < ref.sum() < len(ids)
    assert got[3] == ref[3]  # a point on the box's face counts


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_block_sum_is_the_numpy_sum_bit_for_bit(dtype):
    rng = np.random.default_rng(2)
    xyz = rng.uniform(0, 9, (8_000, 3)).astype(np.float32)
    g = VoxelGrid(xyz, 0.6, pad=1)
    counts = rng.uniform(0, 3, (g.n_voxels, 5)).astype(dtype) * (rng.random((g.n_voxels, 1)) < 0.7)
    ref = counts.copy()  # the numpy version: offsets in order, occupied neighbours only
    allv = np.arange(g.n_voxels)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if dx == dy == dz == 0:
                    continue
                nb = g.neighbour(allv, dx, dy, dz)
                ok = nb >= 0
                ref[ok] += counts[nb[ok]]
    got = g.block_sum(counts)
    assert got.dtype == dtype and np.array_equal(got, ref)
    assert not np.array_equal(got, counts)
    # integer counts take the numpy path, with the same sums
    ic = (counts * 10).astype(np.int64)
    assert np.array_equal(g.block_sum(ic), np.rint(g.block_sum(ic.astype(np.float64))).astype(np.int64))


def _sparse_voxels(seed: int, n: int = 400, span: float = 30.0):
    """A sparse cloud (most voxels empty, so diagonal neighbours often sit behind empty ones)
    and its voxel grid's integer coordinates."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, span, (n, 3)).astype(np.float32)
    g = VoxelGrid(xyz, 1.0, pad=4)
    c0, rest = np.divmod(g.keys, g.dims[1] * g.dims[2])
    c1, c2 = np.divmod(rest, g.dims[2])
    return g, np.stack([c0, c1, c2], axis=1), rng


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("r", [0, 1, 2, 4])
def test_dilate_is_the_chebyshev_dilation_through_empty_voxels(seed, r):
    """Every occupied voxel within r steps of a given one, whether or not the voxels between
    are occupied (the dilation once stepped through occupied voxels only and missed most of
    them in a sparse cloud)."""
    g, coords, rng = _sparse_voxels(seed)
    given = np.sort(rng.choice(g.n_voxels, 25, replace=False))
    cheb = np.abs(coords[:, None, :] - coords[None, given, :]).max(axis=2).min(axis=1)
    want = np.flatnonzero(cheb <= r)
    got = g.dilate(given, r)
    assert np.array_equal(got, want)
    if r >= 2:
        assert len(want) > len(given)  # the case the old dilation got wrong: far, sparse voxels


def test_dilate_refuses_steps_beyond_the_pad():
    g, _c, _rng = _sparse_voxels(0)
    with pytest.raises(ValueError, match="pad"):
        g.dilate(np.arange(3), 5)


@pytest.mark.parametrize("seed", [0, 3])
@pytest.mark.parametrize("r", [1, 2, 3, 4, 7, 10])
@pytest.mark.parametrize("split", [1, 3])
def test_near_marks_every_voxel_within_r_and_none_far_beyond(seed, r, split):
    g, coords, rng = _sparse_voxels(seed, n=1500, span=60.0)
    given = rng.choice(g.n_voxels, 40, replace=False)
    cheb = np.abs(coords[:, None, :] - coords[None, given, :]).max(axis=2).min(axis=1)
    got = g.near(given, r, split=split)
    assert got.dtype == bool and got.shape == (g.n_voxels,)
    assert got[cheb <= r].all()  # a superset: nothing within r is left out
    b = -(-r // split)
    reach = (-(-r // b) + 1) * b - 1  # the farthest a voxel of a block in reach can be
    assert not got[cheb > reach].any()
    assert reach < 2 * r or r == 1
    assert got.sum() < g.n_voxels
