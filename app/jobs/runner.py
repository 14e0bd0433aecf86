"""Executes jobs: supervisor threads in the server hand each job to an executor.

Each job kind is a function ``run(jc: JobContext) -> dict | None`` registered in
:data:`KINDS` (see ``app/jobs/kinds.py``). Kinds marked ``remote`` (import, selection,
voxelize, export) run in :func:`app.bootstrap.run_job_process` on the job executor from
:mod:`occufly.parallel` -- a local process pool whose workers die with this process
(:func:`occufly.parallel.die_with_parent`: parent-death signal + watchdog), or the Dask cluster
when ``OCCUFLY_DASK_ADDRESS`` is set -- so heavy pipeline work never competes with the API for
the server's interpreter. With ``job_processes=False`` (tests, debugging) they run in the
supervisor thread. The child talks to the same database: status, progress, log and result are
written there, and cancellation is read from there. Pipeline fan-out inside a job (per-frame
export) uses :meth:`JobContext.executor`.

Fencing: claiming a job increments ``jobs.attempts``; that number is the attempt's token.
Every write of an attempt -- progress, log, the outcome -- is an ``UPDATE ... WHERE attempts =
<token> AND status = 'running'``; a write that matches nothing raises :class:`StaleAttempt`
and the attempt stops. Output folders are written under an attempt-private name
(:meth:`JobContext.output_dir`) and moved into place inside the transaction that records
``done`` for that attempt, so a stale attempt can neither mark the job nor touch its output.

Several processes: each runner has an ``owner`` id and beats ``jobs.heartbeat_at`` of the jobs
it holds every :data:`HEARTBEAT_S`; any runner marks ``interrupted`` a queued/running job whose
owner has not beaten for :data:`STALE_S` (a killed API process), at start-up and periodically.

Progress is written to the job row at most every 0.3 s; cancellation is cooperative (the
progress callback raises :class:`JobCancelled` once a cancel was requested).
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import select, update

from app.db import utcnow
from app.jobs import service
from app.jobs.models import Job
from app.pipeline import PipelineMissing
from app.scenes import storage
from occufly.errors import OccuflyError
from occufly.parallel import get_executor

if TYPE_CHECKING:
    from app.context import AppContext

log = logging.getLogger("occufly.jobs")

HEARTBEAT_S = 2.0
# a runner silent this long is gone (OCCUFLY_JOB_STALE_S; tests shorten it)
STALE_S = float(os.environ.get("OCCUFLY_JOB_STALE_S") or 15.0)


class JobCancelled(Exception):
    pass


class StaleAttempt(Exception):
    """This attempt is no longer the job's current one: it must not write anything."""


def _fenced(job_id: int, attempt: int):
    return update(Job).where(Job.id == job_id, Job.attempts == attempt, Job.status == "running")


@dataclass
class JobContext:
    ctx: AppContext
    job_id: int
    kind: str
    scene_id: int | None
    params: dict
    attempt: int = 0
    _last_write: float = 0.0
    _last_msg: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock)
    outputs: list[tuple[Path, Path]] = field(default_factory=list)  # (staging, final)

    def _current(self, s) -> Job:  # noqa: ANN001
        job = s.get(Job, self.job_id)
        if job is None or job.attempts != self.attempt or job.status != "running":
            raise StaleAttempt(f"job {self.job_id} attempt {self.attempt} is stale (the job is "
                               f"{getattr(job, 'status', 'gone')}, attempt "
                               f"{getattr(job, 'attempts', '?')})")
        return job

    def progress(self, fraction: float, message: str = "") -> None:
        now = time.monotonic()
        if now - self._last_write < 0.3 and message == self._last_msg and fraction < 1.0:
            return
        self._last_write = now
        with self._lock, self.ctx.sessions() as s:
            job = self._current(s)
            if job.cancel_requested:
                raise JobCancelled()
            values: dict = {"progress": float(max(0.0, min(1.0, fraction)))}
            if message:
                values["message"] = message[:500]
                if message != self._last_msg:
                    values["log"] = service.append_log(job, f"{fraction:6.1%} {message}")
            if s.execute(_fenced(self.job_id, self.attempt).values(**values)).rowcount != 1:
                s.rollback()
                raise StaleAttempt(f"job {self.job_id} attempt {self.attempt} is stale")
            s.commit()
        self._last_msg = message

    def log(self, line: str) -> None:
        with self._lock, self.ctx.sessions() as s:
            job = self._current(s)
            if s.execute(_fenced(self.job_id, self.attempt).values(
                    log=service.append_log(job, line))).rowcount != 1:
                s.rollback()
                raise StaleAttempt(f"job {self.job_id} attempt {self.attempt} is stale")
            s.commit()

    def output_dir(self, final: Path) -> Path:
        """An attempt-private folder to write ``final``'s content into; it replaces ``final``
        when (and only if) this attempt records ``done``."""
        final = Path(final)
        staging = final.parent / f".{final.name}.attempt{self.attempt}"
        final.parent.mkdir(parents=True, exist_ok=True)
        for old in final.parent.glob(f".{final.name}.attempt*"):  # this and earlier attempts'
            tail = old.name.rsplit(".attempt", 1)[-1]
            if tail.isdigit() and int(tail) <= self.attempt:
                shutil.rmtree(old, ignore_errors=True)
        staging.mkdir()
        self.outputs.append((staging, final))
        return staging

    def executor(self):
        """Fan-out executor inside a job: Dask when configured, else a local pool whose
        workers die with this job process."""
        return get_executor(self.ctx.settings.dask_address, die_with_caller=True)


