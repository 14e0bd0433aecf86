"""``occufly db upgrade`` / ``occufly users create`` against a real database file."""

from __future__ import annotations

import json

from occufly.cli import main


def test_db_upgrade_and_users_create(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("OCCUFLY_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("OCCUFLY_ENV", "development")
    monkeypatch.setenv("OCCUFLY_ARGON2_MEMORY_KIB", "1024")
    monkeypatch.setenv("OCCUFLY_ARGON2_TIME_COST", "1")
    assert main(["db", "upgrade", "--json"]) == 0
    from alembic.script import ScriptDirectory

    from app.db import alembic_config

    head = ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()
    assert head >= "0002"  # the newest migration, not an older one
    assert json.loads(capsys.readouterr().out)["revision"] == head
    assert main(["users", "create", "carol", "--role", "admin", "--password", "s3cret-pass",
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"id": 1, "username": "carol", "role": "admin"}
    assert main(["users", "create", "carol", "--role", "admin", "--password", "s3cret-pass"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["users", "create", "dave", "--role", "reviewer", "--password", "short"]) == 2
    # the created account logs in through the app
    from fastapi.testclient import TestClient

    from app.config import Settings
    from app.main import close, create_app

    app = create_app(Settings.from_env())
    with TestClient(app) as c:
        r = c.post("/api/auth/login", json={"username": "carol", "password": "s3cret-pass"})
        assert r.status_code == 200 and r.json()["user"]["role"] == "admin"
    close(app)


def test_default_secret_refused_outside_development(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("OCCUFLY_DATA_DIR", str(tmp_path))
    monkeypatch.delenv("OCCUFLY_ENV", raising=False)
    monkeypatch.delenv("OCCUFLY_SECRET_KEY", raising=False)
    assert main(["db", "upgrade"]) == 2
    assert "OCCUFLY_SECRET_KEY" in capsys.readouterr().err


def test_demo_seed_imports_selects_and_creates_users(tmp_path):
    from fastapi.testclient import TestClient

    from app.config import Settings
    from app.demo import seed
    from app.main import close, create_app
    from tests.app.conftest import write_tiny_workspace

    roots = tmp_path / "imports"
    src = write_tiny_workspace(roots / "tiny_ws")
    # a synthetic source's truth grid goes with the workspace (the eval job scores against it)
    import numpy as np

    from occufly.grid import SceneGrid

    SceneGrid(np.full((2, 2, 2), 6, np.uint8), np.zeros(3), 0.5).save(src / "truth" / "scene_grid.npz")
    settings = Settings(data_dir=tmp_path / "data", import_roots=[roots], env="development",
                        job_processes=False, argon2_memory_kib=1024, argon2_time_cost=1)
    info = seed(settings, src)
    copies = list((tmp_path / "data").rglob("truth/scene_grid.npz"))
    assert len(copies) == 1 and copies[0].read_bytes() == (src / "truth" / "scene_grid.npz").read_bytes()
    again = seed(settings, src)  # idempotent: same scene, same users
    assert again["scene_id"] == info["scene_id"]
    assert set(info["users"]) == {"admin", "reviewer", "annotator"}
    assert 1 <= len(info["selection"]["frames"]) <= 4
    app = create_app(settings)
    with TestClient(app) as c:
        for role, pw in info["users"].items():
            r = c.post("/api/auth/login", json={"username": role, "password": pw})
            assert r.json()["user"]["role"] == role
        scenes = c.get("/api/scenes").json()
        assert len(scenes) == 1 and scenes[0]["status"] == "ready"
        assert scenes[0]["n_selected"] == len(info["selection"]["frames"])
    close(app)
