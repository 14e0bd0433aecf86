"""The point level of detail (app.viewer.point_lod): a coarse level first, then region tiles,
and a relabel re-sending only the (class, tile) chunks whose points changed."""

from __future__ import annotations

import contextlib
import time

import numpy as np
from viewer_fixtures import COUNTS, FakeClient

from app.viewer import point_lod
from app.viewer import scene_builder as sb
from app.viewer.server import ViewerService
from app.viewer.state import ClientState, default_scenes
from occufly.lifting.corrections import write_overrides


def _service(tiny, coarse: int) -> tuple[ViewerService, ClientState]:
    svc = ViewerService(scenes=default_scenes(tiny.ws.parent), preview_points=coarse)
    svc.refine_pause_s = 0.0
    svc.lod_tiles = 3
    st = ClientState(client=FakeClient(), scene_id="tiny")
    st.gui["classes"] = contextlib.nullcontext()
    st.data = svc.scene_data("tiny")
    with svc._lock:
        svc._clients[1] = st
    return svc, st


def test_plan_coarse_level_is_stratified_and_tiles_go_from_the_middle_out(tiny):
    data = sb.ViewerData.load(tiny.ws)
    plan = point_lod.plan_lod(data, 10_000, coarse_points=200, tiles=3)
    n = sum(COUNTS.values())
    assert len(plan.ids) == n and plan.n_coarse == 200
    coarse = plan.ids[plan.group == 0]
    assert (tiny.labels[coarse] == 11).sum() == 5  # the rare class is in the first picture
    assert set(plan.order) == set(np.unique(plan.group[plan.group > 0]).tolist())
    assert plan.order[0] == 1 + 4  # the middle tile of 3 x 3 first
    chunks = point_lod.build_chunks(data, plan)
    assert sum(len(nd.point_ids) for nd in chunks.values()) == n
    assert chunks[(0, 11)].name == "/points/person/coarse"
    for (g, cid), nd in chunks.items():
        assert (plan.group[np.searchsorted(plan.ids, nd.point_ids)] == g).all()
        assert (tiny.labels[nd.point_ids] == cid).all()
    for n_batches in (1, 2, 4):  # the tiles in order, cut into batches of similar size
        got = point_lod.batches(plan, n_batches)
        assert [g for b in got for g in b] == plan.order and len(got) <= n_batches
    two = [int(np.isin(plan.group, b).sum()) for b in point_lod.batches(plan, 2)]
    assert len(two) == 2 and abs(two[0] - two[1]) < 0.4 * sum(two)
    small = point_lod.plan_lod(data, 10_000, coarse_points=5_000)
    assert small.n_coarse == n and small.order == []  # fits the coarse level: no tiles



def test_chunks_of_some_groups_or_keys_are_those_of_the_whole_build(tiny):
    """``build_chunks`` of a few groups, or of a few (group, class) keys, gathers only their
    rows: the chunks must be exactly the whole build's, point for point and in order."""
    data = sb.ViewerData.load(tiny.ws)
    plan = point_lod.plan_lod(data, 10_000, coarse_points=200, tiles=3, motion_points=60)
    whole = point_lod.build_chunks(data, plan, mode="semantic")
    rest = 1 + 3 * 3
    assert plan.first == (0, rest)

    def same(got: dict, want_keys: set) -> None:
        assert set(got) == want_keys
        for k, nd in got.items():
            ref = whole[k]
            assert nd.name == ref.name and nd.class_id == ref.class_id
            assert np.array_equal(nd.point_ids, ref.point_ids)
            assert np.array_equal(nd.xyz, ref.xyz) and np.array_equal(nd.colors, ref.colors)

    for groups in ({0}, {0, rest}, {plan.order[0]}, set(plan.order[:3]), {99}):
        same(point_lod.build_chunks(data, plan, groups=groups),
             {k for k in whole if k[0] in groups})
    keys = {k for k in whole if k[1] == 11} | {(plan.order[0], 6), (99, 6)}
    same(point_lod.build_chunks(data, plan, keys=keys), keys & set(whole))
    both = point_lod.build_chunks(data, plan, groups={0}, keys=keys)
    same(both, {k for k in keys & set(whole) if k[0] == 0})