KINDS: dict[str, Callable[[JobContext], dict | None]] = {}


def kind(name: str):
    def deco(fn: Callable[[JobContext], dict | None]):
        KINDS[name] = fn
        return fn

    return deco


class JobRunner:
    def __init__(self, workers: int = 2, *, processes: bool = True,
                 entry: Callable[..., None] | None = None) -> None:
        """``entry(settings, job_id, attempt)``: what runs a remote job kind on the executor
        (:func:`app.bootstrap.run_job_process`, which builds that process's own context;
        injected so this module never imports the composition root)."""
        self.entry = entry
        self.pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="occufly-job")
        self.workers = max(1, workers)
        self.processes = processes
        self.ctx: AppContext | None = None
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
                from occufly.parallel import get_executor

                self._executor = get_executor(self.ctx.settings.dask_address,
                                              workers=max(2, self.workers), die_with_caller=True)
            return self._executor

    def bind(self, ctx: AppContext) -> None:
        self.ctx = ctx

    def start(self) -> None:
        """Start the heartbeat / stale-job sweep thread (idempotent)."""
        if self._beat is None:
            self._beat = threading.Thread(target=self._heartbeat_loop, daemon=True,
                                          name="occufly-job-heartbeat")
            self._beat.start()

    def submit(self, job_id: int) -> None:
        if self._closed:
            return
        with self.ctx.sessions() as s:  # ours from now on: no other process sweeps it
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
                with self.ctx.sessions() as s:
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
        # kinds registers itself with this module's registry (it imports runner): a
        # module-level import would be a cycle, so the side-effect import stays here
        from app.jobs import kinds  # noqa: F401 - registers the job kinds

        ctx = self.ctx
        with ctx.sessions() as s:
            res = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued")
                            .values(status="running", started_at=utcnow(), progress=0.0,
                                    attempts=Job.attempts + 1, message="running",
                                    owner=self.owner, heartbeat_at=utcnow()))
            s.commit()
            if res.rowcount != 1:
                return  # cancelled (or taken) before it started
            kind_name, attempt = s.execute(select(Job.kind, Job.attempts)
                                           .where(Job.id == job_id)).one()
        fn = KINDS.get(kind_name)
        if self.processes and getattr(fn, "remote", False):
            try:
                if self.entry is None:
                    raise RuntimeError("JobRunner has no process entry (app.bootstrap sets it)")
                self.job_executor().submit(self.entry, ctx.settings, job_id,
                                           attempt).result()
            except Exception as e:  # noqa: BLE001 - the child died or could not start
                log.exception("job %s: executor failure", job_id)
                _finish(ctx, job_id, attempt, status="failed",
                        message=f"job process failed: {type(e).__name__}: {e}",
                        log_line=f"job process failed: {e}")
            return
        execute_job(ctx, job_id, attempt)


