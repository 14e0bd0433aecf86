"""Suspects (issue 23): clusters of contested points, ranked, with the frames that see them."""

from __future__ import annotations

import numpy as np

from occufly.lifting import LiftState
from occufly.lifting.suspects import contested_share, find_suspects
from occufly.scene import Scene
from tests.lift_scene import BOXES, BUILDING, GRASS, ROAD, ROOF, make_scene, truth_mask


def test_a_wrongly_painted_house_is_the_top_suspect(tmp_path):
    scene, _truth = make_scene()
    scene.save(tmp_path / "ws")
    scene = Scene.load(tmp_path / "ws")
    st = LiftState.open(tmp_path / "ws", scene)
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
