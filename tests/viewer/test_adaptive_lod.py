"""The resting level of detail chosen per browser (issue 38): the refinement measures how long
the browser takes to draw what it shows (a render round trip) and stops before a tile batch
that would make a frame exceed the budget; a fast browser gets the whole plan, the user's own
"LOD max points" is sent whole, and a relabel never sends the tiles that were not sent."""

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

PER_POINT_S = 1e-4  # the fake browser's draw time per point shown (1,000 points: 0.1 s)
GRASS, VEHICLE = 6, 13
TOTAL = sum(COUNTS.values())


class Browser(FakeClient):
    """A client whose render request answers after drawing every point it shows:
    ``per_point_s`` seconds a point (0: a GPU browser)."""

    def __init__(self, per_point_s: float) -> None:
        super().__init__()
        self.per_point_s = per_point_s
        self.st: ClientState | None = None
        self.renders: list[int] = []

    def get_render(self, h: int, w: int, timeout: float | None = None) -> np.ndarray:
        n = self.st.sent_points if self.st is not None else 0
        self.renders.append(n)
        time.sleep(self.per_point_s * n)
        return np.zeros((h, w, 3), np.uint8)


class Field:
    """The "LOD max points" number input: viser calls its update callback in the setter."""

    def __init__(self, svc: ViewerService, st: ClientState, value: int) -> None:
        self.svc, self.st, self._value = svc, st, value

    @property
    def value(self) -> int:
        return self._value

    @value.setter
    def value(self, v: int) -> None:
        if v != self._value:
            self._value = v
            self.svc.lod_field_changed(self.st, v)


def _open(tiny, per_point_s: float, budget: float | None = 0.06,
          client: Browser | None = None):
    svc = ViewerService(scenes=default_scenes(tiny.ws.parent), preview_points=200)
    svc.lod_tiles = 3
    svc.frame_budget_s = budget
    client = client if client is not None else Browser(per_point_s)
    st = ClientState(client=client, scene_id="tiny")
    client.st = st
    st.gui["classes"] = contextlib.nullcontext()
    st.gui["status"] = type("Md", (), {"content": ""})()
    st.gui["lod"] = Field(svc, st, st.max_points)
    st.gui["size"] = type("Slider", (), {"value": st.point_size})()
    st.data = svc.scene_data("tiny")
    with svc._lock:
        svc._clients[1] = st
    svc.send_points(st)
    assert st.lod_done.wait(20), "the refinement did not finish"
    return svc, st


def _shown_groups(st: ClientState) -> set[int]:
    return {g for g, _c in st.chunks}


def _assert_shown_is_the_plan_of(st: ClientState, groups: set[int]) -> None:
    """What the browser holds: exactly the plan's points of ``groups``, each in its class's
    chunk by the workspace's current labels."""
    plan = st.lod_plan
    want = np.sort(plan.ids[np.isin(plan.group, list(groups))])
    got = np.sort(np.concatenate([nd.point_ids for nd in st.chunks.values()]))
    assert np.array_equal(got, want)
    labels = np.asarray(st.data.labels)
    for (g, cid), nd in st.chunks.items():
        assert (labels[nd.point_ids] == cid).all(), (g, cid)


def test_a_slow_browser_stops_the_refinement_within_its_frame_budget(tiny):
    svc, st = _open(tiny, PER_POINT_S, budget=0.06)
    plan = st.lod_plan
    assert len(plan.ids) == TOTAL and plan.n_coarse == 200
    # a frame of 1,000 points would take 0.1 s: some tiles, not all
    assert 200 < st.sent_points < TOTAL
    assert st.sent_points * PER_POINT_S <= 0.06  # the round trip over-estimates: within
    sent = _shown_groups(st) - {0}
    assert sent and list(plan.order[:len(sent)]) == [g for g in plan.order if g in sent]
    _assert_shown_is_the_plan_of(st, sent | {0})  # whole tiles, the middle of the view first
    assert st.sent_groups == sent | {0}
    shown, planned, draw_s = st.lod_stopped
    assert (shown, planned) == (st.sent_points, TOTAL)
    assert draw_s >= PER_POINT_S * st.sent_points * 0.9
    status = svc.status_line(st)
    assert "draws slowly" in status and f"showing {st.sent_points:,} of {TOTAL:,}" in status
    assert "LOD max points" in status
    assert st.gui["lod"].value == st.sent_points  # the field shows the viewer's choice ...
    assert not st.lod_explicit  # ... which is not taken for the user's
    # the points as large as the spacing of those shown (the ground covered): 0.8 x the
    # square root of the footprint's area per point, footprint 40 x 30 m
    xy = np.asarray(st.data.scene.xyz)[:, :2]
    area = float(np.prod(np.ptp(xy, axis=0)))
    assert abs(st.point_size - 0.8 * np.sqrt(area / st.sent_points)) < 0.005
    assert st.gui["size"].value == st.point_size and not st.point_size_set


