"""Every route of the OpenAPI schema x {no token, annotator, reviewer, admin, annotator of another
scene} against the access table that lives next to the routes (``ACCESS`` in each routes module,
merged by :func:`app.access.table`). A route without an entry fails here.

Refused callers must get exactly 401 (no token) or 403; allowed ones anything but 401/403 and
never a 5xx. Every call carries a fresh token, so destructive routes (logout, password change,
session revocation) are walked like the rest; the fixture's objects are reset before each call.
"""

from __future__ import annotations

import json
import os

import pytest
from sqlalchemy import select, update

from app.access import allowed, table
from tests.app.conftest import PASSWORD, mask_png

IDENTITIES = ("anonymous", "annotator", "reviewer", "admin", "outsider")


@pytest.fixture
def walk_world(env):
    from app.db import utcnow
    from app.users import service as users

    hdr = {r: env.bearer(r) for r in ("admin", "reviewer", "annotator")}
    with env.app.state.ctx.sessions() as s:
        users.create_user(session=s, username="outsider", password=PASSWORD, role="annotator")
        victim = users.create_user(session=s, username="victim", password=PASSWORD,
                                   role="annotator")
        victim_id = victim.id
    scene = env.import_tiny(hdr["admin"], members=("annotator", "reviewer", "annotator2"))
    env.select_all(scene["id"])
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr["annotator"]).json()["id"]
    vid = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(6),
                         headers={**hdr["annotator"], "If-Match": "none"}).json()["version"]
    rid = env.client.post(f"/api/scenes/{scene['id']}/review-items",
                          json={"frame_id": fid, "comment": "look"}, headers=hdr["reviewer"]).json()["id"]
    with env.app.state.ctx.sessions() as s:
        from app.jobs.models import Job
        from app.users.models import AuthToken, User

        jid = s.scalar(select(Job.id).where(Job.scene_id == scene["id"]).order_by(Job.id))
        ids = dict(s.execute(select(User.username, User.id)).all())
        tid = s.scalar(select(AuthToken.id).order_by(AuthToken.id))
    return dict(env=env, sid=scene["id"], fid=fid, vid=vid, rid=rid, jid=jid, ids=ids,
                victim=victim_id, tid=tid, utcnow=utcnow)


def _request_for(method: str, path: str, w: dict) -> dict:
    """Path parameters filled with the fixture's objects, and a plausible body."""
    p = (path.replace("{sid}", str(w["sid"])).replace("{fid}", str(w["fid"]))
         .replace("{vid}", str(w["vid"])).replace("{rid}", str(w["rid"]))
         .replace("{jid}", str(w["jid"])).replace("{tid}", str(w["tid"])))
    victim = w["victim"]
    if "{uid}" in p:
        # member routes take a scene member (annotator2), user routes the victim account
        p = p.replace("{uid}", str(w["ids"]["annotator2"] if "/members/" in p else victim))
    key = f"{method} {path}"
    members = [w["ids"][n] for n in ("annotator", "reviewer", "annotator2")]
    bodies = {
        "POST /api/auth/login": {"username": "victim", "password": PASSWORD},
        "POST /api/auth/password": {"current": PASSWORD, "new": PASSWORD},
        "POST /api/users": {"username": "newbie", "password": "longenough1", "role": "annotator"},
        "PATCH /api/users/{uid}": {"active": True},
        "POST /api/users/{uid}/password": {"password": PASSWORD},
        "POST /api/scenes/import": {"name": "other", "source": "missing"},
        "POST /api/scenes/{sid}/selection": {"cell": 25},
        "PUT /api/scenes/{sid}/members": {"user_ids": members},
        "POST /api/scenes/{sid}/members": {"user_ids": members},
        "POST /api/frames/{fid}/review": {"decision": "accept", "version": w["vid"]},
        "POST /api/frames/{fid}/review/undo": {"decision": "accept", "version": w["vid"]},
        "POST /api/scenes/{sid}/review-items": {"frame_id": w["fid"], "comment": "x"},
        "POST /api/review-items/{rid}/comments": {"text": "x"},
        "PATCH /api/review-items/{rid}": {"status": "open"},
        "POST /api/scenes/{sid}/export": {"layout": "occufly"},
        "POST /api/scenes/{sid}/eval": {},
        "POST /api/scenes/{sid}/voxelize": {"voxel_size": 0.5},
    }
    req: dict = {"method": method, "url": p, "headers": {}}
    if key == "PUT /api/frames/{fid}/mask":
        req["content"] = mask_png(8)
        req["headers"] = {"If-Match": "none", "Content-Type": "image/png"}
    elif key in bodies:
        req["json"] = bodies[key]
    if key == "POST /api/frames/{fid}/grabcut":
        req["json"] = {"x": 0, "y": 0, "width": 8, "height": 8, "class_id": 6}
    if key == "POST /api/frames/{fid}/scissors":
        req["json"] = {"start": [2, 2], "end": [30, 20]}
    return req


def _reset(w: dict) -> None:
    """Put back what an allowed call may have changed: the lease, the memberships."""
    from datetime import timedelta

    from app.scenes.models import Frame
    from app.scenes.service import set_members

    env = w["env"]
    with env.app.state.ctx.sessions() as s:
        s.execute(update(Frame).where(Frame.id == w["fid"]).values(
            assignee_id=w["ids"]["annotator"], state="in_progress",
            lease_expires_at=w["utcnow"]() + timedelta(hours=1)))
        s.commit()
        from app.scenes.models import Scene

        set_members(session=s, scene=s.get(Scene, w["sid"]),
                    user_ids=[w["ids"][n] for n in ("annotator", "reviewer", "annotator2")],
                    replace=True)


