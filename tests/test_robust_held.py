"""The held robust decision (issue 37, eighth round): a live scene's next decision keeps the
fitted model and decides again only around the changed votes.

The reference is the decision of *every* voted point with the held model, written here with
the module's own pieces (its neighbourhood counts over all voted points on their own lattice):
the warm decision must equal it bit for bit, and must fall back to fitting the model where the
model no longer describes the votes.
"""

from __future__ import annotations

import numpy as np
import pytest

from occufly.lifting import robust
from occufly.progress import noop
from tests.test_robust_decision import _votes


def _all_with(h: robust.HeldDecision, cls, feats, col1, n1, col2, n2, xyz, p):  # noqa: ANN001, ANN202
    """Every voted point decided with the held model (the neighbourhood counted over all of
    them, the lattice's corner their minimum): what a warm decision must reproduce."""
    n = len(col1)
    labels, margin, top = np.zeros(n, np.uint8), np.zeros(n, np.float32), np.zeros(n, np.uint16)
    vidx = np.flatnonzero(n1 > 0)
    vox, block = robust.local_votes(xyz, vidx, col1, n1, col2, n2, cls.C, p.local_voxel)
    local = (vox, *robust._local_prior_tables(block, h.prior, p))
    robust._decide_all(cls, vidx, col1, n1, col2, n2, h.logpi, h.logprior_scene, h.logprior,
                       local, min(p.candidates, cls.C), p, feats, h.q, None, labels, margin,
                       top, True, None, 1, noop)
    return labels, margin, top


def _paint(rng, xyz, col1, n1, col2, n2, centre, radius, cls_col):  # noqa: ANN001, ANN202
    """A brush stroke: the points within ``radius`` of ``centre`` get one more vote for
    ``cls_col`` (as their leader where it then leads)."""
    c1, m1, c2, m2 = col1.copy(), n1.copy(), col2.copy(), n2.copy()
    hit = np.flatnonzero(np.abs(xyz - centre).max(axis=1) < radius)
    for i in hit:
        if c1[i] == cls_col:
            m1[i] += 1
        elif c2[i] == cls_col and m2[i] + 1 > m1[i]:
            c1[i], m1[i], c2[i], m2[i] = cls_col, m2[i] + 1, c1[i], m1[i]
        elif c2[i] == cls_col:
            m2[i] += 1
        elif m1[i] == 0:
            c1[i], m1[i] = cls_col, 1
        else:
            c2[i], m2[i] = cls_col, 1
    return c1, m1, c2, m2, hit


