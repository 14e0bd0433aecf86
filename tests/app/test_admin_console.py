"""Issue 28, "the admin's day": import roots named, the folder browser confined to them, the
zip upload of a project folder, deleting scenes and exports with what it frees, export
retention, storage per scene, the overview across scenes, names in the audit log (on
SQLite and PostgreSQL)."""

from __future__ import annotations

import io
import os
import stat
import zipfile
from datetime import timedelta

import numpy as np
import pytest

from tests.app.conftest import H, W, png, write_tiny_workspace


# ---- item 1: import roots, folder browser, upload ---------------------------------------------
def test_outside_the_roots_names_the_roots(env):
    adm = env.bearer("admin")
    r = env.client.post("/api/scenes/import", json={"name": "x", "source": "/etc"}, headers=adm)
    assert r.status_code == 403
    detail = r.json()["detail"]
    assert str(env.import_root) in detail and str(env.settings.data_dir / "uploads") in detail


def test_folder_browser_lists_inside_the_roots_only(env, tmp_path):
    adm = env.bearer("admin")
    root = env.import_root
    (root / "site_a" / "images").mkdir(parents=True)
    (root / "site_a" / "cameras.xml").write_text("<xml/>")
    (root / ".hidden").mkdir()
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("no")
    os.symlink(outside, root / "link_out")  # a symlink leading out of the root
    os.symlink(root / "site_a", root / "link_in")  # one staying inside
    r = env.client.get("/api/imports/browse", headers=adm)
    assert r.status_code == 200
    assert [e["path"] for e in r.json()["entries"]] == [str(root), str(env.settings.data_dir / "uploads")]
    r = env.client.get("/api/imports/browse", params={"path": str(root)}, headers=adm)
    assert r.status_code == 200, r.text
    names = [(e["name"], e["kind"]) for e in r.json()["entries"]]
    assert names == [("link_in", "dir"), ("site_a", "dir")]  # no hidden, nothing outside
    assert r.json()["parent"] is None  # a root: back to the list of roots
    r = env.client.get("/api/imports/browse", params={"path": str(root / "site_a")}, headers=adm)
    assert [(e["name"], e["kind"]) for e in r.json()["entries"]] == [("images", "dir"), ("cameras.xml", "file")]
    assert r.json()["parent"] == str(root.resolve())
    for bad in (str(outside), "/etc", str(root / "link_out"), "/"):
        r = env.client.get("/api/imports/browse", params={"path": bad}, headers=adm)
        assert r.status_code == 403, (bad, r.text)
        assert str(root) in r.json()["detail"]
    assert env.client.get("/api/imports/browse", params={"path": str(root / ".." / "x")},
                          headers=adm).status_code == 422
    for who in ("annotator", "reviewer"):
        assert env.client.get("/api/imports/browse", headers=env.bearer(who)).status_code == 403


