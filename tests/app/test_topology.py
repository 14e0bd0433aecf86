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
from sqlalchemy import select, text, update

from tests.app.conftest import PASSWORD, H, W, png, scratch_postgres, write_tiny_workspace
from tests.harness import ProcessServer

pytestmark = pytest.mark.postgres

APIS = ("a", "b")  # two API processes, each on a free port (tests.harness.ProcessServer)
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
        self.api: dict[str, ProcessServer] = {}
        self.worker: subprocess.Popen | None = None
        self.logs: list = []

    def _spawn(self, args: list[str], name: str) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "ab")  # noqa: SIM115 - closed in stop()
        self.logs.append(log)
        return subprocess.Popen([sys.executable, *args], cwd=REPO, env=self.env, stdout=log,
                                stderr=subprocess.STDOUT)

    def start_api(self, name: str) -> None:
        self.api[name] = ProcessServer(self.env, self.tmp / f"api_{name}.log").spawn()

    def start_worker(self) -> None:
        self.worker = self._spawn(["-m", "app.lifting"], "lifting")

    def wait_healthy(self, name: str) -> None:
        self.api[name].wait_ready()

    def stop(self) -> None:
        for server in self.api.values():
            server.stop()
        if self.worker is not None and self.worker.poll() is None:
            self.worker.send_signal(signal.SIGTERM)
            try:
                self.worker.wait(15)
            except subprocess.TimeoutExpired:
                self.worker.kill()
        for log in self.logs:
            log.close()


@pytest.fixture  # one database per test: each test creates its own users and scenes
def scratch_pg():
    with scratch_postgres("h6_topology") as url:
        yield url


def test_two_api_processes_lifting_worker_and_dask(tmp_path, scratch_pg):  # noqa: PLR0915
    from distributed import LocalCluster

    from app import db, security
    from app.annotations.models import MaskVersion
    from app.blobs import BlobStore
    from app.lifting.models import LiftQueueEntry, LiftStatus
    from app.scenes.models import Frame
    from app.users import service as users
    from occufly.lifting import VoteStore
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
        for name in APIS:
            topo.start_api(name)
        topo.start_worker()
        for name in APIS:
            topo.wait_healthy(name)
        a, b = (httpx.Client(base_url=topo.api[name].url, timeout=30) for name in APIS)

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
        clean = VoteStore.open(ref, ref_scene)
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
        topo.api["b"].kill9()
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

        # ---- issue 37: the admin switches the scene to one model per painter on A; the
        # worker, another process, is told (PostgreSQL NOTIFY) and fills again with it
        with sessions() as s:
            fills = s.get(LiftStatus, sid).fills
        r = a.put(f"/api/scenes/{sid}/lifting", json={"model": "per_author"}, headers=adm)
        assert r.status_code == 200, r.text
        end = time.monotonic() + 40

        def filled_again() -> bool:  # the labels are written before the fill is counted
            with sessions() as s:
                counted = s.get(LiftStatus, sid).fills > fills
            return counted and ws.lift_stats().get("decision") == "confusion"

        while not filled_again() and time.monotonic() < end:
            time.sleep(0.1)
        stats = ws.lift_stats()
        assert stats.get("decision") == "confusion", (tmp_path / "lifting.log").read_text()[-2000:]
        assert stats["painters"] == {"authors": 2, "frames_with_author": 2, "frames_own": 0}
        with sessions() as s:
            assert s.get(LiftStatus, sid).fills > fills
    finally:
        topo.stop()
        cluster.close()
        engine.dispose()


# ---- issue 29: two lifting workers share the scenes ------------------------------------------
def _slots(sessions) -> int:  # noqa: ANN001
    from app.lifting.service import PG_SLOT_LOCK

    with sessions() as s:
        return s.scalar(text("SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND "
                             "classid = :c AND objsubid = 2 AND granted AND database = (SELECT "
                             "oid FROM pg_database WHERE datname = current_database())"),
                        {"c": PG_SLOT_LOCK})


