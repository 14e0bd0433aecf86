"""Per-frame, per-class reliability veto (occufly.lifting.reliability, issue 37)."""

from __future__ import annotations

import numpy as np

from occufly.lifting.classes import ClassColumns
from occufly.lifting.reliability import (
    frame_class_agreement,
    frame_class_agreement_loo,
    vetoed_counts,
    vetoes,
)
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()
CLS = ClassColumns(TAX)
ID = {c.name: c.id for c in TAX.classes}


def _crew(n=2000):
    """Points 0..n/2 grass, the rest road; frames 0-3 careful, frame 4 paints grass as
    vegetation. A thin class (person, points 0..50) that every frame paints poorly."""
    truth = np.where(np.arange(n) < n // 2, ID["grass"], ID["road"]).astype(np.uint8)
    truth[:50] = ID["person"]
    frames = {}
    rng = np.random.default_rng(0)
    for f in range(5):
        pids = np.arange(n, dtype=np.int32)
        lab = truth.copy()
        lab[:50] = np.where(rng.random(50) < 0.3, ID["person"], ID["grass"])  # thin: 30 % right
        if f == 4:
            lab[lab == ID["grass"]] = ID["vegetation"]
        frames[f] = (pids, CLS.col_of[lab].astype(np.uint8), np.ones(n, np.uint8))
    counts = np.zeros((n, CLS.C), np.uint16)
    for pids, cols, w in frames.values():
        counts[pids, cols] += w
    return truth, frames, counts


def test_the_systematically_wrong_frame_loses_that_class_only():
    truth, frames, counts = _crew()
    votes, agree = frame_class_agreement({f: v[:2] for f, v in frames.items()}, truth, CLS)
    veto = vetoes(votes, agree)
    veg, road, person = (CLS.col_of[ID[c]] for c in ("vegetation", "road", "person"))
    assert set(veto) == {4}  # the careful frames keep every vote, even the thin class's
    assert veto[4][veg] and not veto[4][road] and not veto[4][person]
    out = vetoed_counts(counts, frames, veto)
    assert out[:, veg].sum() == 0 and np.array_equal(out[:, road], counts[:, road])
    assert out.sum() == counts.sum() - (frames[4][1] == veg).sum()
    assert counts[:, veg].sum() > 0  # the input is not changed


def test_no_veto_with_too_few_frames_or_votes():
    truth, frames, _ = _crew()
    two = {f: frames[f][:2] for f in (0, 4)}
    assert vetoes(*frame_class_agreement(two, truth, CLS)) == {}
    few = {f: (v[0][:150], v[1][:150]) for f, v in frames.items()}  # < 200 votes per class
    assert vetoes(*frame_class_agreement(few, truth, CLS)) == {}


def test_judged_by_the_other_frames_a_painter_who_won_the_lifting_still_loses():
    truth, frames, counts = _crew()
    veg, grass = CLS.col_of[ID["vegetation"]], CLS.col_of[ID["grass"]]
    # a first lifting that went his way (his grass-as-vegetation won): he agrees with it
    lifted = truth.copy()
    lifted[truth == ID["grass"]] = ID["vegetation"]
    pairs = {f: v[:2] for f, v in frames.items()}
    assert 4 not in vetoes(*frame_class_agreement(pairs, lifted, CLS))
    # the other frames' votes on the same points still outvote him
    veto = vetoes(*frame_class_agreement_loo(pairs, counts, CLS))
    assert set(veto) == {4} and veto[4][veg] and not veto[4][grass]
