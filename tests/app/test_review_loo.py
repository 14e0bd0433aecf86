"""Review agreement is leave-one-out (issue 23, defect 1), through the API on both databases."""

from __future__ import annotations

import os

import numpy as np
import pytest

from occufly.workspace import Workspace
from tests.app.conftest import H, W, png


def _submit(env, hdr, fid: int, m: np.ndarray) -> None:
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr["admin"], "If-Match": "none"})
    assert r.status_code == 200, r.text


def _paint_grass_and_road(env, hdr, scene, frames) -> None:  # noqa: ANN001
    """The four frames submitted as grass, grass, road, road (the same ground: contested)
    and lifted."""
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    for fid, cid in zip(ids, (6, 6, 1, 1), strict=True):
        _submit(env, hdr, fid, np.full((H, W), cid, np.uint8))
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20, include_fill=True)


def test_wrong_frame_gets_low_loo_agreement_and_sorts_first(world):
    env, hdr, scene, frames = world
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    grass = np.full((H, W), 6, np.uint8)
    for fid in ids[:3]:
        _submit(env, hdr, fid, grass)
    wrong = ids[3]
    _submit(env, hdr, wrong, np.full((H, W), 1, np.uint8))  # the grass painted as road
    lifting = env.app.state.ctx.lifting
    assert lifting.wait_idle(scene["id"], timeout=20, include_fill=True)
    r = env.client.get(f"/api/frames/{wrong}/agreement", headers=hdr["reviewer"]).json()
    assert r["status"] == "ok" and r["independent_coverage"] >= 0.5
    # the other frames see the same ground as grass: independently it is almost all wrong
    assert r["agreement"] < 0.2
    # the old figure is kept apart (here the three grass frames outvote it too)
    assert r["self_agreement"] is not None and r["self_agreement"] < 0.5
    assert r["painted_share"] == pytest.approx(1.0)
    assert r["pixels"] == r["independent_pixels"] > 0
    ok = env.client.get(f"/api/frames/{ids[1]}/agreement", headers=hdr["reviewer"]).json()
    assert ok["agreement"] > 0.9
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement",
                        headers=hdr["reviewer"]).json()
    assert fl[0]["id"] == wrong and fl[0]["agreement"] == pytest.approx(r["agreement"])
    assert fl[0]["self_agreement"] == pytest.approx(r["self_agreement"])
    assert fl[0]["independent_coverage"] == pytest.approx(r["independent_coverage"])


def test_lonely_and_half_painted_frames(world):
    env, hdr, scene, frames = world
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    half = np.zeros((H, W), np.uint8)
    half[:, : W // 2] = 6
    _submit(env, hdr, ids[0], half)
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20, include_fill=True)
    r = env.client.get(f"/api/frames/{ids[0]}/agreement", headers=hdr["reviewer"]).json()
    # nobody else voted: no score, the reason, the painted share, and the old figure apart
    assert r["agreement"] is None and r["status"] == "not_enough_independent_views"
    assert r["independent_coverage"] == 0.0 and r["self_agreement"] == pytest.approx(1.0)
    assert r["painted_share"] == pytest.approx(0.5)
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement",
                        headers=hdr["reviewer"]).json()
    # grouped after scored frames, before never-scored ones; its painted share is listed
    assert fl[0]["id"] == ids[0] and fl[0]["agreement"] is None
    assert fl[0]["painted_share"] == pytest.approx(0.5) and fl[0]["independent_coverage"] == 0.0
    # a second frame painting the other half gives independent evidence on the first's half
    other = np.zeros((H, W), np.uint8)
    other[:, :] = 6
    _submit(env, hdr, ids[1], other)
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20, include_fill=True)
    r = env.client.get(f"/api/frames/{ids[0]}/agreement", headers=hdr["reviewer"]).json()
    assert r["status"] == "ok" and r["agreement"] == pytest.approx(1.0)
    assert r["painted_share"] == pytest.approx(0.5)


