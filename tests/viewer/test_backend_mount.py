"""The backend's real app (app.main.create_app) mounts the viewer: roles decide access."""

from __future__ import annotations

from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from app.users import service as users


def test_create_app_admits_reviewers_only(tmp_path):
    settings = Settings(data_dir=tmp_path, env="development")
    app = create_app(settings)
    with TestClient(app) as client:
        with app.state.ctx.sessions() as s:
            users.create_user(session=s, username="ann", password="annotator-pw-1", role="annotator")
            users.create_user(session=s, username="rev", password="reviewer-pw-1", role="reviewer")
        tokens = {}
        for name, pw in (("ann", "annotator-pw-1"), ("rev", "reviewer-pw-1")):
            r = client.post("/api/auth/login", json={"username": name, "password": pw})
            assert r.status_code == 200, r.text
            tokens[name] = r.json()["token"]
        client.cookies.clear()
        assert client.get("/viewer/").status_code == 401
        r = client.get("/viewer/", headers={"Authorization": f"Bearer {tokens['ann']}"})
        assert r.status_code == 403
        r = client.get("/viewer/", headers={"Authorization": f"Bearer {tokens['rev']}"})
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        svc = app.state.viewer
        assert svc.running and svc.server.get_host() == "127.0.0.1"
    assert not app.state.viewer.running
