"""A correction reaches open viewers as a delta (issue 38): the data is brought up to date from
the correction layer alone (the fill output is not read again, nothing is compared point by
point) and only the (class, tile) chunks holding changed points are re-sent. Whatever the
sequence -- relabel, undo, an overlapping relabel, a class hidden meanwhile, another user's
change arriving -- what the browser was sent must equal the workspace's labels."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
from viewer_fixtures import FakeClient

from app.viewer import corrections_panel, point_lod
from app.viewer import scene_builder as sb
from app.viewer.server import ViewerService
from app.viewer.state import ClientState, default_scenes
from occufly.fsutil import atomic_save_npy
from occufly.lifting import load_labels
from occufly.lifting.corrections import write_overrides
from occufly.workspace import Workspace

GRASS, BUILDING, PERSON, VEHICLE, WATER = 6, 16, 11, 13, 14


class Widget:
    def __init__(self, value=None) -> None:  # noqa: ANN001
        self.value, self.content, self.disabled, self.options = value, "", False, []


class Edits:
    """The app's corrections hooks over one shared edit stack (users undo their own last
    edit), writing the net override layer as the app does."""

    def __init__(self, ws) -> None:  # noqa: ANN001
        self.ws, self.edits, self.undone = ws, [], []

    def _write(self) -> None:
        ids = [e[1] for e in self.edits] or [np.zeros(0, np.int64)]
        lab = [np.full(len(e[1]), e[2], np.uint8) for e in self.edits] or [np.zeros(0, np.uint8)]
        write_overrides(self.ws, np.concatenate(ids), np.concatenate(lab))  # last one wins

    def relabel(self, scene_id, point_ids, to_class, comment, user, frame_index=None) -> dict:  # noqa: ANN001
        self.edits.append((user, np.asarray(point_ids, np.int64), int(to_class)))
        self._write()
        return {"id": len(self.edits), "n_points": len(point_ids)}

    def undo(self, scene_id, user) -> dict:  # noqa: ANN001
        i = max(k for k, e in enumerate(self.edits) if e[0] == user)
        e = self.edits.pop(i)
        self.undone.append(e)
        self._write()
        return {"id": i + 1, "n_points": len(e[1])}

    def redo(self, scene_id, user) -> dict:  # noqa: ANN001
        self.edits.append(self.undone.pop())
        self._write()
        return {"id": len(self.edits), "n_points": len(self.edits[-1][1])}

    def stack(self, scene_id, user) -> dict:  # noqa: ANN001
        return {"undo": 1 if self.edits else None, "redo": 1 if self.undone else None}

    def hooks(self) -> dict:
        return {"relabel": self.relabel, "undo": self.undo, "redo": self.redo,
                "stack": self.stack}


def _open(tiny, edits: Edits, user: str = "rita") -> tuple[ViewerService, ClientState]:
    svc = ViewerService(scenes=default_scenes(tiny.ws.parent), preview_points=200,
                        corrections=edits.hooks())
    svc.lod_tiles = 3
    st = ClientState(client=FakeClient(), scene_id="tiny", user=user)
    st.gui.update({"classes": contextlib.nullcontext(), "edit_info": Widget(),
                   "counts": Widget(), "relabel_btn": Widget(), "f_class": Widget("any class"),
                   "f_origin": Widget("any origin"), "f_hmin": Widget(-1000.0),
                   "f_hmax": Widget(1000.0)})
    st.data = svc.scene_data("tiny")
    with svc._lock:
        svc._clients[id(st)] = st
    svc._rebuild_class_boxes(st)
    svc.send_points(st)
    assert st.lod_done.wait(10)
    return svc, st


def _sorted_rows(xyz: np.ndarray) -> np.ndarray:
    return xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]


def assert_shows_workspace(svc: ViewerService, st: ClientState) -> None:
    """The tab's data equals what every reader reads (occufly.lifting.load_labels), and the
    point clouds the client was sent (replayed from its log) hold every shown point once, in
    the chunk of its current label and level, in its label's colour; the class boxes count
    the workspace's labels."""
    res = load_labels(st.data.workspace)
    for name in ("labels", "confidence", "origin"):
        assert np.array_equal(np.asarray(getattr(st.data, name)), np.asarray(getattr(res, name))), name
    assert svc.scene_data("tiny") is st.data
    view: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for e in st.client.scene.log:
        if e[0] == "points":
            view[e[1]] = (e[3], e[4])
        elif e[0] == "remove":
            view.pop(e[1], None)
    view.pop("/selection", None)
    plan, tax = st.lod_plan, st.data.taxonomy
    key = plan.group.astype(np.int64) * 256 + res.labels[plan.ids]
    want = {}
    for k in np.unique(key):
        g, cid = divmod(int(k), 256)
        want[point_lod.chunk_name(tax, cid, g)] = (cid, plan.ids[key == k])
    assert set(view) == set(want)
    lut = tax.colour_lut()
    for name, (cid, ids) in want.items():
        xyz, cols = view[name]
        assert np.array_equal(_sorted_rows(xyz),
                              _sorted_rows(np.asarray(st.data.scene.xyz[ids], np.float32))), name
        assert (cols == lut[cid]).all(), name
    counts = np.bincount(res.labels, minlength=256)
    assert {c: b.label for c, b in st.class_boxes.items()} == {
        int(c): f"{sb.class_name(tax, int(c))} ({int(counts[c]):,})" for c in np.flatnonzero(counts)}


