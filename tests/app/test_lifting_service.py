"""The lifting service (queue order, exactly once, crash resume), events across processes, job
attempt fencing and worker parent-death -- on SQLite and PostgreSQL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from sqlalchemy import select, update

from tests.app.conftest import H, W, png


def _frames(env, admin) -> list[dict]:  # noqa: ANN001
    scene = env.client.get("/api/scenes", headers=admin).json()[-1]
    return scene, env.client.get(f"/api/scenes/{scene['id']}/frames", headers=admin).json()


def _put(env, hdr, fid: int, cls: int, base) -> int:  # noqa: ANN001
    """Submit a mask (only submitted versions are lifted); a frame submitted before is
    reopened first, as its annotator would."""
    m = np.full((H, W), cls, np.uint8)
    m[:, : W // 3] = 1
    if base is not None:
        r = env.client.post(f"/api/frames/{fid}/reopen", headers=hdr)
        assert r.status_code == 200, r.text
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr, "If-Match": "none" if base is None else str(base)})
    assert r.status_code == 200, r.text
    return r.json()["version"]


def _queue(env, scene_id: int) -> list:
    from app.lifting.models import LiftQueueEntry

    with env.app.state.ctx.sessions() as s:
        return s.execute(select(LiftQueueEntry.id, LiftQueueEntry.frame_id,
                                LiftQueueEntry.version_id, LiftQueueEntry.status,
                                LiftQueueEntry.applied_seq)
                         .where(LiftQueueEntry.scene_id == scene_id)
                         .order_by(LiftQueueEntry.id)).all()


def test_queue_applied_in_version_order_exactly_once_and_resumed_after_a_crash(env):
    from app.lifting.models import LiftQueueEntry, LiftStatus
    from occufly.workspace import Workspace

    admin, ann, ann2 = env.bearer("admin"), env.bearer("annotator"), env.bearer("annotator2")
    env.import_tiny(admin)
    scene, frames = _frames(env, admin)
    sid = scene["id"]
    env.select_all(sid)
    ctx = env.app.state.ctx
    ctx.lifting.stop()  # the worker is down: saves still land in the queue
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    v1 = _put(env, ann, fa, 6, None)
    v2 = _put(env, ann, fa, 8, v1)
    v3 = _put(env, ann, fa, 13, v2)
    fb = env.client.post(f"/api/scenes/{sid}/next", headers=ann2).json()["id"]
    w1 = _put(env, ann2, fb, 6, None)
    assert [r.status for r in _queue(env, sid)] == ["pending"] * 4
    assert not ctx.lifting.wait_idle(sid, timeout=0.3)

    ctx.lifting.start()  # the worker comes back and drains the queue
    assert ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    q = _queue(env, sid)
    assert [(r.frame_id, r.version_id, r.status) for r in q] == [
        (fa, v1, "superseded"), (fa, v2, "superseded"), (fa, v3, "applied"), (fb, w1, "applied")]
    assert [r.applied_seq for r in q] == sorted(r.applied_seq for r in q)  # in queue order
    idx = {f["id"]: f["index"] for f in frames}
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=admin).json()
    assert st["included_versions"] == {str(fa): v3, str(fb): w1}
    assert st["filled_versions"] == {str(fa): v3, str(fb): w1}
    ws = Workspace(env.settings.workspaces_dir / "tiny")
    votes = np.array(np.load(ws.votes))
    labels = np.array(ws.labels())
    assert votes.sum() > 0 and set(np.unique(labels)) <= {0, 1, 6, 13}
    assert ctx.lifting.service.applied == 2

    # kill -9 after frame A's votes were written but before its entry was marked, in the
    # middle of the fill: the entry is pending again and the fill "running"
    ctx.lifting.stop()
    with ctx.sessions() as s:
        s.execute(update(LiftQueueEntry).where(LiftQueueEntry.version_id == v3)
                  .values(status="pending", applied_seq=None))
        s.execute(update(LiftStatus).where(LiftStatus.scene_id == sid)
                  .values(fill_state="running"))
        s.commit()
    ws.labels_path.unlink()  # the interrupted fill had not written the labels yet
    with ctx.sessions() as s:
        fills_before = s.get(LiftStatus, sid).fills
    ctx.lifting.start()
    assert ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    assert [r.status for r in _queue(env, sid)] == ["superseded", "superseded", "applied",
                                                    "applied"]
    assert ctx.lifting.service.applied == 1  # marked, not counted twice
    np.testing.assert_array_equal(np.load(ws.votes), votes)
    np.testing.assert_array_equal(ws.labels(), labels)  # the fill reran, same labels
    with ctx.sessions() as s:
        row = s.get(LiftStatus, sid)
        assert row.fills == fills_before + 1 and row.fill_state == "idle"
    assert idx[fa] != idx[fb]


def test_a_broken_scene_does_not_hold_up_the_others(env):
    """Entries of a scene whose workspace cannot be opened wait (error in its status); the
    other scenes' entries are applied meanwhile."""
    from app.lifting.models import LiftQueueEntry, LiftStatus
    from app.scenes.models import Frame, Scene

    admin, ann = env.bearer("admin"), env.bearer("annotator")
    env.import_tiny(admin)
    scene, _frames_ = _frames(env, admin)
    env.select_all(scene["id"])
    ctx = env.app.state.ctx
    ctx.lifting.stop()
    with ctx.sessions() as s:
        bad = Scene(name="gone", status="ready", workspace=str(env.settings.data_dir / "nope"))
        s.add(bad)
        s.flush()
        fr = Frame(scene_id=bad.id, index=0, name="x.png", width=W, height=H)
        s.add(fr)
        s.flush()
        s.add_all([LiftQueueEntry(scene_id=bad.id, frame_id=fr.id, frame_index=0,
                                  version_id=None, status="pending") for _ in range(300)])
        s.commit()  # more than one batch of the broken scene, queued first
        bad_id = bad.id
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=ann).json()["id"]
    v = _put(env, ann, fid, 6, None)
    ctx.lifting.start()
    assert ctx.lifting.wait_idle(scene["id"], timeout=30)
    assert [r.status for r in _queue(env, scene["id"])] == ["applied"]
    with ctx.sessions() as s:
        assert s.get(LiftStatus, bad_id).last_error  # reported, kept pending
        assert s.query(LiftQueueEntry).filter_by(scene_id=bad_id, status="pending").count() == 300
    assert v