def test_two_lifting_workers_share_the_scenes_and_take_over_after_kill_9(tmp_path, scratch_pg):  # noqa: PLR0915
    """Two ``python -m app.lifting`` processes on one PostgreSQL database: every scene is
    lifted by exactly one of them, in order (per-scene applied_seq, one votes_applied event per
    batch, one labels_updated per fill); ``kill -9`` of either in the middle of a fill moves
    its scenes to the other, whose labels equal a clean run's."""
    from fastapi.testclient import TestClient

    from app import db, security
    from app.annotations.models import MaskVersion
    from app.blobs import BlobStore
    from app.config import Settings
    from app.lifting.models import Event, LiftQueueEntry, LiftStatus
    from app.lifting.service import PG_SCENE_LOCK, preferred_slot
    from app.main import close, create_app
    from app.pipeline import stored_mask_ids
    from app.scenes.models import Frame, Scene
    from app.users import service as users
    from occufly.lifting import VoteStore
    from occufly.scene import Scene as WsScene
    from occufly.workspace import Workspace

    db.upgrade(scratch_pg)
    security.configure(time_cost=1, memory_kib=1024)
    (tmp_path / "imports").mkdir()
    settings = Settings(data_dir=tmp_path / "data", database_url=scratch_pg,
                        import_roots=[tmp_path / "imports"], env="development",
                        lifting="external", job_workers=2, argon2_memory_kib=1024,
                        argon2_time_cost=1, auto_upgrade=False)
    app = create_app(settings)  # the API in this process; lifting only in the two workers
    ctx = app.state.ctx
    names = ["ann0", "ann1", "ann2", "ann3"]
    with ctx.sessions() as s:
        users.create_user(session=s, username="admin", password=PASSWORD, role="admin")
        for n in names:
            users.create_user(session=s, username=n, password=PASSWORD, role="annotator")
    client = TestClient(app)

    def bearer(user: str) -> dict:
        r = client.post("/api/auth/login", json={"username": user, "password": PASSWORD})
        assert r.status_code == 200, r.text
        client.cookies.clear()
        return {"Authorization": f"Bearer {r.json()['token']}"}

    adm = bearer("admin")
    hdr = {n: bearer(n) for n in names}
    sids = []
    for k in range(4):
        src = tmp_path / "imports" / f"s{k}"
        _dense_workspace(src)
        r = client.post("/api/scenes/import", json={"name": f"s{k}", "source": str(src)},
                        headers=adm)
        assert r.status_code == 202, r.text
        ctx.jobs.wait(r.json()["id"], timeout=120)
        sid = client.get("/api/scenes", headers=adm).json()[-1]["id"]
        with ctx.sessions() as s:
            s.execute(update(Frame).where(Frame.scene_id == sid).values(selected=True))
            s.commit()
        sids.append(sid)
    with ctx.sessions() as s:
        from app.users.models import User

        uids = list(s.scalars(select(User.id).where(User.role == "annotator")))
    for sid in sids:
        r = client.post(f"/api/scenes/{sid}/members", json={"user_ids": uids}, headers=adm)
        assert r.status_code == 200, r.text
    assert {preferred_slot(sid, [0, 1]) for sid in sids} == {0, 1}  # both get scenes

    topo = Topology(tmp_path, scratch_pg, "")
    topo.env.pop("OCCUFLY_DASK_ADDRESS")
    workers: dict[str, subprocess.Popen] = {}

    def start(name: str) -> None:
        n = _slots(ctx.sessions)
        workers[name] = topo._spawn(["-m", "app.lifting"], name)  # noqa: SLF001
        end = time.monotonic() + 60
        while _slots(ctx.sessions) < n + 1:  # its slot lock taken: it is running
            assert workers[name].poll() is None, (tmp_path / f"{name}.log").read_text()[-3000:]
            assert time.monotonic() < end, "worker did not take a slot"
            time.sleep(0.05)

    acked: dict[int, list[int]] = {}  # frame id -> versions
    frame_of: dict[tuple[int, str], int] = {}

    def save(sid: int, user: str) -> int:
        h = hdr[user]
        fid = frame_of.get((sid, user))
        if fid is None:
            fid = frame_of[(sid, user)] = client.post(f"/api/scenes/{sid}/next",
                                                      headers=h).json()["id"]
            acked[fid] = []
        else:
            r = client.post(f"/api/frames/{fid}/reopen", headers=h)
            assert r.status_code == 200, r.text
        base = acked[fid][-1] if acked[fid] else "none"
        r = client.put(f"/api/frames/{fid}/mask", content=_mask(len(acked[fid]) + fid),
                       params={"kind": "submitted"}, headers={**h, "If-Match": str(base)})
        assert r.status_code == 200, r.text
        acked[fid].append(r.json()["version"])
        return fid

    with ctx.sessions() as s:
        index = dict(s.execute(select(Frame.id, Frame.index)).all())
        scene_of_frame = dict(s.execute(select(Frame.id, Frame.scene_id)).all())
        ws_of = {sid: Workspace(s.get(Scene, sid).workspace) for sid in sids}

    def wait_lifted(timeout: float = 90) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            done = True
            for sid in sids:
                want = {str(index[f]): str(v[-1]) for f, v in acked.items()
                        if scene_of_frame[f] == sid}
                with ctx.sessions() as s:
                    pending = s.scalar(select(LiftQueueEntry.id).where(
                        LiftQueueEntry.scene_id == sid,
                        LiftQueueEntry.status == "pending").limit(1))
                    st = s.get(LiftStatus, sid)
                if pending is not None or st is None or st.fill_state != "idle" or \
                        ws_of[sid].lift_stats().get("versions") != want:
                    done = False
                    break
            if done:
                return
            time.sleep(0.1)
        logs = "".join((tmp_path / f"{n}.log").read_text()[-1500:] for n in workers)
        raise AssertionError(f"scene {sid} not lifted: {logs}")

    def owner_rows(sid: int) -> list:
        with ctx.sessions() as s:
            return s.execute(select(LiftQueueEntry.id, LiftQueueEntry.applied_by,
                                    LiftQueueEntry.applied_seq, LiftQueueEntry.status)
                             .where(LiftQueueEntry.scene_id == sid)
                             .order_by(LiftQueueEntry.id)).all()

    def check_order(sid: int) -> None:
        rows = owner_rows(sid)
        seqs = [r.applied_seq for r in rows]
        assert seqs == list(range(1, len(rows) + 1)), seqs  # per scene, in queue order, once
        with ctx.sessions() as s:
            ev = s.execute(select(Event.kind, Event.payload).where(Event.scene_id == sid)
                           .order_by(Event.id)).all()
            fills = s.get(LiftStatus, sid).fills
        batches = [e.payload["seq"] for e in ev if e.kind == "votes_applied"]
        assert batches == sorted(set(batches)) and batches[-1] == len(rows)  # once per batch
        labels = [e.payload for e in ev if e.kind == "labels_updated"]
        assert len(labels) == fills  # one event per completed fill, by one worker

    def clean_labels(sid: int) -> tuple[np.ndarray, np.ndarray]:
        ws = ws_of[sid]
        ref = tmp_path / f"ref{sid}"
        shutil.rmtree(ref, ignore_errors=True)
        shutil.copytree(ws.root, ref, ignore=shutil.ignore_patterns("lifting"))
        ref_scene = WsScene.load(ref)
        clean = VoteStore.open(ref, ref_scene)
        store = BlobStore(tmp_path / "data" / "masks")
        with ctx.sessions() as s:
            for fid, versions in acked.items():
                if scene_of_frame[fid] == sid:
                    sha = s.get(MaskVersion, versions[-1]).sha256
                    clean.apply_frame(index[fid], stored_mask_ids(store.get(sha),
                                                                  ref_scene.taxonomy),
                                      version=str(versions[-1]))
        want = clean.fill_and_denoise(write=False)
        return np.asarray(clean.votes).copy(), want.labels

    def kill_mid_fill(victim: str, survivor: str) -> None:
        # a scene whose advisory lock the victim holds (its lock connection is named)
        pids = {n: p.pid for n, p in workers.items()}
        with ctx.sessions() as s:
            held = s.execute(text(
                "SELECT l.objid, a.application_name FROM pg_locks l JOIN pg_stat_activity a "
                "ON a.pid = l.pid WHERE l.locktype = 'advisory' AND l.classid = :c AND "
                "l.objsubid = 2 AND l.granted"), {"c": PG_SCENE_LOCK}).all()
        mine = sorted(int(o) for o, app_name in held if f":{pids[victim]}:" in app_name)
        assert mine, (held, pids)
        sid = mine[0]
        name_of = {sid: owner_rows(sid)[-1].applied_by}
        users_of = [u for (s_, u) in frame_of if s_ == sid]
        for u in users_of:
            save(sid, u)
        end = time.monotonic() + 60
        while time.monotonic() < end:
            with ctx.sessions() as s:
                st = s.get(LiftStatus, sid)
                # the victim has applied every save (a loaded host may start a fill after the
                # first batch, with later entries still pending) and is filling
                pending = s.scalar(select(LiftQueueEntry.id).where(
                    LiftQueueEntry.scene_id == sid, LiftQueueEntry.status == "pending").limit(1))
                if st.fill_state == "running" and pending is None:
                    break
            time.sleep(0.005)
        fills_before = st.fills
        workers[victim].send_signal(signal.SIGKILL)
        workers[victim].wait(10)
        with ctx.sessions() as s:
            st = s.get(LiftStatus, sid)
            assert st.fill_state == "running" and st.fills == fills_before  # died mid-fill
        wait_lifted()  # the survivor took the scene over
        # the victim had applied the entries before it died (its name stays on them)
        assert owner_rows(sid)[-1].applied_by == name_of[sid]
        with ctx.sessions() as s:
            last = s.execute(select(Event.payload).where(
                Event.scene_id == sid, Event.kind == "labels_updated")
                .order_by(Event.id.desc()).limit(1)).scalar_one()
        assert last["applied_by"].split(":")[1] == str(pids[survivor])  # the fill reran there
        votes, labels = clean_labels(sid)
        np.testing.assert_array_equal(np.load(ws_of[sid].votes), votes)
        np.testing.assert_array_equal(ws_of[sid].labels(), labels)
        assert {1, 6} <= set(np.unique(labels).tolist())
        check_order(sid)

    try:
        start("lift_a")
        start("lift_b")
        for sid in sids:
            for u in names[:2]:
                save(sid, u)
        for sid in sids:
            for u in names[:2]:
                save(sid, u)
        wait_lifted()
        by = {}
        for sid in sids:
            rows = owner_rows(sid)
            assert {r.status for r in rows} <= {"applied", "superseded"}
            who = {r.applied_by for r in rows}
            assert len(who) == 1, who  # exactly one worker lifted the scene
            by[sid] = who.pop()
            check_order(sid)
        assert len(set(by.values())) == 2  # both workers had scenes
        kill_mid_fill("lift_a", "lift_b")
        start("lift_c")  # a fresh worker joins: idle scenes that hash to it move to it
        kill_mid_fill("lift_b", "lift_c")
    finally:
        for p in workers.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in workers.values():
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for log in topo.logs:
            log.close()
        client.close()
        close(app)
