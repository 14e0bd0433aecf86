"""kill -9 of the server in the middle of an export (issue 14 defect 6): the job's worker
processes die with it, nothing of the dead attempt is written afterwards, and after a restart
the job is interrupted, resumes as attempt 2 and completes in a folder only it wrote."""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx
import numpy as np

from occufly.scene import Scene
from tests.app.conftest import PASSWORD, write_tiny_workspace
from tests.harness import ProcessServer

REPO = Path(__file__).resolve().parents[2]


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            children.setdefault(ppid, []).append(int(d))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            if c not in out:
                out.add(c)
                todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _listing(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*")} \
        if root.exists() else {}


def _seed(tmp: Path, env: dict) -> int:
    """Import a 48-frame tiny scene, give it labels and a scene grid (in-process jobs).

    48 frames, not 12: at 12 the export's last 85 % once finished (and published) between the
    test's last progress poll and the kill, in a fresh-clone CI run."""
    from app.config import Settings
    from app.jobs import service as jobs
    from app.main import close, create_app
    from app.scenes import service as scenes
    from app.users import service as users
    from occufly.workspace import Workspace

    settings = Settings.from_env(env, job_processes=False)
    app = create_app(settings)
    ctx = app.state.ctx
    src = tmp / "imports" / "tiny_src"
    write_tiny_workspace(src, n_frames=48, n_side=40)
    with ctx.sessions() as s:
        users.create_user(session=s, username="admin", password=PASSWORD, role="admin")
        scene = scenes.create_scene(session=s, settings=settings, name="tiny", source=src)
        job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                          params={"source": str(src)})
        sid, ws = scene.id, Workspace(scene.workspace)
    ctx.jobs.submit(job.id)
    ctx.jobs.wait(job.id, timeout=120)
    n = Scene.load(ws.root).n_points
    labels = np.where(np.arange(n) % 9 == 0, 8, 1).astype(np.uint8)  # road with trees
    ws.write_labels(labels, np.ones(n, np.float32), np.ones(n, np.uint8), {})
    with ctx.sessions() as s:
        job = jobs.create(session=s, kind="voxelize", scene_id=sid, user_id=None,
                          params={"voxel_size": 0.5})
    ctx.jobs.submit(job.id)
    ctx.jobs.wait(job.id, timeout=120)
    with ctx.sessions() as s:
        assert jobs.get(session=s, job_id=job.id).status == "done"
    close(app)
    return sid


def test_kill_9_during_an_export_leaves_no_writer_behind(tmp_path):
    (tmp_path / "imports").mkdir()
    env = {**os.environ, "OCCUFLY_DATA_DIR": str(tmp_path / "data"),
           "OCCUFLY_IMPORT_ROOTS": str(tmp_path / "imports"), "OCCUFLY_ENV": "development",
           "OCCUFLY_LIFTING": "off", "OCCUFLY_JOB_PROCESSES": "1", "OCCUFLY_JOB_WORKERS": "1",
           "OCCUFLY_JOB_STALE_S": "2", "OCCUFLY_ARGON2_MEMORY_KIB": "1024",
           "OCCUFLY_ARGON2_TIME_COST": "1", "PYTHONPATH": str(REPO)}
    sid = _seed(tmp_path, env)
    exports = tmp_path / "data" / "exports"
    # a free port; the server counts as up only when it is this child that answers there
    server = ProcessServer(env, tmp_path / "server.log", start_timeout=60)
    server.start()
    try:
        c = httpx.Client(base_url=server.url, timeout=30)
        tok = c.post("/api/auth/login", json={"username": "admin", "password": PASSWORD}).json()
        hdr = {"Authorization": f"Bearer {tok['token']}"}
        c.cookies.clear()
        r = c.post(f"/api/scenes/{sid}/export", json={}, headers=hdr)
        assert r.status_code == 202, r.text
        jid = r.json()["id"]
        end = time.monotonic() + 60
        while time.monotonic() < end:  # until the export is writing frames
            j = c.get(f"/api/jobs/{jid}", headers=hdr).json()
            if j["status"] not in ("queued", "running") or j["progress"] >= 0.15:
                break
            time.sleep(0.02)
        assert j["status"] == "running", f"the export was not interruptible: {j}"
        workers = _descendants(server.pid)
        assert workers  # the job pool (and the export's own pool)
        server.kill9()
        end = time.monotonic() + 6
        while time.monotonic() < end and any(_alive(p) for p in workers):
            time.sleep(0.05)
        assert not [p for p in workers if _alive(p)], "job workers outlived the killed server"
        staged = _listing(exports)
        time.sleep(1.0)
        assert _listing(exports) == staged  # nobody writes any more
        assert not (exports / f"job_{jid}").exists()  # the dead attempt published nothing

        server.start()  # the same port: the client's URL stays valid
        end = time.monotonic() + 30
        while (j := c.get(f"/api/jobs/{jid}", headers=hdr).json())["status"] == "running" and \
                time.monotonic() < end:
            time.sleep(0.2)  # the new server's sweep: no heartbeat for 2 s -> interrupted
        assert j["status"] == "interrupted", j
        assert c.post(f"/api/jobs/{jid}/resume", headers=hdr).status_code == 200
        end = time.monotonic() + 90
        while (j := c.get(f"/api/jobs/{jid}", headers=hdr).json())["status"] in (
                "queued", "running") and time.monotonic() < end:
            time.sleep(0.2)
        assert j["status"] == "done" and j["attempts"] == 2, j
        out = exports / f"job_{jid}"
        assert j["result"]["output"] == str(out) and any(p.is_file() for p in out.rglob("*"))
        assert not [p.name for p in exports.iterdir() if ".attempt" in p.name]
    finally:
        server.stop()
