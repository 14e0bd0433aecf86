"""GET /api/frames/{fid}/corrections (issue 40, the reviewer page's "Propose from 3D"), on
SQLite and PostgreSQL: the scene's active 3D corrections one frame sees, newest first, with what
a proposal from each would change in the frame's voting mask and the open proposal already
filed; edits the frame does not see, and undone ones, are left out; reviewers only."""

from __future__ import annotations

import numpy as np

from tests.app.conftest import H, W, png


def test_frame_corrections_lists_what_a_proposal_would_change(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    a, rv = hdr["annotator"], hdr["reviewer"]
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=a).json()["id"]
    url = f"/api/frames/{fid}/corrections"
    # no voting mask yet: an edit the frame sees is listed, with nothing to compare
    info = env.client.get(f"/api/frames/{fid}", headers=rv).json()
    ws = env.app.state.ctx.load_scene(str(env.settings.workspaces_dir / "tiny"))
    seen = np.sort(np.asarray(ws.visibility.frame(info["index"])[0], np.int64))
    unseen = np.setdiff1d(np.arange(len(ws.xyz)), seen)
    assert len(seen) > 100 and len(unseen) > 10  # the fixture's scene has both
    e0 = env.client.post(f"/api/scenes/{sid}/corrections",
                         json={"point_ids": seen[:30].tolist(), "to_class": 6}, headers=rv).json()
    rows = env.client.get(url, headers=rv).json()
    assert [r["id"] for r in rows] == [e0["id"]]
    assert rows[0]["voting_version"] is None and rows[0]["disagreeing_px"] is None
    assert rows[0]["proposable_px"] is None and rows[0]["pixels"] > 10

    # the annotator submits an all-grass mask (class 6): it votes
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                       content=png(np.full((H, W), 6, np.uint8)),
                       headers={**a, "If-Match": "none"})
    assert r.status_code == 200, r.text
    voting = r.json()["version"]
    e1 = env.client.post(f"/api/scenes/{sid}/corrections",
                         json={"point_ids": seen[:60].tolist(), "to_class": 1}, headers=rv).json()
    e2 = env.client.post(f"/api/scenes/{sid}/corrections",  # not seen by this frame
                         json={"point_ids": unseen[:10].tolist(), "to_class": 1},
                         headers=rv).json()
    assert e2["state"] == "active"
    assert env.client.get(url, headers=a).status_code == 403  # reviewers' tool
    rows = env.client.get(url, headers=rv).json()
    assert [r["id"] for r in rows] == [e1["id"], e0["id"]]  # newest first, e2 left out
    road, grass = rows
    assert road["voting_version"] == voting and road["to_class"] == 1
    assert road["author"] == "reviewer" and road["n_points"] == 60
    # every seen pixel is grass: all disagree with road, none with grass
    assert road["disagreeing_px"] == road["proposable_px"] == road["pixels"] > 20
    assert grass["disagreeing_px"] == grass["proposable_px"] == 0
    assert road["open_proposal"] is None
    # the same figures as the per-edit list of disagreeing frames
    per_edit = env.client.get(f"/api/scenes/{sid}/corrections/{e1['id']}/frames",
                              headers=rv).json()
    assert [(x["frame_id"], x["pixels"], x["disagreeing_px"]) for x in per_edit] == \
        [(fid, road["pixels"], road["disagreeing_px"])]

    # a proposal filed from it is named; it changes exactly the proposable pixels (dilate 0)
    p = env.client.post(f"/api/scenes/{sid}/corrections/{e1['id']}/proposals",
                        json={"frame_id": fid, "dilate": 0}, headers=rv)
    assert p.status_code == 201, p.text
    assert p.json()["changed_px"] == road["proposable_px"]
    rows = env.client.get(url, headers=rv).json()
    assert rows[0]["open_proposal"] == p.json()["id"] and rows[1]["open_proposal"] is None

    # an undone edit is no longer offered
    u = env.client.post(f"/api/scenes/{sid}/corrections/undo", headers=rv)
    assert u.status_code == 200 and u.json()["id"] == e2["id"]
    u = env.client.post(f"/api/scenes/{sid}/corrections/undo", headers=rv)
    assert u.status_code == 200 and u.json()["id"] == e1["id"]
    assert [r["id"] for r in env.client.get(url, headers=rv).json()] == [e0["id"]]
    assert env.client.get("/api/frames/999999/corrections", headers=rv).status_code == 404
