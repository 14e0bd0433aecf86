"""occufly.workspace.Workspace: the one owner of the workspace layout."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from occufly.errors import WorkspaceError
from occufly.grid import SceneGrid
from occufly.workspace import Workspace

REPO = Path(__file__).resolve().parents[1]


def test_layout_is_the_documented_one(tmp_path):
    ws = Workspace(tmp_path)
    assert ws.scene_json == tmp_path / "scene.json"
    assert ws.points_xyz == tmp_path / "points" / "xyz.npy"
    assert ws.visibility_array("uv") == tmp_path / "visibility" / "uv.npy"
    assert ws.labels_path == tmp_path / "lifting" / "labels.npy"
    assert ws.votes == tmp_path / "lifting" / "votes.npy"
    assert ws.lifting_frame(7) == tmp_path / "lifting" / "frames" / "7.npz"
    assert ws.grid_path() == tmp_path / "grid" / "scene_grid.npz"
    assert ws.grid_path(40) == tmp_path / "grid" / "scene_grid_40.npz"
    assert ws.truth_grid_path == tmp_path / "truth" / "scene_grid.npz"
    assert Workspace.report_path_of(ws.grid_path()).name == "scene_grid_report.json"
    with pytest.raises(ValueError):
        ws.visibility_array("../x")


def test_missing_workspace_is_a_clear_error(tmp_path):
    with pytest.raises(WorkspaceError, match="not a scene workspace"):
        Workspace(tmp_path).header()


def test_labels_round_trip_and_stamp_changes(tmp_path):
    ws = Workspace(tmp_path)
    assert ws.labels() is None and ws.confidence() is None and not ws.has_labels()
    s0 = ws.stamp()
    assert ws.stamp() == s0  # nothing changed, same stamp
    labels = np.array([1, 6, 0, 16], np.uint8)
    ws.write_labels(labels, np.array([1, 0.5, 0, 0.25], np.float32), np.array([1, 2, 0, 3], np.uint8),
                    {"points": 4, "score": np.float32(0.5)})
    assert np.array_equal(ws.labels(), labels)
    assert ws.confidence().dtype == np.float32 and ws.label_origin()[3] == 3
    assert ws.lift_stats() == {"points": 4, "score": 0.5}
    s1 = ws.stamp()
    assert s1 != s0
    g = SceneGrid(np.full((2, 3, 4), 6, np.uint8), np.array([500000.0, 4.2e6, 10.0]), 0.5)
    p = ws.write_grid(g, report={"voxels": 24})
    assert p == ws.grid_path() and ws.report_path_of(p).is_file()
    assert ws.grid().labels.shape == (2, 3, 4) and ws.stamp() != s1
    ws.write_grid(g, altitude=40)
    assert list(ws.altitude_grids()) == [40]
    assert ws.steps() == {"lifting": True, "grid": True, "truth_grid": False}
    with pytest.raises(ValueError, match="one value per point"):
        ws.write_labels(labels, np.zeros(3, np.float32), np.zeros(4, np.uint8))


# every workspace artefact path is spelled in occufly/workspace.py only
_SPELLINGS = re.compile(
    r"""["'](lifting|grid|points|visibility)/|/\s*["'](lifting|votes\.npy|labels\.npy|state\.json)["']"""
    r"""|["'](scene|taxonomy)\.json["']|["'](confidence|origin|labels|votes)\.npy["']"""
)


def test_no_module_spells_a_workspace_path():
    offenders = []
    for top in ("occufly", "app"):
        for p in sorted((REPO / top).rglob("*.py")):
            rel = p.relative_to(REPO).as_posix()
            if rel == "occufly/workspace.py" or rel.startswith("occufly/synthetic/"):
                continue  # the synthetic generator writes a reconstruction, not a workspace
            for n, line in enumerate(p.read_text().splitlines(), 1):
                if _SPELLINGS.search(line) and not line.lstrip().startswith("#"):
                    offenders.append(f"{rel}:{n}: {line.strip()}")
    assert not offenders, "workspace paths spelled outside occufly/workspace.py:\n" + "\n".join(offenders)



