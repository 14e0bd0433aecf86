"""API behaviour on SQLite and PostgreSQL: roles, leases, versioned masks, review, jobs."""

from __future__ import annotations

import hashlib
import sys
import threading

import numpy as np
import pytest
from sqlalchemy import func, select

from app.annotations.models import MaskVersion
from app.scenes.models import Scene
from tests.app.conftest import H, W, mask_png, png


def _count(env, model) -> int:
    with env.app.state.ctx.sessions() as s:
        return int(s.scalar(select(func.count()).select_from(model)))


# ---- auth -----------------------------------------------------------------------------------
def test_login_cookie_bearer_logout(env):
    c = env.login("reviewer")
    assert c.cookies.get("occufly_session")
    r = c.post("/api/auth/login", json={"username": "reviewer", "password": "correct-horse-battery"})
    cookie_header = r.headers["set-cookie"].lower()
    assert "httponly" in cookie_header and "samesite=lax" in cookie_header
    assert c.get("/api/auth/me").json()["role"] == "reviewer"
    token = r.json()["token"]
    anon = env.client
    assert anon.get("/api/auth/me").status_code == 401
    assert anon.get("/api/auth/me", headers={"Authorization": f"Bearer {token}"}).json()[
        "username"] == "reviewer"
    assert anon.post("/api/auth/logout", headers={"Authorization": f"Bearer {token}"}).status_code == 204
    assert anon.get("/api/auth/me", headers={"Authorization": f"Bearer {token}"}).status_code == 401
    # the stored token is a keyed hash, never the token itself
    from app.users.models import AuthToken

    with env.app.state.ctx.sessions() as s:
        stored = list(s.scalars(select(AuthToken.token_hash)))
    assert stored and token not in stored


def test_login_bruteforce_is_throttled(env, monkeypatch):
    # the service's clock stands still: the first lock lasts 1 s, and on a loaded machine the
    # next request came more than a second after the failure that set it (the lock had
    # expired: 401, not 429); the expiry is checked by moving the clock on
    from datetime import timedelta

    from app.db import utcnow
    from app.users import service as users_service

    clock = [utcnow()]
    monkeypatch.setattr(users_service, "utcnow", lambda: clock[0])
    for _ in range(3):  # login_free_failures=3 in the fixture
        r = env.client.post("/api/auth/login", json={"username": "admin", "password": "wrong-pass"})
        assert r.status_code == 401
    r = env.client.post("/api/auth/login", json={"username": "admin", "password": "wrong-pass"})
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    # even the right password is refused while locked
    r = env.client.post("/api/auth/login", json={"username": "admin",
                                                 "password": "correct-horse-battery"})
    assert r.status_code == 429
    # spraying many user names from one address locks the address (after 4x the failures)
    for i in range(12 - 3):  # the address already has 3 failures (admin, above)
        r = env.client.post("/api/auth/login", json={"username": f"u{i}", "password": "nope-nope"})
        assert r.status_code == 401, i
    r = env.client.post("/api/auth/login", json={"username": "reviewer", "password": "nope-nope"})
    assert r.status_code == 429
    # once the locks have run out, the right password gets in
    clock[0] += timedelta(minutes=10)
    r = env.client.post("/api/auth/login", json={"username": "admin",
                                                 "password": "correct-horse-battery"})
    assert r.status_code == 200, r.text


def test_admin_creates_users_and_duplicates_conflict(env):
    adm = env.bearer("admin")
    r = env.client.post("/api/users", json={"username": "bob", "password": "longenough1",
                                            "role": "reviewer"}, headers=adm)
    assert r.status_code == 201 and r.json()["role"] == "reviewer"
    r = env.client.post("/api/users", json={"username": "bob", "password": "longenough1",
                                            "role": "reviewer"}, headers=adm)
    assert r.status_code == 409
    r = env.client.post("/api/users", json={"username": "eve", "password": "longenough1",
                                            "role": "superuser"}, headers=adm)
    assert r.status_code == 422
    names = [u["username"] for u in env.client.get("/api/users", headers=adm).json()]
    assert names == ["admin", "reviewer", "annotator", "annotator2", "bob"]
    assert all("password" not in k for u in env.client.get("/api/users", headers=adm).json() for k in u)


def test_role_matrix(world):
    env, hdr, scene, frames = world
    sid, fid = scene["id"], frames[0]["id"]
    # (method, path, json) -> roles allowed
    routes = [
        ("GET", "/api/users", None, {"admin"}),
        ("POST", "/api/users", {"username": "x1", "password": "longenough1", "role": "annotator"}, {"admin"}),
        ("POST", "/api/scenes/import", {"name": "x", "source": "nope"}, {"admin"}),
        ("POST", f"/api/scenes/{sid}/selection", {"cell": 25}, {"admin"}),
        ("POST", f"/api/scenes/{sid}/voxelize", None, {"admin"}),
        ("POST", f"/api/scenes/{sid}/export", {"layout": "occufly"}, {"admin"}),
        ("GET", "/api/jobs", None, {"admin", "reviewer"}),
        ("GET", f"/api/scenes/{sid}/metrics", None, {"admin", "reviewer"}),
        ("POST", f"/api/frames/{fid}/review", {"decision": "accept", "version": 1}, {"admin", "reviewer"}),
        ("POST", f"/api/scenes/{sid}/review-items", {"frame_id": fid, "comment": "x"}, {"admin", "reviewer"}),
        ("GET", f"/api/frames/{fid}/agreement", None, {"admin", "reviewer"}),
        ("POST", f"/api/scenes/{sid}/next", None, {"admin", "annotator"}),
        ("GET", "/api/scenes", None, {"admin", "reviewer", "annotator"}),
        ("GET", f"/api/scenes/{sid}", None, {"admin", "reviewer", "annotator"}),
        ("GET", f"/api/scenes/{sid}/frames", None, {"admin", "reviewer", "annotator"}),
        ("GET", f"/api/frames/{fid}/image?size=thumb", None, {"admin", "reviewer", "annotator"}),
        ("GET", f"/api/scenes/{sid}/labels/status", None, {"admin", "reviewer", "annotator"}),
    ]
    for method, path, body, allowed in routes:
        r = env.client.request(method, path, json=body)
        assert r.status_code == 401, (method, path, r.status_code)
        for role in ("admin", "reviewer", "annotator"):
            r = env.client.request(method, path, json=body, headers=hdr[role])
            if role in allowed:
                assert r.status_code != 403 and r.status_code != 401, (role, method, path, r.text)
                assert r.status_code < 500, (role, method, path, r.text)
            else:
                assert r.status_code == 403, (role, method, path, r.status_code, r.text)


