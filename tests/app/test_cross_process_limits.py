"""Security round three (issue 36), carried over from round two: limits that hold across API
processes. Two real API processes (uvicorn children) share one PostgreSQL database:

- the job quota: concurrent job requests spread over both processes create at most the quota
  (before: each process serialised its own requests only, so up to 2 x the quota);
- the viewer-socket cap per user counts the sockets of both processes (before: per process);
- an open viewer socket in one process closes when the membership is removed through the
  other (the access re-check reads the database).

The review-item and comment quotas (one process, both databases, concurrent requests) are in
tests/app/test_review_quotas.py; the minimum body rate in tests/app/test_body_rate.py.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from tests.app.conftest import PASSWORD, scratch_postgres, write_tiny_workspace
from tests.harness import ProcessServer

pytestmark = [pytest.mark.postgres, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
JOB_QUOTA = 2
SOCKET_CAP = 2
CLOSE_LIMIT_S = 2.0  # as tests/app/test_viewer_socket_access.py (re-check every 0.25 s)
# the app served by uvicorn with two changes: a job is never handed to the runner, so every
# job the quota let in stays queued (and counted) for the whole test -- what is checked is how
# many the quota lets in, not how fast they run; and a request that passed the quota check
# waits 0.2 s before going on to create its job, which widens the race between the count and
# the insert to where every run hits it (a race the fix must close, not a timing it may win)
LAUNCH = ("import sys, time, uvicorn\n"
          "from app.jobs import runner, service\n"
          "runner.JobRunner.submit = lambda self, job_id: None\n"
          "_check = service.check_quota\n"
          "def slow_check(**kw):\n"
          "    _check(**kw)\n"
          "    time.sleep(0.2)\n"
          "service.check_quota = slow_check\n"
          "uvicorn.run('app.main:app_from_env', factory=True, host='127.0.0.1',"
          " port=int(sys.argv[1]), log_level='warning')\n")


class Pair:
    """Two API processes on one PostgreSQL database, an admin, a reviewer, a ready scene."""

    def __init__(self, tmp: Path, url: str) -> None:
        from app import db, security
        from app.scenes.models import Scene, SceneMember
        from app.scenes.service import sync_frames
        from app.users import service as users
        from occufly.scene import Scene as WsScene

        db.upgrade(url)
        security.configure(time_cost=1, memory_kib=1024)
        self.engine = db.make_engine(url, pooled=False)
        self.sessions = db.make_sessionmaker(self.engine)
        ws = write_tiny_workspace(tmp / "data" / "scenes" / "tiny")
        with self.sessions() as s:
            ids = {name: users.create_user(session=s, username=name, password=PASSWORD,
                                           role=name).id for name in ("admin", "reviewer")}
            scene = Scene(name="tiny", status="importing", workspace=str(ws), source=str(ws))
            s.add(scene)
            s.commit()
            sync_frames(session=s, scene=scene, ws_scene=WsScene.load(ws))
            s.add(SceneMember(scene_id=scene.id, user_id=ids["reviewer"]))
            s.commit()
            self.scene_id, self.user_ids = scene.id, ids
        (tmp / "imports").mkdir()
        env = {**os.environ, "OCCUFLY_DATABASE_URL": url, "OCCUFLY_DATA_DIR": str(tmp / "data"),
               "OCCUFLY_IMPORT_ROOTS": str(tmp / "imports"), "OCCUFLY_ENV": "development",
               "OCCUFLY_LIFTING": "off", "OCCUFLY_AUTO_UPGRADE": "0",
               "OCCUFLY_ARGON2_MEMORY_KIB": "1024", "OCCUFLY_ARGON2_TIME_COST": "1",
               "OCCUFLY_JOB_STALE_S": "600",  # the queued jobs are never swept
               "OCCUFLY_ACTIVE_JOBS_PER_USER": str(JOB_QUOTA),
               "OCCUFLY_VIEWER_SOCKETS_PER_USER": str(SOCKET_CAP), "PYTHONPATH": str(REPO)}
        self.api = [ProcessServer(env, tmp / f"api_{n}.log", ("{python}", "-c", LAUNCH, "{port}"))
                    for n in ("a", "b")]
        for server in self.api:
            server.spawn()
        try:
            for server in self.api:
                server.wait_ready()
        except BaseException:
            self.stop()
            raise
        self.tokens = {name: self._login(name) for name in ("admin", "reviewer")}

    def _login(self, name: str) -> str:
        r = httpx.post(f"{self.api[0].url}/api/auth/login",
                       json={"username": name, "password": PASSWORD}, timeout=30)
        assert r.status_code == 200, r.text
        return r.json()["token"]

    def headers(self, name: str) -> dict:
        return {"Authorization": f"Bearer {self.tokens[name]}"}

    def stop(self) -> None:
        for server in self.api:
            server.stop()
        self.engine.dispose()


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    with scratch_postgres("cross_process") as url:
        p = Pair(tmp_path_factory.mktemp("cross_process"), url)
        try:
            yield p
        finally:
            p.stop()


def test_job_quota_holds_across_two_api_processes(pair):
    """20 concurrent job requests of one admin, alternately to process A and B, with the quota
    at 2 active jobs per user: 2 are accepted, every other one is 429 naming the quota."""
    from sqlalchemy import func, select

    from app.jobs.models import Job

    def post(i: int) -> httpx.Response:
        server = pair.api[i % 2]
        return httpx.post(f"{server.url}/api/scenes/{pair.scene_id}/voxelize",
                          headers=pair.headers("admin"), timeout=60)

    with ThreadPoolExecutor(20) as pool:
        answers = list(pool.map(post, range(20)))
    codes = [r.status_code for r in answers]
    accepted = codes.count(202)
    with pair.sessions() as s:
        active = s.scalar(select(func.count()).select_from(Job).where(
            Job.status.in_(("queued", "running"))))
    print(f"2 API processes, quota {JOB_QUOTA}, 20 concurrent requests: {accepted} accepted, "
          f"{active} jobs queued")
    refused = [r for r in answers if r.status_code == 429]
    assert accepted + len(refused) == 20, codes
    assert accepted == JOB_QUOTA and active == JOB_QUOTA, codes
    assert all("OCCUFLY_ACTIVE_JOBS_PER_USER" in r.json()["detail"] for r in refused)
    assert all(r.headers.get("retry-after") == "10" for r in refused)
