"""Next best frames as a job (issue 37): POST /api/scenes/{sid}/next-frames."""

from __future__ import annotations

import numpy as np

from tests.app.conftest import H, W, png


def _job(env, hdr, sid, k=3):
    r = env.client.post(f"/api/scenes/{sid}/next-frames", json={"k": k}, headers=hdr["admin"])
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"])
    return env.client.get(f"/api/jobs/{r.json()['id']}", headers=hdr["admin"]).json()


def test_next_frames_job(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    # only an admin proposes; k is bounded
    assert env.client.post(f"/api/scenes/{sid}/next-frames", json={"k": 3},
                           headers=hdr["annotator"]).status_code == 403
    assert env.client.post(f"/api/scenes/{sid}/next-frames", json={"k": 0},
                           headers=hdr["admin"]).status_code == 422
    # no votes yet: the job fails and says what is missing
    j = _job(env, hdr, sid)
    assert j["status"] == "failed" and "no votes yet" in j["message"], j
    # one frame painted grass, another road: the points both see are contested
    a = hdr["annotator"]
    lifting = env.app.state.ctx.lifting
    painted = []
    for cls in (6, 1):
        r = env.client.post(f"/api/scenes/{sid}/next", headers=a)
        fid = r.json()["id"]
        v = env.client.put(f"/api/frames/{fid}/mask?kind=submitted",
                           content=png(np.full((H, W), cls, np.uint8)),
                           headers={**a, "If-Match": "none"})
        assert v.status_code == 200, v.text
        painted.append(next(f["index"] for f in frames if f["id"] == fid))
    assert lifting.wait_idle(sid, timeout=30, include_fill=True)
    j = _job(env, hdr, sid, k=4)
    assert j["status"] == "done", j
    res = j["result"]
    assert res["contested_points"] > 0 and res["frames"], res
    assert not set(res["frames"]) & set(painted)
    assert len(res["frames"]) == len(set(res["frames"])) <= 4
    why = res["reasons"][0]
    assert why["frame"] == res["frames"][0] and why["needy_points"] > 0 and why["classes"]