@pytest.mark.parametrize("seed", [0, 1])
def test_a_warm_decision_equals_every_point_decided_with_the_held_model(seed):
    cls, feats, col1, n1, col2, n2, xyz = _votes(seed)
    rng = np.random.default_rng(seed + 10)
    p = robust.RobustParams()
    h = robust.HeldDecision()
    first = robust.redecide(cls, feats, col1, n1, col2, n2, p, xyz=xyz, held=h)
    assert first[3]["robust_cold_why"] == "no held model"
    # the cold decision is what the held model gives every point
    for a, b in zip(first[:3], _all_with(h, cls, feats, col1, n1, col2, n2, xyz, p), strict=True):
        np.testing.assert_array_equal(a, b)
    cur = (col1, n1, col2, n2)
    for step in range(3):
        centre = rng.uniform(3, 27, 3).astype(np.float32)
        c1, m1, c2, m2, hit = _paint(rng, xyz, *cur, centre, 2.0, int(rng.integers(0, cls.C)))
        assert len(hit) > 50
        if step == 2:  # votes taken away as well: a frame's points that lose every vote
            gone = hit[: len(hit) // 3]
            c1[gone], m1[gone], c2[gone], m2[gone] = -1, 0, -1, 0
        cur = (c1, m1, c2, m2)
        got = robust.redecide(cls, feats, *cur, p, xyz=xyz, held=h)
        stats = got[3]
        assert stats["robust_warm"] is True
        # only the stroke and the blocks around it were decided again
        assert 0 < stats["robust_warm_decided"] < 0.2 * len(col1)
        want = _all_with(h, cls, feats, *cur, xyz, p)
        for a, b in zip(got[:3], want, strict=True):
            np.testing.assert_array_equal(a, b)
        # the matrix it reports is the held one, for the review's leave-one-out labels
        assert stats["robust_matrix"] == first[3]["robust_matrix"]


def test_unchanged_votes_keep_the_last_result():
    cls, feats, col1, n1, col2, n2, xyz = _votes(2, 20_000)
    h = robust.HeldDecision()
    first = robust.redecide(cls, feats, col1, n1, col2, n2, xyz=xyz, held=h)
    again = robust.redecide(cls, feats, col1, n1, col2, n2, xyz=xyz, held=h)
    assert again[3]["robust_warm_decided"] == 0
    for a, b in zip(first[:3], again[:3], strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_model_is_fitted_again_when_too_much_changed_or_a_new_class_is_voted():
    cls, feats, col1, n1, col2, n2, xyz = _votes(3, 30_000)
    rng = np.random.default_rng(3)
    p = robust.RobustParams()
    h = robust.HeldDecision()
    robust.redecide(cls, feats, col1, n1, col2, n2, p, xyz=xyz, held=h)
    # a quarter of the points voted again in one save: over max_share_save, fitted again
    big = rng.random(len(col1)) < 0.25
    c1 = np.where(big & (n1 > 0), (col1 + 1) % cls.C, col1).astype(col1.dtype)
    got = robust.redecide(cls, feats, c1, n1, col2, n2, p, xyz=xyz, held=h)
    assert "robust_warm" not in got[3]
    assert got[3]["robust_cold_why"].endswith(f"changed votes, over 1% of {(n1 > 0).sum():,}")
    # strokes of under 1% each, until their sum since the fit passes max_share (here 2%)
    h = robust.HeldDecision(max_share=0.02)
    robust.redecide(cls, feats, c1, n1, col2, n2, p, xyz=xyz, held=h)
    cur, whys = (c1, n1, col2, n2), []
    for k in range(12):
        *cur, _hit = _paint(rng, xyz, *cur, np.float32([4 + 2 * k, 15, 15]), 2.5, k % cls.C)
        whys.append(robust.redecide(cls, feats, *cur, p, xyz=xyz, held=h)[3].get("robust_cold_why"))
    assert whys[0] is None and any(w and "since the fit, over 2%" in w for w in whys), whys
    # the fit above saw no vote for the last column; a stroke of it refits
    keep = c1 != cls.C - 1
    c1 = np.where(keep, c1, 0).astype(c1.dtype)
    c2 = np.where(col2 == cls.C - 1, -1, col2).astype(col2.dtype)
    m2 = np.where(c2 >= 0, n2, 0).astype(n2.dtype)
    h.clear()
    robust.redecide(cls, feats, c1, n1, c2, m2, p, xyz=xyz, held=h)
    c1b, m1b, c2b, m2b, _ = _paint(rng, xyz, c1, n1, c2, m2, np.float32([15, 15, 15]), 1.5,
                                   cls.C - 1)
    got = robust.redecide(cls, feats, c1b, m1b, c2b, m2b, p, xyz=xyz, held=h)
    assert got[3]["robust_cold_why"] == "a class voted that had no vote at the fit"
    # other parameters: fitted again
    got = robust.redecide(cls, feats, c1b, m1b, c2b, m2b, robust.RobustParams(refit_rounds=1),
                          xyz=xyz, held=h)
    assert got[3]["robust_cold_why"] == "other parameters, classes or points"
    # after clear(): fitted again
    h.clear()
    got = robust.redecide(cls, feats, c1b, m1b, c2b, m2b, robust.RobustParams(refit_rounds=1),
                          xyz=xyz, held=h)
    assert got[3]["robust_cold_why"] == "no held model"
