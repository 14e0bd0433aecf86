"""Honest confidence (issue 23, defect 3): no extrapolation, calibrated confidence that falls
with distance and disagreement, reliability / ECE."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.lifting import ORIGIN_DIRECT, ORIGIN_FILLED, ORIGIN_NONE, LiftParams, fill_and_denoise
from occufly.lifting import calibration as cal
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()
ROAD, GRASS = 1, 6


def _plane(rng, x0: float, n: int = 400) -> np.ndarray:
    return np.column_stack([rng.uniform(x0, x0 + 1, n), rng.uniform(0, 1, n),
                            rng.uniform(0, 0.01, n)])


def _scene():
    """A pure road patch and a 70/30 road/grass patch 50 m apart, unvoted query points at
    0.2, 1.5 and 2.7 m from the pure patch, one at 0.2 m from the mixed patch, one 9 m from
    any vote (beyond the 3 m fill radius)."""
    rng = np.random.default_rng(0)
    pure = _plane(rng, 0.0)
    mixed = _plane(rng, 50.0)
    mix_lab = np.where(rng.random(400) < 0.7, ROAD, GRASS)
    q = np.array([[1.2, 0.5, 0], [2.5, 0.5, 0], [3.7, 0.5, 0], [51.2, 0.5, 0], [10.0, 0.5, 0]])
    xyz = np.vstack([pure, mixed, q]).astype(np.float32)
    direct = np.concatenate([np.full(400, ROAD), mix_lab, np.zeros(5)]).astype(np.uint8)
    margin = (direct > 0).astype(np.float32)
    top = (direct > 0).astype(np.uint16) * 2
    return xyz, direct, margin, top


@pytest.mark.parametrize("method", ["voxel", "exact"])
def test_no_extrapolation_and_confidence_falls_with_distance_and_disagreement(method):
    xyz, direct, margin, top = _scene()
    res = fill_and_denoise(xyz, direct, TAX, vote_margin=margin, vote_top=top,
                           params=LiftParams(method=method))
    near, mid, far, mixed, beyond = 800, 801, 802, 803, 804
    # beyond the radius from any vote: unlabelled, origin none, confidence 0 (the default)
    assert res.labels[beyond] == 0 and res.origin[beyond] == ORIGIN_NONE
    assert res.confidence[beyond] == 0.0
    for i in (near, mid, far, mixed):
        assert res.labels[i] == ROAD and res.origin[i] == ORIGIN_FILLED, (method, i)
    c = res.confidence
    # a filled label's confidence falls with the distance to the votes ...
    assert c[near] > c[mid] > c[far] > 0, (method, c[[near, mid, far]])
    # ... and with disagreement among them (same distance, 70 % instead of 100 % road)
    assert c[mixed] < c[near] - 0.05, (method, c[[near, mixed]])
    # filled labels are never as certain as unanimous votes nearby
    assert c[near] < c[:400][res.origin[:400] == ORIGIN_DIRECT].mean()
    # the old far fill is an explicit opt-in: it labels the point, at the lowest filled
    # confidence (the calibration's floor for a raw score of 0)
    old = fill_and_denoise(xyz, direct, TAX, vote_margin=margin, vote_top=top,
                           params=LiftParams(method=method, fill_far=True))
    assert old.labels[beyond] == ROAD and old.origin[beyond] == ORIGIN_FILLED
    assert old.confidence[beyond] <= old.confidence[far] < old.confidence[near]
    assert np.array_equal(old.labels[:804], res.labels[:804])
    # before issue 23 (legacy confidence) the filled points were as confident as the votes
    legacy = fill_and_denoise(xyz, direct, TAX, vote_margin=margin, vote_top=top,
                              params=LiftParams(method=method, fill_far=True, confidence="legacy"))
    assert legacy.confidence[beyond] > 0.99 and legacy.confidence[far] > 0.99


def test_reliability_bins_and_ece_analytic():
    conf = np.array([0.05, 0.15, 0.15, 0.95, 0.95, 0.95, 0.95, 1.0])
    ok = np.array([False, False, True, True, True, True, False, True])
    r = cal.reliability(conf, ok, bins=10)
    assert len(r["bins"]) == 10 and r["n"] == 8
    b0, b1, b9 = r["bins"][0], r["bins"][1], r["bins"][9]
    assert (b0["count"], b0["accuracy"], b0["mean_conf"]) == (1, 0.0, pytest.approx(0.05))
    assert (b1["count"], b1["accuracy"]) == (2, 0.5)
    assert b9["count"] == 5 and b9["accuracy"] == pytest.approx(0.8)  # 1.0 falls in the last bin
    assert r["bins"][5]["count"] == 0 and r["bins"][5]["accuracy"] is None
    ece = (1 * 0.05 + 2 * abs(0.5 - 0.15) + 5 * abs(0.8 - 0.96)) / 8
    assert r["ece"] == pytest.approx(ece)
    # perfectly calibrated: ECE 0
    assert cal.reliability(np.array([0.0, 1.0]), np.array([False, True]))["ece"] == 0.0
    with pytest.raises(ValueError, match="same length"):
        cal.reliability(np.zeros(3), np.zeros(2, bool))


def test_isotonic_fit_is_monotone_and_matches_block_rates():
    rng = np.random.default_rng(1)
    s = rng.uniform(0, 1, 20_000)
    ok = rng.random(20_000) < s ** 2  # true P(correct | s) = s^2
    x, y, n = cal.fit_isotonic(s, ok, max_knots=20, min_block=100)
    assert np.all(np.diff(x) > 0) and np.all(np.diff(y) >= 0) and n.sum() == 20_000
    assert np.abs(y - x ** 2).max() < 0.06  # each block's rate is about its centre's s^2
    table = cal.fit_table(s, np.full(20_000, ORIGIN_FILLED, np.uint8), ok)
    p = table.probability(np.full(20_000, ORIGIN_FILLED, np.uint8), s)
    assert cal.reliability(p, ok)["ece"] < 0.02
    assert cal.reliability(s, ok)["ece"] > 0.1  # the raw score is not calibrated


def test_shipped_table_names_what_it_was_fitted_on():
    table = cal.default_table()
    assert table is not None and set(table.maps) == {"direct", "filled", "denoised"}
    fitted = {(c["preset"], c["seed"]) for c in table.meta["fitted_on"]}
    # never fitted on the scenes the benchmark reports ECE on
    assert ("small", 0) not in fitted and ("bench", 0) not in fitted
    for x, y in table.maps.values():
        assert np.all(np.diff(x) >= 0) and np.all(np.diff(y) >= -1e-9)


def test_tiny_scene_wrong_filled_labels_are_less_confident(tmp_path, synth_tiny):
    """On the tiny synthetic scene (stratified selection, degraded masks), the filled labels
    that are wrong have a mean confidence well below the right ones; filled labels are less
    confident than voted ones; unlabelled points have confidence 0."""
    from occufly.io.importer import import_scene
    from occufly.io.masks import read_mask
    from occufly.lifting import VoteStore
    from occufly.scene import Scene
    from occufly.selection import select_frames
    from occufly.synthetic.degrade import degrade_masks

    syn = synth_tiny  # generate(preset="tiny", seed=0), once per run (read-only)
    import_scene(syn, tmp_path / "ws")
    scene = Scene.load(tmp_path / "ws")
    truth = np.load(syn / "truth" / "point_labels.npy")
    sel = select_frames(scene, mode="stratified")
    exact = {fi: read_mask(syn / "truth" / "masks" / f"{scene.frames[fi].stem}.png",
                           scene.frames[fi], scene.taxonomy) for fi in sel.frames}
    st = VoteStore.open(tmp_path / "ws", scene)
    for fi, m in degrade_masks(exact, scene.taxonomy, seed=0).items():
        st.apply_frame(fi, m)
    res = st.fill_and_denoise()
    lab, org, conf = np.asarray(res.labels), np.asarray(res.origin), np.asarray(res.confidence)
    ev = (truth > 0) & (truth < 255)
    f = ev & (org == ORIGIN_FILLED)
    right, wrong = f & (lab == truth), f & (lab != truth)
    assert right.sum() > 50 and wrong.sum() > 20
    assert conf[wrong].mean() < conf[right].mean() - 0.06, (conf[wrong].mean(), conf[right].mean())
    assert conf[lab == 0].max(initial=0.0) == 0.0
    assert (conf[org == ORIGIN_FILLED].mean() < conf[org == ORIGIN_DIRECT].mean())


def test_prefill_leaves_unlabelled_points_unpainted():
    """Unlabelled points (beyond the fill radius) render as 0 in the prefill: the hole
    closing fills only pixels no point reaches, never pixels of unlabelled points."""
    from occufly.camera import Camera, look_at
    from occufly.render import render_prefill
    from occufly.scene import Frame, Scene

    g = np.arange(0.125, 40, 0.25)
    gx, gy = np.meshgrid(g, g)
    xyz = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]).astype(np.float32)
    labels = np.where(xyz[:, 0] < 20, GRASS, 0).astype(np.uint8)  # the right half unlabelled
    cam = Camera("PINHOLE", 200, 200, np.array([200.0, 200.0, 100.0, 100.0]))
    T = look_at([20.0, 20.0, 20.0], [20.0, 20.0, 0.0], up=(0.0, 1.0, 0.0))
    scene = Scene(frames=[Frame("f.jpg", cam, T)], xyz=xyz, rgb=np.zeros_like(xyz, np.uint8))
    img, depth, holes = render_prefill(scene, labels, 0)
    assert (depth > 0).mean() > 0.95  # the whole plane is seen
    seen_unlabelled = img == 0
    assert 0.4 < seen_unlabelled.mean() < 0.6  # half the image stays unpainted
    assert (img[:, :90] == GRASS).mean() > 0.95 and (img[:, 110:] == 0).all()
