"""Per-annotator confusion model of the votes (occufly.lifting.confusion, issue 37)."""

from __future__ import annotations

import numpy as np

from occufly.lifting.classes import ClassColumns
from occufly.lifting.confusion import ConfusionParams, fit_confusion, vote_table
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()
CLS = ClassColumns(TAX)
COL = {c.name: int(CLS.col_of[c.id]) for c in TAX.classes}
A, B, R = COL["grass"], COL["vegetation"], COL["road"]


def _frames(groups):
    """groups: list of (true column, n points, {frame: painted column}) -> frames, truth."""
    frames: dict[int, tuple[list, list]] = {}
    truth = []
    start = 0
    for t, n, painted in groups:
        pids = np.arange(start, start + n, dtype=np.int32)
        truth += [t] * n
        for f, c in painted.items():
            frames.setdefault(f, ([], []))
            frames[f][0].append(pids)
            frames[f][1].append(np.full(n, c, np.uint8))
        start += n
    out = {f: (np.concatenate(p), np.concatenate(c), None) for f, (p, c) in frames.items()}
    return out, np.array(truth), start


def _plain(frames, n):
    counts = np.zeros((n, CLS.C), np.int64)
    for pids, cols, _ in frames.values():
        np.add.at(counts, (pids.astype(np.int64), cols.astype(np.int64)), 1)
    return counts


def _sloppy_crew():
    """Frames 0-3 careful; frames 4 and 5 painted by one sloppy annotator who paints every
    grass point vegetation (one way: vegetation stays vegetation). Group G3 is grass seen by
    one careful frame and both sloppy frames: the plain vote says vegetation 2:1."""
    return _frames([
        (A, 400, {0: A, 1: A, 4: B}),          # G1 grass, majority right
        (B, 400, {0: B, 1: B, 4: B}),          # G2 vegetation
        (A, 300, {2: A, 4: B, 5: B}),          # G3 grass, plain vote vegetation
        (B, 300, {2: B, 4: B, 5: B}),          # G4 vegetation
        (R, 400, {3: R, 5: R, 0: R}),          # road, everybody right
    ])


def test_a_one_way_swapping_annotator_is_corrected():
    frames, truth, n = _sloppy_crew()
    counts = _plain(frames, n)
    plain = counts.argmax(axis=1)
    g3 = np.arange(800, 1100)
    assert (plain[g3] == B).all()  # the plain vote picks the sloppy annotator's class
    for annotators in ({4: "bad", 5: "bad"}, None):  # by author, and each frame its own
        table = vote_table(frames, n, annotators)
        model = fit_confusion(table, CLS.C, init_labels=plain)
        post = model.posterior(np.arange(n))
        got = post.argmax(axis=1)
        assert (got[g3] == A).all(), annotators
        assert (got == truth).mean() == 1.0, annotators
    # the sloppy annotator's matrix learned the one-way swap, the careful ones' did not
    bad = vote_table(frames, n, {4: "bad", 5: "bad"}).names.index(("author", "bad"))
    model = fit_confusion(vote_table(frames, n, {4: "bad", 5: "bad"}), CLS.C, init_labels=plain)
    assert model.matrix(bad)[A, B] > 0.9 and model.matrix(bad)[B, B] > 0.9
    careful = model.matrix(0)
    assert careful[A, A] > 0.9 and careful[B, A] < 0.05


def test_balanced_noise_gives_the_plain_vote():
    rng = np.random.default_rng(3)
    n, views = 3000, 3
    k = rng.integers(0, 3, n)
    truth = np.array([A, B, R])[k]
    frames = {}
    for f in range(views):
        # symmetric: each class painted as each of the other two with probability 0.05
        u = rng.random(n)
        painted = np.array([A, B, R])[np.where(u < 0.05, (k + 1) % 3,
                                               np.where(u < 0.10, (k + 2) % 3, k))]
        frames[f] = (np.arange(n, dtype=np.int32), painted.astype(np.uint8), None)
    counts = _plain(frames, n)
    plain = counts.argmax(axis=1)
    decided = counts.max(axis=1) >= 2  # no three-way tie
    model = fit_confusion(vote_table(frames, n), CLS.C, init_labels=None)
    got = model.posterior(np.arange(n)).argmax(axis=1)
    assert np.array_equal(got[decided], plain[decided])
    assert (plain[decided] != truth[decided]).any()  # the plain vote is not the truth itself


