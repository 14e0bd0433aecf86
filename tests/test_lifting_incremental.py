"""Issue 29: the incremental fill (occufly.lifting.incremental) equals a full fill bit for bit
and recomputes only a neighbourhood of the points whose decided label changed."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.lifting import LiftParams, fill_and_denoise
from occufly.lifting.incremental import IncrementalFill
from occufly.taxonomy import default_taxonomy

ROAD, GRASS, TREE, BUILDING, PERSON = 1, 6, 8, 16, 10


def _cloud(n: int = 60_000, side: float = 160.0, seed: int = 0):
    """Jittered ground with a few raised blocks (no duplicate points: no distance ties)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    z = rng.normal(0, 0.05, n)
    blocks = (np.abs(xy[:, 0] - 40) < 8) & (np.abs(xy[:, 1] - 50) < 10)
    z[blocks] += 6 + rng.uniform(0, 0.5, blocks.sum())
    xyz = np.column_stack([xy, z]).astype(np.float32)
    truth = np.full(n, GRASS, np.uint8)
    truth[np.abs(xy[:, 1] - 80) < 6] = ROAD
    truth[blocks] = BUILDING
    truth[np.hypot(xy[:, 0] - 120, xy[:, 1] - 120) < 9] = TREE
    return xyz, truth, rng


def _votes(xyz, truth, rng, covered: np.ndarray):  # noqa: ANN001
    """Direct labels on the covered points (some noise), margins and supports."""
    direct = np.where(covered, truth, 0).astype(np.uint8)
    noise = covered & (rng.random(len(truth)) < 0.03)
    direct[noise] = rng.choice([ROAD, GRASS, TREE], noise.sum())
    top = np.where(covered, rng.integers(1, 4, len(truth)), 0).astype(np.uint16)
    margin = np.where(covered, rng.choice([0.0, 0.34, 0.5, 1.0], len(truth)), 0).astype(np.float32)
    return direct, margin, top


def _same(a, b) -> None:  # noqa: ANN001
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.origin, b.origin)
    np.testing.assert_array_equal(a.confidence, b.confidence)


@pytest.mark.parametrize("robust_like", [False, True])
def test_incremental_fill_equals_the_full_fill_and_stays_local(robust_like):
    xyz, truth, rng = _cloud()
    tax = default_taxonomy()
    p = LiftParams(robust=False)
    # frames' footprints: the covered part grows, one footprint at a time
    covered = (xyz[:, 0] < 70) & (xyz[:, 1] < 110)
    direct, margin, top = _votes(xyz, truth, rng, covered)
    inc = IncrementalFill(xyz, tax)
    first = inc.fill(direct, params=p, vote_margin=margin, vote_top=top)
    _same(first, fill_and_denoise(xyz, direct, tax, params=p, vote_margin=margin, vote_top=top))
    assert not inc.last["incremental"]
    new = None
    for step in range(3):
        # a reviewer's correction / a resubmitted mask: a 12 m patch of the covered part
        c = np.array([15.0 + 20 * step, 20.0 + 25 * step])
        patch = covered & (np.abs(xyz[:, 0] - c[0]) < 6) & (np.abs(xyz[:, 1] - c[1]) < 6)
        direct = direct.copy()
        direct[patch] = PERSON if step % 2 else ROAD
        if step == 2:  # a new footprint next to the covered part
            new = (xyz[:, 0] >= 70) & (xyz[:, 0] < 85) & (xyz[:, 1] < 30)
            direct[new] = truth[new]
            top = top.copy()
            top[new] = 1
            margin = margin.copy()
            margin[new] = 1.0
            covered = covered | new
        if robust_like:  # a re-estimated annotator model: margins move everywhere (a
            # posterior margin is a tie only where it is exactly 0, and stays so)
            margin = np.where(margin > 0, np.clip(margin + rng.normal(0, 0.05, len(margin)),
                                                  0.01, 1), 0).astype(np.float32)
        got = inc.fill(direct, params=p, vote_margin=margin, vote_top=top)
        want = fill_and_denoise(xyz, direct, tax, params=p, vote_margin=margin, vote_top=top)
        _same(got, want)
        assert inc.last["incremental"], inc.last
        assert 0 < inc.last["updated_points"] <= inc.last["region_points"] < 0.5 * len(xyz)
    assert (first.labels[new] == 0).mean() > 0.5  # beyond the fill radius at first ...
    assert (got.labels[new] > 0).all()  # ... labelled by the update


def test_a_change_across_most_of_the_cloud_falls_back_to_a_full_fill():
    xyz, truth, rng = _cloud(n=20_000, side=60.0)
    tax = default_taxonomy()
    p = LiftParams(robust=False)
    covered = xyz[:, 0] < 40
    direct, margin, top = _votes(xyz, truth, rng, covered)
    inc = IncrementalFill(xyz, tax)
    inc.fill(direct, params=p, vote_margin=margin, vote_top=top)
    direct2 = np.where(direct > 0, ROAD, 0).astype(np.uint8)
    got = inc.fill(direct2, params=p, vote_margin=margin, vote_top=top)
    assert not inc.last["incremental"] and "context region" in inc.last["reason"]
    _same(got, fill_and_denoise(xyz, direct2, tax, params=p, vote_margin=margin, vote_top=top))
    # other parameters: a full fill, not an update against the old ones
    p2 = LiftParams(robust=False, denoise_keep_share=None)
    got = inc.fill(direct2, params=p2, vote_margin=margin, vote_top=top)
    assert not inc.last["incremental"]
    _same(got, fill_and_denoise(xyz, direct2, tax, params=p2, vote_margin=margin, vote_top=top))