def test_suspects_route(world):
    env, hdr, scene, frames = world
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    for fid, cid in zip(ids, (6, 6, 1, 1), strict=True):  # two frames say grass, two road
        _submit(env, hdr, fid, np.full((H, W), cid, np.uint8))
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20, include_fill=True)
    assert env.client.get(f"/api/scenes/{scene['id']}/suspects",
                          headers=hdr["annotator"]).status_code == 403
    r = env.client.get(f"/api/scenes/{scene['id']}/suspects", headers=hdr["reviewer"])
    assert r.status_code == 200, r.text
    sus = r.json()["suspects"]
    assert sus and sus[0]["contested"] > 0 and sus[0]["best_frame_id"] in ids
    assert set(sus[0]["frame_ids"]) <= set(ids)
    # what the reviewer page draws and stores marks against
    top = sus[0]
    assert top["key"].startswith("p") and top["n_frames"] >= len(top["frame_ids"]) >= 1
    assert set(top["class_names"].values()) <= {"road", "grass"}
    assert len(top["outline"]) >= 3
    assert all(0 <= x <= W and 0 <= y <= H for x, y in top["outline"])
    assert top["kind"] == "contested" and top["mark"] is None and r.json()["n_open"] == len(sus)


def test_suspects_list_is_computed_after_a_fill_not_when_opened(world, monkeypatch):
    """Issue 38: the suspects of a survey take seconds of CPU; the process that owns the
    scene's lifting computes them after each fill, so the reviewer's tab computes nothing."""
    import time

    from app.review import service as review

    env, hdr, scene, frames = world
    calls = []
    real = review.find_suspects
    monkeypatch.setattr(review, "find_suspects", lambda *a, **k: calls.append(1) or real(*a, **k))
    _paint_grass_and_road(env, hdr, scene, frames)
    end = time.monotonic() + 30
    while not calls and time.monotonic() < end:  # the fill's subscriber, in the background
        time.sleep(0.05)
    assert calls, "the suspects were not computed after the fill"
    time.sleep(0.5)  # a later fill's refresh, if one was still due
    n = len(calls)
    r = env.client.get(f"/api/scenes/{scene['id']}/suspects", headers=hdr["reviewer"])
    assert r.status_code == 200 and r.json()["suspects"], r.text
    assert len(calls) == n  # served from what the fill's refresh computed


