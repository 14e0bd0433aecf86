"""Fixtures for the web-app tests: every API test runs on SQLite *and* PostgreSQL.

PostgreSQL comes from ``OCCUFLY_TEST_POSTGRES_URL`` (default
``postgresql+psycopg://postgres@127.0.0.1:5432/test``). A fresh database is created for the
test session next to it and dropped afterwards. If the server is unreachable the tests
error out (they never skip).
"""

from __future__ import annotations

import io
import os
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image
from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url

from app import db
from app.config import Settings
from app.main import close, create_app
from app.users import service as users
from occufly.camera import Camera, look_at
from occufly.scene import Frame, Scene, Visibility
from occufly.taxonomy import default_taxonomy

PG_DEFAULT = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


@contextmanager
def scratch_postgres(prefix: str):
    """URL of a fresh PostgreSQL database ``<prefix>_<random>``, dropped afterwards."""
    base = make_url(os.environ.get("OCCUFLY_TEST_POSTGRES_URL", PG_DEFAULT))
    name = f"{prefix}_{uuid.uuid4().hex[:8]}"
    admin = create_engine(base, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
    except Exception as e:  # noqa: BLE001
        admin.dispose()
        raise RuntimeError(
            f"PostgreSQL at {base.render_as_string(hide_password=True)} is unreachable or "
            f"refused CREATE DATABASE: {e}. The web-app tests need it (set "
            "OCCUFLY_TEST_POSTGRES_URL).") from e
    try:
        yield base.set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()
BACKENDS = ["sqlite", "postgresql"]
PASSWORD = "correct-horse-battery"
W, H = 64, 48  # frame size of the tiny scene


@pytest.fixture(scope="session")
def pg_url():
    """A fresh, migrated PostgreSQL database for this test session (dropped afterwards)."""
    with scratch_postgres("occufly_test") as url:
        db.upgrade(url)
        yield url


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory) -> Path:
    """A migrated SQLite file, copied per test (Alembic runs once per session)."""
    path = tmp_path_factory.mktemp("sqlite-template") / "template.db"
    db.upgrade(f"sqlite:///{path}")
    return path


def _truncate_pg(url: str) -> None:
    """Empty every table of the session's database and restart its sequences, as ``TRUNCATE
    ... RESTART IDENTITY`` would: ``DELETE`` in reverse dependency order instead (0.015 s
    against 0.2 s for TRUNCATE's new files per table, once per PostgreSQL test)."""
    from app.models import metadata

    eng = create_engine(url)
    with eng.begin() as c:
        for t in reversed(metadata.sorted_tables):
            c.execute(text(f'DELETE FROM "{t.name}"'))
        c.execute(text("SELECT setval(c.oid, 1, false) FROM pg_class c JOIN pg_namespace n "
                       "ON n.oid = c.relnamespace WHERE c.relkind = 'S' "
                       "AND n.nspname = current_schema()"))
    eng.dispose()