def _finish(ctx: AppContext, job_id: int, attempt: int, *,
            outputs: list[tuple[Path, Path]] = (), **values: Any) -> bool:
    """Record the attempt's outcome, if it is still the job's current attempt; move its
    output folders into place in the same transaction. False (and the staging folders
    removed) for a stale attempt."""
    with ctx.sessions() as s:
        values.setdefault("finished_at", utcnow())
        line = values.pop("log_line", None)
        job = s.get(Job, job_id)
        if job is not None and line:
            values["log"] = service.append_log(job, line)
        res = s.execute(_fenced(job_id, attempt).values(**values))
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
    from app.jobs import kinds  # noqa: F401 - registers the job kinds (a cycle at module level)

    with ctx.sessions() as s:
        job = s.get(Job, job_id)
        attempt = job.attempts if attempt is None else attempt
        jc = JobContext(ctx=ctx, job_id=job.id, kind=job.kind, scene_id=job.scene_id,
                        params=dict(job.params or {}), attempt=attempt)
        if job.attempts != attempt or job.status != "running":
            log.warning("job %s: attempt %s is stale before it started", job_id, attempt)
            return
    fn = KINDS.get(jc.kind)
    if fn is None:
        _finish(ctx, job_id, attempt, status="failed", message=f"unknown job kind {jc.kind!r}")
        return
    try:
        result = fn(jc)
    except StaleAttempt as e:
        log.warning("job %s: %s; stopping without writing", job_id, e)
        _drop_staging(jc)
    except JobCancelled:
        if _finish(ctx, job_id, attempt, status="cancelled", message="cancelled",
                   log_line="cancelled"):
            _on_failure(jc, "cancelled")
        _drop_staging(jc)
    except (PipelineMissing, OccuflyError) as e:
        if _finish(ctx, job_id, attempt, status="failed", message=str(e)[:500],
                   log_line=f"failed: {e}"):
            _on_failure(jc, str(e))
        _drop_staging(jc)
    except Exception as e:  # a bug: keep the traceback in the job log
        log.exception("job %s (%s) crashed", job_id, jc.kind)
        tb = traceback.format_exc(limit=8)
        if _finish(ctx, job_id, attempt, status="failed",
                   message=f"internal error: {type(e).__name__}: {e}"[:500], log_line=tb):
            _on_failure(jc, str(e))
        _drop_staging(jc)
    else:
        if _finish(ctx, job_id, attempt, outputs=jc.outputs, status="done", progress=1.0,
                   message="done", result=_jsonable(result or {}), log_line="done"):
            _publish_done(ctx, jc)
            if jc.kind == "export":  # retention counts the export that just finished
                try:
                    storage.apply_export_retention(ctx, jc.scene_id)
                except Exception:  # noqa: BLE001 - the export is done; retention runs again
                    log.exception("export retention after job %s", job_id)


# job kinds whose success changes what subscribers show (the viewer's scene grid)
DONE_EVENTS = {"voxelize": "grid_updated"}


def _publish_done(ctx: AppContext, jc: JobContext) -> None:
    kind_event = DONE_EVENTS.get(jc.kind)
    if kind_event is None or ctx.events is None or jc.scene_id is None:
        return
    try:
        from app.scenes.models import Scene
        from occufly.workspace import Workspace

        with ctx.sessions() as s:
            ws = s.get(Scene, jc.scene_id).workspace
        ctx.events.publish(kind_event, jc.scene_id, stamp=Workspace(ws).stamp(), job=jc.job_id)
    except Exception:  # noqa: BLE001 - the job is done; a lost notice only delays a refresh
        log.warning("job %s: publishing %s failed", jc.job_id, kind_event, exc_info=True)


def _drop_staging(jc: JobContext) -> None:
    for staging, _final in jc.outputs:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)


def _on_failure(jc: JobContext, message: str) -> None:
    hook = getattr(KINDS.get(jc.kind), "on_failure", None)
    if hook is not None:
        try:
            hook(jc, message)
        except Exception:  # noqa: BLE001 - never mask the job's own failure
            log.exception("failure hook of job %s", jc.job_id)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and obj != obj:
        return None
    if hasattr(obj, "__fspath__"):
        return str(obj)
    return obj
