"""Apps of one process share their routers' resolved routes (app.main._share_included_routers):
each app still answers from its own database, data folder and settings, while the routes'
dependencies are resolved once."""

from __future__ import annotations

import dataclasses

from fastapi.testclient import TestClient

from app.main import close, create_app
from tests.app.conftest import PASSWORD


def test_two_live_apps_share_routes_and_keep_their_own_data(env, tmp_path):
    from fastapi import routing

    from app.users import service as users

    admin = env.bearer("admin")
    assert env.client.post("/api/users", json={"username": "only-in-the-first",
                                                "password": PASSWORD, "role": "annotator"},
                           headers=admin).status_code in (200, 201)
    url = f"sqlite:///{tmp_path / 'second.db'}"
    second = create_app(dataclasses.replace(env.settings, database_url=url,
                                            data_dir=tmp_path / "second", auto_upgrade=True))
    try:
        with second.state.ctx.sessions() as s:
            users.create_user(session=s, username="admin", password=PASSWORD, role="admin")
            users.create_user(session=s, username="only-in-the-second", password=PASSWORD,
                              role="reviewer")
        c2 = TestClient(second)
        r = c2.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
        assert r.status_code == 200, r.text
        h2 = {"Authorization": f"Bearer {r.json()['token']}"}
        c2.cookies.clear()
        # each app answers from its own database, alternately, both alive
        for _ in range(2):
            one = {u["username"] for u in env.client.get("/api/users", headers=admin).json()}
            two = {u["username"] for u in c2.get("/api/users", headers=h2).json()}
            assert "only-in-the-first" in one and "only-in-the-second" not in one
            assert "only-in-the-second" in two and "only-in-the-first" not in two
        # a token of one app means nothing to the other
        assert c2.get("/api/users", headers=admin).status_code == 401
        # the included routers are the same objects, resolved once
        shared = [r for r in env.app.router.routes if type(r) is routing._IncludedRouter]
        again = [r for r in second.router.routes if type(r) is routing._IncludedRouter]
        assert shared and [id(r) for r in shared] == [id(r) for r in again]
        assert all(r.include_context.dependency_overrides_provider is None for r in shared)
    finally:
        close(second)