def test_coarse_level_is_sent_first_then_every_tile(tiny):
    svc, st = _service(tiny, coarse=200)
    nodes = svc.send_points(st)
    assert sum(len(nd.point_ids) for nd in nodes) == 200
    assert st.lod_done.wait(10), "the refinement did not finish"
    clouds = [e for e in st.client.scene.log if e[0] == "points"]
    n_coarse = sum(1 for e in clouds if e[1].endswith("/coarse"))
    assert all(e[1].endswith("/coarse") for e in clouds[:n_coarse])  # coarse before any tile
    assert sum(e[2] for e in clouds[:n_coarse]) == 200
    tiles = clouds[n_coarse:]
    assert tiles and all("/detail/t0" in e[1] for e in tiles)
    assert sum(e[2] for e in clouds) == sum(COUNTS.values()) == st.sent_points
    frames = {e[1] for e in st.client.scene.log if e[0] == "frame"}
    assert "/points/person" in frames  # a class toggle flips its frame's visibility
    ids = np.concatenate([nd.point_ids for nd in st.point_nodes.values()])
    assert np.array_equal(np.sort(ids), st.lod_plan.ids)
    svc.set_class_visible(st, 11, False)
    assert st.point_handles[11].visible is False
    # orbiting: the tiles' frames are hidden (the coarse level alone is drawn) until the
    # camera rests, then shown again
    svc.motion_rest_s = 0.3
    assert st.detail_handles and all(h.visible for h in st.detail_handles.values())
    svc.camera_moved(st)
    assert st.moving and not any(h.visible for h in st.detail_handles.values())
    time.sleep(0.15)
    svc.camera_moved(st)  # still moving: the rest starts again
    time.sleep(0.2)
    assert not any(h.visible for h in st.detail_handles.values())
    deadline = time.time() + 5
    while st.moving and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.05)
    assert all(h.visible for h in st.detail_handles.values())


def test_relabel_resends_only_the_changed_chunks_and_undo_restores(tiny):
    svc, st = _service(tiny, coarse=200)
    svc.send_points(st)
    assert st.lod_done.wait(10)
    log = st.client.scene.log
    plan = st.lod_plan
    grass = np.flatnonzero(tiny.labels == 6)
    tile_of = plan.group[np.searchsorted(plan.ids, grass)]
    target = grass[tile_of == plan.order[0]]  # grass of the middle tile -> vehicle
    assert len(target) > 10
    write_overrides(tiny.ws, target, np.full(len(target), 13, np.uint8))
    before = len(log)
    time.sleep(0.02)  # a new stamp
    assert svc.refresh_now("tiny") == {6, 13}
    sent = [e for e in log[before:] if e[0] == "points"]
    names = {e[1] for e in sent}
    tile = f"detail/t{plan.order[0] - 1:03d}"
    assert names <= {"/points/grass/coarse", "/points/vehicle/coarse",
                     f"/points/grass/{tile}", f"/points/vehicle/{tile}"}
    assert f"/points/vehicle/{tile}" in names
    assert sum(e[2] for e in sent) < sum(COUNTS.values()) / 2  # not the whole scene again
    vehicle = np.asarray(sb.ViewerData.load(tiny.ws).taxonomy.colour_lut()[13])
    vehicle_chunk = [e for e in sent if e[1] == f"/points/vehicle/{tile}"][-1]
    assert vehicle_chunk[2] >= len(target) and (vehicle_chunk[4] == vehicle).all()
    assert np.isin(target, st.point_nodes[13].point_ids).all()
    assert not np.isin(target, st.point_nodes[6].point_ids).any()
    # undo: the layer is gone, the same chunks go back
    write_overrides(tiny.ws, np.zeros(0, np.int64), np.zeros(0, np.uint8))
    before = len(log)
    time.sleep(0.02)
    assert svc.refresh_now("tiny") == {6, 13}
    back = {e[1] for e in log[before:] if e[0] == "points"}
    assert back <= names | {f"/points/grass/{tile}"}
    assert np.isin(target, st.point_nodes[6].point_ids).all()
    assert not np.isin(target, st.point_nodes[13].point_ids).any()


def test_direct_votes_start_once_the_points_are_on_screen(tiny):
    """The direct-vote labels (a pass over every point's vote counts) do not take a core from
    a tab's first picture: they start when the level of detail is sent, not at the load."""
    n = tiny.scene.n_points
    votes = np.zeros((n, len(tiny.scene.taxonomy)), np.uint16)
    votes[:, 1] = 1
    np.save(tiny.ws / "lifting" / "votes.npy", votes)
    svc, st = _service(tiny, coarse=200)
    assert isinstance(st.data.direct, sb.LazyLabels) and not st.data.direct.started
    svc.send_points(st)
    assert st.lod_done.wait(10), "the refinement did not finish"
    assert st.data.direct.started
    assert st.data.direct.get().shape == (n,)