def test_suspects_list_survives_a_restart(world, monkeypatch):
    """Issue 38: after a restart (or in an API process that did not run the fill) the
    suspects list is read from the data dir's shared cache, not computed again (~65 s of CPU
    on the survey); the 3D jump's point ids come back the same."""
    from app.review import service as review

    env, hdr, scene, frames = world
    sid = scene["id"]
    _paint_grass_and_road(env, hdr, scene, frames)
    first = env.client.get(f"/api/scenes/{sid}/suspects", headers=hdr["reviewer"])
    assert first.status_code == 200 and first.json()["suspects"], first.text
    ctx = env.app.state.ctx
    from app.scenes.models import Scene

    with ctx.sessions() as s:
        sc = s.get(Scene, sid)
        key = first.json()["suspects"][0]["key"]
        before = review.suspect_points(ctx, sc, key)
        assert before is not None and len(before) > 0
        assert (np.diff(before) > 0).all() and before.min() == int(key[1:])
        review._SUSPECT_CACHE.clear()  # a new process: nothing in memory
        calls = []
        monkeypatch.setattr(review, "find_suspects", lambda *a, **k: calls.append(1) or [])
        again = env.client.get(f"/api/scenes/{sid}/suspects", headers=hdr["reviewer"])
        assert again.status_code == 200 and again.json() == first.json()
        np.testing.assert_array_equal(review.suspect_points(ctx, sc, key), before)
        assert calls == []  # read from the shared cache, not computed again
        # new labels (a new stamp): computed again, not the old list
        review._SUSPECT_CACHE.clear()
        labels = Workspace(sc.workspace).labels_path
        st = os.stat(labels)
        os.utime(labels, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        r = env.client.get(f"/api/scenes/{sid}/suspects", headers=hdr["reviewer"])
        assert r.status_code == 200 and calls == [1] and r.json()["suspects"] == []


def test_suspect_marks_are_shared_and_idempotent(world):
    from sqlalchemy import func, select

    from app.audit.models import AuditEvent

    env, hdr, scene, frames = world
    sid = scene["id"]
    _paint_grass_and_road(env, hdr, scene, frames)
    key = env.client.get(f"/api/scenes/{sid}/suspects", headers=hdr["reviewer"]).json()[
        "suspects"][0]["key"]
    url = f"/api/scenes/{sid}/suspects/{key}/mark"
    assert env.client.put(url, json={"status": "done"}, headers=hdr["annotator"]).status_code == 403
    assert env.client.put(url, json={"status": "done"}).status_code == 401
    for bad in ({"status": "fixed"}, {"status": "done", "extra": 1}, {}):
        r = env.client.put(url, json=bad, headers=hdr["reviewer"])
        assert r.status_code == 422, (bad, r.text)
    for bad_key in ("x1", "p", "p1234567890123", "p1;drop", "..%2Fp1"):
        r = env.client.put(f"/api/scenes/{sid}/suspects/{bad_key}/mark", json={"status": "done"},
                           headers=hdr["reviewer"])
        assert 400 <= r.status_code < 500, (bad_key, r.status_code)  # 405: a routed-away path
    assert env.client.put(f"/api/scenes/999999/suspects/{key}/mark", json={"status": "done"},
                          headers=hdr["reviewer"]).status_code == 404

    def n_audit() -> int:
        with env.app.state.ctx.sessions() as s:
            return s.execute(select(func.count()).select_from(AuditEvent).where(
                AuditEvent.action == "suspect_mark")).scalar_one()

    r = env.client.put(url, json={"status": "done"}, headers=hdr["reviewer"])
    assert r.status_code == 200, r.text
    m = r.json()["mark"]
    assert m["status"] == "done" and m["by"] == "reviewer"
    # the same mark again is a no-op: no second audit event, who and when unchanged
    r2 = env.client.put(url, json={"status": "done"}, headers=hdr["admin"])
    assert r2.json()["mark"] == m and n_audit() == 1
    # another reviewer (the admin) sees it in the list
    got = env.client.get(f"/api/scenes/{sid}/suspects", headers=hdr["admin"]).json()
    top = next(s for s in got["suspects"] if s["key"] == key)
    assert top["mark"] == m and got["n_open"] == got["n"] - 1
    # changed by the admin, then reopened
    r = env.client.put(url, json={"status": "dismissed"}, headers=hdr["admin"])
    assert r.json()["mark"]["status"] == "dismissed" and r.json()["mark"]["by"] == "admin"
    r = env.client.put(url, json={"status": None}, headers=hdr["reviewer"])
    assert r.status_code == 200 and r.json()["mark"] is None and n_audit() == 3
    assert next(s for s in env.client.get(f"/api/scenes/{sid}/suspects", headers=hdr["reviewer"])
                .json()["suspects"] if s["key"] == key)["mark"] is None


def test_half_painted_frame_ranks_first(world):
    """A half-painted frame agrees where it painted (LOO agreement 1.0, like every right frame
    here): the ranking score counts its unpainted half, which the other frames see, as
    disagreement, so the list opens it first (the LOO sort put it after the right frames)."""
    env, hdr, scene, frames = world
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    grass = np.full((H, W), 6, np.uint8)
    for fid in ids[:3]:
        _submit(env, hdr, fid, grass)
    half = np.zeros((H, W), np.uint8)
    half[:, : W // 2] = 6
    _submit(env, hdr, ids[3], half)
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20, include_fill=True)
    r = env.client.get(f"/api/frames/{ids[3]}/agreement", headers=hdr["reviewer"]).json()
    assert r["agreement"] == pytest.approx(1.0) and r["painted_share"] == pytest.approx(0.5)
    # about the unpainted half of what the other frames see of it
    assert 0.3 < r["review_score"] <= 0.55
    ok = env.client.get(f"/api/frames/{ids[0]}/agreement", headers=hdr["reviewer"]).json()
    assert ok["review_score"] == pytest.approx(0.0, abs=0.02) and ok["shift_gain"] == 0.0
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement",
                        headers=hdr["reviewer"]).json()
    assert fl[0]["id"] == ids[3] and fl[0]["review_score"] == pytest.approx(r["review_score"])


