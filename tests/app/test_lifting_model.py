"""How a scene's votes are decided (issue 37): the admin picks the annotator model of the live
lifting (one for all painters, or one per mask author); the worker
fills again with it at once, tells the painters apart by the mask versions' authors (an
imported mask is a painter of its own) and reports what it used -- on SQLite and PostgreSQL."""

from __future__ import annotations

import time

import numpy as np
from sqlalchemy import select, update

from tests.app.conftest import H, W, png


def _submit(env, hdr, sid: int, cls: int) -> tuple[int, int]:  # noqa: ANN001
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=hdr).json()["id"]
    m = np.full((H, W), cls, np.uint8)
    m[:, : W // 3] = 1
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr, "If-Match": "none"})
    assert r.status_code == 200, r.text
    return fid, r.json()["version"]


def _fills(env, sid: int) -> int:
    from app.lifting.models import LiftStatus

    with env.app.state.ctx.sessions() as s:
        return s.get(LiftStatus, sid).fills


def _wait_fill(env, sid: int, after: int) -> None:
    ctx = env.app.state.ctx
    end = time.monotonic() + 60
    while _fills(env, sid) <= after or not ctx.lifting.wait_idle(sid, 0.1, include_fill=True):
        assert time.monotonic() < end, "no fill after the model changed"
        time.sleep(0.05)


def test_the_admin_picks_the_annotator_model_and_the_scene_is_filled_again_with_it(world):
    env, hdr, scene, _frames = world
    sid = scene["id"]
    ctx = env.app.state.ctx
    for who, cls in (("annotator", 6), ("annotator2", 8), ("annotator", 6), ("annotator2", 8)):
        _submit(env, hdr[who], sid, cls)
    assert ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    got = env.client.get(f"/api/scenes/{sid}/lifting", headers=hdr["annotator"])  # a member
    assert got.status_code == 200, got.text
    r = got.json()
    assert r["model"] == "pooled" and [m["id"] for m in r["models"]] == ["pooled", "per_author"]
    assert r["last_fill"]["decision"] == "robust" and "painters" not in r["last_fill"]
    assert r["last_fill"]["annotated_frames"] == 4 and r["last_fill"]["total_seconds"] > 0

    # who may change it, and what is refused (naming the field)
    url = f"/api/scenes/{sid}/lifting"
    for role in ("annotator", "reviewer"):
        assert env.client.put(url, json={"model": "per_author"}, headers=hdr[role]).status_code == 403
    # region consistency is not offered in the app (docs/lifting.md, seventh round)
    for bad in ({"model": "bogus"}, {"model": "regions"}, {"model": "per_author", "extra": 1},
                {}):
        resp = env.client.put(url, json=bad, headers=hdr["admin"])
        assert resp.status_code == 422, resp.text
        assert "model" in resp.text or "extra" in resp.text
    assert env.client.put(f"/api/scenes/{sid + 999}/lifting", json={"model": "pooled"},
                          headers=hdr["admin"]).status_code == 404
    assert ctx.lifting.model(ctx.sessions(), sid) == "pooled"

    # per author: filled again at once, without a new mask, the two annotators told apart
    before = _fills(env, sid)
    resp = env.client.put(url, json={"model": "per_author"}, headers=hdr["admin"])
    assert resp.status_code == 200, resp.text
    assert resp.json()["model"] == "per_author"
    _wait_fill(env, sid, before)
    last = env.client.get(url, headers=hdr["admin"]).json()["last_fill"]
    assert last["decision"] == "confusion", last
    assert last["painters"] == {"authors": 2, "frames_with_author": 4, "frames_own": 0}
    assert last["confusion_annotators"] == 2

    # the same model again changes nothing: no refill, no audit line
    before = _fills(env, sid)
    assert env.client.put(url, json={"model": "per_author"}, headers=hdr["admin"]).status_code == 200
    time.sleep(0.5)
    assert _fills(env, sid) == before

    # back to the default
    env.client.put(url, json={"model": "pooled"}, headers=hdr["admin"])
    _wait_fill(env, sid, before)
    last = env.client.get(url, headers=hdr["admin"]).json()["last_fill"]
    assert last["decision"] == "robust" and "painters" not in last

    audit = env.client.get("/api/audit?action=lifting_model", headers=hdr["admin"]).json()
    rows = audit["events"] if isinstance(audit, dict) else audit
    assert [(e["detail"]["from"], e["detail"]["to"]) for e in rows][::-1] == [
        ("pooled", "per_author"), ("per_author", "pooled")]
    assert all(e["actor"] == "admin" for e in rows)


