"""Label corrections through the API (issue 25), on SQLite and PostgreSQL: roles, versioned
edits with undo/redo per user and revert by admins, the audit trail, the net layer every
reader applies (and that lifting new masks keeps), kill -9 atomicity in a subprocess, the
re-import refusal, frames that disagree, proposals taken with one call or declined, review
items projected into a frame, notifications."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from sqlalchemy import select

from occufly.lifting import ORIGIN_CORRECTED, load_labels
from tests.app.conftest import H, W, png

REPO = Path(__file__).resolve().parents[2]


def _lifted(world):
    """The annotator submits an all-grass mask on one frame; wait for the fill."""
    env, hdr, scene, frames = world
    a = hdr["annotator"]
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=a).json()["id"]
    v = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                       content=png(np.full((H, W), 6, np.uint8)),
                       headers={**a, "If-Match": "none"})
    assert v.status_code == 200, v.text
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=30, include_fill=True)
    ws = env.settings.workspaces_dir / "tiny"
    assert load_labels(ws) is not None
    return fid, ws


def _seen(env, ws, fid: int) -> np.ndarray:
    frame = env.client.get(f"/api/frames/{fid}", headers=env.bearer("admin")).json()
    scene = env.app.state.ctx.load_scene(str(ws))
    return np.sort(np.asarray(scene.visibility.frame(frame["index"])[0], np.int64))


def test_edit_undo_redo_revert_roles_audit_and_lifting_keeps_them(world):
    env, hdr, scene, frames = world
    fid, ws = _lifted(world)
    sid = scene["id"]
    url = f"/api/scenes/{sid}/corrections"
    seen = _seen(env, ws, fid)
    a_ids, b_ids = seen[:40].tolist(), seen[20:60].tolist()
    events = []
    env.app.state.ctx.events.subscribe("labels_updated", events.append)

    # annotators never edit in 3D (nor list the history)
    r = env.client.post(url, json={"point_ids": a_ids, "to_class": 8}, headers=hdr["annotator"])
    assert r.status_code == 403
    assert env.client.get(url, headers=hdr["annotator"]).status_code == 403
    r = env.client.post(url, json={"point_ids": a_ids, "to_class": 99}, headers=hdr["reviewer"])
    assert r.status_code == 422 and "taxonomy" in r.json()["detail"]
    r = env.client.post(url, json={"point_ids": [10**6], "to_class": 8}, headers=hdr["reviewer"])
    assert r.status_code == 422

    e1 = env.client.post(url, json={"point_ids": a_ids[::-1] + a_ids[:5], "to_class": 8,
                                    "comment": "these are trees"}, headers=hdr["reviewer"])
    assert e1.status_code == 201, e1.text
    e1 = e1.json()
    assert e1["n_points"] == 40 and e1["from_hist"] == {"6": 40} and e1["state"] == "active"
    assert e1["author"] == "reviewer" and e1["comment"] == "these are trees"
    lab = np.asarray(load_labels(ws).labels)
    assert (lab[a_ids] == 8).all()
    assert (load_labels(ws).origin[a_ids] == ORIGIN_CORRECTED).all()
    assert any(m.payload.get("corrections", {}).get("edit") == e1["id"] for m in events)
    # the edit's point file sits in the workspace, compact
    from occufly.lifting import corrections as lib
    from occufly.workspace import Workspace

    assert lib.read_edit_points(ws, e1["id"]).tolist() == sorted(a_ids)
    assert Workspace(ws).correction_edit(e1["id"]).is_file()

    # the admin edits too (a second user's stack); overlapping points: the newer edit wins
    e2 = env.client.post(url, json={"point_ids": b_ids, "to_class": 0},
                         headers=hdr["admin"]).json()
    assert e2["from_hist"] == {"8": 20, "6": 20}
    lab = np.asarray(load_labels(ws).labels)
    assert (lab[seen[:20]] == 8).all() and (lab[seen[20:60]] == 0).all()

    # the reviewer's undo takes back their own edit only; the admin's still decides 20..59
    u = env.client.post(f"{url}/undo", headers=hdr["reviewer"])
    assert u.status_code == 200 and u.json()["id"] == e1["id"] and u.json()["state"] == "undone"
    lab = np.asarray(load_labels(ws).labels)
    assert (lab[seen[:20]] == 6).all() and (lab[seen[20:60]] == 0).all()
    assert env.client.get(f"{url}/stack", headers=hdr["reviewer"]).json() == {
        "undo": None, "redo": e1["id"]}
    assert env.client.post(f"{url}/undo", headers=hdr["reviewer"]).status_code == 404
    r = env.client.post(f"{url}/redo", headers=hdr["reviewer"])
    assert r.status_code == 200 and r.json()["state"] == "active"
    lab = np.asarray(load_labels(ws).labels)
    assert (lab[seen[:20]] == 8).all() and (lab[seen[20:60]] == 0).all()  # e2 is newer

    # lifting a new mask keeps the corrections (they sit above the fill)
    a = hdr["annotator"]
    f2 = env.client.post(f"/api/scenes/{sid}/next", headers=a).json()["id"]
    env.client.put(f"/api/frames/{f2}/mask?kind=submitted", content=png(np.full((H, W), 1, np.uint8)),
                   headers={**a, "If-Match": "none"})
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    res = load_labels(ws)
    assert (np.asarray(res.labels)[seen[:20]] == 8).all()
    assert (np.asarray(res.labels)[seen[20:60]] == 0).all()
    assert load_labels(ws, corrections=False).labels[seen[0]] != 8

    # revert: admins only; the reverted edit stays in the history
    assert env.client.post(f"{url}/{e2['id']}/revert", headers=hdr["reviewer"]).status_code == 403
    r = env.client.post(f"{url}/{e2['id']}/revert", headers=hdr["admin"])
    assert r.status_code == 200 and r.json()["reverted_by"] == "admin"
    lab = np.asarray(load_labels(ws).labels)
    assert (lab[seen[:40]] == 8).all() and (lab[seen[40:60]] != 0).all()
    hist = env.client.get(url, headers=hdr["reviewer"]).json()
    assert [(e["id"], e["state"]) for e in hist] == [(e1["id"], "active"), (e2["id"], "reverted")]
    layer = env.client.get(f"{url}/layer", headers=hdr["reviewer"]).json()
    assert layer == {"corrected_points": 40, "applied": [e1["id"]], "per_class": {"8": 40}}
    audit = env.client.get("/api/audit?action=correction,correction_undo,correction_redo,"
                           "correction_revert", headers=hdr["admin"])
    assert audit.status_code == 200, audit.text
    body = audit.json()
    rows = body if isinstance(body, list) else body.get("events", body.get("items", []))
    assert sorted(r["action"] for r in rows) == sorted(
        ["correction", "correction", "correction_undo", "correction_redo", "correction_revert"])


CHILD = r"""
import sys, json
from app.config import Settings
from app.main import build_context
from app.corrections import service
from app.scenes.models import Scene
from app.users.models import User
cfg = json.loads(sys.argv[1])
ctx = build_context(Settings(data_dir=cfg["data_dir"], database_url=cfg["url"],
                             env="development"), lifting="off", jobs=False)
