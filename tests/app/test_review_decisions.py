"""Issue 40, defect 1 (server side): a review decision names the mask version the reviewer saw
(required); a version that is not the frame's current one is refused with 409 naming both; a
decision can be undone through the API (audited), and only while the frame has not moved on."""

from __future__ import annotations

import numpy as np
from sqlalchemy import select

from tests.app.conftest import H, W, png


def _submitted(env):  # noqa: ANN001
    admin, ann = env.bearer("admin"), env.bearer("annotator")
    env.import_tiny(admin)
    sid = env.client.get("/api/scenes", headers=admin).json()[-1]["id"]
    env.select_all(sid)
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                       content=png(np.full((H, W), 6, np.uint8)),
                       headers={**ann, "If-Match": "none"})
    assert r.status_code == 200, r.text
    return sid, fid, r.json()["version"]


def test_decision_needs_the_current_version_and_names_both_on_409(env):
    sid, fid, v = _submitted(env)
    rev = env.bearer("reviewer")
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "accept"}, headers=rev)
    assert r.status_code == 422 and "version" in r.text
    stale = v + 1000
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "accept", "version": stale},
                        headers=rev)
    assert r.status_code == 409
    body = r.json()
    assert body["current_version"] == v and body["sent_version"] == stale
    assert f"version {v}" in body["detail"] and f"version {stale}" in body["detail"]
    assert env.client.get(f"/api/frames/{fid}", headers=rev).json()["state"] == "submitted"
    r = env.client.post(f"/api/frames/{fid}/review",
                        json={"decision": "reject", "version": v, "comment": "wrong road"},
                        headers=rev)
    assert r.status_code == 200 and r.json()["state"] == "rejected"
    # the same decision again is a no-op (a double press), not a 409
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "reject", "version": v},
                        headers=rev)
    assert r.status_code == 200 and r.json()["state"] == "rejected"


def test_undo_restores_submitted_audited_and_only_while_unchanged(env):
    from app.annotations.models import MaskVersion
    from app.audit.models import AuditEvent
    from app.scenes.models import Frame

    sid, fid, v = _submitted(env)
    rev, admin = env.bearer("reviewer"), env.bearer("admin")
    ctx = env.app.state.ctx
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "accept", "version": v},
                        headers=rev)
    assert r.status_code == 200 and r.json()["state"] == "accepted"
    # undoing a decision that was not made (reject) is refused, the frame stays accepted
    r = env.client.post(f"/api/frames/{fid}/review/undo", json={"decision": "reject", "version": v},
                        headers=rev)
    assert r.status_code == 409 and "accepted" in r.json()["detail"]
    r = env.client.post(f"/api/frames/{fid}/review/undo", json={"decision": "accept", "version": v},
                        headers=rev)
    assert r.status_code == 200, r.text
    assert r.json()["state"] == "submitted"
    with ctx.sessions() as s:
        f = s.get(Frame, fid)
        assert f.reviewed_version_id is None and f.reviewed_by_id is None
        assert f.voting_version_id == v  # it still votes, as a submitted version
        mv = s.get(MaskVersion, v)
        assert mv.kind == "submitted" and mv.decided_by_id is None
        acts = [a for a in s.scalars(select(AuditEvent.action).where(AuditEvent.frame_id == fid)
                                     .order_by(AuditEvent.id))]
    assert acts[-2:] == ["review_accept", "review_undo"]
    # twice: the frame is not accepted any more -> 409, nothing changes
    r = env.client.post(f"/api/frames/{fid}/review/undo", json={"decision": "accept", "version": v},
                        headers=rev)
    assert r.status_code == 409
    # reject, the annotator is told; the annotator takes it back and saves: no undo then
    r = env.client.post(f"/api/frames/{fid}/review",
                        json={"decision": "reject", "version": v, "comment": "sky"}, headers=rev)
    assert r.status_code == 200
    ann = env.bearer("annotator")
    r = env.client.post(f"/api/frames/{fid}/review/undo", json={"decision": "reject", "version": v},
                        headers=rev)
    assert r.status_code == 200 and r.json()["state"] == "submitted"
    texts = [n["text"] for n in env.client.get("/api/notifications", headers=ann).json()["items"]]
    assert any("withdrew the rejection" in t for t in texts), texts
    r = env.client.post(f"/api/frames/{fid}/review",
                        json={"decision": "reject", "version": v, "comment": "sky"}, headers=rev)
    assert r.status_code == 200
    assert env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"] == fid
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                       content=png(np.full((H, W), 1, np.uint8)),
                       headers={**ann, "If-Match": str(v)})
    assert r.status_code == 200
    r = env.client.post(f"/api/frames/{fid}/review/undo", json={"decision": "reject", "version": v},
                        headers=rev)
    assert r.status_code == 409 and "nothing undone" in r.json()["detail"]
    assert env.client.get(f"/api/frames/{fid}", headers=admin).json()["state"] == "submitted"


def test_a_proposal_on_an_accepted_frame_is_refused_with_the_reason(world):
    """Defect 3: a proposal filed on an accepted frame could never be taken by its annotator;
    the server refuses it (409) and says why. Submitted again, the same frame takes them."""
    from tests.app.test_corrections_api import _lifted, _seen

    env, hdr, scene, _frames = world
    fid, ws = _lifted(world)
    sid, rv = scene["id"], hdr["reviewer"]
    seen = _seen(env, ws, fid)
    e = env.client.post(f"/api/scenes/{sid}/corrections",
                        json={"point_ids": seen[:60].tolist(), "to_class": 1}, headers=rv).json()
    v = env.client.get(f"/api/frames/{fid}", headers=rv).json()["current_version"]
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "accept", "version": v},
                        headers=rv)
    assert r.status_code == 200
    r = env.client.post(f"/api/scenes/{sid}/corrections/{e['id']}/proposals",
                        json={"frame_id": fid}, headers=rv)
    assert r.status_code == 409, r.text
    assert "accepted" in r.json()["detail"] and "cannot take" in r.json()["detail"]
    assert env.client.get(f"/api/frames/{fid}/proposals", headers=rv).json() == []
    # submitted again (the decision undone): the annotator can take it, so it is filed
    r = env.client.post(f"/api/frames/{fid}/review/undo", json={"decision": "accept", "version": v},
                        headers=rv)
    assert r.status_code == 200
    r = env.client.post(f"/api/scenes/{sid}/corrections/{e['id']}/proposals",
                        json={"frame_id": fid}, headers=rv)
    assert r.status_code == 201, r.text