def test_sqlite_refuses_a_second_worker_postgresql_gives_it_a_slot(env):
    """SQLite keeps the single-host rule (a lock file in the data directory); on PostgreSQL
    a second worker takes another advisory-lock slot and shares the scenes."""
    from app.bootstrap import build_lifting_service
    from app.lifting.service import LiftingBusy

    ctx = env.app.state.ctx
    assert ctx.lifting.service is not None  # the embedded worker holds the lock
    other = build_lifting_service(ctx)
    if env.backend == "sqlite":
        with pytest.raises(LiftingBusy, match="one lifting worker per data directory"):
            other.acquire()
        return
    other.acquire()
    try:
        mine = ctx.lifting.service._pg  # noqa: SLF001
        assert other._pg.slot != mine.slot  # noqa: SLF001
        assert {mine.slot, other._pg.slot} <= set(mine.live_slots())  # noqa: SLF001
    finally:
        other.stop()
    assert other._pg is None and mine.slot in mine.live_slots()  # noqa: SLF001


def test_events_reach_other_processes_once(env):
    """Two buses over one database stand for two processes."""
    from app import db
    from app.events import EventBus

    ctx = env.app.state.ctx
    engine = db.make_engine(env.settings.database_url)
    other = EventBus(engine, db.make_sessionmaker(engine))
    here, there = [], []
    ctx.events.subscribe("labels_updated", lambda m: here.append(m))
    other.subscribe("labels_updated", lambda m: there.append(m))
    other.subscribe("grid_updated", lambda m: there.append(m))
    t0 = time.monotonic()
    ctx.events.publish("labels_updated", 7, stamp="abc")
    ctx.events.publish("votes_applied", 7)  # a kind neither subscribes to
    while not there and time.monotonic() - t0 < 5:
        time.sleep(0.02)
    latency = time.monotonic() - t0
    time.sleep(0.6)
    other.close()
    engine.dispose()
    assert [(m.kind, m.scene_id, m.payload["stamp"]) for m in here] == [("labels_updated", 7, "abc")]
    assert [(m.kind, m.scene_id, m.payload["stamp"]) for m in there] == [("labels_updated", 7, "abc")]
    assert latency < 2.0


