"""Issue 24: Content-Disposition and a sandboxing CSP on served data (finding 3), and from 9:
the password policy, admin job quotas, and the 500s (a NUL in a viewer URL, a thumbnail of a
file that is not a decodable image)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import mask_png


def _served_path(env, scene: dict, index: int = 0) -> Path:  # noqa: ANN001
    from app.scenes.models import Scene

    with env.app.state.ctx.sessions() as s:
        ws = s.get(Scene, scene["id"]).workspace
    f = env.app.state.ctx.load_scene(ws).frames[index]
    p = Path(f.image_path)
    return p if p.is_absolute() else Path(ws) / p


# ---- finding 3 ------------------------------------------------------------------------------
def test_frame_images_and_masks_carry_disposition_and_sandbox(world):
    env, hdr, scene, frames = world
    fid = frames[0]["id"]
    r = env.client.get(f"/api/frames/{fid}/image", headers=hdr["annotator"])
    assert r.status_code == 200
    assert r.headers["content-disposition"].startswith('inline; filename="img_000.png"')
    assert r.headers["content-security-policy"] == "default-src 'none'; sandbox"
    assert r.headers["x-content-type-options"] == "nosniff"
    r = env.client.get(f"/api/frames/{fid}/image?download=1", headers=hdr["annotator"])
    assert r.headers["content-disposition"].startswith('attachment; filename="img_000.png"')
    r = env.client.get(f"/api/frames/{fid}/image?size=thumb", headers=hdr["annotator"])
    assert r.headers["content-type"] == "image/jpeg"
    assert 'filename="img_000_thumb.jpg"' in r.headers["content-disposition"]
    lease = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr["annotator"]).json()
    v = env.client.put(f"/api/frames/{lease['id']}/mask", content=mask_png(),
                       headers={**hdr["annotator"], "If-Match": "none"}).json()["version"]
    for url in (f"/api/frames/{lease['id']}/mask", f"/api/frames/{lease['id']}/mask/versions/{v}"):
        r = env.client.get(url, headers=hdr["annotator"])
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert r.headers["content-security-policy"] == "default-src 'none'; sandbox", url
        assert r.headers["content-disposition"].startswith("inline;"), url


def test_content_disposition_of_a_hostile_name():
    from app.scenes.service import content_disposition

    cd = content_disposition('a"b\r\nSet-Cookie: x=1;<script>.png', download=True)
    assert "\r" not in cd and "\n" not in cd and "<" not in cd
    assert cd.startswith('attachment; filename="a_b__Set-Cookie__x_1__script_.png"; filename*=')


# ---- the 500s -------------------------------------------------------------------------------
def test_viewer_url_with_a_nul_is_404_not_500(world):
    env, hdr, _scene, _frames = world
    c = TestClient(env.app, raise_server_exceptions=False)
    for url in ("/viewer/js/main.js%00.png", "/viewer/%00", "/viewer/x%01y.js",
                "/viewer/index.html%00"):
        r = c.get(url, headers=hdr["admin"])
        assert r.status_code == 404, (url, r.status_code, r.text[:200])


def test_thumb_of_a_corrupt_image_is_422_not_500(world):
    """A file with PNG magic bytes but no decodable image (truncated): ?size=thumb and
    ?size=preview are 422 naming the frame; a non-image is 404 (landed before)."""
    env, hdr, scene, frames = world
    c = TestClient(env.app, raise_server_exceptions=False)
    p = _served_path(env, scene, 2)
    p.write_bytes(p.read_bytes()[:40])  # the signature and IHDR, no image data
    for size in ("thumb", "preview"):
        r = c.get(f"/api/frames/{frames[2]['id']}/image?size={size}", headers=hdr["annotator"])
        assert r.status_code == 422, (size, r.status_code, r.text[:300])
        assert f"frame {frames[2]['id']}" in r.json()["detail"]


# ---- password policy ------------------------------------------------------------------------
@pytest.mark.parametrize("bad,why", [
    ("password", "most common"), ("12345678", "most common"), ("qwertyuiop", "most common"),
    ("newuser1", "user name"), ("NewUser", "at least 8"), ("newuser-x", "user name"),
    ("zzzzzzzzzz", "fewer than three"), ("Password1", "most common"),
])
def test_password_policy_refuses_weak_passwords(env, bad, why):
    adm = env.bearer("admin")
    r = env.client.post("/api/users", json={"username": "newuser", "password": bad,
                                            "role": "annotator"}, headers=adm)
    assert r.status_code == 422, (bad, r.status_code, r.text)
    assert why in r.json()["detail"], r.json()["detail"]


def test_password_policy_on_change_and_reset(env):
    adm = env.bearer("admin")
    r = env.client.post("/api/users", json={"username": "newuser", "password": "tram-lamp-quiet",
                                            "role": "annotator"}, headers=adm)
    assert r.status_code in (200, 201), r.text
    uid = r.json()["id"]
    r = env.client.post(f"/api/users/{uid}/password", json={"password": "12345678"}, headers=adm)
    assert r.status_code == 422 and "most common" in r.text
    tok = env.client.post("/api/auth/login", json={"username": "newuser",
                                                   "password": "tram-lamp-quiet"}).json()["token"]
    env.client.cookies.clear()
    r = env.client.post("/api/auth/password", json={"current": "tram-lamp-quiet",
                                                    "new": "newuser123"},
                        headers={"Authorization": f"Bearer {tok}"})
    assert r.status_code == 422 and "user name" in r.text, r.text


def test_common_password_list_is_bundled():
    from app.users.service import COMMON_PASSWORDS_FILE, common_passwords

    assert COMMON_PASSWORDS_FILE.is_file() and len(common_passwords()) > 19000


# ---- job quotas -----------------------------------------------------------------------------
def test_admin_job_quota_429(world):
    """40 export requests: at most ``active_jobs_per_user`` queued or running at once; the rest
    are 429 with Retry-After, nothing created for them."""
    env, hdr, scene, _frames = world
    ctx = env.app.state.ctx
    ctx.settings = dataclasses.replace(ctx.settings, active_jobs_per_user=3)
    from app.jobs.models import Job

    # hold the job runner so the jobs stay queued
    ctx.jobs.submit = lambda job_id: None
    codes = []
    for _ in range(40):
        r = env.client.post(f"/api/scenes/{scene['id']}/export", json={}, headers=hdr["admin"])
        codes.append(r.status_code)
        if r.status_code == 429:
            assert r.headers["retry-after"] == "10" and "job quota" in r.json()["detail"]
    assert codes.count(202) == 3 and codes.count(429) == 37, codes
    with ctx.sessions() as s:
        assert s.query(Job).filter(Job.kind == "export").count() == 3


def test_every_job_kind_counts_against_the_quota(world):
    """Selection and next-frames jobs are jobs like the others (CPU-heavy on a survey): with
    quota 2 and the runner held, the third request of any kind is a 429 naming the quota."""
    env, hdr, scene, _frames = world
    ctx = env.app.state.ctx
    ctx.settings = dataclasses.replace(ctx.settings, active_jobs_per_user=2)
    ctx.jobs.submit = lambda job_id: None  # hold the job runner so the jobs stay queued
    sid, adm = scene["id"], hdr["admin"]
    for _ in range(2):
        r = env.client.post(f"/api/scenes/{sid}/selection", json={}, headers=adm)
        assert r.status_code == 202, r.text
    for path, body in ((f"/api/scenes/{sid}/selection", {}), (f"/api/scenes/{sid}/export", {}),
                       (f"/api/scenes/{sid}/next-frames", {"k": 3})):
        r = env.client.post(path, json=body, headers=adm)
        assert r.status_code == 429, (path, r.status_code, r.text)
        assert "job quota" in r.json()["detail"], r.text


def test_export_disk_quota_507(world):
    env, hdr, scene, _frames = world
    ctx = env.app.state.ctx
    from app.jobs import service as jobs

    d = ctx.settings.exports_dir / "job_999"
    d.mkdir(parents=True)
    (d / "big.bin").write_bytes(b"\0" * 200_000)
    ctx.settings = dataclasses.replace(ctx.settings, export_quota_bytes=100_000)
    jobs.exports_bytes(ctx.settings.exports_dir, fresh=True)
    r = env.client.post(f"/api/scenes/{scene['id']}/export", json={}, headers=hdr["admin"])
    assert r.status_code == 507, r.text
    assert "export quota" in r.json()["detail"]
