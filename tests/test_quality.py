"""Quality report and re-lifting of chosen versions (issue 23: provenance end to end,
quality report)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from occufly.cli import main as cli_main
from occufly.lifting import VoteStore, load_labels
from occufly.lifting.quality import distribution, quality_report
from occufly.lifting.relift import labels_digest, relift
from occufly.scene import Scene
from tests.lift_scene import BUILDING, GRASS, ROAD, ROOF, make_scene, truth_mask

WRONG = 5
SELECTED = (1, 4, 5, 6, 9, 10)


def _truth_points(scene: Scene) -> np.ndarray:
    """Point truth by the majority of the exact masks over every frame that sees a point."""
    st = VoteStore(Path("."), scene, np.zeros((scene.n_points, len(scene.taxonomy.ids)), np.uint16), {})
    flat = st.votes.reshape(-1)
    C = len(scene.taxonomy.ids)
    for fi, fr in enumerate(scene.frames):
        pids, cols, w = st.frame_votes(fi, truth_mask(fr))
        np.add.at(flat, pids.astype(np.int64) * C + cols, w)
    return st.direct_labels()


@pytest.fixture(scope="module")
def lifted(tmp_path_factory):
    scene, _ = make_scene()
    path = tmp_path_factory.mktemp("quality") / "ws"
    scene.save(path)
    scene = Scene.load(path)
    st = VoteStore.open(path, scene)
    masks = {}
    for fi in SELECTED:
        m = truth_mask(scene.frames[fi])
        if fi == WRONG:  # houses painted as grass and road
            m = m.copy()
            m[m == BUILDING] = GRASS
            m[m == ROOF] = ROAD
        masks[fi] = m
    # the live state is built incrementally, with a mask replaced and one frame removed
    st.set_mask(SELECTED[0], np.full_like(masks[SELECTED[0]], GRASS), version="x")
    for fi in SELECTED:
        st.set_mask(fi, masks[fi], version=str(fi))
    st.set_mask(0, truth_mask(scene.frames[0]), version="0")
    st.remove_frame(0)
    st.fill_and_denoise()
    return path, scene, masks


def test_distribution_quantiles_and_histogram():
    d = distribution([0.5, 1.0, None, 0.95, 0.05])
    assert d["n"] == 4 and d["quantiles"]["p0"] == 0.05 and d["quantiles"]["p100"] == 1.0
    assert d["histogram"]["counts"] == [1, 0, 0, 0, 0, 1, 0, 0, 0, 2]
    assert distribution([])["quantiles"] is None


def test_report_names_the_wrong_frame_and_measures_calibration(lifted):
    path, scene, _masks = lifted
    truth = _truth_points(scene)
    q = quality_report(path, scene, truth=truth)
    assert q["format"] == "occufly-quality" and q["annotated_frames"] == len(SELECTED)
    rows = {r["frame"]: r for r in q["loo"]["per_frame"]}
    assert set(rows) == set(SELECTED)
    assert min(rows, key=lambda f: rows[f]["agreement"]) == WRONG
    others = [r["agreement"] for f, r in rows.items() if f != WRONG]
    assert rows[WRONG]["agreement"] < 0.85 < min(others) and np.median(others) > 0.95
    assert q["loo"]["agreement_distribution"]["n"] == len(SELECTED)
    # what the wrong frame paints differently (issue 37): its houses as grass and road
    names = {c.id: c.name for c in scene.taxonomy.classes}
    top = {(d["painted"], d["independent"]) for d in rows[WRONG]["disagreements"][:2]}
    assert top == {(names[GRASS], names[BUILDING]), (names[ROAD], names[ROOF])}, \
        rows[WRONG]["disagreements"]
    # the same figures by hand: views per point from the per-frame vote files
    views = np.zeros(scene.n_points, int)
    for fi in SELECTED:
        with np.load(path / "lifting" / "frames" / f"{fi}.npz") as z:
            views[z["point_ids"]] += 1
    lab = np.asarray(load_labels(path).labels)
    labelled = lab > 0
    assert q["votes"]["multi_view_points"] == int((views >= 2).sum())
    assert q["votes"]["multi_view_share"] == pytest.approx((views[labelled] >= 2).mean(), abs=1e-6)
    # the wrong frame's houses make contested points; the per-class table shows them
    assert q["contested"]["points"] > 0
    assert q["classes"][str(BUILDING)]["contested"] > q["classes"][str(GRASS)]["contested"]
    t = q["confidence"]["truth"]
    assert t is not None and 0 <= t["ece"] < 0.2 and len(t["reliability"]) == 10
    has = labelled & (truth > 0)
    assert t["accuracy"] == pytest.approx((lab[has] == truth[has]).mean(), abs=1e-6)
    json.dumps(q)  # JSON-able as it is


def test_cli_report_json_and_summary(lifted, capsys):
    path, _scene, _masks = lifted
    assert cli_main(["report", str(path), "--json", "--no-loo"]) == 0
    q = json.loads(capsys.readouterr().out)
    assert q["loo"] is None and q["annotated_frames"] == len(SELECTED)
    assert cli_main(["report", str(path)]) == 0
    out = capsys.readouterr().out
    assert "LOO agreement" in out and "contested" in out and "ECE not measured" in out
    assert "where the others say" in out  # the lowest frames' disagreements


def test_cli_report_without_labels_is_a_clear_error(tmp_path, capsys):
    scene, _ = make_scene()
    scene.save(tmp_path / "ws")
    assert cli_main(["report", str(tmp_path / "ws")]) == 2
    assert "nothing to report" in capsys.readouterr().err


def test_relift_of_the_counted_versions_reproduces_the_live_labels_byte_for_byte(lifted, tmp_path):
    path, scene, masks = lifted
    live = load_labels(path, corrections=False)
    versions = live.stats["versions"]
    assert versions == {str(f): str(f) for f in SELECTED}
    # applied in another order: counts are sums
    items = [(int(f), tag, masks[int(f)]) for f, tag in reversed(list(versions.items()))]
    res = relift(scene, items, tmp_path / "scratch", features_ws=path)
    for name in ("labels", "confidence", "origin"):
        a = (path / "lifting" / f"{name}.npy").read_bytes()
        b = (tmp_path / "scratch" / "lifting" / f"{name}.npy").read_bytes()
        assert a == b, name
    assert labels_digest(res) == labels_digest(live)
    # a narrower set gives other labels (the wrong frame left out)
    res2 = relift(scene, [i for i in items if i[0] != WRONG], tmp_path / "scratch2")
    assert labels_digest(res2)["labels"] != labels_digest(live)["labels"]
    with pytest.raises(FileExistsError):
        relift(scene, items, tmp_path / "scratch")


def test_truth_kept_with_the_workspace_measures_the_calibration(lifted, capsys):
    from occufly.lifting.quality import workspace_truth

    path, scene, _masks = lifted
    tdir = path / "truth"
    tdir.mkdir(exist_ok=True)
    try:
        np.save(tdir / "point_labels.npy", np.zeros(scene.n_points + 1, np.uint8))
        assert workspace_truth(path, scene.n_points) is None  # does not fit the cloud
        truth = _truth_points(scene)
        np.save(tdir / "point_labels.npy", truth)
        assert np.array_equal(workspace_truth(path, scene.n_points), truth)
        assert cli_main(["report", str(path), "--json", "--no-loo"]) == 0
        q = json.loads(capsys.readouterr().out)
        assert q["confidence"]["truth"]["points"] > 0
        assert q["confidence"]["truth"]["ece"] == quality_report(
            path, scene, truth=truth, loo=False)["confidence"]["truth"]["ece"]
    finally:
        (tdir / "point_labels.npy").unlink()