with ctx.sessions() as s:
    service.create_edit(session=s, ctx=ctx, scene=s.get(Scene, cfg["sid"]),
                        user=s.get(User, cfg["uid"]), point_ids=cfg["ids"], to_class=13)
print("survived")
"""


def test_kill9_during_an_edit_leaves_it_entirely_applied_or_not_at_all(world):
    env, hdr, scene, frames = world
    fid, ws = _lifted(world)
    from app.corrections import service
    from app.corrections.models import CorrectionEdit
    from app.scenes.models import Scene
    from app.users.models import User

    seen = _seen(env, ws, fid)
    ctx = env.app.state.ctx
    with ctx.sessions() as s:
        uid = s.scalar(select(User.id).where(User.username == "reviewer"))
    outcomes = {}
    for step, ids in (("after_points", seen[:30]), ("after_commit", seen[30:70]),
                      ("after_layer", seen[70:90])):
        cfg = {"data_dir": str(env.settings.data_dir), "url": env.settings.database_url,
               "sid": scene["id"], "uid": uid, "ids": ids.tolist()}
        p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(cfg)], cwd=REPO,
                           env={**os.environ, service.FAULT_ENV: step},
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == -9, (step, p.returncode, p.stderr[-2000:])  # SIGKILL
        assert "survived" not in p.stdout
        with ctx.sessions() as s:
            service.repair(s, s.get(Scene, scene["id"]))  # what the next start-up/edit does
        lab = np.asarray(load_labels(ws).labels)
        outcomes[step] = set(np.unique(lab[ids]).tolist())
    # killed before the row committed: not applied (the orphan point file is never read);
    # after it: applied entirely (the layer is rebuilt from the active edits)
    assert outcomes == {"after_points": {6}, "after_commit": {13}, "after_layer": {13}}
    with ctx.sessions() as s:
        rows = s.execute(select(CorrectionEdit.n_points, CorrectionEdit.state).where(
            CorrectionEdit.scene_id == scene["id"]).order_by(CorrectionEdit.id)).all()
    assert [tuple(r) for r in rows] == [(40, "active"), (20, "active")]
    # the app's start-up repairs too: break the layer, restart, it is whole again
    from occufly.lifting import corrections as lib

    lib.write_net(ws, lib.NetLayer.empty())
    env.restart()
    assert set(np.unique(np.asarray(load_labels(ws).labels)[seen[30:90]]).tolist()) == {13}


def test_reimport_refuses_with_the_count_unless_asked_to_drop(world):
    env, hdr, scene, frames = world
    fid, ws = _lifted(world)
    sid = scene["id"]
    seen = _seen(env, ws, fid)
    for chunk in (seen[:10], seen[10:20]):
        r = env.client.post(f"/api/scenes/{sid}/corrections",
                            json={"point_ids": chunk.tolist(), "to_class": 8},
                            headers=hdr["reviewer"])
        assert r.status_code == 201
    r = env.client.post(f"/api/scenes/{sid}/reimport", json={}, headers=hdr["admin"])
    assert r.status_code == 422  # the admin must say what happens to the corrections
    r = env.client.post(f"/api/scenes/{sid}/reimport", json={"drop_corrections": False},
                        headers=hdr["admin"])
    assert r.status_code == 409 and r.json()["corrections"] == 2
    assert "2 active label correction" in r.json()["detail"]
    assert env.client.post(f"/api/scenes/{sid}/reimport", json={},
                           headers=hdr["reviewer"]).status_code == 403
    r = env.client.post(f"/api/scenes/{sid}/reimport", json={"drop_corrections": True},
                        headers=hdr["admin"])
    assert r.status_code == 202 and r.json()["dropped_corrections"] == 2
    j = env.app.state.ctx.jobs.wait(r.json()["id"], timeout=60)
    job = env.client.get(f"/api/jobs/{r.json()['id']}", headers=hdr["admin"]).json()
    assert job["status"] == "done", (j, job)
    states = [e["state"] for e in env.client.get(f"/api/scenes/{sid}/corrections",
                                                  headers=hdr["admin"]).json()]
    assert states == ["dropped", "dropped"]
    assert env.client.get(f"/api/scenes/{sid}/corrections/layer",
                          headers=hdr["admin"]).json()["corrected_points"] == 0


def test_disagreeing_frames_proposal_taken_or_declined_items_and_notifications(world):
    env, hdr, scene, frames = world
    fid, ws = _lifted(world)
    sid = scene["id"]
    a, rv = hdr["annotator"], hdr["reviewer"]
    seen = _seen(env, ws, fid)
    e = env.client.post(f"/api/scenes/{sid}/corrections",
                        json={"point_ids": seen[:60].tolist(), "to_class": 1}, headers=rv).json()
    rows = env.client.get(f"/api/scenes/{sid}/corrections/{e['id']}/frames", headers=rv).json()
    assert [r["frame_id"] for r in rows] == [fid]  # the only voting mask: all grass
    assert rows[0]["disagreeing_px"] == rows[0]["pixels"] > 20
    assert env.client.get(f"/api/scenes/{sid}/corrections/{e['id']}/frames",
                          headers=a).status_code == 403

    # the reviewer rejects the frame with a comment: the annotator is notified
    v = env.client.get(f"/api/frames/{fid}", headers=rv).json()["current_version"]
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "reject", "version": v,
                                                           "comment": "road, not grass"},
                        headers=rv)
    assert r.status_code == 200, r.text
    n = env.client.get("/api/notifications", headers=a).json()
    assert n["unread"] == 1 and n["items"][0]["kind"] == "rejected"
    assert "road, not grass" in n["items"][0]["text"] and n["items"][0]["frame_id"] == fid
    # rejection withdrew the votes; give the frame a voting mask again and propose
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=a).json()
    assert fa["id"] == fid, fa
    cur = env.client.get(f"/api/frames/{fid}", headers=a).json()["current_version"]
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                       content=png(np.full((H, W), 6, np.uint8)),
                       headers={**a, "If-Match": str(cur)})
    assert r.status_code == 200, r.text
    p = env.client.post(f"/api/scenes/{sid}/corrections/{e['id']}/proposals",
                        json={"frame_id": fid, "dilate": 0}, headers=rv)
    assert p.status_code == 201, p.text
    p = p.json()
    assert p["changed_px"] == rows[0]["pixels"] and p["status"] == "open"
    n = env.client.get("/api/notifications?unread=true", headers=a).json()
    assert {x["kind"] for x in n["items"]} == {"rejected", "proposal"}
    assert env.client.post("/api/notifications/read", json={}, headers=a).json()["marked"] == 2
    assert env.client.get("/api/notifications", headers=a).json()["unread"] == 0
    listed = env.client.get(f"/api/frames/{fid}/proposals?status=open", headers=a).json()
    assert [x["id"] for x in listed] == [p["id"]]
    ov = env.client.get(f"/api/frames/{fid}/proposals/{p['id']}/overlay", headers=a)
    import io

    from PIL import Image

    rgba = np.asarray(Image.open(io.BytesIO(ov.content)))
    assert rgba.shape == (H, W, 4) and (rgba[..., 3] > 0).sum() == p["changed_px"]
    assert (rgba[rgba[..., 3] > 0][:, :3] == (128, 0, 128)).all()  # road's colour

    # reviewers cannot take it for the annotator; the annotator (holding the lease) can
    assert env.client.post(f"/api/frames/{fid}/proposals/{p['id']}/take",
                           headers=rv).status_code == 403
    r = env.client.post(f"/api/frames/{fid}/reopen", headers=a)  # back in their hands
    assert r.status_code == 200, r.text
    t = env.client.post(f"/api/frames/{fid}/proposals/{p['id']}/take", headers=a)
    assert t.status_code == 200, t.text
    t = t.json()
    assert t["status"] == "taken" and t["taken_version"]
    m = env.client.get(f"/api/frames/{fid}/mask", headers=a)
    assert m.status_code == 200
    got = np.asarray(Image.open(io.BytesIO(m.content)))
    assert (got == 1).sum() == p["changed_px"] and ((got == 1) | (got == 6)).all()
    v = env.client.get(f"/api/frames/{fid}/mask/versions", headers=a).json()
    newest = max(v, key=lambda x: x["version"])
    assert newest["version"] == t["taken_version"] and newest["kind"] == "draft"

    # a second proposal (against the voting mask, still all grass), declined with a reply
    p2 = env.client.post(f"/api/scenes/{sid}/corrections/{e['id']}/proposals",
                         json={"frame_id": fid}, headers=rv)
    assert p2.status_code == 201, p2.text
    p2 = p2.json()
    assert p2["changed_px"] > p["changed_px"]  # grown by one pixel (dilate=1)
    d = env.client.post(f"/api/frames/{fid}/proposals/{p2['id']}/decline",
                        json={"reply": "that is a shadow"}, headers=a)
    assert d.status_code == 200 and d.json()["status"] == "declined"
    assert env.client.post(f"/api/frames/{fid}/proposals/{p2['id']}/take",
                           headers=a).status_code == 409
    n = env.client.get("/api/notifications", headers=rv).json()
    assert n["items"][0]["kind"] == "declined" and "that is a shadow" in n["items"][0]["text"]

    # a review item filed on 3D points shows on the annotator page of a frame that sees them,
    # with the outline of its points in that frame; a comment on a frame notifies its annotator
    r = env.client.post(f"/api/scenes/{sid}/review-items",
                        json={"point_ids": seen[:60].tolist(), "comment": "check these"},
                        headers=rv)
    assert r.status_code == 201
    items = env.client.get(f"/api/frames/{fid}/projected-items", headers=a).json()
    assert [it["id"] for it in items] == [r.json()["id"]]
    it = items[0]
    assert it["visible_points"] == 60 and len(it["outline"]) >= 3
    xy = np.asarray(it["outline"])
    assert (xy[:, 0] >= 0).all() and (xy[:, 0] <= W).all() and (xy[:, 1] <= H).all()
    assert it["comments"][0]["text"] == "check these"
    r = env.client.post(f"/api/scenes/{sid}/review-items",
                        json={"frame_id": fid, "pixel": [3, 4], "comment": "and here"},
                        headers=rv)
    n = env.client.get("/api/notifications?unread=true", headers=a).json()
    assert [x["kind"] for x in n["items"]] == ["comment", "proposal"]  # newest first
    assert "and here" in n["items"][0]["text"]


def test_a_reviewer_corrects_a_2d_mask_directly(world):
    env, hdr, scene, frames = world
    fid, ws = _lifted(world)
    a, rv = hdr["annotator"], hdr["reviewer"]
    cur = env.client.get(f"/api/frames/{fid}", headers=a).json()["current_version"]
    fixed = np.full((H, W), 6, np.uint8)
    fixed[:, :10] = 1
    r = env.client.put(f"/api/frames/{fid}/reviewer-correction", content=png(fixed),
                       headers={**a, "Content-Type": "image/png"})
    assert r.status_code == 403  # annotators use their own editor
    r = env.client.put(f"/api/frames/{fid}/reviewer-correction", content=png(fixed),
                       headers={**rv, "Content-Type": "image/png", "If-Match": str(cur)})
    assert r.status_code == 201, r.text
    v = r.json()
    assert v["author"] == "reviewer" and v["kind"] == "submitted"
    from app.annotations.models import MaskVersion
    from app.scenes.models import Frame

    with env.app.state.ctx.sessions() as s:
        row = s.get(MaskVersion, v["version"])
        assert row.source == "reviewer_correction"
        assert s.get(Frame, fid).voting_version_id == row.id  # it votes
    # a stale If-Match is a 409 (the upload kept as a conflict)
    r = env.client.put(f"/api/frames/{fid}/reviewer-correction", content=png(fixed),
                       headers={**rv, "Content-Type": "image/png", "If-Match": str(cur)})
    assert r.status_code == 409
    n = env.client.get("/api/notifications", headers=a).json()
    assert n["items"][0]["kind"] == "corrected"
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=30, include_fill=True)
    st = env.client.get(f"/api/scenes/{scene['id']}/labels/status", headers=rv).json()
    assert st["included_versions"] == {str(fid): v["version"]}  # the correction was lifted
