"""The production topology as local processes: two API processes on one PostgreSQL database,
the lifting worker, a Dask LocalCluster (docker-compose.yml runs the same as containers).

Checks: saves through both API processes are lifted once and in order; ``kill -9`` of the
lifting worker in the middle of a fill, then a restart, gives votes and labels identical to a
clean run; ``kill -9`` of an API process loses no acknowledged save (and the other process
carries on, leases included).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from sqlalchemy import select, update

from tests.app.conftest import PASSWORD, H, W, png, scratch_postgres, write_tiny_workspace

pytestmark = pytest.mark.postgres

PORTS = (9611, 9612)
REPO = Path(__file__).resolve().parents[2]


def _dense_workspace(path: Path) -> None:
    """The tiny scene's ground at 150 x 150 points (a fill takes ~1-2 s: time to kill it)."""
    write_tiny_workspace(path, n_side=150)


def _mask(version_seed: int) -> bytes:
    m = np.full((H, W), 6, np.uint8)  # grass
    cut = 8 + (version_seed * 7) % (W - 16)
    m[:, :cut] = 1  # road
    m[H // 4: H // 4 + 16, cut: cut + 16] = 13 if version_seed % 2 else 8  # ~10 m square
    return png(m)


class Topology:
    def __init__(self, tmp: Path, url: str, dask_address: str) -> None:
        self.tmp = tmp
        self.url = url
        self.env = {**os.environ, "OCCUFLY_DATABASE_URL": url,
                    "OCCUFLY_DATA_DIR": str(tmp / "data"),
                    "OCCUFLY_IMPORT_ROOTS": str(tmp / "imports"), "OCCUFLY_ENV": "development",
                    "OCCUFLY_LIFTING": "external", "OCCUFLY_DASK_ADDRESS": dask_address,
                    "OCCUFLY_FILL_DEBOUNCE_S": "0.3", "OCCUFLY_ARGON2_MEMORY_KIB": "1024",
                    "OCCUFLY_ARGON2_TIME_COST": "1", "OCCUFLY_AUTO_UPGRADE": "0",
                    "PYTHONPATH": str(REPO)}
        self.api: dict[int, subprocess.Popen] = {}
        self.worker: subprocess.Popen | None = None
        self.logs: list = []

    def _spawn(self, args: list[str], name: str) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "ab")  # noqa: SIM115 - closed in stop()
        self.logs.append(log)
        return subprocess.Popen([sys.executable, *args], cwd=REPO, env=self.env, stdout=log,
                                stderr=subprocess.STDOUT)

    def start_api(self, port: int) -> None:
        self.api[port] = self._spawn(["-m", "uvicorn", "app.main:app_from_env", "--factory",
                                      "--host", "127.0.0.1", "--port", str(port),
                                      "--log-level", "warning"], f"api{port}")

    def start_worker(self) -> None:
        self.worker = self._spawn(["-m", "app.lifting"], "lifting")

    def wait_healthy(self, port: int, timeout: float = 60) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.api[port].poll() is not None:
                raise AssertionError((self.tmp / f"api{port}.log").read_text()[-3000:])
            try:
                if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"API on {port} did not come up")

    def stop(self) -> None:
        for p in [*self.api.values(), self.worker]:
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in [*self.api.values(), self.worker]:
            if p is not None:
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
        for log in self.logs:
            log.close()


@pytest.fixture(scope="module")
def scratch_pg():
    with scratch_postgres("h6_topology") as url:
        yield url


