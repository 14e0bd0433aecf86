"""The compiled parts of a frame's leave-one-out labels (a reviewer's first open of a 20 MP
frame) against the code they replaced, bit for bit: the fill's k-NN vote by a grid search
(``loo._fill_vote``) against the k-d tree of the voted points ``_near`` keeps
(``loo._fill_tree``), including ties at the k-th neighbour, points with no voted point in
reach and empty inputs."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.lifting import loo as L
from occufly.lifting.classes import ClassColumns
from occufly.lifting.knn import LiftParams
from occufly.taxonomy import default_taxonomy

CLS = ClassColumns(default_taxonomy())


def _same(a: tuple, b: tuple) -> bool:
    return (a[0].dtype == b[0].dtype and a[1].dtype == b[1].dtype
            and np.array_equal(a[0], b[0]) and np.array_equal(a[1].view(np.uint32), b[1].view(np.uint32)))


def _cloud(seed: int, n: int, *, grid: bool = False):
    """A clustered cloud (surfaces with gaps: many points to fill far from any vote), its
    gathered ids (sorted, a subset of the scene), voted rows and rows to fill."""
    rng = np.random.default_rng(seed)
    if grid:  # integer coordinates: many points at equal distances (ties at the k-th)
        xyz = rng.integers(0, 12, (n, 3)).astype(np.float32)
    else:
        centres = rng.uniform(0, 40, (12, 3))
        xyz = (centres[rng.integers(0, 12, n)] + rng.normal(0, 2.5, (n, 3))).astype(np.float32)
        xyz[:, 2] *= 0.3
    ids = np.sort(rng.choice(n, int(n * 0.8), replace=False)).astype(np.int64)
    col = np.full(len(ids), -1, np.int64)
    voted = rng.random(len(ids)) < 0.6
    col[voted] = rng.integers(0, CLS.C, int(voted.sum()))
    todo = np.flatnonzero(~voted & (rng.random(len(ids)) < 0.5))
    src = np.flatnonzero(voted)
    return xyz, ids, todo, src, col


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("k,radius", [(100, 3.0), (8, 1.0), (1, 0.7), (30, 0.25)])
def test_fill_vote_equals_the_tree(seed, k, radius):
    xyz, ids, todo, src, col = _cloud(seed, 6000)
    p = LiftParams(fill_k=k, fill_radius=radius)
    got = L._fill_vote(xyz, ids, todo, src, col, p, CLS)
    want = L._fill_tree(xyz, ids, todo, src, col, p, CLS)
    assert _same(got, want)
    assert (got[0] >= 0).any()
    if radius <= 1.0:
        assert (got[0] < 0).any()  # points with no voted point within the radius


@pytest.mark.parametrize("k", [1, 6, 27, 100])
def test_fill_vote_ties_at_the_kth_neighbour_take_the_trees_answer(k, monkeypatch):
    xyz, ids, todo, src, col = _cloud(5, 4000, grid=True)
    p = LiftParams(fill_k=k, fill_radius=4.0)
    calls = []
    tree = L._fill_tree

    def spy(*a, **kw):
        calls.append(kw.get("only"))
        return tree(*a, **kw)

    monkeypatch.setattr(L, "_fill_tree", spy)
    got = L._fill_vote(xyz, ids, todo, src, col, p, CLS)
    assert calls and calls[0] is not None and 0 < len(calls[0]) < len(todo)  # the tied ones only
    monkeypatch.setattr(L, "_fill_tree", tree)
    assert _same(got, tree(xyz, ids, todo, src, col, p, CLS))


def test_fill_vote_edge_cases():
    xyz, ids, todo, src, col = _cloud(7, 3000)
    p = LiftParams()
    for t, s in ((todo[:0], src), (todo, src[:0]), (todo[:1], src), (todo, src[:3])):
        assert _same(L._fill_vote(xyz, ids, t, s, col, p, CLS), L._fill_tree(xyz, ids, t, s, col, p, CLS))
    # no voted point in the box of the points to fill
    far = xyz.copy()
    far[ids[todo]] += 1000.0
    got = L._fill_vote(far, ids, todo, src, col, p, CLS)
    assert _same(got, L._fill_tree(far, ids, todo, src, col, p, CLS))
    assert (got[0] == -1).all() and (got[1] == 0).all()
    # a grid too large for the dense voxels: the tree answers
    wide = xyz.copy()
    wide[ids[todo[0]]] = (1e6, -1e6, 1e5)
    old = L._FILL_GRID_MAX_CELLS
    try:
        L._FILL_GRID_MAX_CELLS = 1000
        assert _same(L._fill_vote(wide, ids, todo, src, col, p, CLS),
                     L._fill_tree(wide, ids, todo, src, col, p, CLS))
    finally:
        L._FILL_GRID_MAX_CELLS = old


def test_gauss_at_equals_gauss_row():
    from occufly.lifting import robust as R

    rng = np.random.default_rng(0)
    n, F, C = 2000, 10, 4
    x = rng.normal(size=(n, F)).astype(np.float32)
    mean = rng.normal(size=(C, F)).astype(np.float32)
    wh = np.triu(rng.normal(size=(C, F, F))).astype(np.float32)
    ld = rng.normal(size=C).astype(np.float32)
    d, z = np.empty(F, np.float32), np.empty(F, np.float32)
    for i in range(n):
        c = i % C
        a = R._gauss_row(x[i], mean[c], wh[c], ld[c], d)
        b = R._gauss_at(x, i, mean, wh, ld, c, d, z)
        assert np.float32(a).view(np.uint32) == np.float32(b).view(np.uint32)


def test_loo_labels_compiled_fill_equals_the_tree(tmp_path, monkeypatch):
    """Every annotated frame's leave-one-out labels and shares through the compiled fill and
    through the k-d tree (the analytic scene, a house painted as ground in one frame)."""
    from occufly.lifting import VoteStore
    from occufly.scene import Scene
    from tests.lift_scene import BUILDING, GRASS, make_scene, truth_mask

    scene, _ = make_scene()
    path = tmp_path / "ws"
    scene.save(path)
    scene = Scene.load(path)
    st = VoteStore.open(path, scene)
    frames = (1, 4, 5, 9)
    for fi in frames:
        m = truth_mask(scene.frames[fi])
        if fi == 5:
            m = np.where(m == BUILDING, GRASS, m).astype(np.uint8)
        st.set_mask(fi, m, version=str(fi))
    st.fill_and_denoise()
    st.close()
    for fi in frames:
        out = {}
        for flag in (False, True):
            monkeypatch.setattr(L, "COMPILED_FILL", flag)
            out[flag] = L.loo_labels(path, scene, fi)
        a, b = out[False], out[True]
        assert np.array_equal(a.point_ids, b.point_ids) and np.array_equal(a.labels, b.labels)
        assert np.array_equal(a.voted, b.voted)
        assert np.array_equal(a.share.view(np.uint32), b.share.view(np.uint32))
        assert (b.labels[~b.voted] > 0).any()  # the fill gave labels


def test_rows_in_equals_a_point_to_row_map():
    """rows_in (merge walk for sorted queries, binary search otherwise) against the (N,) map
    it replaced: sorted, repeated, unsorted and absent ids, and empty inputs."""
    rng = np.random.default_rng(11)
    n = 50_000
    ids = np.sort(rng.choice(n, 20_000, replace=False)).astype(np.int64)
    row_of = np.full(n, -1, np.int32)
    row_of[ids] = np.arange(len(ids))
    for q in (np.sort(rng.integers(0, n, 9000)), rng.integers(0, n, 9000), ids, ids[::-1],
              np.zeros(0, np.int64), np.array([n - 1]), np.array([0, 0, 0])):
        assert np.array_equal(L.rows_in(ids, q), row_of[q].astype(np.int64))
    assert np.array_equal(L.rows_in(ids[:0], np.array([1, 2])), [-1, -1])


@pytest.mark.parametrize("seed", [0, 1])
def test_local_votes_compiled_counts_equal_the_bincounts(seed, monkeypatch):
    """local_votes' compiled sums of whole vote counts against the chunked float64 bincounts
    they replace (bit for bit), and fractional counts (weighted votes) still through those."""
    from occufly.lifting import robust as R

    rng = np.random.default_rng(seed)
    n, C = 40_000, 9
    xyz = rng.uniform(0, 20, (n, 3)).astype(np.float32)
    c1 = rng.integers(0, C, n).astype(np.int16)
    n1 = rng.integers(1, 6, n).astype(np.uint16)
    c2 = np.where(rng.random(n) < 0.4, (c1 + 1) % C, -1).astype(np.int8)
    n2 = np.where(c2 >= 0, rng.integers(1, 3, n), 0).astype(np.uint16)
    voted = np.flatnonzero(rng.random(n) < 0.9)
    assert R._integral_votes(n1, n2, voted, c2)
    got = R.local_votes(xyz, voted, c1, n1, c2, n2, C, 0.7, chunk=7000)
    monkeypatch.setattr(R, "_integral_votes", lambda *a: False)
    want = R.local_votes(xyz, voted, c1, n1, c2, n2, C, 0.7, chunk=7000)
    assert np.array_equal(got[0], want[0]) and got[1].dtype == want[1].dtype
    assert np.array_equal(got[1].view(np.uint32), want[1].view(np.uint32))
    monkeypatch.undo()
    frac = n2.astype(np.float32) / 3
    assert not R._integral_votes(n1, frac, voted, c2)
    assert not R._integral_votes(np.full(n, 60_000, np.int64), n2, voted, c2)  # > 2^24 in all
    assert not R._integral_votes(np.full(n, -1, np.int64), n2, voted, c2)


def test_redecide_without_the_support_gives_the_same_labels_and_margins():
    from occufly.lifting import robust as R

    rng = np.random.default_rng(2)
    n, C = 30_000, CLS.C
    xyz = rng.uniform(0, 30, (n, 3)).astype(np.float32)
    truth = (xyz[:, 0] // 4 + xyz[:, 1] // 4).astype(np.int64) % C
    col1 = np.where(rng.random(n) < 0.15, rng.integers(0, C, n), truth)
    n1 = rng.integers(1, 4, n).astype(np.uint16)
    col2 = np.where(rng.random(n) < 0.3, rng.integers(0, C, n), -1)
    col2[col2 == col1] = -1
    n2 = np.minimum(np.where(col2 >= 0, rng.integers(1, 3, n), 0), n1).astype(np.uint16)
    feats = (rng.normal(size=(n, 8)) + truth[:, None] * 0.3).astype(np.float16)
    args = (CLS, feats, col1.astype(np.int16), n1, col2.astype(np.int8), n2)
    a = R.redecide(*args, xyz=xyz)
    b = R.redecide(*args, xyz=xyz, with_top=False)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1].view(np.uint32), b[1].view(np.uint32))
    assert (a[2] > 0).any() and not b[2].any()
    # threads (the neighbourhood votes beside the classifier's fit, the chunks shared out):
    # the same labels, margins and support as one thread, however the points are chunked
    from dataclasses import replace
    for workers, chunk in ((2, 1_000_000), (3, 7_001), (4, 1)):
        params = replace(R.RobustParams(), chunk=chunk)
        one = R.redecide(*args, params=params, xyz=xyz)
        t = R.redecide(*args, params=params, xyz=xyz, workers=workers)
        for u, v in zip(t[:3], one[:3], strict=True):
            assert u.dtype == v.dtype and np.array_equal(u.view(np.uint8), v.view(np.uint8))
        assert np.array_equal(t[0], a[0])
        assert t[3]["robust_points_changed"] == one[3]["robust_points_changed"]


def test_redecide_of_a_row_subset_equals_redecide_of_the_gathered_rows(tmp_path):
    """The review decides a subset of the cloud and hands the features as a RowSubset (rows
    gathered where the classifier reads them): the same labels, margins and statistics as
    the rows gathered first, from a memory map as the features cache is, with threads."""
    from occufly.lifting import robust as R

    rng = np.random.default_rng(5)
    N, n, C = 60_000, 25_000, CLS.C
    xyz = rng.uniform(0, 30, (N, 3)).astype(np.float32)
    truth = (xyz[:, 0] // 4 + xyz[:, 1] // 4).astype(np.int64) % C
    np.save(tmp_path / "f.npy", (rng.normal(size=(N, 8)) + truth[:, None] * 0.3)
            .astype(np.float16))
    feats = np.load(tmp_path / "f.npy", mmap_mode="r")
    pts = np.sort(rng.choice(N, n, replace=False))
    col1 = np.where(rng.random(n) < 0.15, rng.integers(0, C, n), truth[pts])
    n1 = rng.integers(1, 4, n).astype(np.uint16)
    col2 = np.where(rng.random(n) < 0.3, rng.integers(0, C, n), -1)
    col2[col2 == col1] = -1
    n2 = np.minimum(np.where(col2 >= 0, rng.integers(1, 3, n), 0), n1).astype(np.uint16)
    sub = R.RowSubset(feats, pts)
    assert sub.shape == (n, 8) and len(sub) == n
    assert np.array_equal(sub[np.array([3, 0, 7])], np.asarray(feats[pts[[3, 0, 7]]]))
    assert np.array_equal(R.half_rows_as_float32(sub, np.array([9, 2])),
                          np.asarray(feats[pts[[9, 2]]], np.float32))
    votes = (col1.astype(np.int16), n1, col2.astype(np.int8), n2)
    for workers in (1, 2):
        a = R.redecide(CLS, R.half_rows(feats, pts), *votes, xyz=xyz[pts], with_top=False,
                       workers=workers)
        b = R.redecide(CLS, sub, *votes, xyz=xyz[pts], with_top=False, workers=workers)
        # the cloud's rows as a RowSubset too (gathered where the neighbourhood votes run)
        c = R.redecide(CLS, sub, *votes, xyz=R.RowSubset(xyz, pts), with_top=False,
                       workers=workers)
        for x in (b, c):
            assert np.array_equal(a[0], x[0]) and np.array_equal(a[1].view(np.uint32),
                                                                x[1].view(np.uint32))
            assert a[3]["robust_points_evaluated"] == x[3]["robust_points_evaluated"] > 0
            assert a[3]["robust_points_changed"] == x[3]["robust_points_changed"]


def test_half_rows_equal_numpys_gather_and_cast():
    """The compiled float16 row gathers against numpy's fancy index and float16 -> float32
    cast: every one of the 65,536 halves (zeros, subnormals, infinities, NaN payloads), a
    memory map, and the numpy fallback for other arrays."""
    from occufly.lifting import robust as R

    allh = np.arange(65536, dtype=np.uint32).astype(np.uint16).view(np.float16).reshape(-1, 16)
    rows = np.random.default_rng(0).permutation(len(allh))
    got = R.half_rows_as_float32(allh, rows)
    assert got.dtype == np.float32
    assert np.array_equal(got.view(np.uint32), allh[rows].astype(np.float32).view(np.uint32))
    got16 = R.half_rows(allh, rows)
    assert got16.dtype == np.float16
    assert np.array_equal(got16.view(np.uint16), allh[rows].view(np.uint16))
    f64 = np.arange(12.0).reshape(4, 3)
    assert np.array_equal(R.half_rows(f64, [2, 0]), f64[[2, 0]])
    assert np.array_equal(R.half_rows_as_float32(f64, [1]), f64[[1]].astype(np.float32))


def test_half_rows_of_a_memory_map(tmp_path):
    from occufly.lifting import robust as R

    a = np.random.default_rng(1).normal(size=(5000, 10)).astype(np.float16)
    np.save(tmp_path / "f.npy", a)
    m = np.load(tmp_path / "f.npy", mmap_mode="r")
    rows = np.sort(np.random.default_rng(2).choice(5000, 1200, replace=False))
    assert np.array_equal(R.half_rows(m, rows).view(np.uint16), a[rows].view(np.uint16))
    assert np.array_equal(R.half_rows_as_float32(m, rows), a[rows].astype(np.float32))


def test_neighbour_counts_merge_equals_the_vote_map():
    """disagreeing_neighbours' merge walk against the (N,) vote map it replaced: repeated
    points on both sides (the frame's first vote counts), points without an independent label,
    and unsorted votes (refused: the map answers)."""
    rng = np.random.default_rng(21)
    n = 20_000
    own_p = np.sort(rng.integers(0, n, 6000)).astype(np.int64)  # repeats
    own_c = rng.integers(0, 6, len(own_p)).astype(np.int64)
    gp = np.sort(rng.integers(0, n, 8000)).astype(np.int32)
    gc = rng.integers(0, 6, len(gp)).astype(np.uint8)
    pids = np.sort(rng.choice(n, 9000, replace=False)).astype(np.int64)
    loo = L.LooLabels(0, pids, np.zeros(len(pids), np.uint8), np.zeros(len(pids), bool))
    loo_cols = rng.integers(-1, 6, len(pids)).astype(np.int64)
    mine_of = np.full(n, -1, np.int16)
    mine_of[own_p[::-1]] = own_c[::-1]
    want = L._neighbour_counts_map(mine_of, gp, gc, loo, loo_cols)
    got = L._neighbour_counts(own_p, own_c, gp, gc, pids, loo_cols)
    assert tuple(int(v) for v in got) == want and want[1] > 0 and want[2] > 0
    assert L._neighbour_counts(own_p, own_c, gp[::-1], gc[::-1], pids, loo_cols)[0] == -1
    assert tuple(L._neighbour_counts(own_p, own_c, gp[:0], gc[:0], pids, loo_cols)) == (0, 0, 0, 0)


def test_disagreeing_neighbours_merge_equals_the_map_path(tmp_path, monkeypatch):
    from occufly.lifting import VoteStore
    from occufly.scene import Scene
    from tests.lift_scene import BUILDING, GRASS, ROAD, ROOF, make_scene, truth_mask

    scene, _ = make_scene()
    path = tmp_path / "ws"
    scene.save(path)
    scene = Scene.load(path)
    st = VoteStore.open(path, scene)
    for fi in (1, 4, 5, 6, 9, 10):
        m = truth_mask(scene.frames[fi])
        if fi == 5:
            m = m.copy()
            m[m == BUILDING] = GRASS
            m[m == ROOF] = ROAD
        st.set_mask(fi, m, version=str(fi))
    st.fill_and_denoise()
    st.close()
    for fi in (1, 5, 9):
        loo = L.loo_labels(path, scene, fi)
        got = L.disagreeing_neighbours(path, scene, fi, loo, limit=10)
        with monkeypatch.context() as mp:
            mp.setattr(L, "_neighbour_counts", lambda *a: (-1, 0, 0, 0))
            want = L.disagreeing_neighbours(path, scene, fi, loo, limit=10)
        assert got == want
    assert any(L.disagreeing_neighbours(path, scene, fi, L.loo_labels(path, scene, fi))
               for fi in (1, 4, 6, 9, 10))  # the wrong frame 5 is named


def test_gallop_finds_the_first_index_not_below():
    a = np.array([1, 3, 3, 3, 7, 8, 20, 21, 22, 40], np.int64)
    for j in range(len(a) + 1):
        for v in range(-1, 45):
            want = max(j, int(np.searchsorted(a, v, side="left")))
            assert L._gallop(a, j, v) == want


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("radius", [3.0, 1.0])
def test_the_near_voted_points_hold_every_neighbour_within_the_radius(seed, radius, monkeypatch):
    """``_near`` (and the compiled grid that mirrors it) keep only the voted points in voxels
    next to a point to fill: the fill must equal the k-NN vote against every voted point, also
    where most voxels are empty (a voxel diagonal behind an empty one was once left out)."""
    rng = np.random.default_rng(seed)
    n = 5000
    xyz = rng.uniform(0, 50, (n, 3)).astype(np.float32)
    ids = np.arange(n, dtype=np.int64)
    col = np.full(n, -1, np.int64)
    voted = rng.random(n) < 0.7
    col[voted] = rng.integers(0, CLS.C, int(voted.sum()))
    todo, src = np.flatnonzero(~voted), np.flatnonzero(voted)
    p = LiftParams(fill_k=10, fill_radius=radius)
    got_tree = L._fill_tree(xyz, ids, todo, src, col, p, CLS)
    got_grid = L._fill_vote(xyz, ids, todo, src, col, p, CLS)
    monkeypatch.setattr(L, "_near", lambda q, pts, r: np.ones(len(pts), bool))
    want = L._fill_tree(xyz, ids, todo, src, col, p, CLS)
    assert (want[0] >= 0).any()
    assert _same(got_tree, want) and _same(got_grid, want)