def test_a_fast_browser_gets_the_whole_plan(tiny):
    svc, st = _open(tiny, 0.0, budget=0.06)
    assert st.sent_points == TOTAL and st.lod_stopped is None
    _assert_shown_is_the_plan_of(st, set(np.unique(st.lod_plan.group).tolist()))
    assert "slowly" not in svc.status_line(st)
    assert st.gui["lod"].value == sb.DEFAULT_MAX_POINTS
    # one batch: the round trips (drawn, then measured) before it, none between tiles
    tiles = [e for e in st.client.scene.log if e[0] == "points" and "/detail/" in e[1]]
    assert len(tiles) == len({e[1] for e in tiles})
    assert len(st.client.renders) == 1 + svc.draw_samples


class Mute(Browser):
    """A client that never answers a render request (each one waits out its timeout)."""

    def get_render(self, h: int, w: int, timeout: float | None = None) -> np.ndarray:
        self.renders.append(self.st.sent_points if self.st is not None else 0)
        raise TimeoutError("no render answer")


def test_a_client_that_does_not_answer_is_asked_once_and_gets_the_plan(tiny):
    """No answer within draw_wait_s: the rest of the plan goes at once, without asking again
    (each request waits the whole timeout: a socket-level client waited 3 x 15 s)."""
    _svc, st = _open(tiny, 0.0, budget=0.06, client=Mute(0.0))
    assert st.sent_points == TOTAL and st.lod_stopped is None
    assert len(st.client.renders) == 1


def test_without_a_budget_the_slow_browser_gets_everything(tiny):
    _svc, st = _open(tiny, PER_POINT_S, budget=None)
    assert st.sent_points == TOTAL and st.lod_stopped is None


def test_the_users_lod_setting_is_sent_whole(tiny):
    svc, st = _open(tiny, PER_POINT_S, budget=0.06)
    stopped_at = st.sent_points
    assert stopped_at < TOTAL
    st.gui["lod"].value = 1000  # the user asks for 1,000 points (the field's least), more
    assert st.lod_explicit  # than this browser's choice: a frame of them takes 0.1 s
    assert st.lod_done.wait(20)
    assert st.sent_points == TOTAL > stopped_at and st.lod_stopped is None
    assert len(st.lod_plan.ids) == TOTAL
    _assert_shown_is_the_plan_of(st, set(np.unique(st.lod_plan.group).tolist()))
    assert "slowly" not in svc.status_line(st)


def test_budgets_are_per_client(tiny):
    svc, slow = _open(tiny, PER_POINT_S, budget=0.06)
    fast = ClientState(client=Browser(0.0), scene_id="tiny")
    fast.client.st = fast
    fast.gui["classes"] = contextlib.nullcontext()
    fast.data = slow.data
    with svc._lock:
        svc._clients[2] = fast
    svc.send_points(fast)
    assert fast.lod_done.wait(20)
    assert fast.sent_points == TOTAL and slow.sent_points < TOTAL
    assert fast.lod_plan is slow.lod_plan  # one plan for the scene's tabs, made once
    assert fast.lod_stopped is None and slow.lod_stopped is not None


def test_a_relabel_updates_the_shown_tiles_and_sends_no_unsent_one(tiny):
    svc, st = _open(tiny, PER_POINT_S, budget=0.06)
    plan = st.lod_plan
    sent = _shown_groups(st) - {0}
    unsent = set(plan.order) - sent
    assert sent and unsent
    grass = plan.ids[(np.asarray(st.data.labels)[plan.ids] == GRASS)]
    group = plan.group[np.searchsorted(plan.ids, grass)]
    target = np.concatenate([grass[np.isin(group, list(sent))][:20],
                             grass[np.isin(group, list(unsent))][:20],
                             grass[group == 0][:5]])
    assert len(target) == 45
    write_overrides(tiny.ws, target, np.full(len(target), VEHICLE, np.uint8))
    log = st.client.scene.log
    before = len(log)
    time.sleep(0.02)  # a new stamp
    assert svc.refresh_now("tiny") == {GRASS, VEHICLE}
    names = {e[1] for e in log[before:] if e[0] == "points"}
    unsent_names = {point_lod.chunk_name(st.data.taxonomy, c, g)
                    for g in unsent for c in COUNTS}
    assert names and not names & unsent_names  # no tile that was never sent
    assert "/points/vehicle/coarse" in names
    assert any("/vehicle/detail/" in n for n in names)  # the shown tiles are updated
    assert _shown_groups(st) - {0} == sent
    _assert_shown_is_the_plan_of(st, sent | {0})  # and match the new labels
    shown = np.concatenate([nd.point_ids for nd in st.point_nodes.values()])
    assert not np.isin(target[20:40], shown).any()