def make_tiny_scene(n_frames: int = 4, n_side: int = 20) -> Scene:
    """A flat 40 m x 40 m ground of 400 points seen by ``n_frames`` nadir cameras at 30 m."""
    g = np.linspace(-19.0, 19.0, n_side)  # n_side^2 points (20: 400)
    xx, yy = np.meshgrid(g, g)
    xyz = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1).astype(np.float32)
    rgb = np.full_like(xyz, 128, dtype=np.uint8)
    cam = Camera("PINHOLE", W, H, np.array([50.0, 50.0, W / 2, H / 2]))
    frames, parts = [], []
    for i, x in enumerate(np.linspace(-8, 8, n_frames)):
        T = look_at(np.array([x, 0.0, 30.0]), np.array([x, 0.0, 0.0]), up=(0.0, 1.0, 0.0))
        frames.append(Frame(name=f"img_{i:03d}.png", camera=cam, T_cam_world=T,
                            image_path=f"images/img_{i:03d}.png", altitude=30.0,
                            nominal_altitude=30))
        xyz_cam = xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        uv = xyz_cam[:, :2] / xyz_cam[:, 2:3] * 50.0 + np.array([W / 2, H / 2])
        ok = (xyz_cam[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        ids = np.nonzero(ok)[0]
        parts.append((ids.astype(np.int32), uv[ok].astype(np.float32), xyz_cam[ok, 2].astype(np.float32)))
    return Scene(frames=frames, xyz=xyz, rgb=rgb, visibility=Visibility.from_parts(parts),
                 taxonomy=default_taxonomy())


def write_tiny_workspace(path: Path, n_frames: int = 4, n_side: int = 20) -> Path:
    scene = make_tiny_scene(n_frames, n_side)
    scene.save(path)
    (path / "images").mkdir()
    rng = np.random.default_rng(0)
    for f in scene.frames:
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(path / f.image_path)
    return path


def png(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(arr)).save(buf, format="PNG")
    return buf.getvalue()


def mask_png(class_id: int = 6, w: int = W, h: int = H) -> bytes:
    m = np.zeros((h, w), np.uint8)
    m[:, : w // 2] = class_id
    m[:, w // 2:] = 1  # road
    return png(m)


@dataclass
class Env:
    settings: Settings
    app: object
    client: TestClient
    backend: str
    import_root: Path

    def login(self, username: str, password: str = PASSWORD) -> TestClient:
        c = TestClient(self.app)
        r = c.post("/api/auth/login", json={"username": username, "password": password})
        assert r.status_code == 200, r.text
        return c

    def bearer(self, username: str) -> dict:
        r = self.client.post("/api/auth/login", json={"username": username, "password": PASSWORD})
        assert r.status_code == 200, r.text
        self.client.cookies.clear()  # the shared client stays anonymous; callers use the header
        return {"Authorization": f"Bearer {r.json()['token']}"}

    def restart(self) -> None:
        """Simulate a server restart: a new app over the same database and data dir."""
        self.client.close()
        close(self.app)
        import dataclasses

        # a real start-up, including the Alembic upgrade (a no-op at head)
        self.app = create_app(dataclasses.replace(self.settings, auto_upgrade=True))
        self.client = TestClient(self.app)

    def import_tiny(self, admin: dict, name: str = "tiny", n_frames: int = 4,
                    members=None) -> dict:  # noqa: ANN001
        """Import the tiny scene; ``members`` (user names, default every annotator and
        reviewer) are assigned to it."""
        src = self.import_root / f"{name}_src"
        if not src.exists():
            write_tiny_workspace(src, n_frames)
        r = self.client.post("/api/scenes/import", json={"name": name, "source": str(src)},
                             headers=admin)
        assert r.status_code == 202, r.text
        job = r.json()
        self.app.state.ctx.jobs.wait(job["id"], timeout=60)
        j = self.client.get(f"/api/jobs/{job['id']}", headers=admin).json()
        assert j["status"] == "done", j.get("message") or j
        scene = self.client.get("/api/scenes", headers=admin).json()[-1]
        assert scene["status"] == "ready" and scene["n_frames"] == n_frames
        self.add_members(scene["id"], members, admin)
        return scene

    def add_members(self, scene_id: int, names=None, admin: dict | None = None) -> None:  # noqa: ANN001
        """Make users members of the scene (default: every annotator and reviewer)."""
        from sqlalchemy import select

        from app.users.models import User

        with self.app.state.ctx.sessions() as s:
            rows = s.execute(select(User.id, User.username, User.role)).all()
        ids = [i for i, name, role in rows if role != "admin" and (names is None or name in names)]
        if ids:
            r = self.client.post(f"/api/scenes/{scene_id}/members", json={"user_ids": ids},
                                 headers=admin or self.bearer("admin"))
            assert r.status_code == 200, r.text

    def select_all(self, scene_id: int) -> None:
        from sqlalchemy import update

        from app.scenes.models import Frame

        with self.app.state.ctx.sessions() as s:
            s.execute(update(Frame).where(Frame.scene_id == scene_id).values(selected=True))
            s.commit()


@pytest.fixture(params=BACKENDS)
def env(request, tmp_path: Path):
    backend = request.param
    if backend == "sqlite":
        import shutil

        shutil.copy(request.getfixturevalue("sqlite_template"), tmp_path / "occufly.db")
        url = f"sqlite:///{tmp_path / 'occufly.db'}"
    else:
        url = request.getfixturevalue("pg_url")
        _truncate_pg(url)
    root = tmp_path / "imports"
    root.mkdir()
    settings = Settings(data_dir=tmp_path / "data", database_url=url, import_roots=[root],
                        env="development", fill_debounce_s=0.2, fill_settle_s=0, job_workers=2,
                        job_processes=request.node.get_closest_marker("job_processes") is not None,
                        # the review's after-fill refresh in the fill thread, unless marked
                        review_refresh_process=request.node.get_closest_marker(
                            "review_process") is not None,
                        login_free_failures=3, max_upload_bytes=1 << 20,
                        # argon2id at a test cost (production default: 64 MiB, 3 passes)
                        argon2_memory_kib=1024, argon2_time_cost=1,
                        auto_upgrade=False)  # migrated once per session (see above)
    app = create_app(settings)
    with app.state.ctx.sessions() as s:
        for role in ("admin", "reviewer", "annotator"):
            users.create_user(session=s, username=role, password=PASSWORD, role=role)
        users.create_user(session=s, username="annotator2", password=PASSWORD, role="annotator")
    e = Env(settings=settings, app=app, client=TestClient(app), backend=backend, import_root=root)
    yield e
    e.client.close()
    close(e.app)


@pytest.fixture
def world(env):
    """The tiny scene imported, all frames selected; bearer headers per role."""
    hdr = {r: env.bearer(r) for r in ("admin", "reviewer", "annotator", "annotator2")}
    scene = env.import_tiny(hdr["admin"])
    env.select_all(scene["id"])
    frames = env.client.get(f"/api/scenes/{scene['id']}/frames", headers=hdr["admin"]).json()
    return env, hdr, scene, frames


def pytest_configure(config) -> None:  # noqa: ANN001
    config.addinivalue_line(
        "markers", "job_processes: run remote job kinds in spawned worker processes")
    config.addinivalue_line(
        "markers", "review_process: run the review's after-fill refresh in its child process "
        "(the default outside the in-process test apps)")


def seed_served_data(tmp: Path, extra_env: dict | None = None, *,
                     n_points: int | None = None) -> tuple[dict, int]:
    """A data folder under ``tmp`` with an admin (``PASSWORD``) and the tiny scene imported,
    for an app started afterwards in a child process (tests that measure the server's own
    memory or talk to it over raw sockets): (the child's environment, the scene id).
    ``n_points``: the scene's recorded point count, for the caps that scale with it."""
    from app.jobs import service as jobs
    from app.scenes import service as scenes
    from app.scenes.models import Scene as SceneRow

    (tmp / "imports").mkdir()
    env = {**os.environ, "OCCUFLY_DATA_DIR": str(tmp / "data"),
           "OCCUFLY_IMPORT_ROOTS": str(tmp / "imports"), "OCCUFLY_ENV": "development",
           "OCCUFLY_LIFTING": "off", "OCCUFLY_JOB_PROCESSES": "0",
           "OCCUFLY_ARGON2_MEMORY_KIB": "1024", "OCCUFLY_ARGON2_TIME_COST": "1",
           "PYTHONPATH": str(Path(__file__).resolve().parents[2]), **(extra_env or {})}
    settings = Settings.from_env(env, job_processes=False)
    app = create_app(settings)
    ctx = app.state.ctx
    src = tmp / "imports" / "tiny"
    write_tiny_workspace(src)
    with ctx.sessions() as s:
        users.create_user(session=s, username="admin", password=PASSWORD, role="admin")
        scene = scenes.create_scene(session=s, settings=settings, name="tiny", source=src)
        job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                          params={"source": str(src)})
        sid = scene.id
    ctx.jobs.submit(job.id)
    ctx.jobs.wait(job.id, timeout=120)
    if n_points is not None:
        with ctx.sessions() as s:
            s.get(SceneRow, sid).n_points = n_points
            s.commit()
    close(app)
    return env, sid