def test_listen_wakes_at_each_notify_and_stops_on_its_own_channel(pg_url):
    """A NOTIFY wakes the subscriber as it arrives, not at the listener's next heartbeat (the
    old loop woke only when psycopg's notifies() generator timed out: every cross-process
    event and every save's "frame queued" waited up to that heartbeat, 1 s / 0.5 s), and
    stopping ends the wait at once (an app's close waited out the heartbeat). The heartbeat
    is set to 120 s here so that the old behaviour fails by a wide margin."""
    import threading

    from sqlalchemy import text

    from app import db
    from app.events import listen, stop_channel_name, wake_listener

    engine = db.make_engine(pg_url)
    stop, woke = threading.Event(), threading.Event()
    channel = stop_channel_name()
    t = threading.Thread(target=listen, args=(engine, ("occufly_test_wake",)), daemon=True,
                         kwargs=dict(stop=stop, on_wake=woke.set, timeout_s=120,
                                     stop_channel=channel))
    t.start()
    try:
        assert woke.wait(30), "no first wake-up (LISTEN never started)"
        for _ in range(2):
            woke.clear()
            t0 = time.monotonic()
            with engine.connect() as c:
                c.execute(text("SELECT pg_notify('occufly_test_wake', 'x')"))
                c.commit()
            assert woke.wait(30), "a NOTIFY did not wake the subscriber"
            assert time.monotonic() - t0 < 30
        t0 = time.monotonic()
        stop.set()
        wake_listener(engine, channel)
        t.join(30)
        assert not t.is_alive() and time.monotonic() - t0 < 30
    finally:
        stop.set()
        wake_listener(engine, channel)
        engine.dispose()


def test_viewer_refreshes_on_the_event_not_on_a_poll(env):
    viewer = env.app.state.viewer
    assert viewer.watch_interval_s is None  # no file-stamp poll in the app
    queued = []
    viewer.refresh = lambda sid, classes=None: queued.append(sid)  # noqa: ARG005
    assert not viewer.on_labels_updated("42", "s1")  # nobody has scene 42 open
    viewer._data["42"] = object()  # noqa: SLF001 - as if a client had it open
    viewer._stamps["42"] = "s1"  # noqa: SLF001
    assert not viewer.on_labels_updated("42", "s1")  # already showing that stamp
    env.app.state.ctx.events.publish("labels_updated", 42, stamp="s2")
    assert queued == ["42"]  # subscribed by create_app: the event queued the refresh
    viewer._data.pop("42")  # noqa: SLF001