def test_a_colour_change_resends_the_shown_tiles_only(tiny):
    svc, st = _open(tiny, PER_POINT_S, budget=0.06)
    sent = _shown_groups(st)
    rgb = np.asarray(st.data.scene.rgb)
    st.mode = "rgb"
    log = st.client.scene.log
    before = len(log)
    svc.send_points(st)
    assert st.lod_done.wait(20)
    assert _shown_groups(st) == sent  # the tiles shown before, in the new colours ...
    for nd in st.chunks.values():
        assert np.array_equal(nd.colors, rgb[nd.point_ids])
    again = {e[1] for e in log[before:] if e[0] == "points"}
    assert {nd.name for nd in st.chunks.values()} <= again  # ... none left stale


def test_the_grid_is_hidden_while_the_camera_moves(tiny, tiny_grid):
    svc = ViewerService(scenes=default_scenes(tiny.ws.parent), preview_points=200)
    svc.motion_rest_s = 0.2
    st = ClientState(client=FakeClient(), scene_id="tiny")
    st.data = svc.scene_data("tiny")
    box = type("Box", (), {})
    for k, v in (("grid_surface", True), ("grid_scene", True), ("grid_frame", "(none)")):
        st.gui[k] = box()
        st.gui[k].value = v
    svc.send_grids(st)
    boxes = [e for e in st.client.scene.log if e[0] == "boxes"]
    assert boxes and all(e[3] == sb.GRID_MATERIAL == "toon3" for e in boxes)
    assert st.grid_handles and all(h.visible for h in st.grid_handles.values())
    svc.set_class_visible(st, 11, False)  # persons' boxes off
    person = [n for n in st.grid_handles if n.endswith("/person")]
    assert person
    svc.camera_moved(st)
    assert not any(h.visible for h in st.grid_handles.values())
    svc.send_grids(st)  # a grid sent while moving comes hidden too
    assert not any(h.visible for h in st.grid_handles.values())
    deadline = time.time() + 5
    while st.moving and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.05)
    for n, h in st.grid_handles.items():  # back at rest, the hidden class stays hidden
        assert h.visible == (n not in person), n


def test_the_motion_level_is_part_of_the_coarse_level(tiny):
    """With ``motion_points`` below the coarse level, only the motion part is group 0 (drawn
    while the camera moves) and the first send (the first picture); the rest of the coarse
    level is a detail group, hidden with the tiles, sent right after it and before any tile
    (``motion_first``; off: the whole coarse level in the first send)."""
    svc = ViewerService(scenes=default_scenes(tiny.ws.parent), preview_points=200)
    svc.lod_tiles, svc.motion_points, svc.motion_rest_s = 3, 50, 0.2
    st = ClientState(client=FakeClient(), scene_id="tiny")
    st.gui["classes"] = contextlib.nullcontext()
    st.data = svc.scene_data("tiny")
    with svc._lock:
        svc._clients[1] = st
    first = svc.send_points(st)
    assert st.lod_done.wait(20)
    plan = st.lod_plan
    rest = 1 + 3 * 3
    assert plan.first == (0, rest) and rest not in plan.order
    assert plan.n_coarse == 50 and int((plan.group == rest).sum()) == 150
    assert sum(len(nd.point_ids) for nd in first) == 50  # the first picture: the motion level
    log = [e for e in st.client.scene.log if e[0] == "points"]
    n_motion = sum(1 for e in log if e[1].endswith("/coarse"))
    assert all(e[1].endswith("/coarse") for e in log[:n_motion])
    after = [e for e in log[n_motion:] if "/detail/t009" in e[1]]
    assert log[n_motion:len(after) + n_motion] == after  # the coarse level's rest next
    motion = plan.ids[plan.group == 0]
    # stratified: the rare class moves along (a floor of a quarter of 50 over 5 classes)
    assert (tiny.labels[motion] == 11).sum() >= int(0.25 * 50 / 5) > 0
    log = [e for e in st.client.scene.log if e[0] == "points"]
    assert sum(e[2] for e in log if "/detail/t009" in e[1]) == 150  # sent once, with the
    assert st.sent_points == TOTAL  # coarse level; no client round trips: everything sent
    svc.camera_moved(st)
    assert svc._points_drawn(st) == 50
    shown = [h for h in st.detail_handles.values() if h.visible]
    assert not shown  # the rest of the coarse level is hidden with the tiles
    _assert_shown_is_the_plan_of(st, set(np.unique(plan.group).tolist()))
    svc.motion_first = False  # the path before: the whole coarse level in the first send
    st.lod_plan = None
    assert sum(len(nd.point_ids) for nd in svc.send_points(st)) == 200
    assert st.lod_done.wait(20)
