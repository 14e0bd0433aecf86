"""Frame selection: stratified cells (centre / border targets), coverage, greedy, altitude."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.camera import Camera, look_at
from occufly.errors import InputFormatError
from occufly.scene import Frame, Scene, Visibility
from occufly.selection import coverage, select_frames

CAM = Camera("PINHOLE", 100, 100, np.array([100.0, 100.0, 50.0, 50.0]))


def _scene(cam_xy, alts, *, see_radius=20.0, extent=75.0, step=1.0):
    """Points on [0, extent]^2; camera i sees the points within ``see_radius`` (x, y)."""
    g = np.arange(step / 2, extent, step)
    gx, gy = np.meshgrid(g, g)
    xyz = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]).astype(np.float32)
    frames, parts = [], []
    radii = np.broadcast_to(np.asarray(see_radius, dtype=float), (len(cam_xy),))
    for i, ((x, y), a) in enumerate(zip(cam_xy, alts, strict=True)):
        T = look_at([x, y, a], [x, y, 0.0], up=(0.0, 1.0, 0.0))
        frames.append(Frame(f"f{i:03d}.jpg", CAM, T, nominal_altitude=int(a)))
        d = np.hypot(xyz[:, 0] - x, xyz[:, 1] - y)
        ids = np.flatnonzero(d < radii[i]).astype(np.int32)
        parts.append((ids, np.zeros((len(ids), 2), np.float32), np.ones(len(ids), np.float32)))
    return Scene(frames=frames, xyz=xyz, rgb=np.zeros_like(xyz, np.uint8),
                 visibility=Visibility.from_parts(parts))


def test_stratified_picks_centre_and_border_targets():
    # 75 m square -> 3 x 3 cells of 25 m: the centre cell targets its centre, edge cells the
    # middle of their outer edge, corner cells the scene corner
    targets = [(x, y) for x in (0.0, 37.5, 75.0) for y in (0.0, 37.5, 75.0)]
    rng = np.random.default_rng(0)
    distract = [tuple(p) for p in rng.uniform(3, 72, (60, 2))
                if min(np.hypot(p[0] - tx, p[1] - ty) for tx, ty in targets) > 4]
    # cell centres are distractors too: border cells must not pick them
    distract += [(12.5, 12.5), (12.5, 37.5), (37.5, 12.5), (62.5, 62.5)]
    xy = distract + targets
    scene = _scene(xy, [50] * len(xy))
    res = select_frames(scene, cell=25.0)
    picked = sorted(tuple(np.round(scene.frames[f].center[:2], 3)) for f in res.frames)
    assert picked == sorted(targets)
    assert res.cells == 9 and res.mode == "stratified"
    assert res.ratio == pytest.approx(9 / len(xy))
    assert res.coverage == pytest.approx(coverage(scene, res.frames))


def test_coverage_is_share_of_points_seen():
    scene = _scene([(10.0, 10.0), (60.0, 60.0)], [50, 50], see_radius=10.0)
    seen = np.zeros(scene.n_points, bool)
    for f in range(2):
        p = scene.xyz
        seen |= np.hypot(p[:, 0] - scene.frames[f].center[0], p[:, 1] - scene.frames[f].center[1]) < 10
    assert coverage(scene, [0, 1]) == pytest.approx(seen.mean())
    assert coverage(scene, []) == 0.0


def test_greedy_reaches_target_with_max_gain_steps():
    rng = np.random.default_rng(1)
    xy = [tuple(p) for p in rng.uniform(0, 75, (80, 2))]
    scene = _scene(xy, [50] * 80, see_radius=9.0)
    strat = select_frames(scene, cell=25.0)
    res = select_frames(scene, cell=25.0, mode="greedy", target_coverage=0.95)
    assert res.frames[: len(strat.frames)] == strat.frames
    assert res.coverage >= 0.95 or res.coverage == pytest.approx(res.max_coverage)
    cov = [c for _, c in res.curve]
    assert all(b > a for a, b in zip(cov, cov[1:], strict=False))
    assert res.curve[0] == (len(strat.frames), pytest.approx(strat.coverage))
    assert res.coverage == pytest.approx(coverage(scene, res.frames))
    # the first added frame has the largest gain (brute force over all candidates)
    base = coverage(scene, strat.frames)
    gains = {f: coverage(scene, strat.frames + [f]) - base for f in range(80) if f not in strat.frames}
    first = res.frames[len(strat.frames)]
    assert gains[first] == pytest.approx(max(gains.values()))
    # stopping: one frame fewer would miss the target
    assert coverage(scene, res.frames[:-1]) < 0.95


def test_altitude_restriction():
    xy = [(12.5, 12.5), (37.5, 37.5), (62.5, 62.5), (12.5, 62.5)] * 2
    alts = [50] * 4 + [30] * 4
    scene = _scene(xy, alts)
    for a in (50, 30):
        res = select_frames(scene, altitude=a, mode="greedy")
        assert res.n_candidates == 4
        assert all(scene.frames[f].nominal_altitude == a for f in res.frames)
    with pytest.raises(InputFormatError, match="40"):
        select_frames(scene, altitude=40)
    with pytest.raises(InputFormatError):
        select_frames(scene, mode="random")
    d = select_frames(scene, cell=25.0, mode="greedy").to_dict()
    assert d["cell_in_method_range"] and d["selected"] == len(d["frames"])


def test_prune_drops_frames_the_target_does_not_need():
    targets = [(x, y) for x in (0.0, 37.5, 75.0) for y in (0.0, 37.5, 75.0)]
    # a wide view (sees everything) placed away from every cell target
    xy = targets + [(20.0, 55.0)]
    radii = [12.0] * 9 + [200.0]
    scene = _scene(xy, [50] * 10, see_radius=radii)
    strat = select_frames(scene, cell=25.0)
    assert sorted(strat.frames) == list(range(9)) and strat.coverage < 0.9
    res = select_frames(scene, cell=25.0, mode="greedy", target_coverage=0.99)
    assert res.frames == [9] and res.coverage == 1.0
    assert res.curve[-2] == (10, 1.0) and res.curve[-1] == (1, 1.0)
    keep_all = select_frames(scene, cell=25.0, mode="greedy", prune_redundant=False)
    assert len(keep_all.frames) == 10
    assert select_frames(scene, mode="cover").frames == [9]


def test_auto_cell_keeps_the_fewest_frames_reaching_the_target():
    from occufly.selection import AUTO_CELLS

    rng = np.random.default_rng(4)
    xy = [tuple(p) for p in rng.uniform(0, 75, (90, 2))]
    scene = _scene(xy, [50] * 90, see_radius=12.0)
    auto = select_frames(scene, cell="auto", mode="greedy", target_coverage=0.95)
    runs = {c: select_frames(scene, cell=c, mode="greedy", target_coverage=0.95) for c in AUTO_CELLS}
    assert AUTO_CELLS[0] == 23.0 and AUTO_CELLS[-1] == 28.0 and len(AUTO_CELLS) == 11
    reaching = [r for r in runs.values() if r.coverage >= 0.95]
    assert reaching and auto.coverage >= 0.95
    assert len(auto.frames) == min(len(r.frames) for r in reaching)
    assert auto.frames == runs[auto.cell].frames
    assert [c for c, _, _ in auto.to_dict()["auto_cells"]] == list(AUTO_CELLS)
    with pytest.raises(InputFormatError, match="target coverage"):
        select_frames(scene, cell="auto")  # stratified has no target to compare cells by
    with pytest.raises(InputFormatError, match="auto"):
        select_frames(scene, cell="big", mode="greedy")


def test_selection_reports_the_cell_lattice_it_used():
    xy = [(12.5, 12.5), (37.5, 12.5), (62.5, 62.5)]
    scene = _scene(xy, [50] * 3, see_radius=30.0, extent=75.0)
    res = select_frames(scene, cell=25.0).to_dict()
    pts = np.asarray(scene.xyz[:, :2], np.float64)
    assert res["cell_origin"] == pytest.approx(pts.min(axis=0).tolist())
    occ = {tuple(c) for c in res["occupied_cells"]}
    ij = np.minimum(((pts - pts.min(axis=0)) / 25.0).astype(int), 2)
    assert occ == {tuple(c) for c in ij.tolist()} and len(occ) == res["cells"] == 9


# ---- next best frames (occufly.lifting.nextbest, `occufly select --next K`, issue 37) ------
def _voted_workspace(tmp_path, *, contested: bool):
    """Ten cameras over a 75 m square, each seeing 20 m around itself (uv all 0, so a constant
    mask votes its class for every point the frame sees). Frames 0-5 are annotated: grass
    everywhere, except -- with ``contested`` -- frame 1 says road: the points only frames 0
    and 1 see are a 1:1 tie. Labels = the vote majority, confidence 0.95."""
    from occufly.lifting import VoteStore
    from occufly.lifting.result import LiftResult, save_result
    from occufly.taxonomy import default_taxonomy

    tax = default_taxonomy()
    ids = {c.name: c.id for c in tax.classes}
    cams = [(10, 10), (30, 10), (60, 10), (10, 60), (60, 60), (37, 37),
            (20, 10), (65, 40), (40, 65), (5, 35)]
    sc = _scene(cams, [50] * len(cams))
    sc.taxonomy = tax
    ws = tmp_path / "ws"
    sc.save(ws)
    scene = Scene.load(ws)
    st = VoteStore.open(ws, scene)
    for f in range(6):
        cls = "road" if (contested and f == 1) else "grass"
        st.apply_frame(f, np.full((100, 100), ids[cls], np.uint8), version="v1")
    direct = st.direct_labels()
    save_result(ws, LiftResult(direct, np.full(len(direct), 0.95, np.float32),
                               (direct > 0).astype(np.uint8)))
    st.close()
    return ws, scene, ids


def test_next_frames_see_the_contested_region_and_never_repeat(tmp_path):
    from occufly.lifting import VoteStore, load_labels
    from occufly.lifting.nextbest import propose_next

    ws, scene, ids = _voted_workspace(tmp_path, contested=True)
    st = VoteStore.open(ws, scene, read_only=True)
    lab = load_labels(ws)
    votes = np.asarray(st.votes)
    total = votes.sum(axis=1)
    tied = np.flatnonzero((total == 2) & (votes.max(axis=1) == 1))
    assert len(tied) > 50  # the region frames 0 and 1 disagree on
    res = propose_next(scene, st.votes, lab.labels, lab.confidence, 4,
                       annotated=set(st.included_versions()))
    assert res.frames and res.contested >= len(tied)
    # the first proposal sees the contested region (frame 6 sits between frames 0 and 1)
    first = set(scene.visibility.frame(res.frames[0])[0].tolist())
    assert res.frames[0] == 6 and len(first & set(tied.tolist())) > 0.5 * len(tied)
    assert res.reasons[0]["contested_points"] > 0 and "grass" in res.reasons[0]["classes"]
    # no frame proposed twice, none of the annotated ones; asking for all gives each once
    every = propose_next(scene, st.votes, lab.labels, lab.confidence, 50,
                         annotated=set(st.included_versions()))
    assert len(every.frames) == len(set(every.frames))
    assert not set(every.frames) & set(range(6))


def test_next_frames_cli_writes_the_proposal_and_exits_2_when_nothing_is_contested(tmp_path, capsys):
    import json

    from occufly.cli import main

    ws, _, _ = _voted_workspace(tmp_path / "a", contested=True)
    assert main(["select", str(ws), "--next", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"][0] == 6 and len(out["frames"]) == 2
    assert json.loads((ws / "next_frames.json").read_text())["frames"] == out["frames"]
    # the reviewer's contested suspect points to the proposed frame that sees it
    top = out["suspects"][0]
    assert top["kind"] == "contested" and 6 in top["proposed_frames"]
    assert top["id"] in out["reasons"][0]["suspects"]
    ws2, _, _ = _voted_workspace(tmp_path / "b", contested=False)
    assert main(["select", str(ws2), "--next", "2", "--json"]) == 2
    cap = capsys.readouterr()
    assert json.loads(cap.out)["frames"] == []
    assert "nothing is contested or uncertain" in cap.err
    assert not (ws2 / "next_frames.json").exists()
    # a workspace without votes is a clear error, not a traceback
    bare = tmp_path / "c" / "ws"
    _scene([(10, 10)], [50]).save(bare)
    assert main(["select", str(bare), "--next", "1"]) == 2
    assert "no votes yet" in capsys.readouterr().err
