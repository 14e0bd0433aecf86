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


def test_viewer_lists_and_opens_only_member_scenes_of_a_reviewer(tmp_path):
    """A reviewer's scene dropdown holds only their member scenes; switching to another
    (a stale dropdown, a forged GUI message) is refused and loads nothing."""
    from types import SimpleNamespace

    from app.scenes.models import Scene, SceneMember
    from app.viewer.state import ClientState

    settings = Settings(data_dir=tmp_path, env="development")
    app = create_app(settings)
    with TestClient(app):
        with app.state.ctx.sessions() as s:
            rev = users.create_user(session=s, username="rev", password="reviewer-pw-1",
                                    role="reviewer")
            adm = users.create_user(session=s, username="adm", password="admin-pw-123",
                                    role="admin")
            mine = Scene(name="mine", status="ready", workspace=str(tmp_path / "a"))
            other = Scene(name="other", status="ready", workspace=str(tmp_path / "b"))
            s.add_all([mine, other])
            s.flush()
            s.add(SceneMember(scene_id=mine.id, user_id=rev.id))
            s.commit()
            ids = (str(mine.id), str(other.id))
            rev_id, adm_id = rev.id, adm.id
        with app.state.ctx.sessions() as s:
            from app.users.models import User

            rev, adm = s.get(User, rev_id), s.get(User, adm_id)
            s.expunge_all()
        svc = app.state.viewer
        assert set(svc.scenes_for(rev)) == {ids[0]}
        assert set(svc.scenes_for(adm)) == set(ids)
        status = SimpleNamespace(content="")
        st = ClientState(client=None, user=rev)
        st.gui["status"] = status
        svc.open_scene(st, ids[1])
        assert st.scene_id is None and st.data is None
        assert "cannot open scene" in status.content
        assert st.ready.is_set()
