"""occufly.subsample: the viewer's stratified choice and tile binning, compiled (issue 38)."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.subsample import selection_sample, tile_groups


def _reference_groups(xyz: np.ndarray, ids: np.ndarray, tiles: int) -> np.ndarray:
    """The numpy version the kernel replaced (app/viewer/point_lod.py before issue 38's
    compiled pass)."""
    xy = np.asarray(np.take(xyz, ids, axis=0)[:, :2], np.float64)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = np.maximum(hi - lo, 1e-6)
    cell = np.minimum(((xy - lo) / span * tiles).astype(np.int64), tiles - 1)
    return (1 + cell[:, 0] * tiles + cell[:, 1]).astype(np.int16)


@pytest.mark.parametrize("tiles", [1, 4, 7])
def test_tile_groups_equal_the_numpy_cells(tmp_path, tiles):
    rng = np.random.default_rng(3)
    xyz = (rng.normal(size=(200_000, 3)) * [300.0, 80.0, 5.0]).astype(np.float32)
    xyz[7] = [xyz[:, 0].max(), xyz[:, 1].max(), 0]  # on the upper bound: the last cell
    np.save(tmp_path / "xyz.npy", xyz)
    mm = np.load(tmp_path / "xyz.npy", mmap_mode="r")  # the viewer's cloud is memory-mapped
    ids = np.sort(rng.choice(len(xyz), 50_000, replace=False)).astype(np.int64)
    ids[0] = 7
    ids.sort()
    group, lo, hi = tile_groups(mm, ids, tiles)
    np.testing.assert_array_equal(group, _reference_groups(xyz, ids, tiles))
    sel = np.asarray(xyz[ids, :2], np.float64)
    np.testing.assert_array_equal(lo, sel.min(axis=0))
    np.testing.assert_array_equal(hi, sel.max(axis=0))
    assert group.min() >= 1 and group.max() <= tiles * tiles


def test_tile_groups_of_a_line_and_float64_cloud():
    xyz = np.zeros((10, 3), np.float64)
    xyz[:, 1] = np.arange(10)  # every x the same: span 1e-6, one column of cells
    ids = np.arange(10, dtype=np.int64)
    group, _lo, _hi = tile_groups(xyz, ids, 4)
    np.testing.assert_array_equal(group, _reference_groups(xyz, ids, 4))
    with pytest.raises(ValueError, match="no points"):
        tile_groups(xyz, ids[:0], 4)


def test_selection_sample_takes_each_quota_exactly_sorted_and_deterministic():
    rng = np.random.default_rng(0)
    labels = rng.choice(np.array([0, 3, 9, 200], np.uint8), size=300_000, p=[.7, .2, .0999, .0001])
    counts = np.bincount(labels, minlength=256).astype(np.int64)
    quotas = np.zeros(256, np.int64)
    quotas[0], quotas[3], quotas[9], quotas[200] = 1000, counts[3], 0, counts[200] - 1
    idx = selection_sample(labels, quotas, counts, seed=5)
    assert idx.dtype == np.int64 and (np.diff(idx) > 0).all()
    np.testing.assert_array_equal(np.bincount(labels[idx], minlength=256), quotas)
    np.testing.assert_array_equal(idx, selection_sample(labels, quotas, counts, seed=5))
    assert not np.array_equal(idx, selection_sample(labels, quotas, counts, seed=6))


def test_selection_sample_is_uniform_within_a_class():
    """Every member equally likely: over 400 draws of 100 of 1,000 points (one class
    interleaved with another), each point's frequency stays near 0.1, and the first and the
    last tenth of the class are chosen as often (a biased pass favours one end)."""
    labels = np.tile(np.array([1, 2], np.uint8), 1000)
    counts = np.bincount(labels, minlength=256).astype(np.int64)
    quotas = np.zeros(256, np.int64)
    quotas[1] = 100
    hits = np.zeros(len(labels))
    for s in range(400):
        hits[selection_sample(labels, quotas, counts, seed=s)] += 1
    freq = hits[labels == 1] / 400
    assert hits[labels == 2].sum() == 0
    assert abs(freq.mean() - 0.1) < 1e-12
    assert freq.min() > 0.03 and freq.max() < 0.2  # binomial(400, 0.1): sd 0.015
    assert abs(freq[:100].mean() - freq[-100:].mean()) < 0.01


def test_selection_sample_refuses_impossible_quotas():
    labels = np.zeros(10, np.uint8)
    counts = np.bincount(labels, minlength=256).astype(np.int64)
    quotas = np.zeros(256, np.int64)
    quotas[0] = 11
    with pytest.raises(ValueError, match="quota <= count"):
        selection_sample(labels, quotas, counts)
    with pytest.raises(TypeError, match="uint8"):
        selection_sample(labels.astype(np.int32), np.zeros(256, np.int64), counts)