def test_painters_come_from_the_counted_versions_authors_and_imports_paint_alone(world):
    """The worker's decision inputs: frame -> author of the version its votes count; a version
    imported from another tool is a painter of its own; per-frame votes whose version changed
    after the snapshot are left out of the per-frame model (their file holds newer votes)."""
    from app.annotations.models import MaskVersion
    from app.lifting.models import LiftStatus
    from app.users.models import User

    env, hdr, scene, _frames = world
    sid = scene["id"]
    ctx = env.app.state.ctx
    made = [_submit(env, hdr[w], sid, 6) for w in ("annotator", "annotator2", "annotator")]
    assert ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    with ctx.sessions() as s:
        s.execute(update(LiftStatus).where(LiftStatus.scene_id == sid).values(model="per_author"))
        s.execute(update(MaskVersion).where(MaskVersion.id == made[2][1])
                  .values(source="import:cvat"))
        s.commit()
        uid = dict(s.execute(select(User.username, User.id)).all())
    svc = ctx.lifting.service
    sc = svc._scenes[sid]
    with sc.lock:
        snap = sc.state.snapshot()
    model, params, annotators = svc._decision(sc, snap)
    index = {f["id"]: f["index"] for f in env.client.get(f"/api/scenes/{sid}/frames",
                                                         headers=hdr["admin"]).json()}
    assert model == "per_author" and params.robust_params.confusion is not None
    assert annotators == {index[made[0][0]]: uid["annotator"],
                          index[made[1][0]]: uid["annotator2"]}
    assert sorted(snap.frame_votes) == sorted(index[f] for f, _v in made)
    # a frame whose counted version moved on after the snapshot: its per-frame votes are left out
    snap.versions[index[made[0][0]]] = "999999"
    assert index[made[0][0]] not in svc._frame_votes(sc, snap)
    assert len(svc._frame_votes(sc, snap)) == 2


def test_an_export_that_lifts_again_decides_with_the_scenes_model(world, tmp_path):
    """Accepted masks only: the export lifts them again in a scratch folder with the scene's
    annotator model and painters (not the default), says so in the manifest, and lifting the
    manifest's versions again with the same inputs reproduces its labels byte for byte."""
    import hashlib
    import json
    from pathlib import Path

    from app import pipeline
    from app.lifting.service import decision_for
    from occufly.lifting.relift import labels_digest, relift
    from occufly.scene import Scene

    env, hdr, scene, _frames = world
    sid = scene["id"]
    ctx = env.app.state.ctx
    made = [_submit(env, hdr[w], sid, c) for w, c in
            (("annotator", 6), ("annotator2", 8), ("annotator", 6))]
    for fid, v in made[:2]:  # the third stays submitted: the export lifts the two again
        r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "accept", "version": v},
                            headers=hdr["reviewer"])
        assert r.status_code == 200, r.text
    r = env.client.put(f"/api/scenes/{sid}/lifting", json={"model": "per_author"},
                       headers=hdr["admin"])
    assert r.status_code == 200
    assert ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    r = env.client.post(f"/api/scenes/{sid}/export", json={}, headers=hdr["admin"])
    assert r.status_code == 202, r.text
    ctx.jobs.wait(r.json()["id"], timeout=180)
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=hdr["admin"]).json()
    assert j["status"] == "done", j.get("message")
    mp = (Path(j["result"]["output"]) / "OccuFly_Dataset" / j["result"]["summary"]["scene_id"]
          / "manifest.json")
    labels = json.loads(mp.read_text())["provenance"]
    assert labels["labels"]["relifted"] is True
    assert labels["labels"]["decision"] == "confusion"
    assert labels["labels"]["painters"] == {"authors": 2, "frames_with_author": 2, "frames_own": 0}
    ws = env.settings.workspaces_dir / "tiny"
    ws_scene = Scene.load(ws)
    items = []
    for e in labels["masks"]:
        data = ctx.store.get(e["sha256"])
        assert hashlib.sha256(data).hexdigest() == e["sha256"]
        items.append((e["frame"], str(e["version"]),
                      pipeline.stored_mask_ids(data, ws_scene.taxonomy)))
    with ctx.sessions() as s:
        _m, params, annotators = decision_for(s, sid, {e["frame"]: e["version"]
                                                       for e in labels["masks"]})
    again = relift(ws_scene, items, tmp_path / "again", params=params, annotators=annotators)
    assert labels_digest(again) == labels["labels"]["sha256"]
    assert again.stats["decision"] == "confusion"