# ---- jobs: fencing and parent death ----------------------------------------------------------
def test_a_stale_job_attempt_cannot_write_the_row_or_the_output(env, tmp_path):
    from app.jobs import service as jobs
    from app.jobs.models import Job
    from app.jobs.registry import JobContext, StaleAttempt
    from app.jobs.runner import finish_attempt

    ctx = env.app.state.ctx
    with ctx.sessions() as s:
        job = jobs.create(session=s, kind="export", scene_id=None, params={}, user_id=None)
        jid = job.id

    def claim() -> int:
        with ctx.sessions() as s:
            s.execute(update(Job).where(Job.id == jid).values(
                status="running", attempts=Job.attempts + 1))
            s.commit()
            return s.scalar(select(Job.attempts).where(Job.id == jid))

    a1 = JobContext(ctx=ctx, job_id=jid, kind="export", scene_id=None, params={},
                    attempt=claim())
    final = tmp_path / "exports" / f"job_{jid}"
    out1 = a1.output_dir(final)
    (out1 / "frame.txt").write_text("attempt 1")
    a1.progress(0.5, "half way")
    # the server died; after a restart the job is interrupted and resumed: attempt 2
    with ctx.sessions() as s:
        s.execute(update(Job).where(Job.id == jid).values(status="interrupted"))
        s.commit()
        jobs.prepare_resume(session=s, job=s.get(Job, jid))
    a2 = JobContext(ctx=ctx, job_id=jid, kind="export", scene_id=None, params={},
                    attempt=claim())
    out2 = a2.output_dir(final)
    (out2 / "frame.txt").write_text("attempt 2")
    # the orphan of attempt 1 keeps going: every write is refused
    with pytest.raises(StaleAttempt):
        a1.progress(0.9, "orphan")
    with pytest.raises(StaleAttempt):
        a1.log("orphan line")
    out1.mkdir(parents=True, exist_ok=True)  # the orphan recreates its staging folder
    (out1 / "frame.txt").write_text("orphan")
    assert not finish_attempt(ctx.sessions, jid, a1.attempt, outputs=a1.outputs, status="done", message="done")
    assert not final.exists() and not out1.exists()
    with ctx.sessions() as s:
        j = s.get(Job, jid)
        assert (j.status, j.attempts) == ("running", 2) and "orphan" not in (j.log or "")
    a2.progress(0.5, "attempt 2 half way")
    assert finish_attempt(ctx.sessions, jid, a2.attempt, outputs=a2.outputs, status="done", message="done")
    assert (final / "frame.txt").read_text() == "attempt 2" and not out2.exists()
    with ctx.sessions() as s:
        assert s.get(Job, jid).status == "done"


def test_local_executor_workers_die_with_their_parent(tmp_path):
    """kill -9 of the process owning the pool: its workers exit within a few seconds."""
    pidfile = tmp_path / "worker.pid"
    code = textwrap.dedent(f"""
        import os, time
        from occufly.parallel import get_executor

        def work(path):
            open(path, "w").write(str(os.getpid()))
            time.sleep(120)

        if __name__ == "__main__":
            ex = get_executor(workers=2, die_with_caller=True)
            ex.submit(work, {str(pidfile)!r})
            time.sleep(120)
    """)
    script = tmp_path / "owner.py"
    script.write_text(code)
    proc = subprocess.Popen([sys.executable, str(script)], cwd=os.getcwd())
    try:
        end = time.monotonic() + 30
        while not (pidfile.exists() and pidfile.read_text()) and time.monotonic() < end:
            time.sleep(0.05)
        worker = int(pidfile.read_text())
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        end = time.monotonic() + 5
        while time.monotonic() < end and _alive(worker):
            time.sleep(0.05)
        assert not _alive(worker), "the pool worker outlived its killed parent"
    finally:
        if proc.poll() is None:
            proc.kill()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie waiting for its reaper is dead for our purpose
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_the_fill_thread_yields_the_cpu_to_requests(env):
    """OCCUFLY_FILL_NICE (default 5): the fill thread of a scene runs at a higher niceness
    than the process (request threads keep theirs), so a fill does not slow saves on a busy
    host; the setting is checked."""
    import threading

    from app.config import ConfigError, Settings

    admin, ann = env.bearer("admin"), env.bearer("annotator")
    env.import_tiny(admin)
    scene, _frames_ = _frames(env, admin)
    sid = scene["id"]
    env.select_all(sid)
    fa = env.client.post(f"/api/scenes/{sid}/next", headers=ann).json()["id"]
    _put(env, ann, fa, 6, None)
    ctx = env.app.state.ctx
    assert ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    fill = next(t for t in threading.enumerate() if t.name == f"occufly-fill-{sid}")
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert os.getpriority(os.PRIO_PROCESS, fill.native_id) == min(19, base + env.settings.fill_nice)
    assert env.settings.fill_nice == 5
    assert Settings.from_env({"OCCUFLY_FILL_NICE": "0", "OCCUFLY_ENV": "development"}).fill_nice == 0
    with pytest.raises(ConfigError, match="OCCUFLY_FILL_NICE must be 0..19"):
        Settings.from_env({"OCCUFLY_FILL_NICE": "25", "OCCUFLY_ENV": "development"})
