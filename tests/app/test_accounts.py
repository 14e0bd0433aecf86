"""Accounts a team can run (issue 14): own password, admin reset, deactivation revoking every
session at once, session lists, and the audit log; on SQLite and PostgreSQL."""

from __future__ import annotations

from tests.app.conftest import PASSWORD, mask_png


def _login(env, name: str, password: str = PASSWORD, agent: str = "pytest") -> dict:
    r = env.client.post("/api/auth/login", json={"username": name, "password": password},
                        headers={"User-Agent": agent})
    env.client.cookies.clear()
    assert r.status_code == 200, r.text
    return {"Authorization": f"Bearer {r.json()['token']}"}


def _uid(env, adm: dict, name: str) -> int:
    return next(u["id"] for u in env.client.get("/api/users", headers=adm).json()
                if u["username"] == name)


def test_password_change_reset_deactivate_and_sessions(env):
    c = env.client
    adm = _login(env, "admin")
    s1, s2 = _login(env, "annotator", agent="laptop"), _login(env, "annotator", agent="tablet")
    mine = c.get("/api/auth/sessions", headers=s1).json()
    assert [(x["user_agent"], x["current"]) for x in mine] == [("laptop", True), ("tablet", False)]
    assert all(x["client_ip"] == "testclient" for x in mine)
    # own change: needs the current password, ends the other session, keeps this one
    r = c.post("/api/auth/password", json={"current": "wrong-one!", "new": "a-new-password"}, headers=s1)
    assert r.status_code == 403
    r = c.post("/api/auth/password", json={"current": PASSWORD, "new": "short"}, headers=s1)
    assert r.status_code == 422
    r = c.post("/api/auth/password", json={"current": PASSWORD, "new": "a-new-password"}, headers=s1)
    assert r.status_code == 200 and r.json()["count"] == 1
    assert c.get("/api/auth/me", headers=s1).status_code == 200
    assert c.get("/api/auth/me", headers=s2).status_code == 401
    assert c.post("/api/auth/login", json={"username": "annotator", "password": PASSWORD}).status_code == 401
    s3 = _login(env, "annotator", "a-new-password")
    # revoke one of one's own sessions
    sid3 = next(x["id"] for x in c.get("/api/auth/sessions", headers=s1).json() if not x["current"])
    assert c.delete(f"/api/auth/sessions/{sid3}", headers=s1).status_code == 204
    assert c.get("/api/auth/me", headers=s3).status_code == 401
    # the admin resets: every session of the user ends
    uid = _uid(env, adm, "annotator")
    assert len(c.get(f"/api/users/{uid}/sessions", headers=adm).json()) == 1
    r = c.post(f"/api/users/{uid}/password", json={"password": "reset-by-admin"}, headers=adm)
    assert r.status_code == 200 and r.json()["count"] == 1
    assert c.get("/api/auth/me", headers=s1).status_code == 401
    s4, s5 = _login(env, "annotator", "reset-by-admin"), _login(env, "annotator", "reset-by-admin")
    # deactivation revokes every session at once and refuses new logins
    r = c.patch(f"/api/users/{uid}", json={"active": False}, headers=adm)
    assert r.status_code == 200 and r.json()["active"] is False
    assert c.get("/api/auth/me", headers=s4).status_code == 401
    assert c.get("/api/auth/me", headers=s5).status_code == 401
    assert c.get(f"/api/users/{uid}/sessions", headers=adm).json() == []
    assert c.post("/api/auth/login", json={"username": "annotator",
                                           "password": "reset-by-admin"}).status_code == 401
    assert c.patch(f"/api/users/{uid}", json={"active": True}, headers=adm).json()["active"] is True
    s6 = _login(env, "annotator", "reset-by-admin")
    # role change; an admin cannot lock themself out
    assert c.patch(f"/api/users/{uid}", json={"role": "reviewer"}, headers=adm).json()["role"] == "reviewer"
    assert c.get("/api/auth/me", headers=s6).json()["role"] == "reviewer"
    assert c.patch(f"/api/users/{_uid(env, adm, 'admin')}", json={"active": False},
                   headers=adm).status_code == 409
    # admin ends all sessions of a user
    r = c.delete(f"/api/users/{uid}/sessions", headers=adm)
    assert r.status_code == 200 and r.json()["count"] == 1
    assert c.get("/api/auth/me", headers=s6).status_code == 401


def test_audit_log_records_who_did_what(env):
    c = env.client
    adm = env.bearer("admin")
    c.post("/api/auth/login", json={"username": "annotator", "password": "wrong-pass"})
    scene = env.import_tiny(adm)
    env.select_all(scene["id"])
    ann = env.bearer("annotator")
    rev = env.bearer("reviewer")
    fid = c.post(f"/api/scenes/{scene['id']}/next", headers=ann).json()["id"]
    v1 = c.put(f"/api/frames/{fid}/mask", content=mask_png(6),
               headers={**ann, "If-Match": "none"}).json()["version"]
    v2 = c.put(f"/api/frames/{fid}/mask?kind=submitted", content=mask_png(1),
               headers={**ann, "If-Match": str(v1)}).json()["version"]
    c.post(f"/api/frames/{fid}/review", json={"decision": "reject", "comment": "sky", "version": v2},
           headers=rev)
    c.post("/api/users", json={"username": "carol", "password": "longenough1", "role": "reviewer"},
           headers=adm)
    c.post(f"/api/scenes/{scene['id']}/export", json={}, headers=adm)
    events = c.get("/api/audit?limit=1000", headers=adm).json()
    seen = [(e["actor"], e["action"]) for e in reversed(events)]
    for expected in [("annotator", "login_failed"), ("admin", "import"), ("admin", "membership"),
                     ("annotator", "login"), ("annotator", "mask_save"),
                     ("annotator", "mask_submit"), ("reviewer", "review_reject"),
                     ("admin", "user_create"), ("admin", "export")]:
        assert expected in seen, (expected, seen)
    # filters: by action, by scene, paging newest first
    saves = c.get("/api/audit?action=mask_save,mask_submit", headers=adm).json()
    assert [e["action"] for e in saves] == ["mask_submit", "mask_save"]
    assert saves[1]["frame_id"] == fid and saves[1]["detail"]["version"] == v1
    assert {e["scene_id"] for e in c.get(f"/api/audit?scene_id={scene['id']}", headers=adm).json()} == {scene["id"]}
    page = c.get(f"/api/audit?limit=2&before_id={events[0]['id']}", headers=adm).json()
    assert [e["id"] for e in page] == [events[1]["id"], events[2]["id"]]
    assert c.get("/api/audit", headers=rev).status_code == 403
    # the export job's wait: no background work left behind
    jobs = c.get(f"/api/jobs?scene_id={scene['id']}", headers=adm).json()
    for j in jobs:
        env.app.state.ctx.jobs.wait(j["id"], timeout=60)
