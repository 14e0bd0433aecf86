"""Issue 37: the ``interior`` vote weighting (a vote falls off near its own mask's boundaries,
scaled to the painted region's size) -- the weights, the vote store, the review's unit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from occufly.errors import WorkspaceError
from occufly.lifting import VoteStore, interior_weights
from occufly.lifting.loo import _vote_unit
from occufly.lifting.votes import VOTE_UNITS, vote_unit
from occufly.scene import Scene
from occufly.workspace import Workspace
from tests.lift_scene import BUILDING, GRASS, ROAD, make_scene, truth_mask

UNIT = VOTE_UNITS["interior"]


@pytest.fixture(scope="module")
def built():
    return make_scene()


@pytest.fixture()
def ws(tmp_path, built):
    scene, truth = built
    scene.save(tmp_path / "ws")
    return tmp_path / "ws", Scene.load(tmp_path / "ws"), truth


def test_boundary_pixels_vote_less_than_interior_ones():
    m = np.full((320, 480), GRASS, np.uint8)  # d0 = 480 / 128 = 3.75 px
    m[:, 240:] = ROAD
    w = interior_weights(m)
    assert w.dtype == np.uint8 and w.shape == m.shape
    row = w[100]
    # on the class change both sides vote a quarter of a view, rising inwards to a full view
    assert row[239] == 1 and row[240] == 1
    assert list(row[235:240]) == sorted(row[235:240], reverse=True)
    assert list(row[236:241]) == [UNIT, 3, 2, 1, 1] and row[0] == UNIT and row[479] == UNIT and row[120] == UNIT
    assert (interior_weights(np.full((50, 80), GRASS, np.uint8)) == UNIT).all()


def test_small_and_thin_regions_keep_a_full_vote_at_their_core():
    m = np.full((320, 480), GRASS, np.uint8)
    m[100:103, 50:53] = BUILDING  # a 3x3 blob (a person seen from the air)
    m[:, 400:402] = ROAD          # a 2 px line (a cable)
    w = interior_weights(m)
    assert w[101, 51] == UNIT  # the blob's centre: a full view
    assert 1 <= w[100, 50] < UNIT  # its rim less
    assert (w[:, 400:402] == UNIT).all()  # the line is all core
    assert w[101, 49] == 1 and w[101, 53] == 1  # the grass touching the blob: a quarter
    # with the old fixed-width weighting the blob's core is a third of a view
    from occufly.lifting import boundary_weights

    assert boundary_weights(m)[101, 51] == 1


def test_large_masks_are_weighted_on_a_subsample():
    m = np.full((1536, 2048), GRASS, np.uint8)  # 3.1 MP: over INTERIOR_MAX_PIXELS
    m[:, 1024:] = ROAD
    w = interior_weights(m)
    assert w.shape == m.shape
    assert w[700, 1023] == 1 and w[700, 1024] == 1
    # d0 = 2048 / 128 = 16 px: full weight from about 16 px in, less closer
    assert w[700, 1000] == UNIT and w[700, 1060] == UNIT and w[700, 1015] < UNIT
    m2 = m.copy()
    m2[:, -3:] = BUILDING  # odd edges: the lookup covers every row and column
    assert interior_weights(m2[:1537 - 2, :2047]).shape == (1535, 2047)


def test_vote_store_counts_the_weights(ws):
    path, scene, _ = ws
    st = VoteStore.open(path, scene, vote_weighting="interior")
    assert st.vote_weighting == "interior" and vote_unit("interior") == UNIT
    mask = truth_mask(scene.frames[5])
    stats = st.apply_frame(5, mask, version="v1")
    pids, cols, wts = st.frame_votes(5, mask)
    assert stats["votes_added"] == int(wts.sum()) == int(np.asarray(st.votes).sum())
    assert (wts >= 1).all() and (wts <= UNIT).all() and (wts < UNIT).any() and (wts == UNIT).any()
    snap = st.snapshot()
    assert snap.vote_unit == UNIT
    voted = snap.direct > 0
    assert snap.top[voted].max() == 1  # one view: the confirmation rule sees one view
    assert _vote_unit(path) == UNIT
    st.close()
    again = VoteStore.open(path, scene)
    assert again.vote_weighting == "interior"
    with pytest.raises(WorkspaceError, match="'interior' votes"):
        VoteStore.open(path, scene, vote_weighting="plain")
    with pytest.raises(ValueError, match="vote_weighting 'edges'"):
        VoteStore.open(path, scene, vote_weighting="edges")
    state = json.loads(Workspace(path).lifting_state.read_text())
    assert state["vote_weighting"] == "interior"


def test_weighted_and_plain_agree_on_exact_masks_away_from_boundaries(ws, tmp_path, built):
    path, scene, _ = ws
    other = tmp_path / "plain"
    built[0].save(other)
    plain = VoteStore.open(other, Scene.load(other), vote_weighting="plain")
    inter = VoteStore.open(path, scene, vote_weighting="interior")
    full = np.ones(scene.n_points, bool)
    for fi in (1, 5, 9, 13):
        mask = truth_mask(scene.frames[fi])
        plain.apply_frame(fi, mask, version="t")
        inter.apply_frame(fi, mask, version="t")
        pids, _, wts = inter.frame_votes(fi, mask)
        full[pids[wts < UNIT]] = False  # a point some view sees near a boundary
    vp, vi = np.asarray(plain.votes), np.asarray(inter.votes)
    voted = vp.sum(axis=1) > 0
    core = voted & full
    assert core.sum() > 0.3 * voted.sum()
    # every vote of a core point has full weight: the counts are the plain ones times the unit
    assert np.array_equal(vi[core].astype(np.int64), UNIT * vp[core].astype(np.int64))
    dp, di = plain.direct_labels(), inter.direct_labels()
    assert np.array_equal(dp[core], di[core])
    assert (dp[voted] == di[voted]).mean() > 0.98