# ---- scenes, frames, images -----------------------------------------------------------------
def test_scene_detail_frames_and_images(world):
    env, hdr, scene, frames = world
    d = env.client.get(f"/api/scenes/{scene['id']}", headers=hdr["annotator"]).json()
    assert d["n_points"] == 400 and len(d["taxonomy"]["classes"]) == 21
    assert {"id": 16, "name": "building", "rgb": [255, 0, 0], "group": "instance"} in d["taxonomy"]["classes"]
    assert [f["index"] for f in frames] == [0, 1, 2, 3]
    f0 = frames[0]
    assert (f0["width"], f0["height"], f0["altitude"], f0["selected"], f0["state"]) == (W, H, 30.0, True, "unassigned")
    detail = env.client.get(f"/api/frames/{f0['id']}", headers=hdr["reviewer"]).json()
    assert np.allclose(detail["center"], [-8.0, 0.0, 30.0])
    full = env.client.get(f"/api/frames/{f0['id']}/image", headers=hdr["annotator"])
    assert full.status_code == 200 and "max-age" in full.headers["cache-control"]
    src = (env.import_root / "tiny_src" / "images" / "img_000.png").read_bytes()
    assert full.content == src
    etag = full.headers["etag"]
    again = env.client.get(f"/api/frames/{f0['id']}/image",
                           headers={**hdr["annotator"], "If-None-Match": etag})
    assert again.status_code == 304
    thumb = env.client.get(f"/api/frames/{f0['id']}/image?size=thumb", headers=hdr["annotator"])
    assert thumb.status_code == 200 and thumb.headers["content-type"] == "image/jpeg"
    assert env.client.get("/api/frames/999999/image", headers=hdr["admin"]).status_code == 404
    assert env.client.get("/api/scenes/999999", headers=hdr["admin"]).status_code == 404


def test_import_path_traversal_refused(env, tmp_path):
    adm = env.bearer("admin")
    outside = tmp_path / "outside_ws"
    from tests.app.conftest import write_tiny_workspace

    write_tiny_workspace(outside)
    (env.import_root / "escape").symlink_to(outside)
    for source in [str(outside), f"{env.import_root}/../outside_ws", "../outside_ws",
                   "escape", str(env.import_root / "escape"), "/etc"]:
        r = env.client.post("/api/scenes/import", json={"name": "bad", "source": source}, headers=adm)
        assert r.status_code == 403, (source, r.status_code, r.text)
    r = env.client.post("/api/scenes/import", json={"name": "bad", "source": "missing"}, headers=adm)
    assert r.status_code == 422
    assert _count(env, Scene) == 0
    assert not (env.settings.workspaces_dir / "bad").exists()


def test_import_of_garbage_fails_the_job_not_the_server(env):
    adm = env.bearer("admin")
    junk = env.import_root / "junk"
    junk.mkdir()
    (junk / "readme.txt").write_text("not a reconstruction")
    r = env.client.post("/api/scenes/import", json={"name": "junk", "source": "junk"}, headers=adm)
    assert r.status_code == 202
    env.app.state.ctx.jobs.wait(r.json()["id"])
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()
    assert j["status"] == "failed" and j["message"] and "internal error" not in j["message"]
    assert env.client.get("/api/scenes", headers=adm).json()[0]["status"] == "failed"


# ---- leases ---------------------------------------------------------------------------------
def test_next_never_hands_out_the_same_frame(world):
    env, hdr, scene, frames = world
    got: list = []
    lock = threading.Lock()

    def grab(who: str) -> None:
        r = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr[who])
        with lock:
            got.append((who, r.status_code, r.json()["id"] if r.status_code == 200 else None))

    threads = [threading.Thread(target=grab, args=(w,)) for w in ("annotator", "annotator2")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    ids = [g[2] for g in got]
    assert len(set(ids)) == 2 and None not in ids
    # asking again returns the frame already held, not a new one
    again = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr["annotator"]).json()
    assert again["id"] == dict((w, i) for w, _, i in got)["annotator"]
    assert again["assignee"] == "annotator"


