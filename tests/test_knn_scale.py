"""kNN fill + denoise at scale: threads do not change a byte, the up-front memory check."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.errors import OccuflyError
from occufly.lifting import knn
from occufly.lifting.knn import LiftParams, fill_and_denoise
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()


def _cloud(n: int = 40_000, seed: int = 0):
    """A ground plane with class patches, a few boxes, 25 % unvoted points and 5 % noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 60, (n, 2))
    z = np.where((xy[:, 0] % 20 < 6) & (xy[:, 1] % 20 < 6), rng.uniform(0, 5, n), 0.0)
    xyz = np.column_stack([xy, z + rng.normal(0, 0.05, n)]).astype(np.float32)
    ids = np.array(TAX.ids[:6])
    truth = ids[(np.floor(xy[:, 0] / 7) + 2 * np.floor(xy[:, 1] / 9)).astype(int) % 6]
    truth = np.where(z > 0.5, ids[0], truth).astype(np.uint8)
    direct = truth.copy()
    flip = rng.random(n) < 0.05
    direct[flip] = rng.choice(ids, int(flip.sum()))
    direct[(xy[:, 0] > 40) | (rng.random(n) < 0.1)] = 0  # a far unvoted strip + holes
    margin = np.where(direct > 0, 1.0, 0.0).astype(np.float32)
    top = np.where(direct > 0, 2, 0).astype(np.uint16)
    return xyz, direct, margin, top


@pytest.mark.parametrize("k", [(100, 200), (10, 30)])
def test_threads_give_the_same_bytes(k):
    xyz, direct, margin, top = _cloud()
    out = []
    for w in (1, 2, 3):
        r = fill_and_denoise(xyz, direct, TAX, vote_margin=margin, vote_top=top,
                             params=LiftParams(fill_k=k[0], denoise_k=k[1], workers=w))
        out.append(r)
    assert out[0].stats["block_denoise_points"] > 1000  # the threaded boundary pass ran
    for r in out[1:]:
        for a in ("labels", "confidence", "origin"):
            assert getattr(r, a).tobytes() == getattr(out[0], a).tobytes(), a


def test_memory_check_refuses_before_any_work(monkeypatch):
    xyz, direct, margin, top = _cloud(2000)
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: 64 * 2**20)
    with pytest.raises(OccuflyError, match=r"2,000 points needs about 0\.4 GB .* 0\.1 GB are available"):
        fill_and_denoise(xyz, direct, TAX, vote_margin=margin, vote_top=top)
    with pytest.raises(OccuflyError, match="needs about"):
        fill_and_denoise(xyz, direct, TAX, params=LiftParams(method="exact"))
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: None)  # unknown: no check
    assert len(fill_and_denoise(xyz, direct, TAX).labels) == 2000


def test_memory_estimate_is_linear():
    a, b = knn.fill_memory_estimate(10**6), knn.fill_memory_estimate(2 * 10**6)
    assert b - a == knn.FILL_BYTES_PER_POINT * 10**6
    assert knn.fill_memory_estimate(0) == knn.FILL_FIXED_BYTES
