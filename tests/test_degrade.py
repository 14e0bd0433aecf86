"""The degraded-mask generator: each effect does what it says, seeded and order-free."""

from __future__ import annotations

import numpy as np

from occufly.synthetic.degrade import Degradation, degrade_mask, degrade_masks
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()
ID = {c.name: c.id for c in TAX.classes}


def _mask():
    m = np.full((120, 160), ID["road"], np.uint8)
    m[:, 80:] = ID["grass"]
    m[10:50, 10:60] = ID["building"]
    m[70:73, 100:103] = ID["person"]  # 9 px: a tiny object
    return m


OFF = dict(shift_px=0, min_blob=0, skip_prob=0, confusion_rate=0, patches=0)


def test_each_effect():
    m = _mask()
    same = degrade_mask(m, TAX, 0, Degradation(**OFF))
    assert np.array_equal(same, m)
    # boundaries move by a few pixels, never more than shift_px
    b = degrade_mask(m, TAX, 1, Degradation(**{**OFF, "shift_px": 3.0}))
    changed = b != m
    assert 0 < changed.mean() < 0.1
    rows, cols = np.nonzero(changed)
    assert (np.abs(cols - 80) <= 3).sum() + ((rows >= 7) & (rows <= 53)).sum() >= len(rows)
    # tiny objects are painted over by their surroundings
    s = degrade_mask(m, TAX, 2, Degradation(**{**OFF, "min_blob": 20, "skip_prob": 1.0}))
    assert not (s == ID["person"]).any() and (s[70:73, 100:103] == ID["grass"]).all()
    kept = [(degrade_mask(m, TAX, k, Degradation(**{**OFF, "min_blob": 20, "skip_prob": 0.5}))
             == ID["person"]).any() for k in range(40)]
    assert 8 < sum(kept) < 32  # skipped in about half the frames
    # confusions swap whole regions with their look-alike only
    c = degrade_mask(m, TAX, 3, Degradation(**{**OFF, "confusion_rate": 1.0}))
    assert (c[m == ID["road"]] == ID["parking_lot"]).all()
    assert (c[m == ID["grass"]] == ID["vegetation"]).all()
    assert (c[m == ID["building"]] == ID["roof"]).all()
    assert (c[m == ID["person"]] == ID["person"]).all()
    # unpainted patches are 0 (no vote), everything else untouched
    u = degrade_mask(m, TAX, 4, Degradation(**{**OFF, "patches": 3, "patch_frac": 0.2}))
    assert (u == 0).any() and ((u == m) | (u == 0)).all()


def test_seeded_and_independent_of_order():
    masks = {3: _mask(), 7: _mask()}
    a = degrade_masks(masks, TAX, seed=5)
    b = degrade_masks({7: masks[7], 3: masks[3]}, TAX, seed=5)
    assert all(np.array_equal(a[k], b[k]) for k in masks)
    assert not np.array_equal(a[3], a[7])  # each frame its own draw
    assert not np.array_equal(a[3], degrade_masks(masks, TAX, seed=6)[3])


# ---- the second noise model: the sloppy crew (occufly.synthetic.noise, issue 37) ----------
def _crew_mask():
    m = np.full((120, 160), ID["road"], np.uint8)
    m[:, 80:] = ID["grass"]
    m[:, 140:] = ID["parking_lot"]
    m[10:50, 10:60] = ID["roof"]
    m[60:80, 20:50] = ID["vehicle"]
    m[100:102, :] = ID["cable"]
    return m


def test_crew_sloppy_annotator_is_systematic_and_one_way():
    from occufly.synthetic.noise import CAREFUL, SLOPPY, paint

    m = _crew_mask()
    s = paint(m, TAX, np.random.default_rng(0), SLOPPY)
    # every grass / parking lot / roof region painted as its look-alike; cables never painted
    for gone in ("grass", "parking_lot", "roof", "cable"):
        assert not (s == ID[gone]).any(), gone
    assert (s[30, 30] == ID["building"]) and (s[60, 110] == ID["vegetation"])
    # the reverse confusions never happen: a vegetation region stays vegetation
    v = np.full((60, 60), ID["vegetation"], np.uint8)
    assert (paint(v, TAX, np.random.default_rng(1), SLOPPY) != ID["grass"]).all()
    # a careful annotator keeps the regions (only boundary drift, a patch, rare object swaps)
    c = paint(m, TAX, np.random.default_rng(0), CAREFUL)
    assert (c == ID["grass"]).mean() > 0.3 and (c == ID["roof"]).any()
    assert 0 < (c != m).mean() < 0.1


def test_crew_deals_frames_seeded_and_order_free():
    from occufly.synthetic.noise import Crew, crew_masks

    masks = {i: _crew_mask() for i in range(40)}
    a, who = crew_masks(masks, TAX, seed=3)
    b, who2 = crew_masks(dict(reversed(list(masks.items()))), TAX, seed=3)
    assert who == who2 and all(np.array_equal(a[i], b[i]) for i in masks)
    sloppy = [f for f, w in who.items() if w < Crew().sloppy]
    assert 4 <= len(sloppy) <= 18  # about a quarter of the frames
    for f in sloppy:
        assert not (a[f] == ID["grass"]).any()
    careful = [f for f, w in who.items() if w >= Crew().sloppy]
    assert all((a[f] == ID["grass"]).any() for f in careful)
