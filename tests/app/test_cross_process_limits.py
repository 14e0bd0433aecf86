"""Security round three (issue 36), carried over from round two: limits that hold across API
processes. Two real API processes (uvicorn children) share one PostgreSQL database:

- the job quota: concurrent job requests spread over both processes create at most the quota
  (before: each process serialised its own requests only, so up to 2 x the quota);
- the viewer-socket cap per user counts the sockets of both processes (before: per process);
- an open viewer socket in one process closes when the membership is removed through the
  other (the access re-check reads the database).

The review-item and comment quotas and the socket leases' expiry (one process, both
databases) are in tests/app/test_shared_limits.py; the minimum body rate in
tests/app/test_body_rate.py.
"""

from __future__ import annotations

import asyncio
import os
import time
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


# ---- viewer sockets --------------------------------------------------------------------------
async def _open(port: int, token: str, scene_id: int):  # noqa: ANN202
    """A viewer socket as the browser opens it (session and scene cookies, viser's protocol)."""
    import viser
    from websockets.asyncio.client import connect
    from websockets.exceptions import ConnectionClosed

    from tests.viewer.viewer_live import camera_message

    ws = await connect(f"ws://127.0.0.1:{port}/viewer",
                       subprotocols=[f"viser-v{viser.__version__}"],
                       additional_headers={"Cookie": f"occufly_session={token}; "
                                                     f"occufly_viewer_scene={scene_id}",
                                           "Origin": f"http://127.0.0.1:{port}"},
                       max_size=None, open_timeout=30)
    try:
        await ws.send(camera_message())
    except ConnectionClosed:  # refused at once (the caller reads close_code)
        pass
    return ws


async def _closed_within(ws, limit_s: float) -> float | None:  # noqa: ANN001
    """Seconds until the server closed ``ws``, reading what it sends; None: still open."""
    from websockets.exceptions import ConnectionClosed

    t0 = time.perf_counter()
    while (left := limit_s - (time.perf_counter() - t0)) > 0:
        try:
            await asyncio.wait_for(ws.recv(), timeout=max(0.05, left))
        except TimeoutError:
            return None
        except ConnectionClosed:
            return time.perf_counter() - t0
    return None


def _open_rows(pair) -> int:  # noqa: ANN001
    from sqlalchemy import func, select

    from app.shared_limits import ViewerSocket

    with pair.sessions() as s:
        return int(s.scalar(select(func.count()).select_from(ViewerSocket)) or 0)


def test_viewer_socket_cap_holds_across_two_api_processes(pair):
    """Cap 2 per user: 4 sockets of one reviewer opened alternately through A and B -- the
    first two stay open, the other two are closed 1008 naming the cap, whichever process they
    reached (before: each process counted its own, so all 4 stayed open). Closing one on A
    frees a place for a socket on B."""
    port = {name: int(server.port) for name, server in zip("ab", pair.api, strict=True)}
    tok = pair.tokens["reviewer"]

    async def run() -> dict:
        socks = []
        for name in "abab":
            socks.append(await _open(port[name], tok, pair.scene_id))
            # the open ones keep receiving the scene; a refused one is closed at once
            await asyncio.sleep(0.3)
        closed = await asyncio.gather(*(_closed_within(w, 2.0) for w in socks))
        rows = _open_rows(pair)
        await socks[0].close()
        t0 = time.monotonic()
        while _open_rows(pair) > 1 and time.monotonic() - t0 < 5:
            await asyncio.sleep(0.05)
        again = await _open(port["b"], tok, pair.scene_id)
        again_closed = await _closed_within(again, 1.5)
        out = {"closed": closed, "codes": [w.close_code for w in socks],
               "reasons": [w.close_reason for w in socks], "rows": rows,
               "again_closed": again_closed, "again_code": again.close_code}
        for w in (*socks, again):
            await w.close()
        return out

    out = asyncio.run(run())
    accepted = sum(c is None for c in out["closed"])
    print(f"2 API processes, cap {SOCKET_CAP}, 4 sockets of one user: {accepted} stayed open")
    assert out["closed"][0] is None and out["closed"][1] is None, out
    assert out["codes"][2:] == [1008, 1008], out
    assert all("too many 3D viewer windows" in r for r in out["reasons"][2:]), out
    assert out["rows"] == SOCKET_CAP, out
    assert out["again_closed"] is None, out  # the place freed on A is taken on B
    t0 = time.monotonic()  # every closed socket's row is deleted by the process that held it
    while _open_rows(pair) and time.monotonic() - t0 < 5:
        time.sleep(0.05)
    assert _open_rows(pair) == 0


def test_removal_through_one_process_closes_the_socket_on_the_other(pair):
    """The reviewer's viewer socket is on B; an admin removes them from the scene through A:
    the socket closes within CLOSE_LIMIT_S (B re-reads the membership from the database 4
    times a second), with 1008."""
    port_b = int(pair.api[1].port)

    async def run() -> dict:
        ws = await _open(port_b, pair.tokens["reviewer"], pair.scene_id)
        still = await _closed_within(ws, 1.0)  # open, receiving the scene
        t0 = time.perf_counter()
        r = await asyncio.to_thread(
            httpx.delete, f"{pair.api[0].url}/api/scenes/{pair.scene_id}/members/"
                          f"{pair.user_ids['reviewer']}", headers=pair.headers("admin"),
            timeout=30)
        assert r.status_code == 204, r.text
        request_s = time.perf_counter() - t0
        closed = await _closed_within(ws, CLOSE_LIMIT_S + 1.0)
        return {"still_open": still, "request_s": request_s, "closed_s": closed,
                "code": ws.close_code}

    out = asyncio.run(run())
    print(f"socket on B closed {out['closed_s']} s after the removal through A "
          f"(request {out['request_s']:.2f} s)")
    assert out["still_open"] is None, out
    assert out["closed_s"] is not None and out["closed_s"] <= CLOSE_LIMIT_S, out
    assert out["code"] == 1008, out
