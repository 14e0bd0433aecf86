"""Suspects (issue 23): clusters of contested points, ranked, with the frames that see them."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.lifting import VoteStore
from occufly.lifting.suspects import contested_share, find_suspects
from occufly.scene import Scene
from tests.lift_scene import BOXES, BUILDING, GRASS, ROAD, ROOF, make_scene, truth_mask


def test_a_wrongly_painted_house_is_the_top_suspect(tmp_path):
    scene, _truth = make_scene()
    scene.save(tmp_path / "ws")
    scene = Scene.load(tmp_path / "ws")
    st = VoteStore.open(tmp_path / "ws", scene)
    for fi in (1, 4, 5, 6):
        m = truth_mask(scene.frames[fi]).copy()
        if fi == 5:
            m[m == BUILDING] = GRASS
            m[m == ROOF] = ROAD
        st.set_mask(fi, m, version=str(fi))
    res = st.fill_and_denoise()
    sus = find_suspects(scene, st.votes, res.labels)
    assert sus, "no suspect found"
    assert [s["points"] for s in sus] == sorted((s["points"] for s in sus), reverse=True)
    top = sus[0]
    x0, x1, y0, y1, h, *_ = BOXES[0]
    cx, cy, cz = top["centroid"]
    assert x0 - 1 <= cx <= x1 + 1 and y0 - 1 <= cy <= y1 + 1  # the first house
    assert top["contested"] > 100 and 5 in top["frames"]
    # every frame listed sees some of its points; the best one sees the most
    vis = scene.visibility
    seen = {f: np.isin(top["point_ids"], vis.frame_ids(f)).sum() for f in top["frames"]}
    assert all(v > 0 for v in seen.values())
    assert seen[top["best_frame"]] == max(seen.values())
    lo, hi = np.array(top["bbox"][0]), np.array(top["bbox"][1])
    pts = scene.xyz[top["point_ids"]]
    assert (pts >= lo - 1e-6).all() and (pts <= hi + 1e-6).all()
    share = contested_share(st.votes, res.labels, scene)
    assert 0.0 < share < 0.5
    # with all masks right nothing on the house is contested
    st.set_mask(5, truth_mask(scene.frames[5]), version="5b")
    res = st.fill_and_denoise()
    clean = find_suspects(scene, st.votes, res.labels)
    assert not clean or clean[0]["points"] < top["points"] // 3


def _lawn_road_car():
    """A 40 x 40 m plane (0.3 m spacing): grass (3), a road strip (7) past x = 30 with a car
    (9, a 4.5 x 1.8 x 1.2 m box of points) standing on it, and a 2.4 m patch of class 5 in the
    middle of the lawn."""
    g = np.mgrid[0:40:0.3, 0:40:0.3].reshape(2, -1).T
    xyz = np.c_[g, np.zeros(len(g))]
    lab = np.full(len(g), 3, np.uint8)
    lab[g[:, 0] > 30] = 7
    patch = (np.abs(g[:, 0] - 10) < 1.2) & (np.abs(g[:, 1] - 10) < 1.2)
    lab[patch] = 5
    car = np.mgrid[33:37.5:0.3, 10:11.8:0.3, 0.3:1.5:0.3].reshape(3, -1).T
    return np.r_[xyz, car], np.r_[lab, np.full(len(car), 9, np.uint8)], np.flatnonzero(patch)


def test_a_small_patch_inside_another_class_is_an_island_and_a_car_on_a_road_is_not():
    from occufly.lifting.suspects import SuspectParams, find_islands
    xyz, lab, patch = _lawn_road_car()
    isl = find_islands(xyz, lab, SuspectParams(voxel=1.0), chunk=1000)  # several chunks
    assert len(isl) == 1, isl
    (i,) = isl
    assert (i["class"], i["inside"]) == (5, 3)
    assert 2 <= i["voxels"] <= 6 and i["border"] >= 6
    # its points are the patch's points in the voxels the patch holds the majority of
    assert set(i["point_ids"].tolist()) <= set(patch.tolist())
    assert len(i["point_ids"]) >= 0.5 * len(patch)
    # a class exempt from islands (the instance group in find_suspects) is not one
    assert find_islands(xyz, lab, SuspectParams(voxel=1.0), exempt=np.array([5])) == []
    # the same patch, larger than island_max_voxels, is a region, not an island
    assert find_islands(xyz, lab, SuspectParams(voxel=1.0, island_max_voxels=1)) == []
    # nothing is an island where every class is large
    lab2 = lab.copy()
    lab2[lab2 == 5] = 3
    assert find_islands(xyz, lab2, SuspectParams(voxel=1.0)) == []
    # a single stray point does not outvote its voxel
    lab3 = lab2.copy()
    lab3[patch[0]] = 5
    assert find_islands(xyz, lab3, SuspectParams(voxel=1.0)) == []


def test_find_suspects_lists_an_island_the_votes_did_not_contest(tmp_path):
    """All masks right, then a patch of grass without votes filled as road (as a bad fill
    would): nothing contests it (no votes, so nothing overridden either), and find_suspects
    lists it as an island with its frames."""
    scene, _truth = make_scene()
    scene.save(tmp_path / "ws")
    scene = Scene.load(tmp_path / "ws")
    st = VoteStore.open(tmp_path / "ws", scene)
    for fi in (1, 4, 5, 6):
        st.set_mask(fi, truth_mask(scene.frames[fi]), version=str(fi))
    labels = st.fill_and_denoise().labels.copy()
    before = [s for s in find_suspects(scene, np.array(st.votes), labels) if s["kind"] == "island"]
    xyz = np.asarray(scene.xyz)
    grass = np.flatnonzero(labels == GRASS)
    # a grass point whose 4 m surroundings are all grass, well inside the scene
    from scipy.spatial import cKDTree
    tree = cKDTree(xyz[:, :2])
    lo, hi = xyz[:, :2].min(0) + 5, xyz[:, :2].max(0) - 5
    c = next(xyz[g] for g in grass[::7]
             if (lo <= xyz[g, :2]).all() and (xyz[g, :2] <= hi).all()
             and (labels[tree.query_ball_point(xyz[g, :2], 4.0)] == GRASS).all())
    near = grass[np.linalg.norm(xyz[grass, :2] - c[:2], axis=1) < 1.2]
    labels[near] = ROAD
    votes = np.array(st.votes)
    votes[near] = 0
    sus = find_suspects(scene, votes, labels)
    isl = [s for s in sus if s["kind"] == "island"]
    assert len(isl) == len(before) + 1, [(s["kind"], s["points"]) for s in sus]
    new = [s for s in isl if np.isin(s["point_ids"], near).all()]
    assert new, "the relabelled patch is not an island"
    s = new[0]
    assert s["island_of"] == ROAD and s["inside"] == GRASS
    assert s["best_frame"] is not None and s["frames"][0] == s["best_frame"]
    assert [r["id"] for r in sus] == list(range(1, len(sus) + 1))
    assert [r["points"] for r in sus] == sorted((r["points"] for r in sus), reverse=True)


@pytest.mark.parametrize("step, dense_max", [(1 << 24, 1 << 22), (997, 1 << 22), (997, 0)])
def test_frames_seeing_groups_counts_each_groups_views_like_a_search_per_group(step, dense_max):
    """The one-pass (point -> group map) count of the frames that see each group of points
    equals counting each group's points in each frame's visibility on its own; ordered by
    count, ties by frame index -- in one chunk or many, with the (group, frame) table or the
    merged keys; no group seen: nothing."""
    from occufly.lifting.suspects import _frames_seeing_groups

    scene, _truth = make_scene()
    rng = np.random.default_rng(0)
    group = np.full(scene.n_points, -1, np.int32)
    members = {}
    for g in range(6):  # disjoint random groups, one of them seen by no frame possibly
        free = np.flatnonzero(group < 0)
        pts = np.sort(rng.choice(free, size=int(rng.integers(1, 400)), replace=False))
        group[pts] = g
        members[g] = pts
    got = _frames_seeing_groups(scene, group, step, dense_max)
    assert _frames_seeing_groups(scene, np.full(scene.n_points, -1, np.int32), step, dense_max) == {}
    vis = scene.visibility
    for g, pts in members.items():
        counts = np.array([np.isin(vis.frame_ids(f), pts).sum() for f in range(vis.n_frames)])
        seen = np.flatnonzero(counts)
        want = seen[np.argsort(-counts[seen], kind="stable")]
        fr, cnt = got.get(g, (np.zeros(0, np.int64), np.zeros(0, np.int64)))
        assert fr.tolist() == want.tolist()
        assert cnt.tolist() == counts[want].tolist()