def test_queue_drains_then_204_and_lease_expiry(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    held = []
    for who in ("annotator", "annotator2"):
        f = env.client.post(f"/api/scenes/{sid}/next", headers=hdr[who]).json()
        held.append(f["id"])
        env.client.post(f"/api/frames/{f['id']}/release", headers=hdr[who])
    # two annotators with different leases take all four frames
    taken = set()
    for who in ("annotator", "annotator2", "annotator", "annotator2"):
        r = env.client.post(f"/api/scenes/{sid}/next", headers=hdr[who])
        taken.add(r.json()["id"])
        env.client.put(f"/api/frames/{r.json()['id']}/mask?kind=submitted", content=mask_png(),
                       headers={**hdr[who], "If-Match": "none"})
    assert taken == {f["id"] for f in frames}
    assert env.client.post(f"/api/scenes/{sid}/next", headers=hdr["annotator"]).status_code == 204
    # an expired lease is handed to somebody else
    from sqlalchemy import update

    from app.db import utcnow
    from app.scenes.models import Frame

    fid = frames[0]["id"]
    with env.app.state.ctx.sessions() as s:
        s.execute(update(Frame).where(Frame.id == fid).values(
            state="in_progress", assignee_id=1, lease_expires_at=utcnow().replace(year=2000)))
        s.commit()
    r = env.client.post(f"/api/scenes/{sid}/next", headers=hdr["annotator2"])
    assert r.status_code == 200 and r.json()["id"] == fid


# ---- masks ----------------------------------------------------------------------------------
def _lease(env, hdr, scene, who="annotator") -> int:
    r = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr[who])
    assert r.status_code == 200, r.text
    return r.json()["id"]


def test_mask_versions_history_restore(world):
    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    m1, m2 = mask_png(6), mask_png(8)
    r1 = env.client.put(f"/api/frames/{fid}/mask", content=m1, headers={**a, "If-Match": "none"})
    assert r1.status_code == 200, r1.text
    v1 = r1.json()["version"]
    assert r1.json()["sha256"] == hashlib.sha256(m1).hexdigest() and r1.json()["kind"] == "draft"
    r2 = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=m2,
                        headers={**a, "If-Match": f'"{v1}"'})
    assert r2.status_code == 200
    v2 = r2.json()["version"]
    cur = env.client.get(f"/api/frames/{fid}/mask", headers=a)
    assert cur.content == m2 and cur.headers["etag"] == f'"{v2}"'
    hist = env.client.get(f"/api/frames/{fid}/mask/versions", headers=a).json()
    assert [(h["version"], h["kind"], h["author"]) for h in hist] == [
        (v1, "draft", "annotator"), (v2, "submitted", "annotator")]
    assert env.client.get(f"/api/frames/{fid}/mask/versions/{v1}", headers=a).content == m1
    # restore (an admin; reviewers may not write masks: issue 14 defect 3) makes v1's content
    # current as a new version
    r3 = env.client.post(f"/api/frames/{fid}/mask/versions/{v1}/restore",
                         headers={**hdr["reviewer"], "If-Match": str(v2)})
    assert r3.status_code == 403
    r3 = env.client.post(f"/api/frames/{fid}/mask/versions/{v1}/restore",
                         headers={**hdr["admin"], "If-Match": str(v2)})
    assert r3.status_code == 200 and r3.json()["restored_from"] == v1
    assert env.client.get(f"/api/frames/{fid}/mask", headers=a).content == m1
    f = env.client.get(f"/api/frames/{fid}", headers=a).json()
    assert f["state"] == "submitted" and f["current_version"] == r3.json()["version"]
    # another annotator may not read or write this frame
    assert env.client.get(f"/api/frames/{fid}/mask", headers=hdr["annotator2"]).status_code == 403
    r = env.client.put(f"/api/frames/{fid}/mask", content=m1,
                       headers={**hdr["annotator2"], "If-Match": "none"})
    assert r.status_code == 403


def test_stale_if_match_409_keeps_upload_as_conflict(world):
    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    v1 = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(6),
                        headers={**a, "If-Match": "none"}).json()["version"]
    stale = mask_png(9)
    r = env.client.put(f"/api/frames/{fid}/mask", content=stale, headers={**a, "If-Match": "none"})
    assert r.status_code == 409
    body = r.json()
    assert body["current_version"] == v1 and body["detail"]
    assert env.client.get(f"/api/frames/{fid}/mask/versions/{body['conflict_version']}",
                          headers=a).content == stale
    assert env.client.get(f"/api/frames/{fid}/mask", headers=a).content == mask_png(6)
    assert env.client.put(f"/api/frames/{fid}/mask", content=stale, headers=a).status_code == 428


def test_concurrent_writers_exactly_one_wins(world):
    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    base = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(6),
                          headers={**a, "If-Match": "none"}).json()["version"]
    # the two writers: the lease holder and an admin (reviewers may not write: issue 14)
    payloads = {"annotator": mask_png(8), "admin": mask_png(14)}
    barrier = threading.Barrier(2)
    results = {}

    def write(who: str) -> None:
        from fastapi.testclient import TestClient

        c = TestClient(env.app)
        barrier.wait()
        results[who] = c.put(f"/api/frames/{fid}/mask", content=payloads[who],
                             headers={**hdr[who], "If-Match": str(base)})

    for _ in range(3):  # a few rounds: the race must resolve the same way every time
        results.clear()
        threads = [threading.Thread(target=write, args=(w,)) for w in payloads]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        codes = sorted(r.status_code for r in results.values())
        assert codes == [200, 409], {w: r.text for w, r in results.items()}
        winner = next(w for w, r in results.items() if r.status_code == 200)
        loser = next(w for w, r in results.items() if r.status_code == 409)
        assert env.client.get(f"/api/frames/{fid}/mask", headers=a).content == payloads[winner]
        cv = results[loser].json()["conflict_version"]
        assert env.client.get(f"/api/frames/{fid}/mask/versions/{cv}",
                              headers=a).content == payloads[loser]
        assert results[loser].json()["current_version"] == results[winner].json()["version"]
        base = results[winner].json()["version"]


BAD_CASES = ["corrupt", "not_png", "wrong_size", "bad_scale", "unknown_id", "rgb_unknown",
             "oversize", "empty"]