def _relabel(svc, st, ids, to_class: int) -> None:  # noqa: ANN001
    corrections_panel.set_selection(svc, st, np.asarray(ids, np.int64))  # highlighted
    name = sb.class_name(st.data.taxonomy, to_class)
    assert corrections_panel.relabel(svc, st, f"{name} ({to_class})", "") is not None


def _windows(log: list) -> list[list]:
    """The outermost atomic() blocks of a client's log, each as the entries inside it."""
    out, depth = [], 0
    for e in log:
        if e[0] == "atomic":
            depth += 1 if e[1] == "begin" else -1
            if depth == 1 and e[1] == "begin":
                out.append([])
        elif depth > 0:
            out[-1].append(e)
    return out


def _sent_since(st: ClientState, n0: int) -> int:
    return sum(e[2] for e in st.client.scene.log[n0:] if e[0] == "points" and e[1] != "/selection")


def test_relabel_undo_and_overlapping_relabels_show_the_workspace(tiny):
    edits = Edits(tiny.ws)
    svc, st = _open(tiny, edits)
    scene0 = st.data.scene
    assert_shows_workspace(svc, st)
    rng = np.random.default_rng(0)
    n = scene0.n_points
    a = np.sort(rng.choice(np.flatnonzero(np.isin(tiny.labels, [GRASS, BUILDING])), 300, False))
    b = np.sort(np.union1d(a[::2], rng.choice(n, 200, False)))  # half of a, and others
    c = np.sort(np.union1d(b[::3], rng.choice(n, 100, False)))
    log = st.client.scene.log
    steps = [("relabel", a, VEHICLE), ("undo", None, None), ("relabel", a, VEHICLE),
             ("relabel", b, PERSON), ("relabel", c, GRASS), ("undo", None, None),
             ("undo", None, None), ("redo", None, None)]
    for what, ids, to in steps:
        n0 = len(log)
        if what == "relabel":
            _relabel(svc, st, ids, to)
        else:
            assert corrections_panel.undo_redo(svc, st, what) is not None
        assert_shows_workspace(svc, st)
        assert st.data.scene is scene0  # a delta: the workspace was not read again
        assert 0 < _sent_since(st, n0) < n  # only the chunks holding changed points
        # the panel's messages and the new chunks went in one window (viser's atomic())
        blocks = _windows(log[n0:])
        with_points = [b for b in blocks if any(e[0] == "points" for e in b)]
        assert len(with_points) == 1, what
        outside = [e for e in log[n0:] if e[0] == "points" and e[1] != "/selection"]
        assert sum(1 for e in with_points[0] if e[0] == "points") == len(outside), what
        if what == "relabel":  # the selection's highlight goes in the same window
            assert ("remove", "/selection") in [e[:2] for e in with_points[0]]
    assert not st.updating  # the tiles are back (shown again once drawn)
    assert all(h.visible for h in st.detail_handles.values())
    # the event the corrections service publishes after the layer is written finds the
    # viewer's data current: no second refresh
    assert svc.on_labels_updated("tiny", Workspace(tiny.ws).stamp()) is False


