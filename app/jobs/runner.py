"""Executes jobs: supervisor threads in the server hand each job to an executor.

The job kinds are declared by their domains in :mod:`app.jobs.registry` (the runner looks
them up by name and knows none of them). Kinds marked ``remote`` (import, selection,
voxelize, export) run in the ``entry`` the composition root gives the runner
(:func:`app.bootstrap.run_job_process`) on the job executor from
:mod:`occufly.parallel` -- a local process pool whose workers die with this process
(:func:`occufly.parallel.die_with_parent`: parent-death signal + watchdog), or the Dask cluster
when ``OCCUFLY_DASK_ADDRESS`` is set -- so heavy pipeline work never competes with the API for
the server's interpreter. With ``job_processes=False`` (tests, debugging) they run in the
supervisor thread. The child talks to the same database: status, progress, log and result are
written there, and cancellation is read from there. Pipeline fan-out inside a job (per-frame
export) uses :meth:`JobContext.executor`.

Fencing (:mod:`app.jobs.registry`): every write of an attempt is conditional on its token;
output folders are moved into place inside the transaction that records ``done`` for that
attempt (:func:`finish_attempt`), so a stale attempt can neither mark the job nor touch its
output.

Several processes: each runner has an ``owner`` id and beats ``jobs.heartbeat_at`` of the jobs
it holds every :data:`HEARTBEAT_S`; any runner marks ``interrupted`` a queued/running job whose
owner has not beaten for :data:`STALE_S` (a killed API process), at start-up and periodically.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import threading
import time
import traceback
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import select, update

from app.db import utcnow
from app.jobs import service
from app.jobs.models import Job
from app.jobs.registry import KINDS, JobCancelled, JobContext, StaleAttempt, fenced, jsonable
from app.pipeline import PipelineMissing
from app.scenes.models import Scene
from occufly.errors import OccuflyError
from occufly.parallel import get_executor
from occufly.workspace import Workspace

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from app.config import Settings
    from app.context import AppContext

log = logging.getLogger("occufly.jobs")

HEARTBEAT_S = 2.0
# a runner silent this long is gone (OCCUFLY_JOB_STALE_S; tests shorten it)
STALE_S = float(os.environ.get("OCCUFLY_JOB_STALE_S") or 15.0)


class JobRunner:
    def __init__(self, workers: int = 2, *, settings: Settings, sessions: sessionmaker[Session],
                 run_here: Callable[[int, int], None], processes: bool = True,
                 entry: Callable[..., None] | None = None) -> None:
        """settings / sessions: the process's; ``run_here(job_id, attempt)`` runs a claimed
        attempt in this process (:func:`execute_job` over the process's context);
        ``entry(settings, job_id, attempt)`` runs a remote kind on the executor
        (:func:`app.bootstrap.run_job_process`, which builds that process's own context). All
        three come from the composition root, so this module imports none of it."""
        self.settings = settings
        self.sessions = sessions
        self.run_here = run_here
        self.entry = entry
        self.pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="occufly-job")
        self.workers = max(1, workers)
        self.processes = processes
        self.futures: dict[int, Future] = {}
        self.owner = f"{socket.gethostname()[:30]}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self._closed = False
        self._executor = None
        self._executor_lock = threading.Lock()
        self._held: set[int] = set()
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None

    def job_executor(self):
        """The executor remote job kinds run on (created on first use, one per runner):
        ``occufly.parallel``'s, with workers that die with this process."""
        with self._executor_lock:
            if self._executor is None:
                self._executor = get_executor(self.settings.dask_address,
                                              workers=max(2, self.workers), die_with_caller=True)
            return self._executor

    def start(self) -> None:
        """Start the heartbeat / stale-job sweep thread (idempotent)."""
        if self._beat is None:
            self._beat = threading.Thread(target=self._heartbeat_loop, daemon=True,
                                          name="occufly-job-heartbeat")
            self._beat.start()

    def submit(self, job_id: int) -> None:
        if self._closed:
            return
        with self.sessions() as s:  # ours from now on: no other process sweeps it
            s.execute(update(Job).where(Job.id == job_id, Job.status == "queued")
                      .values(owner=self.owner, heartbeat_at=utcnow()))
            s.commit()
        self._held.add(job_id)
        self.futures[job_id] = self.pool.submit(self._run, job_id)

    def wait(self, job_id: int, timeout: float = 60.0) -> None:
        fut = self.futures.get(job_id)
        if fut is not None:
            fut.result(timeout=timeout)

    def shutdown(self, wait: bool = True) -> None:
        self._closed = True
        self._stop.set()
        self.pool.shutdown(wait=wait, cancel_futures=True)
        if self._beat is not None:
            self._beat.join(timeout=5)
        if self._executor is not None:
            self._executor.close()

    def _heartbeat_loop(self) -> None:
        last_sweep = 0.0
        while not self._stop.wait(HEARTBEAT_S):
            try:
                with self.sessions() as s:
                    held = sorted(self._held)
                    if held:
                        s.execute(update(Job).where(Job.id.in_(held), Job.owner == self.owner,
                                                    Job.status.in_(("queued", "running")))
                                  .values(heartbeat_at=utcnow()))
                        s.commit()
                    if time.monotonic() - last_sweep > STALE_S / 2:
                        last_sweep = time.monotonic()
                        ids = service.mark_interrupted(session=s, stale_s=STALE_S,
                                                       alive_owner=self.owner)
                        if ids:
                            log.warning("jobs %s lost their runner; marked interrupted", ids)
            except Exception:  # noqa: BLE001 - database briefly away
                log.warning("job heartbeat failed", exc_info=True)

    def _run(self, job_id: int) -> None:
        try:
            self._run_attempt(job_id)
        finally:
            self._held.discard(job_id)

    def _run_attempt(self, job_id: int) -> None:
        with self.sessions() as s:
            res = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued")
                            .values(status="running", started_at=utcnow(), progress=0.0,
                                    attempts=Job.attempts + 1, message="running",
                                    owner=self.owner, heartbeat_at=utcnow()))
            s.commit()
            if res.rowcount != 1:
                return  # cancelled (or taken) before it started
            kind_name, attempt = s.execute(select(Job.kind, Job.attempts)
                                           .where(Job.id == job_id)).one()
        record = KINDS.get(kind_name)
        if self.processes and record is not None and record.remote:
            try:
                if self.entry is None:
                    raise RuntimeError("JobRunner has no process entry (app.bootstrap sets it)")
                self.job_executor().submit(self.entry, self.settings, job_id,
                                           attempt).result()
            except Exception as e:  # noqa: BLE001 - the child died or could not start
                log.exception("job %s: executor failure", job_id)
                finish_attempt(self.sessions, job_id, attempt, status="failed",
                               message=f"job process failed: {type(e).__name__}: {e}",
                               log_line=f"job process failed: {e}")
            return
        self.run_here(job_id, attempt)


def finish_attempt(sessions: sessionmaker[Session], job_id: int, attempt: int, *,
                   outputs: list[tuple[Path, Path]] = (), **values: Any) -> bool:
    """Record the attempt's outcome, if it is still the job's current attempt; move its
    output folders into place in the same transaction. False (and the staging folders
    removed) for a stale attempt."""
    with sessions() as s:
        values.setdefault("finished_at", utcnow())
        line = values.pop("log_line", None)
        job = s.get(Job, job_id)
        if job is not None and line:
            values["log"] = service.append_log(job, line)
        res = s.execute(fenced(job_id, attempt).values(**values))
        ok = res.rowcount == 1
        if ok:
            try:
                for staging, final in outputs:
                    _replace_dir(staging, final)
            except OSError:
                s.rollback()
                raise
            s.commit()
        else:
            s.rollback()
    if not ok:
        log.warning("job %s: attempt %s is stale; its outcome (%s) is discarded", job_id,
                    attempt, values.get("status"))
    for staging, _final in outputs:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return ok


def _replace_dir(staging: Path, final: Path) -> None:
    if not staging.exists():
        return
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.old.{uuid.uuid4().hex[:8]}"
        os.replace(final, old)
    os.replace(staging, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def execute_job(ctx: AppContext, job_id: int, attempt: int | None = None) -> None:
    """Run attempt ``attempt`` of a job already marked ``running`` and record its outcome
    (any process). ``attempt`` None = the job's current attempt."""
    with ctx.sessions() as s:
        job = s.get(Job, job_id)
        attempt = job.attempts if attempt is None else attempt
        jc = JobContext(ctx=ctx, job_id=job.id, kind=job.kind, scene_id=job.scene_id,
                        params=dict(job.params or {}), attempt=attempt)
        if job.attempts != attempt or job.status != "running":
            log.warning("job %s: attempt %s is stale before it started", job_id, attempt)
            return
    record = KINDS.get(jc.kind)
    if record is None:
        finish_attempt(ctx.sessions, job_id, attempt, status="failed",
                       message=f"unknown job kind {jc.kind!r}")
        return
    try:
        result = record.run(jc)
    except StaleAttempt as e:
        log.warning("job %s: %s; stopping without writing", job_id, e)
        _drop_staging(jc)
    except JobCancelled:
        if finish_attempt(ctx.sessions, job_id, attempt, status="cancelled", message="cancelled",
                   log_line="cancelled"):
            _on_failure(jc, "cancelled")
        _drop_staging(jc)
    except (PipelineMissing, OccuflyError) as e:
        if finish_attempt(ctx.sessions, job_id, attempt, status="failed", message=str(e)[:500],
                   log_line=f"failed: {e}"):
            _on_failure(jc, str(e))
        _drop_staging(jc)
    except Exception as e:  # a bug: keep the traceback in the job log
        log.exception("job %s (%s) crashed", job_id, jc.kind)
        tb = traceback.format_exc(limit=8)
        if finish_attempt(ctx.sessions, job_id, attempt, status="failed",
                          message=f"internal error: {type(e).__name__}: {e}"[:500], log_line=tb):
            _on_failure(jc, str(e))
        _drop_staging(jc)
    else:
        if finish_attempt(ctx.sessions, job_id, attempt, outputs=jc.outputs, status="done", progress=1.0,
                          message="done", result=jsonable(result or {}), log_line="done"):
            _after_done(ctx, jc, record)


def _after_done(ctx: AppContext, jc: JobContext, record) -> None:  # noqa: ANN001 - JobKind
    """The kind's ``done_event`` (with the scene's workspace stamp) and its ``on_done`` hook;
    the job is done whatever they do (a lost notice only delays a refresh)."""
    if record.done_event is not None and ctx.events is not None and jc.scene_id is not None:
        try:
            with ctx.sessions() as s:
                ws = s.get(Scene, jc.scene_id).workspace
            ctx.events.publish(record.done_event, jc.scene_id, stamp=Workspace(ws).stamp(),
                               job=jc.job_id)
        except Exception:  # noqa: BLE001
            log.warning("job %s: publishing %s failed", jc.job_id, record.done_event,
                        exc_info=True)
    if record.on_done is not None:
        try:
            record.on_done(jc)
        except Exception:  # noqa: BLE001 - e.g. export retention: it runs again next time
            log.exception("after job %s (%s)", jc.job_id, jc.kind)


def _drop_staging(jc: JobContext) -> None:
    for staging, _final in jc.outputs:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def _on_failure(jc: JobContext, message: str) -> None:
    record = KINDS.get(jc.kind)
    if record is not None and record.on_failure is not None:
        try:
            record.on_failure(jc, message)
        except Exception:  # noqa: BLE001 - never mask the job's own failure
            log.exception("failure hook of job %s", jc.job_id)
