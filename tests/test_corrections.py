"""The corrections override layer (occufly.lifting.corrections): the net layer of versioned
edits, last-wins, incremental activate/deactivate equal to a rebuild, edit point files, and
every consumer of labels seeing the corrections (load_labels, prefill of another frame,
agreement, the voxelize input)."""

from __future__ import annotations

import numpy as np
import pytest

from occufly import render
from occufly.lifting import ORIGIN_CORRECTED, load_labels
from occufly.lifting import corrections as lib
from occufly.scene import Scene
from occufly.workspace import Workspace
from tests.app.conftest import make_tiny_scene


@pytest.fixture
def ws(tmp_path):
    scene = make_tiny_scene(4)
    scene.save(tmp_path / "ws")
    n = scene.n_points
    w = Workspace(tmp_path / "ws")
    w.write_labels(np.full(n, 6, np.uint8), np.full(n, 0.7, np.float32),
                   np.full(n, 2, np.uint8), {})
    return w


def _net_dict(net: lib.NetLayer) -> dict:
    return {int(p): (int(c), int(e)) for p, c, e in zip(net.point_ids, net.labels, net.edit_ids,
                                                            strict=True)}


def test_write_overrides_last_wins_and_keeps_edit_ids(ws):
    lib.write_overrides(ws, np.array([5, 3, 5, 9]), np.array([1, 2, 8, 0]),
                        edit_ids=np.array([1, 1, 2, 3]), applied=[3, 1, 2])
    net = lib.read_net(ws)
    assert net.point_ids.tolist() == [3, 5, 9]
    assert net.labels.tolist() == [2, 8, 0]  # point 5: the later entry (8) wins
    assert net.edit_ids.tolist() == [1, 2, 3]
    assert net.applied.tolist() == [1, 2, 3]
    ov = lib.read_overrides(ws)  # the seam's reader still reads it
    assert ov.point_ids.tolist() == [3, 5, 9] and ov.labels.tolist() == [2, 8, 0]
    # an empty layer with `applied` is kept (it records that no edit is applied)
    lib.write_net(ws, lib.NetLayer.empty())
    assert ws.overrides_path.is_file() and len(lib.read_net(ws)) == 0
    assert lib.read_net(ws).applied.tolist() == []


def test_incremental_layer_equals_rebuild_under_random_undo_redo(ws):
    rng = np.random.default_rng(3)
    n = 400
    edits = {}
    for eid in range(1, 13):
        edits[eid] = (int(rng.choice([0, 1, 8, 13])),
                      np.unique(rng.integers(0, n, rng.integers(1, 80))))
    active: set[int] = set()
    net = lib.NetLayer.empty()
    for step in range(60):
        eid = int(rng.integers(1, 13))
        cls, ids = edits[eid]
        if eid in active:
            earlier = [(e, edits[e][0], (lambda e=e: edits[e][1]))
                       for e in sorted(active, reverse=True) if e != eid]
            net = lib.deactivate_edit(net, eid, ids, earlier)
            active.discard(eid)
        else:
            net = lib.activate_edit(net, eid, ids, cls)
            active.add(eid)
        ref = lib.rebuild_net((e, edits[e][0], edits[e][1]) for e in active)
        assert _net_dict(net) == _net_dict(ref), f"step {step}"
        assert sorted(net.applied.tolist()) == sorted(active)
        assert np.all(np.diff(net.point_ids) > 0)
    # the highest active edit id wins on every point (analytic check)
    for p, (c, e) in _net_dict(net).items():
        covering = [x for x in active if p in set(edits[x][1].tolist())]
        assert e == max(covering) and c == edits[e][0]


def test_deactivate_reads_only_the_older_edits_it_needs(ws):
    """O(edited points): undoing edit 3 resolves its points from edit 2 and never loads
    edit 1 (all of edit 3's points were decided by edit 2 already)."""
    a, b, c = np.arange(0, 100), np.arange(50, 150), np.arange(60, 90)
    net = lib.rebuild_net([(1, 1, a), (2, 8, b), (3, 13, c)])
    loaded = []

    def loader(eid, ids):
        return lambda: (loaded.append(eid), ids)[1]

    out = lib.deactivate_edit(net, 3, c, [(2, 8, loader(2, b)), (1, 1, loader(1, a))])
    assert loaded == [2]
    d = _net_dict(out)
    assert all(d[p] == (8, 2) for p in range(60, 90))
    assert d[10] == (1, 1) and d[120] == (8, 2) and len(d) == 150