def test_the_quality_report_sums_the_leave_one_out_figures_per_painter(world):
    """GET /quality: per painter (the author of each counted version; an imported one is its
    tool's), frames, votes with an independent label, agreement and the pairs they paint
    differently from the others -- a painter who swaps a class shows it on every frame."""
    from app.annotations.models import MaskVersion

    env, hdr, scene, _frames = world
    sid = scene["id"]
    ctx = env.app.state.ctx
    # three careful frames (grass, road at the left) and one frame painting vegetation for grass
    made = [_submit(env, hdr[w], sid, c) for w, c in
            (("annotator", 6), ("annotator", 6), ("annotator2", 6), ("annotator2", 7))]
    with ctx.sessions() as s:  # the third was imported from CVAT: a painter of its own
        s.execute(update(MaskVersion).where(MaskVersion.id == made[2][1])
                  .values(source="import:cvat"))
        s.commit()
    assert ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    end = time.monotonic() + 120
    while True:
        r = env.client.get(f"/api/scenes/{sid}/quality", headers=hdr["reviewer"])
        if r.status_code == 200 and not r.json().get("computing"):
            break
        assert time.monotonic() < end, r.text
        time.sleep(0.2)
    q = r.json()
    rows = {p["painter"]: p for p in q["painters"]}
    assert set(rows) == {"annotator", "annotator2", "imported from cvat"}, rows
    assert rows["annotator"]["frames"] == 2 and rows["annotator2"]["frames"] == 1
    assert rows["imported from cvat"]["user_id"] is None
    per_frame = q["loo"]["per_frame"]
    assert sum(p["independent"] for p in q["painters"]) == sum(f["independent"] for f in per_frame)
    sloppy = rows["annotator2"]
    assert sloppy["agreement"] < rows["annotator"]["agreement"]
    assert sloppy["disagreements"][0]["painted"] == "vegetation"
    assert sloppy["disagreements"][0]["independent"] == "grass"
    assert q["painters"][0]["painter"] == "annotator2"  # lowest agreement first
    assert all(f["disagreements"] == sorted(f["disagreements"], key=lambda d: -d["votes"])
               for f in per_frame)

    # per painter: the model learns the same thing, and the Lifting panel says so
    before = _fills(env, sid)
    r = env.client.put(f"/api/scenes/{sid}/lifting", json={"model": "per_author"},
                       headers=hdr["admin"])
    assert r.status_code == 200, r.text
    _wait_fill(env, sid, before)
    learned = env.client.get(f"/api/scenes/{sid}/lifting", headers=hdr["admin"]).json()[
        "last_fill"]["learned"]
    # (the tiny scene's masks are flat bands, so every painter disagrees somewhere; the one
    # who painted vegetation over the others' grass is learned most surely)
    assert learned[0]["painter"] == "annotator2", learned
    top = learned[0]["confusions"][0]
    assert (top["true"], top["painted"]) == ("grass", "vegetation") and top["share"] > 0.5
    assert all(c["share"] >= 0.15 for x in learned for c in x["confusions"])
    assert any(x["painter"].endswith("(no author)") for x in learned)  # the imported frame