def test_bad_uploads_are_4xx_and_store_nothing(world):
    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    good = mask_png(6)
    bodies = {
        "corrupt": good[:60] + b"\x00" * 40 + good[100:],
        "not_png": b"GIF89a" + b"\x00" * 100,
        "wrong_size": mask_png(6, w=W + 2, h=H),
        "bad_scale": mask_png(6, w=W // 3, h=H // 3 + 1),
        "unknown_id": mask_png(10),  # 10 is not a class of the default taxonomy
        "rgb_unknown": png(np.full((H, W, 3), 7, np.uint8)),
        "oversize": b"\x89PNG\r\n\x1a\n" + b"\x00" * (env.settings.max_upload_bytes + 1),
        "empty": b"",
    }
    for case in BAD_CASES:
        r = env.client.put(f"/api/frames/{fid}/mask", content=bodies[case],
                           headers={**hdr["annotator"], "If-Match": "none"})
        expected = 413 if case == "oversize" else 422
        assert r.status_code == expected, (case, r.text)
        assert isinstance(r.json()["detail"], str) and r.json()["detail"], case
        assert _count(env, MaskVersion) == 0, case
        assert env.app.state.ctx.store.count() == 0, case
    f = env.client.get(f"/api/frames/{fid}", headers=hdr["annotator"]).json()
    assert f["current_version"] is None and f["state"] == "in_progress"
    # unknown frame / version ids
    r = env.client.put("/api/frames/999999/mask", content=good,
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 404
    assert env.client.get(f"/api/frames/{fid}/mask", headers=hdr["annotator"]).status_code == 404
    assert env.client.get(f"/api/frames/{fid}/mask/versions/12345",
                          headers=hdr["annotator"]).status_code == 404
    r = env.client.put(f"/api/frames/{fid}/mask", content=good,
                       headers={**hdr["annotator"], "If-Match": "abc"})
    assert r.status_code == 422 and _count(env, MaskVersion) == 0


def test_downscaled_mask_is_accepted(world):
    env, hdr, scene, _ = world
    fid = _lease(env, hdr, scene)
    r = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(6, w=W // 2, h=H // 2),
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 200 and (r.json()["width"], r.json()["height"]) == (W // 2, H // 2)


# ---- live lifting and review ----------------------------------------------------------------
def test_live_lifting_tracks_versions(world):
    env, hdr, scene, frames = world
    fid = _lease(env, hdr, scene)
    a = hdr["annotator"]
    m = np.full((H, W), 6, np.uint8)  # all grass
    v1 = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                        headers={**a, "If-Match": "none"}).json()["version"]  # drafts never vote
    lifting = env.app.state.ctx.lifting
    assert lifting.wait_idle(scene["id"], timeout=10)
    st = env.client.get(f"/api/scenes/{scene['id']}/labels/status", headers=a).json()
    assert st["lifting_available"] and st["included_versions"] == {str(fid): v1}
    frame = next(f for f in frames if f["id"] == fid)
    ws_scene = env.app.state.ctx.load_scene(env.settings.workspaces_dir / "tiny" and
                                            str(env.settings.workspaces_dir / "tiny"))
    n_seen = len(ws_scene.visibility.frame(frame["index"])[0])
    assert st["class_histogram"].get("6") == n_seen or st["labels_source"] == "filled"
    m[:] = 1  # now all road
    assert env.client.post(f"/api/frames/{fid}/reopen", headers=a).status_code == 200
    v2 = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                        headers={**a, "If-Match": str(v1)}).json()["version"]
    assert lifting.wait_idle(scene["id"], timeout=10, include_fill=True)
    st = env.client.get(f"/api/scenes/{scene['id']}/labels/status", headers=a).json()
    # a submitted frame gets its agreement refreshed after each fill (the disagreement sort)
    assert env.client.post(f"/api/frames/{fid}/reopen", headers=a).status_code == 200
    env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                   headers={**a, "If-Match": str(v2)})
    assert lifting.wait_idle(scene["id"], timeout=10, include_fill=True)
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement", headers=a).json()
    # the only annotated frame: no independent view (issue 23), its self-agreement is stored
    assert fl[0]["id"] == fid and fl[0]["agreement"] is None
    assert fl[0]["self_agreement"] == pytest.approx(1.0)
    assert st["included_versions"] == {str(fid): v2} and not st["pending_fill"]
    assert st["filled_versions"] == {str(fid): v2}
    assert st["labels_source"] == "filled"
    # the one annotated frame votes road everywhere: every labelled point is road, and fill
    # reached beyond the points the frame sees
    assert set(st["class_histogram"]) == {"1"} and n_seen < st["class_histogram"]["1"] <= 400


def test_review_reject_goes_back_to_annotator_first(world):
    env, hdr, scene, _ = world
    sid = scene["id"]
    fid = _lease(env, hdr, scene, "annotator")
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=mask_png(6),
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 200
    # reviewing a frame that is not submitted is refused
    other = _lease(env, hdr, scene, "annotator2")
    v = r.json()["version"]
    r = env.client.post(f"/api/frames/{other}/review", json={"decision": "accept", "version": v},
                        headers=hdr["reviewer"])
    assert r.status_code == 409
    r = env.client.post(f"/api/frames/{fid}/review",
                        json={"decision": "reject", "comment": "roof missing", "version": v},
                        headers=hdr["reviewer"])
    assert r.status_code == 200 and r.json()["state"] == "rejected"
    # annotator2 (who already holds another frame) never gets it; annotator gets it back first
    env.client.post(f"/api/frames/{other}/release", headers=hdr["annotator2"])
    seen = set()
    while True:
        r = env.client.post(f"/api/scenes/{sid}/next", headers=hdr["annotator2"])
        if r.status_code == 204:
            break
        seen.add(r.json()["id"])
        env.client.put(f"/api/frames/{r.json()['id']}/mask?kind=submitted", content=mask_png(6),
                       headers={**hdr["annotator2"], "If-Match": "none"})
    assert fid not in seen
    back = env.client.post(f"/api/scenes/{sid}/next", headers=hdr["annotator"]).json()
    assert back["id"] == fid and back["state"] == "rejected"
    items = env.client.get(f"/api/scenes/{sid}/review-items", headers=hdr["annotator"]).json()
    assert [i["comments"][0]["text"] for i in items] == ["[reject] roof missing"]
    assert env.client.get(f"/api/scenes/{sid}/review-items", headers=hdr["annotator2"]).json() == []
    # the annotator fixes it, the reviewer accepts
    cur = back["current_version"]
    v = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=mask_png(8),
                       headers={**hdr["annotator"], "If-Match": str(cur)}).json()["version"]
    r = env.client.post(f"/api/frames/{fid}/review", json={"decision": "accept", "version": v},
                        headers=hdr["reviewer"])
    assert r.json()["state"] == "accepted"