def test_edit_point_file_round_trip_and_compact(ws):
    ids = np.unique(np.random.default_rng(0).integers(0, 30_000_000, 200_000))
    p = lib.write_edit_points(ws, 7, ids, 8)
    assert p == ws.correction_edit(7) and p.parent == ws.corrections_dir
    back = lib.read_edit_points(ws, 7)
    assert back.dtype == np.int64 and np.array_equal(back, ids)
    assert p.stat().st_size < 2.5 * len(ids)  # < 2.5 bytes per id (uint32 deltas, zlib)
    with pytest.raises(ValueError):
        lib.write_edit_points(ws, 8, ids[::-1], 8)


def test_load_labels_labels_at_and_apply_to_labels_see_the_layer(ws):
    ids = np.arange(100, 140)
    lib.write_net(ws, lib.activate_edit(lib.NetLayer.empty(), 1, ids, 1))
    res = load_labels(ws)
    assert (np.asarray(res.labels)[ids] == 1).all() and (np.asarray(res.labels)[:100] == 6).all()
    assert (res.origin[ids] == ORIGIN_CORRECTED).all() and (res.confidence[ids] == 1.0).all()
    assert load_labels(ws, corrections=False).labels[ids[0]] == 6
    assert lib.labels_at(ws, np.array([0, 100, 139, 140])).tolist() == [6, 1, 1, 6]
    direct = np.full(400, 6, np.uint8)
    assert (lib.apply_to_labels(direct, ws)[ids] == 1).all()


def test_prefill_of_another_frame_and_agreement_reflect_a_correction(ws):
    scene = Scene.load(ws.root)
    xyz = np.asarray(scene.xyz)
    ids = np.flatnonzero((xyz[:, 0] > -6) & (xyz[:, 0] < -1))  # a strip of ground
    before, _d, _f = render.render_prefill(scene, np.asarray(load_labels(ws).labels), 1)
    assert (before == 1).sum() == 0
    lib.write_net(ws, lib.activate_edit(lib.NetLayer.empty(), 1, ids, 1))
    after, _d, _f = render.render_prefill(scene, np.asarray(load_labels(ws).labels), 1)
    road = after == 1
    fids, uv, _ = scene.visibility.frame(1)
    u = np.asarray(uv)[np.isin(np.asarray(fids), ids), 0]
    cols = np.flatnonzero(road.any(axis=0))
    assert road.sum() > 100 and len(u) > 10
    assert cols.min() >= u.min() - 3 and cols.max() <= u.max() + 3  # exactly the strip
    # agreement of a mask painted all grass against the corrected labels drops by those pixels
    mask = np.full(after.shape, 6, np.uint8)
    ren, _ = render.render_for_mask(scene, np.asarray(load_labels(ws).labels), 1, mask.shape)
    ag = render.agreement(mask, ren, scene.taxonomy)
    ren0, _ = render.render_for_mask(scene, np.asarray(load_labels(ws, corrections=False).labels),
                                     1, mask.shape)
    assert render.agreement(mask, ren0, scene.taxonomy)["agreement"] == 1.0
    assert ag["agreement"] < 0.95


def test_voxelize_input_carries_the_corrections(ws, monkeypatch):
    """voxelize_workspace (without --labels) densifies the corrected labels."""
    from occufly.densify import pipeline

    seen = {}

    def fake_densify(xyz, labels, taxonomy, **kw):
        seen["labels"] = np.asarray(labels).copy()
        raise RuntimeError("stop here")

    monkeypatch.setattr(pipeline, "densify", fake_densify)
    lib.write_net(ws, lib.activate_edit(lib.NetLayer.empty(), 1, np.arange(10), 8))
    with pytest.raises(RuntimeError, match="stop here"):
        pipeline.voxelize_workspace(ws, options=pipeline.DensifyOptions(free_space=False))
    assert (seen["labels"][:10] == 8).all() and (seen["labels"][10:] == 6).all()