def test_top_of_the_list_is_computed_after_a_fill_and_refreshed_on_a_rejection(world, monkeypatch):
    """Issue 40, defect 6: after a fill the review of the list's top frames is already
    computed (opening one computes nothing), and a neighbour's rejection (its votes withdrawn)
    recomputes them in the background; the agreement names the neighbour that disagrees."""
    from app.review import service as review

    env, hdr, scene, frames = world
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    grass = np.full((H, W), 6, np.uint8)
    for fid in ids[:3]:
        _submit(env, hdr, fid, grass)
    wrong = ids[3]
    _submit(env, hdr, wrong, np.full((H, W), 1, np.uint8))
    lifting = env.app.state.ctx.lifting
    assert lifting.wait_idle(scene["id"], timeout=30, include_fill=True)
    calls = []
    real = review.lifting_loo.loo_labels
    monkeypatch.setattr(review.lifting_loo, "loo_labels",
                        lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement&state=submitted",
                        headers=hdr["reviewer"]).json()
    top = [f["id"] for f in fl[:review.PREFETCH_FRAMES]]
    assert top[0] == wrong and set(ids[:4]) <= set(top)
    before = {}
    for fid in top:  # opening them: agreement, disagreement image, labels rendering
        r = env.client.get(f"/api/frames/{fid}/agreement", headers=hdr["reviewer"])
        assert r.status_code == 200, r.text
        before[fid] = r.json()
        for part in ("disagreement", "render"):
            assert env.client.get(f"/api/frames/{fid}/{part}",
                                  headers=hdr["reviewer"]).status_code == 200
    assert calls == []  # all served from what the background refresh computed
    right = before[ids[1]]
    names = [n["frame_id"] for n in right["neighbours"]]
    assert names and names[0] == wrong  # the neighbour painting the grass as road
    nb = right["neighbours"][0]
    assert nb["disagree_share"] > 0.9 and nb["name"]
    assert [n["frame_id"] for n in before[wrong]["neighbours"]][:1] != [wrong]

    # the wrong frame is rejected: its votes are withdrawn, the neighbours' figures refresh
    r = env.client.post(f"/api/frames/{wrong}/review", headers=hdr["reviewer"],
                        json={"decision": "reject", "comment": "grass, not road",
                              "version": before[wrong]["version"]})
    assert r.status_code == 200, r.text
    assert lifting.wait_idle(scene["id"], timeout=30, include_fill=True)
    assert calls  # recomputed in the background after the fill
    n_bg = len(calls)
    after = env.client.get(f"/api/frames/{ids[1]}/agreement", headers=hdr["reviewer"]).json()
    assert len(calls) == n_bg  # served from the refreshed cache
    assert wrong not in [n["frame_id"] for n in after["neighbours"]]
    assert after["agreement"] == pytest.approx(1.0)

    # opening a frame computes the next ones in the list in the background (N finds them)
    import shutil
    import time

    from app.scenes.models import Frame, Scene

    review._CACHE.clear()  # this process's memory and the processes' shared folder
    data_dir = env.app.state.ctx.settings.data_dir
    shutil.rmtree(review._CACHE.shared.folder(data_dir), ignore_errors=True)
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement&state=submitted",
                        headers=hdr["reviewer"]).json()
    first, nxt = fl[0]["id"], fl[1]["id"]
    env.client.get(f"/api/frames/{first}/agreement", headers=hdr["reviewer"])
    with env.app.state.ctx.sessions() as s:
        sc, fr = s.get(Scene, scene["id"]), s.get(Frame, nxt)
        end = time.monotonic() + 30
        while not review.cached_review(env.app.state.ctx, sc, fr, s, data_dir) and time.monotonic() < end:
            time.sleep(0.05)
        assert review.cached_review(env.app.state.ctx, sc, fr, s, data_dir)
    nxt_index = next(f["index"] for f in frames if f["id"] == nxt)
    n = calls.count(nxt_index)  # (the frames after it are being computed meanwhile)
    assert env.client.get(f"/api/frames/{nxt}/agreement", headers=hdr["reviewer"]).status_code == 200
    assert calls.count(nxt_index) == n


def test_a_server_process_warms_the_review_of_a_survey_sized_scene(world, monkeypatch):
    """A process's first review of a big scene paid its state (the cull's bins of the whole
    cloud, numba's kernels, the first reads): at start, one review of the review list's top
    frame runs in a background thread, for scenes of at least WARM_MIN_POINTS points."""
    from app.review import service

    env, hdr, scene, frames = world
    _paint_grass_and_road(env, hdr, scene, frames)
    ctx = env.app.state.ctx
    assert service.warm_process_start(ctx) is None  # the test scene is small: nothing to warm
    calls = []
    real = service.compute_review

    def spy(ws_scene, workspace, frame_index, mask, labels):  # noqa: ANN001
        calls.append(frame_index)
        out = real(ws_scene, workspace, frame_index, mask, labels)
        calls.append(out["figures"]["agreement"])
        return out

    monkeypatch.setattr(service, "WARM_MIN_POINTS", 1)
    monkeypatch.setattr(service, "compute_review", spy)
    th = service.warm_process_start(ctx)
    assert th is not None
    th.join(60)
    assert not th.is_alive()
    top = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement",
                         headers=hdr["reviewer"]).json()[0]
    index = next(f["index"] for f in frames if f["id"] == top["id"])
    assert calls and calls[0] == index and calls[1] is not None  # the list's top, computed