def _zip(entries: dict[str, bytes], *, symlink: str | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in entries.items():
            z.writestr(name, data)
        if symlink:
            info = zipfile.ZipInfo(symlink)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            z.writestr(info, "/etc/passwd")
    return buf.getvalue()


def _tiny_zip(tmp_path) -> bytes:
    src = write_tiny_workspace(tmp_path / "proj" / "tiny_project")
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(src.rglob("*")):
            if p.is_file():
                z.write(p, p.relative_to(src.parent).as_posix())
    return buf.getvalue()


def test_upload_a_zip_of_a_project_and_import_it(env, tmp_path):
    adm = env.bearer("admin")
    data = _tiny_zip(tmp_path)
    r = env.client.post("/api/imports/upload", params={"name": "site_up"}, content=data,
                        headers={**adm, "Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    out = r.json()
    up = env.settings.data_dir / "uploads"
    assert out["path"] == str(up / "site_up") and out["source"] == str(up / "site_up" / "tiny_project")
    assert out["upload_bytes"] == len(data) and out["files"] >= 5
    assert not list((up / ".incoming").iterdir())  # the streamed zip is gone
    # the uploaded folder is importable and browsable
    r = env.client.get("/api/imports/browse", params={"path": out["source"]}, headers=adm)
    assert "scene.json" in {e["name"] for e in r.json()["entries"]}
    r = env.client.post("/api/scenes/import", json={"name": "uploaded", "source": out["source"]},
                        headers=adm)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"], timeout=60)
    assert env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()["status"] == "done"
    # the same name again: 409, nothing replaced
    r = env.client.post("/api/imports/upload", params={"name": "site_up"}, content=data,
                        headers={**adm, "Content-Type": "application/zip"})
    assert r.status_code == 409
    assert env.client.post("/api/imports/upload", params={"name": "x"}, content=data,
                           headers=env.bearer("annotator")).status_code == 403


@pytest.mark.parametrize("entries,symlink,needle", [
    ({"../evil.txt": b"x"}, None, "'..'"),
    ({"/abs/evil.txt": b"x"}, None, "absolute"),
    ({"ok/a.txt": b"x"}, "ok/link", "symbolic link"),
    ({"C:/evil.txt": b"x"}, None, "absolute"),
    ({"p/a": b"x", "p/a/b.txt": b"y"}, None, "clashes"),
    ({"p/a/b.txt": b"y", "p/a": b"x"}, None, "clashes"),
    ({"p/a.txt": b"x", "p//a.txt": b"y"}, None, "clashes"),
])
def test_upload_refuses_unsafe_zips_and_leaves_nothing(env, entries, symlink, needle):
    adm = env.bearer("admin")
    r = env.client.post("/api/imports/upload", params={"name": "bad"},
                        content=_zip(entries, symlink=symlink),
                        headers={**adm, "Content-Type": "application/zip"})
    assert r.status_code == 422, r.text
    assert needle in r.json()["detail"]
    up = env.settings.data_dir / "uploads"
    assert not (up / "bad").exists() and not list((up / ".incoming").iterdir())
    assert not (env.settings.data_dir / "evil.txt").exists()


def test_upload_size_caps(env):
    adm = env.bearer("admin")
    env.settings.max_import_upload_bytes = 4096
    try:
        big = os.urandom(8192)
        r = env.client.post("/api/imports/upload", params={"name": "big"},
                            content=_zip({"p/a.bin": big}),
                            headers={**adm, "Content-Type": "application/zip"})
        assert r.status_code == 413
        # small zip, but it extracts to more than 4x the cap (a zip bomb)
        bomb = _zip_deflated({"p/zeros.bin": b"\0" * (5 * 4096 * 4)})
        assert len(bomb) < 4096
        r = env.client.post("/api/imports/upload", params={"name": "bomb"}, content=bomb,
                            headers={**adm, "Content-Type": "application/zip"})
        assert r.status_code == 413 and "extract" in r.json()["detail"]
        r = env.client.post("/api/imports/upload", params={"name": "notzip"}, content=b"hello",
                            headers={**adm, "Content-Type": "application/zip"})
        assert r.status_code == 422 and "not a zip" in r.json()["detail"]
    finally:
        env.settings.max_import_upload_bytes = 8192 << 20
    assert not (env.settings.data_dir / "uploads" / "bomb").exists()


def _zip_deflated(entries: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return buf.getvalue()


# ---- item 3: deletion, retention, storage ------------------------------------------------------
def _fake_export(env, scene_id: int, name: str, nbytes: int, *, age_days: float = 0.0) -> int:
    from app.db import utcnow
    from app.jobs.models import Job

    out = env.settings.exports_dir / name
    (out / "data").mkdir(parents=True)
    (out / "data" / "a.bin").write_bytes(b"\1" * nbytes)
    (out / ".occufly_export").mkdir()
    (out / ".occufly_export" / "m.json").write_text("{}")
    when = utcnow() - timedelta(days=age_days)
    with env.app.state.ctx.sessions() as s:
        job = Job(kind="export", scene_id=scene_id, status="done", params={"layout": "occufly"},
                  result={"output": str(out)}, progress=1.0, message="done", log="",
                  created_at=when, finished_at=when)
        s.add(job)
        s.commit()
        return job.id


def test_delete_an_export_frees_its_bytes(world):
    env, hdr, scene, _ = world
    jid = _fake_export(env, scene["id"], "job_a", 10_000)
    r = env.client.post(f"/api/jobs/{jid}/archive?format=zip", headers=hdr["admin"])
    assert r.status_code == 200, r.text
    rows = env.client.get("/api/exports", headers=hdr["admin"]).json()
    row = next(x for x in rows if x["job_id"] == jid)
    assert row["output_bytes"] == 10_002 and row["archive_bytes"] > 0
    assert row["bytes"] == row["output_bytes"] + row["archive_bytes"]
    r = env.client.delete(f"/api/jobs/{jid}/export", headers=hdr["admin"])
    assert r.status_code == 200, r.text
    assert r.json()["freed_bytes"] == row["bytes"]
    assert not (env.settings.exports_dir / "job_a").exists()
    assert not list((env.settings.data_dir / "cache" / "archives").glob(f"export_job_{jid}.*"))
    assert env.client.get(f"/api/jobs/{jid}/archive", headers=hdr["admin"]).status_code == 404
    assert env.client.delete(f"/api/jobs/{jid}/export", headers=hdr["admin"]).status_code == 409
    ev = env.client.get("/api/audit?action=export_delete", headers=hdr["admin"]).json()[0]
    assert ev["detail"]["freed_bytes"] == row["bytes"] and ev["scene_name"] == scene["name"]
    assert env.client.delete(f"/api/jobs/{jid}/export", headers=hdr["reviewer"]).status_code == 403


def test_export_retention_keeps_the_newest_and_drops_old_ones(world):
    env, hdr, scene, _ = world
    old = _fake_export(env, scene["id"], "job_old", 100, age_days=40)
    a = _fake_export(env, scene["id"], "job_1", 100)
    b = _fake_export(env, scene["id"], "job_2", 100)
    c = _fake_export(env, scene["id"], "job_3", 100)
    r = env.client.post("/api/exports/retention", headers=hdr["admin"])
    assert r.json()["deleted"] == []  # off by default: everything is kept
    env.settings.export_keep_last, env.settings.export_max_age_days = 2, 30
    try:
        r = env.client.post("/api/exports/retention", headers=hdr["admin"])
        assert r.status_code == 200
        assert sorted(d["job_id"] for d in r.json()["deleted"]) == [old, a]
        assert r.json()["freed_bytes"] == 2 * 102
        left = {x["job_id"]: x["deleted_at"] for x in env.client.get("/api/exports", headers=hdr["admin"]).json()}
        assert left[b] is None and left[c] is None and left[a] and left[old]
        # at start-up as well
        d = _fake_export(env, scene["id"], "job_4", 100)
        env.restart()
        left = {x["job_id"]: x["deleted_at"] for x in env.client.get("/api/exports", headers=env.bearer("admin")).json()}
        assert left[b] and left[c] is None and left[d] is None
    finally:
        env.settings.export_keep_last, env.settings.export_max_age_days = 0, 0.0


def test_delete_a_scene_shows_what_it_frees_then_removes_everything(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    other = env.import_tiny(hdr["admin"], name="other")
    r = env.client.post(f"/api/scenes/{sid}/next", headers=hdr["annotator"])
    fid = r.json()["id"]
    m = np.zeros((H, W), np.uint8)
    m[:, :10] = 6
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 200
    sha = r.json()["sha256"]
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    jid = _fake_export(env, sid, "job_del", 5000)
    st = {s["scene_id"]: s for s in env.client.get("/api/storage", headers=hdr["admin"]).json()["scenes"]}
    assert st[sid]["workspace_bytes"] > 0 and st[sid]["export_bytes"] == 5002
    assert st[sid]["mask_bytes"] > 0 and st[other["id"]]["mask_bytes"] == 0
    assert st[sid]["total_bytes"] == (st[sid]["workspace_bytes"] + st[sid]["export_bytes"]
                                      + st[sid]["cache_bytes"] + st[sid]["mask_bytes"])
    p = env.client.get(f"/api/scenes/{sid}/deletion", headers=hdr["admin"]).json()
    assert p["blocked_by"] == [] and p["freed_bytes"] == st[sid]["total_bytes"]
    assert p["mask_versions"] == 1 and p["exports"] == 1
    ws = p["workspace"]
    # the name must be typed
    r = env.client.delete(f"/api/scenes/{sid}", params={"confirm": "nope"}, headers=hdr["admin"])
    assert r.status_code == 422 and scene["name"] in r.json()["detail"]
    assert env.client.delete(f"/api/scenes/{sid}", params={"confirm": scene["name"]},
                             headers=hdr["reviewer"]).status_code == 403
    r = env.client.delete(f"/api/scenes/{sid}", params={"confirm": scene["name"]}, headers=hdr["admin"])
    assert r.status_code == 200, r.text
    assert r.json()["freed_bytes"] == p["freed_bytes"]
    assert not os.path.exists(ws) and not (env.settings.exports_dir / "job_del").exists()
    assert not env.app.state.ctx.store.exists(sha)
    assert env.client.get(f"/api/scenes/{sid}", headers=hdr["admin"]).status_code == 404
    assert env.client.get(f"/api/jobs/{jid}", headers=hdr["admin"]).status_code == 404
    assert [s["id"] for s in env.client.get("/api/scenes", headers=hdr["admin"]).json()] == [other["id"]]
    assert os.path.isdir(env.import_root / "tiny_src")  # the import source is never touched
    ev = env.client.get("/api/audit?action=scene_delete", headers=hdr["admin"]).json()[0]
    assert ev["target"] == scene["name"] and ev["detail"]["freed_bytes"] == p["freed_bytes"]
    # the same name can be imported again
    again = env.import_tiny(hdr["admin"], name=scene["name"])
    assert again["id"] != sid


def test_a_scene_with_a_running_job_is_not_deleted(world):
    env, hdr, scene, _ = world
    from app.jobs.models import Job

    with env.app.state.ctx.sessions() as s:
        from app.db import utcnow

        # a runner elsewhere holds it (its heartbeat stays fresh for the test's length)
        job = Job(kind="export", scene_id=scene["id"], status="running", params={},
                  progress=0.1, message="running", log="", owner="elsewhere:1:x",
                  heartbeat_at=utcnow() + timedelta(hours=1))
        s.add(job)
        s.commit()
        jid = job.id
    p = env.client.get(f"/api/scenes/{scene['id']}/deletion", headers=hdr["admin"]).json()
    assert p["blocked_by"] and str(jid) in p["blocked_by"][0]
    r = env.client.delete(f"/api/scenes/{scene['id']}", params={"confirm": scene["name"]},
                          headers=hdr["admin"])
    assert r.status_code == 409 and str(jid) in r.json()["detail"]
    assert env.client.get(f"/api/scenes/{scene['id']}", headers=hdr["admin"]).json()["status"] == "ready"


# ---- item 4: overview, names in the audit log --------------------------------------------------
def test_overview_counts_per_scene_and_annotator(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    m = np.full((H, W), 6, np.uint8)

    def take(who):  # noqa: ANN001, ANN202
        return env.client.post(f"/api/scenes/{sid}/next", headers=hdr[who]).json()["id"]

    f1 = take("annotator")
    r = env.client.put(f"/api/frames/{f1}/mask?kind=draft", content=png(m),
                       headers={**hdr["annotator"], "If-Match": "none"})
    v = r.json()["version"]
    r = env.client.put(f"/api/frames/{f1}/mask?kind=submitted", content=png(m),
                       headers={**hdr["annotator"], "If-Match": str(v)})
    assert r.status_code == 200
    v1 = r.json()["version"]
    f2 = take("annotator")
    r = env.client.put(f"/api/frames/{f2}/mask?kind=submitted", content=png(m),
                       headers={**hdr["annotator"], "If-Match": "none"})
    f3 = take("annotator2")  # in progress
    r = env.client.post(f"/api/frames/{f1}/review", json={"decision": "accept", "version": v1},
                        headers=hdr["reviewer"])
    assert r.status_code == 200, r.text
    o = env.client.get("/api/overview", headers=hdr["admin"]).json()
    row = next(s for s in o["scenes"] if s["scene_id"] == sid)
    assert (row["todo"], row["in_progress"], row["submitted"], row["accepted"], row["rejected"]) == (1, 1, 1, 1, 0)
    assert "lift_lag_s" in row and row["submissions"] == 2
    people = {p["username"]: p for p in row["annotators"]}
    a = people["annotator"]
    assert (a["accepted"], a["submitted"], a["in_progress"], a["submissions"]) == (1, 1, 0, 2)
    assert a["time_spent_s"] >= 0 and people["annotator2"]["in_progress"] == 1
    # time spent: mask saves less than 5 minutes apart are summed, a longer gap is not
    from app.audit.models import AuditEvent
    from app.db import utcnow

    t0 = utcnow() - timedelta(hours=2)
    uid = a["user_id"]
    with env.app.state.ctx.sessions() as s:
        for dt in (0, 60, 180, 3600, 3660):  # 180 s, a 57-minute pause, then 60 s
            s.add(AuditEvent(at=t0 + timedelta(seconds=dt), action="mask_save", actor_id=uid,
                             actor="annotator", scene_id=sid, frame_id=f3))
        s.commit()
    o = env.client.get("/api/overview", headers=hdr["admin"]).json()
    a2 = next(p for p in next(s for s in o["scenes"] if s["scene_id"] == sid)["annotators"]
              if p["username"] == "annotator")
    assert a2["time_spent_s"] == pytest.approx(a["time_spent_s"] + 240, abs=1.0)
    assert a2["frames_per_hour"] == pytest.approx(2 / (a2["time_spent_s"] / 3600), rel=1e-2)
    tot = {p["username"]: p for p in o["annotators"]}
    assert tot["annotator"]["submissions"] == 2 and tot["annotator"]["scenes"] == 1
    assert env.client.get("/api/overview", headers=hdr["reviewer"]).status_code == 403


def test_audit_log_names_frames_scenes_and_users(world):
    env, hdr, scene, frames = world
    sid = scene["id"]
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=hdr["annotator"]).json()["id"]
    env.client.put(f"/api/frames/{fid}/mask?kind=draft", content=png(np.full((H, W), 6, np.uint8)),
                   headers={**hdr["annotator"], "If-Match": "none"})
    ev = env.client.get("/api/audit?action=mask_save", headers=hdr["admin"]).json()[0]
    name = next(f["name"] for f in frames if f["id"] == fid)
    assert (ev["frame_id"], ev["frame_name"], ev["scene_name"]) == (fid, name, scene["name"])
    ev = env.client.get("/api/audit?action=membership", headers=hdr["admin"]).json()[0]
    assert set(ev["users"].values()) >= {"annotator", "reviewer"}