def test_direct_labels_is_a_read_only_reader(tmp_path):
    from occufly.lifting import VoteStore, read_direct_labels
    from tests.lift_scene import make_scene, truth_mask

    scene, _truth = make_scene()
    scene.save(tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    assert read_direct_labels(ws.root) is None  # no vote state yet, and none is created
    assert not ws.lifting_dir.exists()
    st = VoteStore.open(ws.root, scene)
    st.apply_frame(5, truth_mask(scene.frames[5]), version="v1")
    st.save()
    expected = st.direct_labels()
    st.close()
    before = {p: p.stat().st_mtime_ns for p in ws.lifting_dir.rglob("*") if p.is_file()}
    got = read_direct_labels(ws.root)
    assert np.array_equal(got, expected) and (got > 0).any()
    assert {p: p.stat().st_mtime_ns for p in ws.lifting_dir.rglob("*") if p.is_file()} == before


def test_frame_votes_have_one_reader_for_every_consumer(tmp_path):
    """Workspace.read_frame_votes is what the votes store, the review's leave-one-out labels,
    the quality report and the confusion model read a frame's votes with: what apply_frame
    wrote comes back as written (weights only where the state weighs votes), a missing file is
    None, and a damaged file is a WorkspaceError naming it -- not a zip or numpy traceback."""
    from occufly.lifting import VoteStore
    from occufly.lifting.confusion import load_frame_votes
    from occufly.lifting.loo import _frame_votes
    from tests.lift_scene import make_scene, truth_mask

    scene, _truth = make_scene()
    scene.save(tmp_path / "ws")
    ws = Workspace(tmp_path / "ws")
    st = VoteStore.open(ws.root, scene)
    mask = truth_mask(scene.frames[5])
    pids, cols, _w = st.frame_votes(5, mask)
    st.apply_frame(5, mask, version="v1")
    st.save()
    assert ws.read_frame_votes(4) is None
    got_p, got_c, got_w = ws.read_frame_votes(5)
    assert np.array_equal(got_p, pids) and np.array_equal(got_c, cols) and got_w is None
    assert got_p.dtype == np.int32 and got_c.dtype == np.uint8 and len(got_p) > 100
    # every consumer sees the same votes
    lp, lc, lw = _frame_votes(ws.root, 5)
    assert np.array_equal(lp, pids) and np.array_equal(lc, cols) and (lw == 1).all()
    cp, cc, cw = load_frame_votes(ws.root, [4, 5])[5]
    assert np.array_equal(cp, pids) and np.array_equal(cc, cols) and cw is None
    assert list(load_frame_votes(ws.root, [4, 5])) == [5]
    # mapped: the same votes, read-only views of the file (the review's neighbours)
    mp, mc, mw = ws.read_frame_votes(5, mmap=True)
    assert np.array_equal(mp, pids) and np.array_equal(mc, cols) and mw is None
    assert isinstance(mp.base, np.memmap) and not mp.flags.writeable
    del mp, mc
    # a file removed between the check and the read (its mask deleted): no votes, not an error
    import occufly.workspace as workspace_mod

    def gone(*_a, **_k):
        raise FileNotFoundError(ws.lifting_frame(5))

    real_load, workspace_mod.load_npz = workspace_mod.load_npz, gone
    try:
        assert ws.read_frame_votes(5) is None
    finally:
        workspace_mod.load_npz = real_load
    # a counted rebuild from the files gives the same counts
    before = np.array(st.votes)
    st.rebuild()
    assert np.array_equal(np.asarray(st.votes), before)
    st.close()
    # damaged: not an archive, a member missing, members that disagree in length
    p = ws.lifting_frame(5)
    for bad in (b"not a zip", None, "short"):
        if bad is None:
            np.savez(p.with_suffix(".tmp.npz"), point_ids=pids)
        elif bad == "short":
            np.savez(p.with_suffix(".tmp.npz"), point_ids=pids, cols=cols[:-1])
        if isinstance(bad, bytes):
            p.write_bytes(bad)
        else:
            p.with_suffix(".tmp.npz").replace(p)
        with pytest.raises(WorkspaceError, match=r"5\.npz"):
            ws.read_frame_votes(5)