def test_a_class_hidden_before_a_relabel_stays_hidden(tiny):
    edits = Edits(tiny.ws)
    svc, st = _open(tiny, edits)
    svc.set_class_visible(st, GRASS, False)
    svc.set_class_visible(st, WATER, False)  # not in the scene yet
    grass = np.flatnonzero(tiny.labels == GRASS)
    _relabel(svc, st, grass[: len(grass) // 2], WATER)
    assert_shows_workspace(svc, st)
    assert st.point_handles[WATER].visible is False  # the new class frame, hidden
    assert st.point_handles[GRASS].visible is False
    frames = [e for e in st.client.scene.log if e[0] == "frame" and e[1] == "/points/water"]
    assert frames and frames[0][4] is False
    svc.set_class_visible(st, WATER, True)
    assert st.point_handles[WATER].visible is True
    # the selection tools' candidates: the water shown again, the hidden grass left out
    cand = corrections_panel.candidates(st)
    assert np.isin(grass[: len(grass) // 2], cand).all()
    assert not np.isin(grass[len(grass) // 2:], cand).any()


def test_another_users_change_arrives_as_a_delta_and_a_new_fill_is_read_again(tiny):
    edits = Edits(tiny.ws)
    svc, st = _open(tiny, edits)
    scene0 = st.data.scene
    rng = np.random.default_rng(1)
    theirs = np.sort(rng.choice(scene0.n_points, 250, False))
    edits.relabel("tiny", theirs, BUILDING, "", "bob")  # another user, another process
    assert svc.on_labels_updated("tiny", Workspace(tiny.ws).stamp()) is True
    svc.refresh_now("tiny")  # what the refresh thread runs for the queued event
    assert_shows_workspace(svc, st)
    assert st.data.scene is scene0
    mine = np.sort(np.union1d(theirs[::2], rng.choice(scene0.n_points, 100, False)))
    _relabel(svc, st, mine, VEHICLE)  # overlapping theirs: mine wins where both
    assert_shows_workspace(svc, st)
    edits.undo("tiny", "bob")  # bob's undo: my edit stays on the shared points
    svc.refresh_now("tiny")
    assert_shows_workspace(svc, st)
    assert (np.asarray(st.data.labels)[mine] == VEHICLE).all()
    # a new fill (the lifting files rewritten) is not a delta: the workspace is read again
    w = Workspace(tiny.ws)
    labels = tiny.labels.copy()
    labels[: len(labels) // 3] = GRASS
    atomic_save_npy(w.labels_path, labels)
    svc.refresh_now("tiny")
    assert st.data.scene is not scene0
    assert_shows_workspace(svc, st)
    _relabel(svc, st, mine[:50], WATER)  # and deltas go on from the new data
    assert_shows_workspace(svc, st)


def test_with_corrections_equals_a_fresh_load(tiny):
    data = sb.ViewerData.load(tiny.ws)
    rng = np.random.default_rng(2)
    for k in range(4):
        ids = rng.choice(data.scene.n_points, 80, False)
        write_overrides(tiny.ws, ids, rng.integers(0, 20, len(ids)).astype(np.uint8))
        new, delta = data.with_corrections()
        fresh = sb.ViewerData.load(tiny.ws)
        for name in ("labels", "confidence", "origin"):
            assert np.array_equal(np.asarray(getattr(new, name)), np.asarray(getattr(fresh, name)))
        assert np.array_equal(new.label_counts(), fresh.label_counts())
        changed = np.flatnonzero((np.asarray(data.labels) != np.asarray(new.labels))
                                 | (np.asarray(data.confidence) != np.asarray(new.confidence))
                                 | (np.asarray(data.origin) != np.asarray(new.origin)))
        assert np.array_equal(delta.ids, changed), k
        assert np.array_equal(delta.old, np.asarray(data.labels)[changed])
        assert np.array_equal(delta.new, np.asarray(new.labels)[changed])
        data = new


def test_tiles_stay_hidden_until_the_browser_has_drawn_the_new_chunks(tiny):
    """The update hides the region tiles in the window that carries the new chunks (the
    browser's next frame draws the coarse level only) and shows them once the browser has
    answered a render request behind them -- not earlier when the camera rests meanwhile."""
    edits = Edits(tiny.ws)
    svc, st = _open(tiny, edits)
    gate = threading.Event()
    st.client.get_render = lambda w, h, timeout: gate.wait(timeout)
    svc.motion_rest_s = 0.05
    grass = np.flatnonzero(tiny.labels == GRASS)
    seen, save = [], svc.corrections["relabel"]

    def hook(*a, **kw):  # noqa: ANN002, ANN003, ANN202 - the tiles while the edit is saved
        seen.append([h.visible for h in st.detail_handles.values()])
        return save(*a, **kw)

    def refused(*a, **kw):  # noqa: ANN002, ANN003, ANN202
        raise PermissionError("not a reviewer of this scene")

    svc.corrections["relabel"] = refused  # a refused correction: the tiles come back
    st.selection = grass[:5]
    assert corrections_panel.relabel(svc, st, "vehicle (13)", "") is None
    assert st.updating == 0 and all(h.visible for h in st.detail_handles.values())
    svc.corrections["relabel"] = hook
    n0 = len(st.client.scene.log)
    _relabel(svc, st, grass[::3], VEHICLE)
    assert seen and not any(seen[0])  # hidden from the click on
    assert st.updating == 1 and st.detail_handles
    assert not any(h.visible for h in st.detail_handles.values())
    svc.camera_moved(st)  # the reviewer orbits and stops while the browser is busy
    time.sleep(0.4)
    assert not st.moving and not any(h.visible for h in st.detail_handles.values())
    gate.set()
    deadline = time.time() + 5
    while st.updating and time.time() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
    assert all(h.visible for h in st.detail_handles.values())
    assert_shows_workspace(svc, st)
    assert _sent_since(st, n0) < st.sent_points