def test_a_review_entry_outlives_saves_of_frames_that_cannot_reach_it(world, monkeypatch):
    """The review cache's key names the vote files of the frames that can vote at the
    frame's leave-one-out points (``loo.frames_reaching``), not the scene's vote counts: a
    save elsewhere in a survey keeps the entry, a save of a reaching frame does not; an
    entry computed while a vote update is under way is answered but not kept."""
    import json
    import shutil

    from app.review import service as review
    from app.scenes.models import Frame, Scene

    env, hdr, scene, frames = world
    _paint_grass_and_road(env, hdr, scene, frames)
    ctx = env.app.state.ctx
    with ctx.sessions() as s:
        ws = Workspace(s.get(Scene, scene["id"]).workspace)
    by_index = {f["index"]: f["id"] for f in frames}
    i0, _i1, i2, i3 = sorted(by_index)[:4]  # painted grass, grass, road, road
    a, b, c = i2, i3, i0
    # the test scene's frames all see the same ground: say that only b reaches a
    monkeypatch.setattr(review.lifting_loo, "frames_reaching",
                        lambda sc, f, ids: np.array([b] if f == a else [], np.int64))
    review._REACH.clear()
    shutil.rmtree(review._REACH_DISK.folder(ctx.settings.data_dir), ignore_errors=True)
    for cache in (review._CACHE, review._LOO_CACHE):
        cache.clear()
        shutil.rmtree(cache.shared.folder(ctx.settings.data_dir), ignore_errors=True)

    def cached() -> bool:
        with ctx.sessions() as s:
            return review.cached_review(ctx, s.get(Scene, scene["id"]), s.get(Frame, by_index[a]),
                                        s, ctx.settings.data_dir)

    def touch(p) -> None:  # noqa: ANN001
        st = os.stat(p)
        os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))

    calls = []
    real = review.lifting_loo.loo_labels
    monkeypatch.setattr(review.lifting_loo, "loo_labels",
                        lambda *x, **k: calls.append(x[2]) or real(*x, **k))

    def agreement() -> dict:
        r = env.client.get(f"/api/frames/{by_index[a]}/agreement", headers=hdr["reviewer"])
        assert r.status_code == 200, r.text
        return r.json()

    first = agreement()
    assert cached() and calls.count(a) == 1  # (opening it computes the next ones too)
    touch(ws.lifting_frame(c))  # a frame that cannot vote at a's points
    touch(ws.votes)  # the counts' file: every save writes it
    assert cached()
    # a fill: the labels change; the leave-one-out part is kept, only the self part computed
    touch(ws.labels_path)
    assert not cached()
    again = agreement()
    assert cached() and calls.count(a) == 1
    assert again == first and again["self_agreement"] is not None
    touch(ws.lifting_frame(b))  # a frame that can vote at a's points
    assert not cached()
    r = agreement()
    assert calls.count(a) == 2 and r["agreement"] == first["agreement"]
    touch(ws.lifting_frame(b))

    # a vote update under way when the key is read: the answer is given, the entry not kept
    state = json.loads(ws.lifting_state.read_text())
    ws.lifting_state.write_text(json.dumps({**state, "dirty": True}))
    try:
        assert agreement()["agreement"] == first["agreement"]
        assert not cached() and calls.count(a) == 3
    finally:
        ws.lifting_state.write_text(json.dumps(state))
    agreement()
    assert cached()
    # a real save and fill that change the labels: the self-agreement follows them, from the
    # cached leave-one-out part (c cannot reach a here, by the patched frames_reaching)
    before = agreement()
    n = calls.count(a)
    with ctx.sessions() as s:
        cur = s.get(Frame, by_index[c]).current_version_id
    r = env.client.put(f"/api/frames/{by_index[c]}/mask?kind=submitted",  # c: grass -> road
                       content=png(np.full((H, W), 1, np.uint8)),
                       headers={**hdr["admin"], "If-Match": str(cur)})
    assert r.status_code == 200, r.text
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20, include_fill=True)
    after = agreement()
    assert calls.count(a) == n
    assert after["self_agreement"] > before["self_agreement"] + 0.2
    assert after["agreement"] == before["agreement"]
    review._REACH.clear()  # the patched frames' sets (this test's workspace only, but not kept)