def test_a_model_set_before_the_first_mask_survives_a_restart_and_decides_the_first_fill(world):
    env, hdr, scene, _frames = world
    sid = scene["id"]
    url = f"/api/scenes/{sid}/lifting"
    r = env.client.put(url, json={"model": "per_author"}, headers=hdr["admin"])
    assert r.status_code == 200 and r.json()["model"] == "per_author"
    assert r.json()["last_fill"] == {}  # nothing lifted yet
    env.restart()  # the worker starts with a status row and no votes: nothing to fill
    admin = env.bearer("admin")
    got = env.client.get(url, headers=admin).json()
    assert got["model"] == "per_author" and not got["status"]["pending_fill"]
    assert got["status"]["last_error"] is None
    _submit(env, env.bearer("annotator"), sid, 6)
    _submit(env, env.bearer("annotator2"), sid, 8)
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    last = env.client.get(url, headers=admin).json()["last_fill"]
    assert last["decision"] == "confusion" and last["painters"]["authors"] == 2


def test_a_save_keeps_the_fitted_model_and_the_quiet_scene_is_decided_again(world):
    """Issue 37, eighth round: the fill after a save keeps the robust decision's fitted model
    (decides again only around the change); once the scene has been quiet for
    ``fill_settle_s`` the worker fills it once more with the model fitted again."""
    env, hdr, scene, _frames = world
    sid = scene["id"]
    ctx = env.app.state.ctx
    url = f"/api/scenes/{sid}/lifting"
    for who, cls in (("annotator", 6), ("annotator2", 8), ("annotator", 6)):
        fid, version = _submit(env, hdr[who], sid, cls)
    assert ctx.lifting.wait_idle(sid, timeout=60, include_fill=True)
    last = env.client.get(url, headers=hdr["admin"]).json()["last_fill"]
    # whole frames fit the model (at the worker's first fill: "no held model"; a later one,
    # where the submits took two fills: "... points with changed votes, over 1% ..."); a fill
    # scheduled by a batch the one before had already counted keeps it and decides nothing
    assert last.get("robust_cold_why") or last.get("robust_warm_decided") == 0, last
    assert ctx.lifting.service._scenes[sid].incremental.held.key is not None  # a model held
    ctx.settings.fill_settle_s = 600.0  # this app's worker (same settings)
    svc = ctx.lifting.service
    sc = svc._scenes[sid]
    # the test scene has a few hundred voted points: a 12 px stroke changes ~4 % of them
    sc.incremental.held.max_share_save = sc.incremental.held.max_share = 0.5
    before = _fills(env, sid)
    # an admin saves the last frame again with a brush stroke of another class
    m = np.full((H, W), 6, np.uint8)
    m[:, : W // 3] = 1
    m[H // 2 - 6:H // 2 + 6, W // 2 - 6:W // 2 + 6] = 8
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr["admin"], "If-Match": str(version)})
    assert r.status_code == 200, r.text
    _wait_fill(env, sid, before)
    last = env.client.get(url, headers=hdr["admin"]).json()["last_fill"]
    assert last.get("robust_warm") is True and last["robust_warm_decided"] > 0, last
    # the settle fill is due fill_settle_s after it; brought forward to now here
    with svc._cv:
        assert sc.settle_due is not None and sc.settle_due > time.monotonic() + 500
        sc.settle_due = time.monotonic()
        svc._cv.notify_all()
    _wait_fill(env, sid, before + 1)
    last = env.client.get(url, headers=hdr["admin"]).json()["last_fill"]
    assert not last.get("robust_warm") and last["robust_cold_why"] == "no held model", last
    # nothing saved since, and a fill that fitted the model schedules no other
    settled = _fills(env, sid)
    assert sc.settle_due is None
    time.sleep(1.0)
    assert _fills(env, sid) == settled
