"""Provenance (issue 23, defects 2 and 4): drafts never vote; deciding twice and repeating a
job request with one Idempotency-Key are no-ops."""

from __future__ import annotations

import numpy as np
from sqlalchemy import func, select

from tests.app.conftest import H, W, png


def _setup(env):  # noqa: ANN001
    admin, ann = env.bearer("admin"), env.bearer("annotator")
    env.import_tiny(admin)
    scene = env.client.get("/api/scenes", headers=admin).json()[-1]
    env.select_all(scene["id"])
    return admin, ann, scene["id"]


def _mask(cls: int) -> bytes:
    return png(np.full((H, W), cls, np.uint8))


def test_a_draft_does_not_vote_a_submitted_version_does(env):
    from app.lifting.models import LiftQueueEntry
    from app.scenes.models import Frame

    admin, ann, sid = _setup(env)
    lm = env.app.state.ctx.lifting
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    r = env.client.put(f"/api/frames/{fa}/mask", content=_mask(1),
                       headers={**ann, "If-Match": "none"})  # a draft painted as road
    assert r.status_code == 200 and r.json()["kind"] == "draft"
    draft = r.json()["version"]
    assert lm.wait_idle(sid, timeout=10, include_fill=True)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=admin).json()
    assert st["included_versions"] == {} and st["class_histogram"] == {}  # nothing lifted
    with env.app.state.ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(LiftQueueEntry)) == 0
        assert s.get(Frame, fa).voting_version_id is None
    # another frame's prefill knows nothing of the draft
    fb = [f["id"] for f in env.client.get(f"/api/scenes/{sid}/frames", headers=admin).json()
          if f["id"] != fa][0]
    assert env.client.get(f"/api/frames/{fb}/prefill", headers=admin).status_code == 404

    r = env.client.put(f"/api/frames/{fa}/mask?kind=submitted", content=_mask(6),
                       headers={**ann, "If-Match": str(draft)})  # grass, submitted
    sub = r.json()["version"]
    assert lm.wait_idle(sid, timeout=30, include_fill=True)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=admin).json()
    assert st["included_versions"] == {str(fa): sub}
    assert set(st["class_histogram"]) == {"6"}  # grass only: the road draft never counted
    pre = env.client.get(f"/api/frames/{fb}/prefill", headers=admin)
    assert pre.status_code == 200


def test_accept_twice_stores_one_decision_reject_withdraws_votes(env):
    from app.annotations.models import MaskVersion
    from app.audit.models import AuditEvent
    from app.review.models import ReviewComment

    admin, ann, sid = _setup(env)
    rev = env.bearer("reviewer")
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    v = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=_mask(6),
                       headers={**ann, "If-Match": "none"}).json()["version"]
    body = {"decision": "accept", "comment": "looks right", "version": v}
    for _ in range(2):
        r = env.client.post(f"/api/frames/{fid}/review", json=body, headers=rev)
        assert r.status_code == 200 and r.json()["state"] == "accepted"
    ctx = env.app.state.ctx
    with ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(ReviewComment)) == 1
        assert s.scalar(select(func.count()).select_from(AuditEvent)
                        .where(AuditEvent.action == "review_accept")) == 1
        mv = s.get(MaskVersion, v)
        assert mv.kind == "accepted" and mv.decided_by_id is not None and mv.decided_at
    assert ctx.lifting.wait_idle(sid, timeout=30)
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "reject", "version": v},
                        headers=rev)
    assert r.status_code == 200 and r.json()["state"] == "rejected"
    assert ctx.lifting.wait_idle(sid, timeout=30)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=admin).json()
    assert st["included_versions"] == {}  # a rejection withdraws the frame's votes
    with ctx.sessions() as s:
        assert s.get(MaskVersion, v).kind == "rejected"


def test_same_idempotency_key_makes_one_job(env):
    from app.jobs.models import Job

    admin, _ann, sid = _setup(env)
    hdr = {**admin, "Idempotency-Key": "k-123"}
    r1 = env.client.post(f"/api/scenes/{sid}/voxelize", json={"voxel_size": 0.5}, headers=hdr)
    r2 = env.client.post(f"/api/scenes/{sid}/voxelize", json={"voxel_size": 0.5}, headers=hdr)
    assert r1.status_code == 202 and r2.status_code == 200
    assert r1.json()["id"] == r2.json()["id"]
    r3 = env.client.post(f"/api/scenes/{sid}/voxelize", json={"voxel_size": 1.0}, headers=hdr)
    assert r3.status_code == 422
    r4 = env.client.post(f"/api/scenes/{sid}/voxelize", json={"voxel_size": 0.5},
                         headers={**admin, "Idempotency-Key": "k-456"})
    assert r4.status_code == 202 and r4.json()["id"] != r1.json()["id"]
    with env.app.state.ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(Job).where(Job.kind == "voxelize")) == 2