def test_the_prior_keeps_a_tiny_annotator_near_the_diagonal():
    # frame 9 votes three grass points (which the others agree are grass) vegetation; frame 8
    # votes 1000 grass points vegetation the same way: only the large one learns the swap
    frames, truth, n = _frames([
        (A, 3, {0: A, 1: A, 9: B}),
        (A, 1000, {0: A, 1: A, 8: B}),
        (B, 1000, {0: B, 1: B, 8: B, 9: B}),
    ])
    plain = _plain(frames, n).argmax(axis=1)
    model = fit_confusion(vote_table(frames, n), CLS.C, init_labels=plain)
    names = vote_table(frames, n).names
    tiny, large = names.index(("frame", 9)), names.index(("frame", 8))
    assert model.matrix(tiny)[A, A] > 0.5
    assert model.matrix(large)[A, B] > 0.9
    # rows of classes nobody voted stay diagonal-dominant for everyone
    for a in range(len(names)):
        assert model.matrix(a)[R, R] > 0.5


def test_deterministic_and_sampled_fit_is_seeded():
    frames, _, n = _sloppy_crew()
    plain = _plain(frames, n).argmax(axis=1)
    p = ConfusionParams(sample=500)
    m1 = fit_confusion(vote_table(frames, n), CLS.C, plain, p)
    m2 = fit_confusion(vote_table(frames, n), CLS.C, plain, p)
    assert np.array_equal(m1.logpi, m2.logpi)
    ids = np.arange(n)
    assert np.array_equal(m1.loglik(ids), m2.loglik(ids))
    # the log-likelihood is the sum of the votes' log pi (an independent reference)
    t = m1.table
    ref = np.zeros((n, CLS.C))
    for pid, c, a in zip(t.pid, t.col, t.ann, strict=True):
        ref[pid] += m1.logpi[a, :, c]
    assert np.allclose(m1.loglik(ids), ref, atol=1e-4)


def test_the_lifting_uses_it_through_robust_params(tmp_path):
    """End to end on the analytic scene: two of the frames are painted by an annotator who
    paints every grass pixel vegetation; RobustParams(confusion=...) fits the model from the
    stored per-frame votes (by author when the caller names them) and lifts more grass right
    than the pooled decision."""
    from occufly.lifting import LiftParams, RobustParams, VoteStore
    from occufly.scene import Scene
    from tests.lift_scene import GRASS, make_scene, truth_mask

    scene, truth = make_scene()
    scene.save(tmp_path / "ws")
    scene = Scene.load(tmp_path / "ws")
    st = VoteStore.open(tmp_path / "ws", scene)
    frames = list(range(0, len(scene.frames), max(1, len(scene.frames) // 8)))[:8]
    sloppy = set(frames[::3])
    for fi in frames:
        m = truth_mask(scene.frames[fi])
        if fi in sloppy:
            m = np.where(m == GRASS, TAX.by_name("vegetation").id, m).astype(np.uint8)
        st.set_mask(fi, m, version=str(fi))
    grass = truth == GRASS
    base = st.fill_and_denoise(write=False)
    params = LiftParams(robust_params=RobustParams(confusion=ConfusionParams()))
    by_frame = st.fill_and_denoise(write=False, params=params)
    by_author = st.fill_and_denoise(write=False, params=params,
                                    annotators={f: "sloppy" for f in sloppy})
    assert "confusion_annotators" not in base.stats
    assert by_frame.stats["confusion_annotators"] == len(frames)
    assert by_author.stats["confusion_annotators"] == len(frames) - len(sloppy) + 1
    runs = (("base", base), ("frame", by_frame), ("author", by_author))
    acc = {k: float((np.asarray(r.labels)[grass] == GRASS).mean()) for k, r in runs}
    overall = {k: float((np.asarray(r.labels) == truth).mean()) for k, r in runs}
    # measured: grass 0.9140 -> 0.9151 / 0.9151, overall 0.9140 -> 0.9146 / 0.9146 (the
    # pooled decision already gets most of it right here: few frames overlap)
    assert acc["author"] > acc["base"] and acc["frame"] > acc["base"], acc
    assert overall["author"] >= overall["base"] and overall["frame"] >= overall["base"], overall
