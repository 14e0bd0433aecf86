"""Issue 36 finding 1: a scene deletion never removes a blob another scene's concurrent save
of the same bytes is about to reference; a missing blob answers a JSON 500 naming the version.

The race is driven deterministically, on both databases: the save in scene C is held after
its blob is stored (found present: scene B has the same bytes) and before its version row is
written, while scene B is deleted from another thread; then the save goes on. The old code
deleted the blob in that window (the version of C was acknowledged, its PNG gone).
"""

from __future__ import annotations

import threading

import numpy as np
from fastapi.testclient import TestClient
from sqlalchemy import event
from sqlalchemy.orm import Session

from app.annotations.models import MaskVersion
from tests.app.conftest import H, W, png


def _mask() -> bytes:
    m = np.zeros((H, W), np.uint8)
    m[:, :7] = 6
    m[3:9, 12:] = 2
    return png(m)


def test_scene_deletion_keeps_a_blob_a_concurrent_save_references(world):
    env, hdr, scene_b, frames_b = world
    scene_c = env.import_tiny(hdr["admin"], name="scene_c")
    frames_c = env.client.get(f"/api/scenes/{scene_c['id']}/frames", headers=hdr["admin"]).json()
    data = _mask()
    admin = hdr["admin"]
    r = env.client.put(f"/api/frames/{frames_b[0]['id']}/mask", content=data,
                       headers={**admin, "If-Match": "none"})
    assert r.status_code == 200, r.text
    sha = r.json()["sha256"]
    fid_c = frames_c[0]["id"]

    held, go = threading.Event(), threading.Event()
    saver: dict = {}

    def hold(session, _ctx, _instances):  # noqa: ANN001 - SQLAlchemy before_flush hook
        if not held.is_set() and any(  # (the route runs in a worker thread of the server)
                isinstance(o, MaskVersion) and o.frame_id == fid_c for o in session.new):
            held.set()
            go.wait(30)

    def save() -> None:
        with TestClient(env.app) as c:
            saver["resp"] = c.put(f"/api/frames/{fid_c}/mask", content=data,
                                  headers={**admin, "If-Match": "none"})

    def delete() -> None:
        with TestClient(env.app) as c:
            saver["del"] = c.delete(f"/api/scenes/{scene_b['id']}",
                                    params={"confirm": scene_b["name"]}, headers=admin)

    event.listen(Session, "before_flush", hold)
    try:
        t_save = threading.Thread(target=save)
        t_save.start()
        assert held.wait(30), "the save never reached its version insert"
        t_del = threading.Thread(target=delete)
        t_del.start()
        t_del.join(3)  # the old code finishes (and removes the blob) here; the fix waits
        go.set()
        t_save.join(60)
        t_del.join(60)
    finally:
        go.set()
        event.remove(Session, "before_flush", hold)
    assert saver["resp"].status_code == 200, saver["resp"].text
    assert saver["del"].status_code == 200, saver["del"].text
    vid = saver["resp"].json()["version"]
    assert env.app.state.ctx.store.exists(sha), "the acknowledged version's blob was deleted"
    r = env.client.get(f"/api/frames/{fid_c}/mask", headers=admin)
    assert r.status_code == 200 and r.content == data and r.headers["X-Mask-Version"] == str(vid)
    # and once scene C goes too, nothing references the blob: it is removed
    r = env.client.delete(f"/api/scenes/{scene_c['id']}", params={"confirm": scene_c["name"]},
                          headers=admin)
    assert r.status_code == 200, r.text
    assert not env.app.state.ctx.store.exists(sha)


def test_a_missing_blob_answers_a_json_500_naming_the_version(world):
    env, hdr, _scene, frames = world
    fid = frames[1]["id"]
    r = env.client.put(f"/api/frames/{fid}/mask", content=_mask(),
                       headers={**hdr["admin"], "If-Match": "none"})
    assert r.status_code == 200, r.text
    vid, sha = r.json()["version"], r.json()["sha256"]
    env.app.state.ctx.store.path(sha).unlink()
    with TestClient(env.app, raise_server_exceptions=False) as c:
        r = c.get(f"/api/frames/{fid}/mask", headers=hdr["admin"])
        assert r.status_code == 500
        body = r.json()
        assert f"mask version {vid}" in body["detail"] and body["sha256"] == sha
        # a restore of that version names it too, and stores nothing
        r = c.post(f"/api/frames/{fid}/mask/versions/{vid}/restore",
                   headers={**hdr["admin"], "If-Match": str(vid)})
        assert r.status_code == 500 and f"mask version {vid}" in r.json()["detail"], r.text
    n = len(env.client.get(f"/api/frames/{fid}/mask/versions", headers=hdr["admin"]).json())
    assert n == 1
