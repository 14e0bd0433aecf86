"""The one confusion matrix (occufly.confusion) and the four metrics built on it."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.confusion import Confusion
from occufly.densify.evaluate import evaluate_grids
from occufly.grid import SceneGrid
from occufly.metrics import SSCAccumulator, evaluate_points
from occufly.render import agreement, merge_agreements
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()
NAMES = {c.id: c.name for c in TAX.classes}


def test_counts_columns_and_absent_rule():
    c = Confusion([6, 16, 8])
    truth = np.array([6, 6, 16, 0, 0, 8, 6], np.uint8)
    pred = np.array([6, 16, 16, 16, 0, 77, 255], np.uint8)
    c.add(truth, pred)
    m = c.matrix
    assert m.shape == (5, 5) and m.sum() == 7
    # rows truth, cols pred; 77 and 255 land in the "other" column 4
    assert m[1, 1] == 1 and m[1, 2] == 1 and m[1, 4] == 1 and m[3, 4] == 1 and m[0, 2] == 1
    iou = c.class_iou()
    assert iou[0] == pytest.approx(1 / 3)  # grass: TP 1, FN 2
    assert iou[1] == pytest.approx(1 / 3)  # building: TP 1, FP 2
    assert iou[2] == 0.0  # tree: in the truth, never predicted -> IoU 0, still in the mean
    assert c.miou() == pytest.approx((1 / 3 + 1 / 3 + 0) / 3)
    comp = c.completion()  # occupied = any column but empty
    assert comp["precision"] == pytest.approx(5 / 6) and comp["recall"] == pytest.approx(5 / 5)
    # a class absent from both sides is n/a and left out of the mean
    c2 = Confusion([6, 16, 8]).add(np.array([6, 6], np.uint8), np.array([6, 16], np.uint8))
    assert c2.per_class_iou() == {"6": 0.5, "16": 0.0, "8": None}
    assert c2.miou() == pytest.approx(0.25) and c2.classes_evaluated() == 2
    # keep mask, merge, chunked counting agree with one pass
    k = np.array([1, 0, 1, 1, 1, 1, 1], bool)
    ck = Confusion([6, 16, 8]).add(truth, pred, k)
    assert ck.total() == 6 and ck.matrix[1, 2] == 0
    assert np.array_equal(Confusion([6, 16, 8]).merge(ck).matrix, ck.matrix)
    with pytest.raises(ValueError):
        c.add(truth, pred[:3])
    with pytest.raises(ValueError):
        Confusion([0, 6])
    assert Confusion([]).miou() is None and Confusion([]).completion()["iou"] is None


def test_chunked_counting_equals_one_pass(monkeypatch):
    import occufly.confusion as cm

    rng = np.random.default_rng(3)
    t = rng.choice([0, 6, 16, 8, 255, 99], 5000).astype(np.uint8)
    p = rng.choice([0, 6, 16, 8, 255, 99], 5000).astype(np.uint8)
    keep = rng.random(5000) < 0.7
    one = Confusion(TAX.ids).add(t, p, keep).matrix.copy()
    monkeypatch.setattr(cm, "_CHUNK", 317)
    assert np.array_equal(Confusion(TAX.ids).add(t, p, keep).matrix, one)
    # brute force
    ref = np.zeros_like(one)
    lut = Confusion(TAX.ids).lut
    for a, b, k in zip(t, p, keep, strict=True):
        if k:
            ref[lut[a], lut[b]] += 1
    assert np.array_equal(one, ref)


def test_four_metrics_agree_on_the_same_labels():
    """Where the evaluated items coincide (every truth item a class, every prediction a class),
    SSC, grid, point and 2-D agreement metrics give the same per-class IoU and mIoU -- also for
    a class that is predicted but absent from the truth (IoU 0, in the mean) and one absent
    from both (n/a, not in the mean)."""
    truth = np.array([6, 6, 6, 16, 16, 1, 1, 1], np.uint8)
    pred = np.array([6, 6, 16, 16, 8, 1, 1, 6], np.uint8)  # 8 (tree) never in the truth
    acc = SSCAccumulator(TAX.ids)
    acc.add(pred, truth)
    ssc = acc.result(TAX)
    grid = evaluate_grids(SceneGrid(pred.reshape(8, 1, 1), np.zeros(3), 0.5),
                          SceneGrid(truth.reshape(8, 1, 1), np.zeros(3), 0.5), TAX)
    pts = evaluate_points(pred, truth, TAX)
    ag = agreement(truth.reshape(2, 4), pred.reshape(2, 4), TAX)
    merged = merge_agreements([ag])
    expect = {"grass": 2 / 4, "building": 1 / 3, "road": 2 / 3, "tree": 0.0}
    for name, v in expect.items():
        assert ssc["per_class_iou"][name] == pytest.approx(v)
        assert grid["per_class_iou"][name] == pytest.approx(v)
        assert pts["per_class"][name]["iou"] == pytest.approx(v)
        assert ag["per_class"][name]["iou"] == pytest.approx(v)
    assert merged["per_class_iou"][8] == 0.0
    miou = sum(expect.values()) / 4
    for r in (ssc, grid, pts, ag, merged):
        assert r["miou"] == pytest.approx(miou)
    # absent from both: n/a (None) in the full listings, missing from the present-only ones
    assert ssc["per_class_iou"]["vehicle"] is None and grid["per_class_iou"]["vehicle"] is None
    assert "vehicle" not in pts["per_class"] and "vehicle" not in ag["per_class"]
    assert 13 not in merged["per_class_iou"]