def test_review_items_pixel_points_threads(world):
    env, hdr, scene, frames = world
    sid, fid = scene["id"], frames[1]["id"]
    rv = hdr["reviewer"]
    r = env.client.post(f"/api/scenes/{sid}/review-items",
                        json={"frame_id": fid, "pixel": [10, 20], "comment": "check this car"},
                        headers=rv)
    assert r.status_code == 201 and r.json()["pixel"] == [10, 20]
    rid = r.json()["id"]
    r = env.client.post(f"/api/scenes/{sid}/review-items",
                        json={"point_ids": [5, 3, 5, 399], "comment": "wrong class"}, headers=rv)
    assert r.status_code == 201 and r.json()["point_ids"] == [3, 5, 399]
    for bad in ({"frame_id": fid, "pixel": [W, 0], "comment": "x"},
                {"point_ids": [400], "comment": "x"}, {"comment": "x"},
                {"frame_id": 999999, "comment": "x"}):
        r = env.client.post(f"/api/scenes/{sid}/review-items", json=bad, headers=rv)
        assert r.status_code in (404, 422), (bad, r.text)
    r = env.client.post(f"/api/review-items/{rid}/comments", json={"text": "agreed"},
                        headers=hdr["admin"])
    assert [c["text"] for c in r.json()["comments"]] == ["check this car", "agreed"]
    r = env.client.patch(f"/api/review-items/{rid}", json={"status": "resolved"}, headers=rv)
    assert r.json()["status"] == "resolved" and r.json()["resolved_at"]
    open_items = env.client.get(f"/api/scenes/{sid}/review-items?status=open", headers=rv).json()
    assert [i["n_points"] for i in open_items] == [3]
    # the 3D viewer's callback files an item the same way
    from app.review.service import make_viewer_callback

    with env.app.state.ctx.sessions() as s:
        from app.users.service import get_by_name

        reviewer = get_by_name(session=s, username="reviewer")
    new_id = make_viewer_callback(env.app.state.ctx)(sid, np.array([1, 2]), "from 3D", reviewer)
    items = env.client.get(f"/api/scenes/{sid}/review-items", headers=rv).json()
    assert items[-1]["id"] == new_id and items[-1]["point_ids"] == [1, 2]


def test_agreement_render_and_disagreement(world):
    env, hdr, scene, frames = world
    fid = _lease(env, hdr, scene)
    m = np.full((H, W), 6, np.uint8)
    env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                   headers={**hdr["annotator"], "If-Match": "none"})
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=10)
    r = env.client.get(f"/api/frames/{fid}/agreement", headers=hdr["reviewer"])
    assert r.status_code == 200, r.text
    # the frame's own votes are all grass: rendering them back agrees everywhere it covers;
    # but no other frame voted, so there is no independent score (issue 23)
    assert r.json()["self_agreement"] == pytest.approx(1.0)
    assert r.json()["agreement"] is None and r.json()["status"] == "not_enough_independent_views"
    img = env.client.get(f"/api/frames/{fid}/disagreement", headers=hdr["reviewer"])
    assert img.status_code == 200 and img.content.startswith(b"\x89PNG")
    import io

    from PIL import Image

    # a palette PNG with per-entry alpha: decoded, an RGBA overlay of the frame's size
    rgba = np.asarray(Image.open(io.BytesIO(img.content)).convert("RGBA"))
    assert rgba.shape == (H, W, 4) and set(np.unique(rgba[..., 3])) <= {0, 96, 230}
    # the labels' rendering the review computed serves /render: the pixels a fresh render gives
    from app.review import service as review
    from app.scenes.models import Frame, Scene

    ren = env.client.get(f"/api/frames/{fid}/render", headers=hdr["reviewer"])
    assert ren.status_code == 200
    with env.app.state.ctx.sessions() as s:
        fr = s.get(Frame, fid)
        fresh = review.rendered(env.app.state.ctx, s.get(Scene, fr.scene_id), fr)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(ren.content))), fresh) and (fresh > 0).any()
    pre = env.client.get(f"/api/frames/{fid}/prefill", headers=hdr["annotator"])

    arr = np.asarray(Image.open(io.BytesIO(pre.content)))
    assert arr.shape == (H, W) and set(np.unique(arr)) <= {0, 6} and (arr == 6).any()
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement",
                        headers=hdr["reviewer"]).json()
    assert fl[0]["id"] == fid and fl[0]["self_agreement"] == pytest.approx(1.0)