def test_two_api_processes_lifting_worker_and_dask(tmp_path, scratch_pg):  # noqa: PLR0915
    from distributed import LocalCluster

    from app import db, security
    from app.annotations.models import MaskVersion
    from app.lifting.models import LiftQueueEntry, LiftStatus
    from app.scenes.models import Frame
    from app.storage import BlobStore
    from app.users import service as users
    from occufly.lifting import LiftState
    from occufly.scene import Scene as WsScene
    from occufly.workspace import Workspace

    db.upgrade(scratch_pg)
    security.configure(time_cost=1, memory_kib=1024)
    engine = db.make_engine(scratch_pg, pooled=False)
    sessions = db.make_sessionmaker(engine)
    with sessions() as s:
        for name, role in (("admin", "admin"), ("ann1", "annotator"), ("ann2", "annotator")):
            users.create_user(session=s, username=name, password=PASSWORD, role=role)
    (tmp_path / "imports").mkdir()
    _dense_workspace(tmp_path / "imports" / "dense_src")

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                           host="127.0.0.1",
                           dashboard_address=None)
    topo = Topology(tmp_path, scratch_pg, cluster.scheduler_address)
    try:
        for port in PORTS:
            topo.start_api(port)
        topo.start_worker()
        for port in PORTS:
            topo.wait_healthy(port)
        a, b = (httpx.Client(base_url=f"http://127.0.0.1:{p}", timeout=30) for p in PORTS)

        def login(c: httpx.Client, user: str) -> dict:
            r = c.post("/api/auth/login", json={"username": user, "password": PASSWORD})
            assert r.status_code == 200, r.text
            c.cookies.clear()
            return {"Authorization": f"Bearer {r.json()['token']}"}

        adm = login(a, "admin")  # a session made by A is valid on B
        h1, h2 = login(b, "ann1"), login(a, "ann2")
        r = a.post("/api/scenes/import", json={"name": "dense",
                                               "source": str(tmp_path / "imports" / "dense_src")},
                   headers=adm)
        assert r.status_code == 202, r.text
        jid = r.json()["id"]
        end = time.monotonic() + 60
        while (j := b.get(f"/api/jobs/{jid}", headers=adm).json())["status"] not in (
                "done", "failed") and time.monotonic() < end:
            time.sleep(0.2)  # the job runs on the Dask worker; B reads its progress
        assert j["status"] == "done", (j["message"], j["log_tail"])
        sid = b.get("/api/scenes", headers=adm).json()[-1]["id"]
        from app.users.models import User

        with sessions() as s:
            s.execute(update(Frame).where(Frame.scene_id == sid).values(selected=True))
            s.commit()
            ids = list(s.scalars(select(User.id).where(User.role != "admin")))
        r = a.post(f"/api/scenes/{sid}/members", json={"user_ids": ids}, headers=adm)
        assert r.status_code in (200, 201, 204), r.text
        ws = Workspace(tmp_path / "data" / "scenes" / "dense")

        # ---- saves through both processes: lifted once, in order -----------------------------
        f1 = a.post(f"/api/scenes/{sid}/next", headers=h1).json()["id"]  # lease on A ...
        f2 = b.post(f"/api/scenes/{sid}/next", headers=h2).json()["id"]
        acked: dict[int, list[int]] = {f1: [], f2: []}

        def save(c: httpx.Client, hdr: dict, fid: int) -> int:
            # only submitted versions are lifted (drafts never vote): every save submits, and
            # takes the frame back first when an earlier save submitted it (409 = not submitted)
            r = c.post(f"/api/frames/{fid}/reopen", headers=hdr)
            assert r.status_code in (200, 409), r.text
            base = acked[fid][-1] if acked[fid] else "none"
            r = c.put(f"/api/frames/{fid}/mask", content=_mask(len(acked[fid]) + fid),
                      params={"kind": "submitted"}, headers={**hdr, "If-Match": str(base)})
            assert r.status_code == 200, r.text
            acked[fid].append(r.json()["version"])
            return acked[fid][-1]

        for i in range(2):  # ... saves alternate between A and B
            save(b if i % 2 == 0 else a, h1, f1)
            save(a if i % 2 == 0 else b, h2, f2)
        index = {f["id"]: f["index"] for f in a.get(f"/api/scenes/{sid}/frames",
                                                   headers=adm).json()}

        def wait_lifted(timeout: float = 40) -> dict:
            want = {str(index[f]): str(v[-1]) for f, v in acked.items()}
            end = time.monotonic() + timeout
            while time.monotonic() < end:
                with sessions() as s:
                    pending = s.scalar(select(LiftQueueEntry.id).where(
                        LiftQueueEntry.scene_id == sid, LiftQueueEntry.status == "pending").limit(1))
                    st = s.get(LiftStatus, sid)
                if pending is None and st is not None and st.fill_state == "idle" and \
                        ws.lift_stats().get("versions") == want:
                    return want
                time.sleep(0.1)
            raise AssertionError(f"not lifted: {ws.lift_stats().get('versions')} != {want}; "
                                 + (tmp_path / "lifting.log").read_text()[-2000:])

        wait_lifted()
        with sessions() as s:
            q = s.execute(select(LiftQueueEntry.frame_id, LiftQueueEntry.version_id,
                                 LiftQueueEntry.status, LiftQueueEntry.applied_seq)
                          .where(LiftQueueEntry.scene_id == sid).order_by(LiftQueueEntry.id)).all()
        for fid, versions in acked.items():
            rows = [r for r in q if r.frame_id == fid]
            assert [r.version_id for r in rows] == versions  # one entry per version, in order
            assert all(r.status in ("applied", "superseded") for r in rows)
            assert rows[-1].status == "applied"
        seqs = [r.applied_seq for r in q]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)  # processed once, in order

        # ---- kill -9 of the lifting worker in the middle of a fill ---------------------------
        save(a, h1, f1)
        save(b, h2, f2)
        end = time.monotonic() + 30
        while time.monotonic() < end:
            with sessions() as s:
                st = s.get(LiftStatus, sid)
                if st.fill_state == "running":
                    break
            time.sleep(0.01)
        fills_before = st.fills
        topo.worker.send_signal(signal.SIGKILL)
        topo.worker.wait(10)
        with sessions() as s:
            st = s.get(LiftStatus, sid)
            assert st.fill_state == "running" and st.fills == fills_before  # died mid-fill
        assert ws.lift_stats().get("versions") != {str(index[f]): str(v[-1])
                                                   for f, v in acked.items()}
        topo.start_worker()
        wait_lifted()

        # a clean run over the same final masks: a fresh vote state, one fill
        ref = tmp_path / "ref"
        shutil.copytree(ws.root, ref, ignore=shutil.ignore_patterns("lifting"))
        ref_scene = WsScene.load(ref)
        clean = LiftState.open(ref, ref_scene)
        store = BlobStore(tmp_path / "data" / "masks")
        from app.pipeline import stored_mask_ids

        with sessions() as s:
            for fid, versions in acked.items():
                sha = s.get(MaskVersion, versions[-1]).sha256
                clean.apply_frame(index[fid], stored_mask_ids(store.get(sha), ref_scene.taxonomy),
                                  version=str(versions[-1]))
        want = clean.fill_and_denoise(write=False)
        np.testing.assert_array_equal(np.load(ws.votes), np.asarray(clean.votes))
        np.testing.assert_array_equal(ws.labels(), want.labels)
        assert {1, 6} <= set(np.unique(want.labels).tolist())  # road and grass: not trivial

        # ---- kill -9 of an API process while annotators save through it ----------------------
        stop = threading.Event()
        errors: list[str] = []

        def hammer() -> None:
            while not stop.is_set():
                try:
                    save(b, h2, f2)
                except (httpx.HTTPError, AssertionError) as e:
                    errors.append(str(e))
                    return

        t = threading.Thread(target=hammer)
        n0 = len(acked[f2])
        t.start()
        end = time.monotonic() + 10
        while len(acked[f2]) < n0 + 3 and time.monotonic() < end:
            time.sleep(0.01)
        topo.api[PORTS[1]].send_signal(signal.SIGKILL)
        topo.api[PORTS[1]].wait(10)
        t.join(10)
        stop.set()
        assert len(acked[f2]) >= n0 + 3 and errors  # B died under the load
        with sessions() as s:
            current = s.scalar(select(Frame.current_version_id).where(Frame.id == f2))
            stored = set(s.scalars(select(MaskVersion.id).where(MaskVersion.frame_id == f2)))
            queued = set(s.scalars(select(LiftQueueEntry.version_id).where(
                LiftQueueEntry.frame_id == f2)))
        assert set(acked[f2]) <= stored and set(acked[f2]) <= queued  # nothing acked is lost
        if current != acked[f2][-1]:  # committed while B died, its answer lost: a successor
            with sessions() as s:
                assert s.get(MaskVersion, current).base_version_id == acked[f2][-1]
            acked[f2].append(current)
        save(a, h2, f2)  # the lease taken on B carries on on A
        wait_lifted()
    finally:
        topo.stop()
        cluster.close()
        engine.dispose()
