"""Issue 29: the client is told the current lifting lag (labels status ``lag_s``)."""

from __future__ import annotations

import time

import numpy as np

from tests.app.conftest import H, W, png


def test_labels_status_reports_the_lag_of_the_oldest_pending_entry(env):
    admin, ann = env.bearer("admin"), env.bearer("annotator")
    env.import_tiny(admin)
    sid = env.client.get("/api/scenes", headers=admin).json()[-1]["id"]
    env.select_all(sid)
    ctx = env.app.state.ctx
    ctx.lifting.stop()  # the worker is down: the submit waits in the queue
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                       content=png(np.full((H, W), 6, np.uint8)),
                       headers={**ann, "If-Match": "none"})
    assert r.status_code == 200, r.text
    time.sleep(1.2)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=admin).json()
    assert st["pending_frames"] == 1 and 1.0 <= st["lag_s"] < 60
    ctx.lifting.start()
    assert ctx.lifting.wait_idle(sid, timeout=30)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=admin).json()
    assert st["pending_frames"] == 0 and st["lag_s"] == 0.0


def test_versions_superseded_beyond_the_batch_are_never_decoded(env):
    """A frame's older versions are superseded without decoding their masks, also when the
    newer version is not in the same batch; the newest is applied, in queue order."""
    from sqlalchemy import select

    from app.lifting.models import LiftQueueEntry
    from app.lifting.service import LiftingService

    admin, ann, ann2 = env.bearer("admin"), env.bearer("annotator"), env.bearer("annotator2")
    env.import_tiny(admin)
    sid = env.client.get("/api/scenes", headers=admin).json()[-1]["id"]
    env.select_all(sid)
    ctx = env.app.state.ctx
    ctx.lifting.stop()
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    versions, base = [], "none"
    for cls in (6, 8, 13):
        if versions:
            r = env.client.post(f"/api/frames/{fa}/reopen", headers=ann)
            assert r.status_code == 200, r.text
        r = env.client.put(f"/api/frames/{fa}/mask?kind=submitted",
                           content=png(np.full((H, W), cls, np.uint8)),
                           headers={**ann, "If-Match": base})
        assert r.status_code == 200, r.text
        base = str(r.json()["version"])
        versions.append(r.json()["version"])
    fb = env.client.post(f"/api/scenes/{sid}/next", headers=ann2).json()["id"]
    r = env.client.put(f"/api/frames/{fb}/mask?kind=submitted",
                       content=png(np.full((H, W), 1, np.uint8)),
                       headers={**ann2, "If-Match": "none"})
    assert r.status_code == 200, r.text
    svc = LiftingService(settings=ctx.settings, engine=ctx.engine, sessions=ctx.sessions,
                         store=ctx.store, load_scene=ctx.load_scene, bus=ctx.events,
                         batch=2)  # batches: [a1, a2], [a3, b1]
    decoded = []
    real = svc._votes_of  # noqa: SLF001

    def counting(sc, entry):  # noqa: ANN001, ANN202
        decoded.append(entry.version_id)
        return real(sc, entry)

    svc._votes_of = counting  # noqa: SLF001
    svc.acquire()
    svc.start()
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end:
            with ctx.sessions() as s:
                st = list(s.scalars(select(LiftQueueEntry.status).where(
                    LiftQueueEntry.scene_id == sid).order_by(LiftQueueEntry.id)))
            if "pending" not in st:
                break
            time.sleep(0.05)
    finally:
        svc.stop()
    assert st == ["superseded", "superseded", "applied", "applied"]
    assert sorted(decoded) == sorted([versions[-1], r.json()["version"]])
    with ctx.sessions() as s:
        seqs = list(s.scalars(select(LiftQueueEntry.applied_seq).where(
            LiftQueueEntry.scene_id == sid).order_by(LiftQueueEntry.id)))
    assert seqs == [1, 2, 3, 4]  # the scene's own sequence, in queue order
