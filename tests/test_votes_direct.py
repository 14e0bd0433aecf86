"""The vote majority the live worker snapshots under its update lock (``VoteStore._direct``):
the compiled pass equals the numpy passes it replaced, bit for bit -- winner by the taxonomy's
tie order, its votes, the second class and its votes, the margin -- on counts with ties, rows
without votes and one-vote rows, for 8/16/32-bit counts, and on a memory-mapped file."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from occufly.lifting import votes as V
from occufly.lifting.classes import ClassColumns
from occufly.taxonomy import default_taxonomy

CLS = ClassColumns(default_taxonomy())


def _counts(rng, n: int, dtype, high: int) -> np.ndarray:
    c = rng.integers(0, high, (n, CLS.C)).astype(dtype)
    c[rng.random((n, CLS.C)) < 0.8] = 0  # sparse rows, as real votes are
    c[: n // 10] = 0  # no votes at all
    tie = np.arange(n // 10, n // 5)
    c[tie, :] = 0
    c[tie, rng.integers(0, CLS.C, len(tie))] = 3  # ties between two columns
    c[tie, rng.integers(0, CLS.C, len(tie))] = 3
    c[n // 5: n // 4] = 0
    c[np.arange(n // 5, n // 4), rng.integers(0, CLS.C, n // 4 - n // 5)] = 1  # one vote
    return c


def _direct(counts, compiled: bool, monkeypatch) -> tuple:
    monkeypatch.setattr(V, "COMPILED_DIRECT", compiled)
    fake = SimpleNamespace(votes=counts, scene=SimpleNamespace(n_points=len(counts)), _cls=CLS)
    return V.VoteStore._direct(fake, with_second=True), V.VoteStore._direct(fake)


@pytest.mark.parametrize("dtype,high", [(np.uint8, 6), (np.uint16, 40), (np.uint16, 60_000),
                                        (np.uint32, 5)])
def test_compiled_majority_equals_the_numpy_passes(dtype, high, monkeypatch):
    rng = np.random.default_rng(high)
    c = _counts(rng, 30_011, dtype, high)
    assert V.direct_compiles(c, CLS)
    got2, got1 = _direct(c, True, monkeypatch)
    want2, want1 = _direct(c, False, monkeypatch)
    for g, w in zip(got2 + got1, want2 + want1, strict=True):
        assert g.dtype == w.dtype and np.array_equal(g.view(np.uint8), w.view(np.uint8))
    labels, margin, top, col2, votes2 = got2
    assert (labels == 0).sum() >= len(c) // 10 and (col2 >= 0).any() and (margin == 0).any()


def test_compiled_majority_reads_a_memory_map(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    c = _counts(rng, 5_000, np.uint16, 30)
    np.save(tmp_path / "votes.npy", c)
    mm = np.load(tmp_path / "votes.npy", mmap_mode="r")
    got, _ = _direct(mm, True, monkeypatch)
    want, _ = _direct(c, False, monkeypatch)
    assert all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))


def test_other_counts_take_the_numpy_path():
    assert not V.direct_compiles(np.zeros((3, CLS.C), np.int32), CLS)
    assert not V.direct_compiles(np.zeros((3, CLS.C), np.uint64), CLS)
    assert not V.direct_compiles(np.zeros((3, CLS.C), np.float32), CLS)