# ---- jobs -----------------------------------------------------------------------------------
@pytest.mark.job_processes  # the resumed import runs in a spawned worker process
def test_job_interrupted_by_restart_is_reported_and_resumable(env):
    adm = env.bearer("admin")
    src = env.import_root / "tiny_src"
    from tests.app.conftest import write_tiny_workspace

    write_tiny_workspace(src)
    from app.jobs import service as jobs
    from app.scenes import service as scenes

    # what a server that died mid-import leaves behind: a running job, an importing scene
    with env.app.state.ctx.sessions() as s:
        scene = scenes.create_scene(session=s, settings=env.settings, name="tiny", source=src)
        job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                          params={"source": str(src), "cloud": None, "depth_maps": None})
        job.status = "running"
        job.heartbeat_at = None  # its runner never beat: it died before
        s.commit()
        jid = job.id
    env.restart()
    adm = env.bearer("admin")
    j = env.client.get(f"/api/jobs/{jid}", headers=adm).json()
    assert j["status"] == "interrupted" and "resume" in j["message"]
    r = env.client.post(f"/api/jobs/{jid}/resume", headers=adm)
    assert r.status_code == 200
    env.app.state.ctx.jobs.wait(jid)
    j = env.client.get(f"/api/jobs/{jid}", headers=adm).json()
    assert j["status"] == "done" and j["attempts"] == 1 and j["result"]["frames"] == 4
    assert env.client.get("/api/scenes", headers=adm).json()[0]["status"] == "ready"
    assert env.client.post(f"/api/jobs/{jid}/resume", headers=adm).status_code == 409



def test_a_job_not_yet_claimed_is_not_swept_as_lost(env):
    """A runner's periodic sweep that falls between a job's creation and its runner's
    submit() (CI: an import 'lost its runner' and was interrupted) must leave it alone; the
    same job, unclaimed for longer than the stale limit, is swept."""
    from datetime import timedelta

    from app.db import utcnow
    from app.jobs import service as jobs
    from app.jobs.models import Job

    with env.app.state.ctx.sessions() as s:
        job = jobs.create(session=s, kind="selection", scene_id=None, user_id=None, params={})
        jid = job.id
        assert jobs.mark_interrupted(session=s, stale_s=15.0, alive_owner="another:1:x") == []
        assert s.get(Job, jid).status == "queued"
        s.get(Job, jid).heartbeat_at = utcnow() - timedelta(seconds=60)
        s.commit()
        assert jobs.mark_interrupted(session=s, stale_s=15.0, alive_owner="another:1:x") == [jid]

def test_selection_job_and_cancel(world):
    env, hdr, scene, _ = world
    adm = hdr["admin"]
    r = env.client.post(f"/api/scenes/{scene['id']}/selection",
                        json={"cell": 10, "mode": "greedy", "target_coverage": 0.99}, headers=adm)
    assert r.status_code == 202
    env.app.state.ctx.jobs.wait(r.json()["id"])
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()
    assert j["status"] == "done", j
    sel = env.client.get(f"/api/scenes/{scene['id']}/selection", headers=adm).json()
    from tests.app.conftest import make_tiny_scene

    vis = make_tiny_scene().visibility
    seen = np.unique(np.concatenate([vis.frame(i)[0] for i in sel["frames"]]))
    assert sel["coverage"] == pytest.approx(len(seen) / 400) and len(sel["cameras"]) == 4
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames", headers=adm).json()
    assert sorted(f["index"] for f in fl if f["selected"]) == sorted(sel["frames"])
    sc = env.client.get(f"/api/scenes/{scene['id']}", headers=adm).json()
    assert sc["n_selected"] == len(sel["frames"]) and sc["coverage"] == pytest.approx(sel["coverage"])
    # cell "auto" searches the method's 23-28 m range (greedy only; a 422 otherwise)
    bad = env.client.post(f"/api/scenes/{scene['id']}/selection", json={"cell": "auto"}, headers=adm)
    assert bad.status_code == 422 and "greedy" in bad.text
    r = env.client.post(f"/api/scenes/{scene['id']}/selection",
                        json={"cell": "auto", "mode": "greedy", "target_coverage": 0.9}, headers=adm)
    assert r.status_code == 202
    env.app.state.ctx.jobs.wait(r.json()["id"])
    assert env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()["status"] == "done"
    sel = env.client.get(f"/api/scenes/{scene['id']}/selection", headers=adm).json()
    assert 23.0 <= sel["cell"] <= 28.0 and len(sel["auto_cells"]) == 11
    # a finished job cannot be cancelled; a queued one can
    assert env.client.post(f"/api/jobs/{j['id']}/cancel", headers=adm).status_code == 409
    from app.jobs import service as jobs

    with env.app.state.ctx.sessions() as s:
        q = jobs.create(session=s, kind="selection", scene_id=scene["id"], user_id=None, params={})
    r = env.client.post(f"/api/jobs/{q.id}/cancel", headers=adm)
    assert r.json()["status"] == "cancelled"
    env.app.state.ctx.jobs.submit(q.id)  # a cancelled job never starts
    env.app.state.ctx.jobs.wait(q.id)
    assert env.client.get(f"/api/jobs/{q.id}", headers=adm).json()["status"] == "cancelled"


def test_voxelize_without_labels_fails_with_a_clear_message(world):
    env, hdr, scene, _ = world
    r = env.client.post(f"/api/scenes/{scene['id']}/voxelize", json={"voxel_size": 0.5},
                        headers=hdr["admin"])
    env.app.state.ctx.jobs.wait(r.json()["id"])
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=hdr["admin"]).json()
    assert j["status"] == "failed" and "no lifted labels" in j["message"]
    assert env.client.get(f"/api/jobs/{j['id']}/archive", headers=hdr["admin"]).status_code == 409


