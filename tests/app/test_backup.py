"""``occufly backup`` / ``restore``: taken while masks are being saved, restored into a fresh data
dir and database (SQLite and PostgreSQL), every mask version's PNG checked against its hash."""

from __future__ import annotations

import hashlib
import json
import threading

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.config import Settings
from tests.app.conftest import PASSWORD, H, W, png, scratch_postgres


@pytest.fixture
def fresh_target(env, tmp_path):
    """A fresh data dir and an empty database of the env's kind (dropped afterwards)."""
    data = tmp_path / "restored"
    if env.backend == "sqlite":
        yield Settings(data_dir=data, env="development", argon2_memory_kib=1024,
                       argon2_time_cost=1, job_processes=False)
        return
    with scratch_postgres("h3_restore") as url:
        yield Settings(data_dir=data, database_url=url, env="development", argon2_memory_kib=1024,
                       argon2_time_cost=1, job_processes=False)


def test_backup_while_saving_then_restore_into_a_fresh_data_dir(env, fresh_target, tmp_path):
    from app.annotations.models import MaskVersion
    from app.backup import BackupError, backup, restore
    from app.main import close, create_app

    adm = env.bearer("admin")
    scene = env.import_tiny(adm)
    env.select_all(scene["id"])
    ann = env.bearer("annotator")
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=ann).json()["id"]
    rng = np.random.default_rng(0)
    acked: list[tuple[int, str]] = []
    last = ["none"]

    def save() -> None:
        m = np.where(rng.random((H, W)) < 0.5, 6, 1).astype(np.uint8)
        data = png(m)
        r = env.client.put(f"/api/frames/{fid}/mask", content=data,
                           headers={**ann, "If-Match": last[0]})
        assert r.status_code == 200, r.text
        acked.append((r.json()["version"], hashlib.sha256(data).hexdigest()))
        last[0] = str(r.json()["version"])

    for _ in range(5):
        save()
    before = list(acked)
    stop = threading.Event()

    def writer() -> None:  # keeps saving while the backup runs
        while not stop.is_set():
            save()

    t = threading.Thread(target=writer)
    t.start()
    try:
        info = backup(env.settings, tmp_path / "bk")
    finally:
        stop.set()
        t.join()
    assert info["tables"]["mask_versions"] >= len(before) and info["scenes"][0]["name"] == "tiny"
    dumped = [json.loads(line) for line in (tmp_path / "bk" / "db" / "mask_versions.jsonl").open()]
    assert {(v["id"], v["sha256"]) for v in dumped} >= set(before)
    with pytest.raises(BackupError, match="not empty"):
        backup(env.settings, tmp_path / "bk")

    out = restore(fresh_target, tmp_path / "bk")
    assert out["tables"]["mask_versions"] == len(dumped) and out["masks"] == len({v["sha256"] for v in dumped})
    app = create_app(fresh_target)
    try:
        ctx = app.state.ctx
        with ctx.sessions() as s:
            rows = list(s.scalars(select(MaskVersion).order_by(MaskVersion.id)))
        assert [(r.id, r.sha256) for r in rows] == [(v["id"], v["sha256"]) for v in dumped]
        for r in rows:  # every version's PNG is there and hashes to its name
            assert hashlib.sha256(ctx.store.get(r.sha256)).hexdigest() == r.sha256
        c = TestClient(app)
        tok = c.post("/api/auth/login", json={"username": "annotator", "password": PASSWORD}).json()["token"]
        h = {"Authorization": f"Bearer {tok}"}
        sc = c.get(f"/api/scenes/{scene['id']}", headers=h).json()
        assert sc["status"] == "ready" and sc["taxonomy"]["classes"]
        cur = c.get(f"/api/frames/{fid}/mask", headers=h)
        assert cur.status_code == 200
        assert hashlib.sha256(cur.content).hexdigest() == dict((v["id"], v["sha256"]) for v in dumped)[
            int(cur.headers["x-mask-version"])]
        # the workspace moved with the data dir, and new rows get fresh ids
        from app.scenes.models import Scene

        with ctx.sessions() as s:
            assert s.get(Scene, scene["id"]).workspace == str(fresh_target.workspaces_dir / "tiny")
        r = c.put(f"/api/frames/{fid}/mask", content=png(np.full((H, W), 6, np.uint8)),
                  headers={**h, "If-Match": cur.headers["x-mask-version"]})
        assert r.status_code == 200 and r.json()["version"] > max(v["id"] for v in dumped), r.text
    finally:
        close(app)
    # a second restore into the now non-empty target is refused
    with pytest.raises(BackupError, match="already holds"):
        restore(fresh_target, tmp_path / "bk")


def test_cli_backup_and_restore(tmp_path, monkeypatch, capsys):
    from occufly.cli import main

    monkeypatch.setenv("OCCUFLY_ENV", "development")
    monkeypatch.setenv("OCCUFLY_ARGON2_MEMORY_KIB", "1024")
    monkeypatch.setenv("OCCUFLY_ARGON2_TIME_COST", "1")
    monkeypatch.setenv("OCCUFLY_DATA_DIR", str(tmp_path / "a"))
    assert main(["users", "create", "carol", "--role", "admin", "--password", "s3cret-pass"]) == 0
    capsys.readouterr()
    assert main(["backup", str(tmp_path / "bk"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["tables"]["users"] == 1
    assert main(["backup", str(tmp_path / "bk")]) == 2
    assert "not empty" in capsys.readouterr().err
    monkeypatch.setenv("OCCUFLY_DATA_DIR", str(tmp_path / "b"))
    assert main(["restore", str(tmp_path / "bk"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["tables"]["users"] == 1
    assert main(["users", "list", "--json"]) == 0
    assert [u["username"] for u in json.loads(capsys.readouterr().out)["users"]] == ["carol"]
    assert main(["restore", str(tmp_path / "bk")]) == 2  # not into a database that has users
    assert main(["restore", str(tmp_path / "nothing")]) == 2