def _headers_for(env, who: str) -> dict:
    if who == "anonymous":
        return {}
    from app.users import service as users

    name = {"outsider": "outsider"}.get(who, who)
    with env.app.state.ctx.sessions() as s:
        token = users.issue_token(session=s, settings=env.settings,
                                  user=users.get_by_name(session=s, username=name))
    return {"Authorization": f"Bearer {token}"}


def test_every_route_against_the_access_table(walk_world):
    w = walk_world
    env = w["env"]
    spec = env.client.get("/openapi.json").json()
    ops = [f"{m.upper()} {p}" for p, item in spec["paths"].items() for m in item
           if m in ("get", "post", "put", "patch", "delete")]
    access = table()
    assert sorted(set(ops) - set(access)) == [], "routes without an entry in an ACCESS table"
    assert sorted(set(access) - set(ops)) == [], "ACCESS entries for routes that do not exist"
    problems: list[str] = []
    checks = 0
    for op in sorted(ops):
        method, path = op.split(" ", 1)
        level = access[op]
        for who in IDENTITIES:
            _reset(w)
            req = _request_for(method, path, w)
            req["headers"] = {**req["headers"], **_headers_for(env, who)}
            r = env.client.request(**req)
            env.client.cookies.clear()  # the login sets one; every identity is header-only
            checks += 1
            role = {"anonymous": None, "outsider": "annotator"}.get(who, who)
            ok = allowed(level, role, member=who != "outsider")
            if r.status_code >= 500:
                problems.append(f"{who:9s} {op}: {r.status_code} {r.text[:200]}")
            elif ok and r.status_code in (401, 403):
                problems.append(f"{who:9s} {op} ({level}): refused {r.status_code} {r.text[:200]}")
            elif not ok and r.status_code != (401 if role is None else 403):
                problems.append(f"{who:9s} {op} ({level}): expected "
                                f"{401 if role is None else 403}, got {r.status_code} {r.text[:200]}")
    from app.jobs.models import Job

    with env.app.state.ctx.sessions() as s:  # let the jobs the admin started finish
        for j in s.scalars(select(Job.id)):
            env.app.state.ctx.jobs.wait(j, timeout=60)
    assert problems == [], "\n".join(problems)
    assert checks == len(ops) * len(IDENTITIES) and len(ops) >= 50
    out = os.environ.get("OCCUFLY_SECURITY_COUNTS")
    if out:
        with open(out, "a") as f:
            f.write(json.dumps({"backend": env.backend, "routes": len(ops),
                                "identities": len(IDENTITIES), "checks": checks}) + "\n")


def test_annotators_see_only_their_scenes(env):
    """Membership: an annotator of another scene lists nothing and reads no image or label."""
    hdr = {r: env.bearer(r) for r in ("admin", "annotator", "annotator2")}
    scene = env.import_tiny(hdr["admin"], members=("annotator",))
    sid = scene["id"]
    fid = env.client.get(f"/api/scenes/{sid}/frames", headers=hdr["admin"]).json()[0]["id"]
    assert [s["id"] for s in env.client.get("/api/scenes", headers=hdr["annotator"]).json()] == [sid]
    assert env.client.get("/api/scenes", headers=hdr["annotator2"]).json() == []
    for url in (f"/api/scenes/{sid}", f"/api/frames/{fid}/image?size=thumb",
                f"/api/scenes/{sid}/labels/status", f"/api/frames/{fid}/prefill"):
        assert env.client.get(url, headers=hdr["annotator2"]).status_code == 403, url
    assert env.client.get(f"/api/frames/{fid}/image?size=thumb",
                          headers=hdr["annotator"]).status_code == 200
    # the admin assigns, and takes away
    uid = next(u["id"] for u in env.client.get("/api/users", headers=hdr["admin"]).json()
               if u["username"] == "annotator2")
    r = env.client.post(f"/api/scenes/{sid}/members", json={"user_ids": [uid]}, headers=hdr["admin"])
    assert sorted(m["username"] for m in r.json()) == ["annotator", "annotator2"]
    assert env.client.get(f"/api/frames/{fid}/image?size=thumb",
                          headers=hdr["annotator2"]).status_code == 200
    assert env.client.delete(f"/api/scenes/{sid}/members/{uid}", headers=hdr["admin"]).status_code == 204
    assert env.client.get(f"/api/scenes/{sid}", headers=hdr["annotator2"]).status_code == 403
    r = env.client.put(f"/api/scenes/{sid}/members", json={"user_ids": [1]}, headers=hdr["admin"])
    assert r.status_code == 422 and "admins" in r.json()["detail"]


def test_viewer_is_scoped_to_member_scenes(env):
    from starlette.requests import Request

    from app.main import authorize_viewer
    from app.users import service as users

    adm = env.bearer("admin")
    scene = env.import_tiny(adm, members=("annotator",))  # the reviewer is not a member
    auth = authorize_viewer(env.app.state.ctx)

    def conn(who: str, query: str) -> Request:
        with env.app.state.ctx.sessions() as s:
            tok = users.issue_token(session=s, settings=env.settings,
                                    user=users.get_by_name(session=s, username=who))
        return Request({"type": "http", "method": "GET", "path": "/viewer/", "query_string":
                        query.encode(), "headers": [(b"authorization", f"Bearer {tok}".encode())]})

    q = f"scene={scene['id']}"
    assert auth(conn("admin", q)) and not auth(conn("reviewer", q))
    assert not auth(conn("annotator", q))  # annotators never open the 3D viewer
    env.add_members(scene["id"], ("reviewer",), adm)
    assert auth(conn("reviewer", q)) and not auth(conn("reviewer", "scene=99999"))