def test_eval_job_metrics_and_viewer_hooks(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    fid = _lease(env, hdr, scene)
    m = np.full((H, W), 6, np.uint8)
    v = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr["annotator"], "If-Match": "none"}).json()["version"]
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=10)
    assert env.client.get(f"/api/scenes/{sid}/metrics", headers=hdr["admin"]).status_code == 404
    r = env.client.post(f"/api/scenes/{sid}/eval", json={}, headers=hdr["admin"])
    env.app.state.ctx.jobs.wait(r.json()["id"])
    met = env.client.get(f"/api/scenes/{sid}/metrics", headers=hdr["reviewer"]).json()
    assert met["n_frames"] == 1 and met["frames"][0]["frame_id"] == fid
    # one annotated frame: no independent score (issue 23); the self-agreement is kept apart
    assert met["agreement"] is None and met["self_agreement"] == pytest.approx(1.0)
    assert "scene_grid" not in met  # no grid, no truth grid yet
    # with a densified grid and a truth grid in the workspace the eval job scores the grid too
    from occufly.grid import SceneGrid
    from occufly.workspace import Workspace

    TRUTH_GRID_RELPATH = Workspace(".").truth_grid_path.relative_to(".")

    ws = env.settings.workspaces_dir / "tiny"
    truth = np.zeros((4, 4, 4), np.uint8)
    truth[:, :, 0] = 6  # 16 grass voxels
    truth[1, 1, 1:3] = 13  # 2 vehicle voxels
    pred = truth.copy()
    pred[0, :, 0] = 0  # 4 grass voxels missed
    pred[2, 2, 1] = 13  # 1 vehicle voxel too many
    SceneGrid(pred, np.array([100.0, 200.0, 10.0]), 0.5).save(Workspace(ws).grid_path())
    SceneGrid(truth, np.array([100.0, 200.0, 10.0]), 0.5).save(ws / TRUTH_GRID_RELPATH)
    r = env.client.post(f"/api/scenes/{sid}/eval", json={}, headers=hdr["admin"])
    env.app.state.ctx.jobs.wait(r.json()["id"])
    met = env.client.get(f"/api/scenes/{sid}/metrics", headers=hdr["reviewer"]).json()
    g = met["scene_grid"]
    assert g["completion_iou"] == pytest.approx(14 / 19)  # TP 14, FP 1, FN 4
    assert g["per_class_iou"]["grass"] == pytest.approx(12 / 16)
    assert g["per_class_iou"]["vehicle"] == pytest.approx(2 / 3)
    assert g["miou"] == pytest.approx((12 / 16 + 2 / 3) / 2)
    assert met["self_agreement"] == pytest.approx(1.0)
    # a truth grid that does not fit (other voxel size): the job still reports the agreement,
    # and the grid section says what is wrong
    SceneGrid(truth, np.array([100.0, 200.0, 10.0]), 0.25).save(ws / TRUTH_GRID_RELPATH)
    r = env.client.post(f"/api/scenes/{sid}/eval", json={}, headers=hdr["admin"])
    env.app.state.ctx.jobs.wait(r.json()["id"])
    assert env.client.get(f"/api/jobs/{r.json()['id']}", headers=hdr["admin"]).json()["status"] == "done"
    met = env.client.get(f"/api/scenes/{sid}/metrics", headers=hdr["reviewer"]).json()
    assert met["self_agreement"] == pytest.approx(1.0) and "voxel sizes" in met["scene_grid"]["error"]
    (ws / TRUTH_GRID_RELPATH).write_bytes(b"not an npz")
    r = env.client.post(f"/api/scenes/{sid}/eval", json={}, headers=hdr["admin"])
    env.app.state.ctx.jobs.wait(r.json()["id"])
    met = env.client.get(f"/api/scenes/{sid}/metrics", headers=hdr["reviewer"]).json()
    assert "not a readable" in met["scene_grid"]["error"] and met["n_frames"] == 1
    # hooks handed to the 3D viewer
    from app.main import authorize_viewer, viewer_callbacks

    hooks = viewer_callbacks(env.app.state.ctx)
    assert hooks["scenes"]() == {str(sid): ("tiny", str(env.settings.workspaces_dir / "tiny"))}
    index = next(f["index"] for f in frames if f["id"] == fid)
    states = hooks["frame_states"](str(sid))
    assert states[index] == "annotated" and set(states.values()) == {"annotated", "selected"}
    assert np.array_equal(hooks["frame_mask"](str(sid), index), m)
    assert hooks["frame_mask"](str(sid), (index + 1) % 4) is None

    class Conn:
        def __init__(self, h):
            self.headers = {k.lower(): v for k, v in h.items()}
            self.cookies = {}

    auth = authorize_viewer(env.app.state.ctx)
    assert [auth(Conn(hdr[r])) for r in ("admin", "reviewer", "annotator")] == [True, True, False]
    assert auth(Conn({})) is False
    assert hooks["identify"](Conn(hdr["reviewer"])).username == "reviewer"
    assert v > 0


