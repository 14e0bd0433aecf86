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