def test_export_download_is_the_archive_and_the_legacy_tar_stream_is_gone(world):
    """Issue 28 item 7: an export is downloaded as a compressed archive with its length and
    without the exporter's bookkeeping; GET /api/jobs/{jid}/download (an uncompressed tar
    stream with .occufly_export entries and no length) no longer exists."""
    import io
    import tarfile

    env, hdr, scene, _ = world
    from app.jobs.models import Job

    out = env.settings.exports_dir / "job_x"
    (out / "OccuFly_Dataset" / "scene_01").mkdir(parents=True)
    (out / "OccuFly_Dataset" / "scene_01" / "a.bin").write_bytes(b"\x01\x02" * 1000)
    (out / ".occufly_export").mkdir()
    (out / ".occufly_export" / "state.json").write_text("{}")
    with env.app.state.ctx.sessions() as s:
        job = Job(kind="export", scene_id=scene["id"], status="done", params={},
                  result={"output": str(out)}, progress=1.0, message="done", log="")
        s.add(job)
        s.commit()
        jid = job.id
    assert env.client.get(f"/api/jobs/{jid}/download", headers=hdr["admin"]).status_code == 404
    assert "/api/jobs/{jid}/download" not in env.client.get("/openapi.json").json()["paths"]
    r = env.client.get(f"/api/jobs/{jid}/archive?format=tar.gz", headers=hdr["admin"])
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
    with tarfile.open(fileobj=io.BytesIO(r.content), mode="r:gz") as tar:
        names = tar.getnames()
        member = tar.extractfile("job_x/OccuFly_Dataset/scene_01/a.bin").read()
    assert member == b"\x01\x02" * 1000
    assert not [n for n in names if ".occufly" in n]
    assert env.client.get(f"/api/jobs/{jid}/archive", headers=hdr["reviewer"]).status_code == 403
    # a job whose recorded output points outside the exports folder is never served
    with env.app.state.ctx.sessions() as s:
        s.get(Job, jid).result = {"output": str(env.import_root)}
        s.commit()
    assert env.client.get(f"/api/jobs/{jid}/archive", headers=hdr["admin"]).status_code == 404


def test_frontend_and_viewer_are_mounted(env):
    r = env.client.get("/")
    assert r.status_code == 200 and "<html" in r.text.lower()
    assert env.client.get("/viewer/").status_code == 401
    assert env.client.get("/viewer/", headers=env.bearer("annotator")).status_code == 403


def test_votes_are_not_delayed_by_a_running_fill(world, monkeypatch):
    import time

    from occufly.lifting import knn as lifting  # the fill is looked up on occufly.lifting.knn

    env, hdr, scene, _ = world
    sid = scene["id"]
    release = threading.Event()
    real = lifting.fill_and_denoise

    def slow_fill(*a, **k):
        release.wait(20)
        return real(*a, **k)

    monkeypatch.setattr(lifting, "fill_and_denoise", slow_fill)
    f1 = _lease(env, hdr, scene, "annotator")
    f2 = _lease(env, hdr, scene, "annotator2")
    v1 = env.client.put(f"/api/frames/{f1}/mask?kind=submitted", content=mask_png(6),
                        headers={**hdr["annotator"], "If-Match": "none"}).json()["version"]
    lm = env.app.state.ctx.lifting
    end = time.monotonic() + 10
    while not lm.status(sid)["fill_running"] and time.monotonic() < end:
        time.sleep(0.02)
    assert lm.status(sid)["fill_running"]
    t0 = time.monotonic()
    v2 = env.client.put(f"/api/frames/{f2}/mask?kind=submitted", content=mask_png(8),
                        headers={**hdr["annotator2"], "If-Match": "none"}).json()["version"]
    assert lm.wait_idle(sid, timeout=5)  # votes only
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=hdr["admin"]).json()
    assert st["included_versions"] == {str(f1): v1, str(f2): v2}
    assert st["fill_running"] and time.monotonic() - t0 < 5
    release.set()
    assert lm.wait_idle(sid, timeout=30, include_fill=True)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=hdr["admin"]).json()
    assert st["filled_versions"] == {str(f1): v1, str(f2): v2}  # a second, debounced fill
    # only submitted / reviewed frames get an agreement stored by the fill (drafts never vote)
    frames = env.client.get(f"/api/scenes/{sid}/frames", headers=hdr["admin"]).json()
    assert all(f["agreement"] is None for f in frames if f["id"] not in (f1, f2))


def test_labels_status_histogram_is_counted_once_per_labels(world, monkeypatch):
    """Every open editor polls labels/status; the class histogram (a pass over every point's
    label, or before the first fill the vote majority of every point) is counted once per
    labels file and counted versions, and again after the next fill changed them."""
    from app.annotations import service as ann

    env, hdr, scene, _frames = world
    a = hdr["annotator"]
    fid = _lease(env, hdr, scene)
    env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=mask_png(6),
                   headers={**a, "If-Match": "none"})
    lifting = env.app.state.ctx.lifting
    assert lifting.wait_idle(scene["id"], timeout=30, include_fill=True)
    calls = []
    real = ann.load_labels

    def counted(ws):  # noqa: ANN001, ANN202 - the histogram's reads only (fill hooks read too)
        f = sys._getframe(1)
        if f.f_code.co_name == "_labels_histogram":
            calls.append(ws)
        return real(ws)

    monkeypatch.setattr(ann, "load_labels", counted)
    url = f"/api/scenes/{scene['id']}/labels/status"
    first = env.client.get(url, headers=a).json()
    assert first["labels_source"] == "filled" and first["class_histogram"].get("6")
    for _ in range(5):
        assert env.client.get(url, headers=a).json() == first
    assert len(calls) <= 1  # (0: an earlier request of this process counted these labels)
    # the next fill: counted again, and the histogram is the new labels'
    fid2 = _lease(env, hdr, scene, "annotator2")
    env.client.put(f"/api/frames/{fid2}/mask?kind=submitted", content=mask_png(8),
                   headers={**hdr["annotator2"], "If-Match": "none"})
    assert lifting.wait_idle(scene["id"], timeout=30, include_fill=True)
    n = len(calls)
    second = env.client.get(url, headers=a).json()
    assert len(calls) == n + 1
    assert second["filled_versions"] != first["filled_versions"]
    assert second["class_histogram"] != first["class_histogram"]
