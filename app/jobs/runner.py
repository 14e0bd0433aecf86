"""Executes jobs: supervisor threads in the server hand each job to an executor.

Each job kind is a function ``run(jc: JobContext) -> dict | None`` registered in
:data:`KINDS` (see ``app/jobs/kinds.py``). Kinds marked ``remote`` (import, selection,
voxelize, export) run in :func:`run_job_process` on the job executor -- a local process pool
(``spawn``, so no server threads or database connections are inherited), or the Dask
cluster when ``OCCUFLY_DASK_ADDRESS`` is set (``occufly.parallel``) -- so heavy pipeline work
never competes with the API for the server's interpreter. With ``job_processes=False`` (tests,
debugging) they run in the supervisor thread. The child talks to the same database: status,
progress, log and result are written there, and cancellation is read from there. Pipeline
fan-out inside a job (per-frame export) uses :meth:`JobContext.executor`.

Progress is written to the job row at most every 0.3 s; cancellation is cooperative (the
progress callback raises :class:`JobCancelled` once a cancel was requested).
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from sqlalchemy import select, update

from app.db import utcnow
from app.jobs import service
from app.jobs.models import Job
from app.pipeline import PipelineMissing
from occufly.errors import OccuflyError

if TYPE_CHECKING:
    from app.context import AppContext

log = logging.getLogger("occufly.jobs")


class JobCancelled(Exception):
    pass


@dataclass
class JobContext:
    ctx: AppContext
    job_id: int
    kind: str
    scene_id: int | None
    params: dict
    _last_write: float = 0.0
    _last_msg: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def progress(self, fraction: float, message: str = "") -> None:
        now = time.monotonic()
        if now - self._last_write < 0.3 and message == self._last_msg and fraction < 1.0:
            return
        self._last_write = now
        with self._lock, self.ctx.sessions() as s:
            job = s.get(Job, self.job_id)
            if job.cancel_requested:
                raise JobCancelled()
            job.progress = float(max(0.0, min(1.0, fraction)))
            if message:
                job.message = message[:500]
                if message != self._last_msg:
                    job.log = service.append_log(job, f"{fraction:6.1%} {message}")
            s.commit()
        self._last_msg = message

    def log(self, line: str) -> None:
        with self._lock, self.ctx.sessions() as s:
            job = s.get(Job, self.job_id)
            job.log = service.append_log(job, line)
            s.commit()

    def executor(self):
        from app.pipeline import get_executor

        return get_executor(self.ctx.settings.dask_address)


KINDS: dict[str, Callable[[JobContext], dict | None]] = {}


def kind(name: str):
    def deco(fn: Callable[[JobContext], dict | None]):
        KINDS[name] = fn
        return fn

    return deco


class JobRunner:
    def __init__(self, workers: int = 2, *, processes: bool = True) -> None:
        self.pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="occufly-job")
        self.workers = max(1, workers)
        self.processes = processes
        self.ctx: AppContext | None = None
        self.futures: dict[int, Future] = {}
        self._closed = False
        self._executor = None
        self._executor_lock = threading.Lock()

    def job_executor(self):
        """The executor remote job kinds run on (created on first use, one per runner)."""
        with self._executor_lock:
            if self._executor is None:
                address = self.ctx.settings.dask_address
                if address:
                    from app.pipeline import get_executor

                    self._executor = get_executor(address)
                else:
                    import multiprocessing
                    from concurrent.futures import ProcessPoolExecutor

                    self._executor = ProcessPoolExecutor(
                        max_workers=self.workers, mp_context=multiprocessing.get_context("spawn"))
            return self._executor

    def bind(self, ctx: AppContext) -> None:
        self.ctx = ctx

    def submit(self, job_id: int) -> None:
        if self._closed:
            return
        self.futures[job_id] = self.pool.submit(self._run, job_id)

    def wait(self, job_id: int, timeout: float = 60.0) -> None:
        fut = self.futures.get(job_id)
        if fut is not None:
            fut.result(timeout=timeout)

    def shutdown(self, wait: bool = True) -> None:
        self._closed = True
        self.pool.shutdown(wait=wait, cancel_futures=True)
        if self._executor is not None:
            close = getattr(self._executor, "close", None)
            if close is not None:
                close()
            else:
                self._executor.shutdown(wait=wait, cancel_futures=True)

    def _run(self, job_id: int) -> None:
        from app.jobs import kinds  # noqa: F401 - registers the job kinds

        ctx = self.ctx
        with ctx.sessions() as s:
            res = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued")
                            .values(status="running", started_at=utcnow(), progress=0.0,
                                    attempts=Job.attempts + 1, message="running"))
            s.commit()
            if res.rowcount != 1:
                return  # cancelled before it started
            kind_name = s.scalar(select(Job.kind).where(Job.id == job_id))
        fn = KINDS.get(kind_name)
        if self.processes and getattr(fn, "remote", False):
            try:
                self.job_executor().submit(run_job_process, ctx.settings, job_id).result()
            except Exception as e:  # noqa: BLE001 - the child died or could not start
                log.exception("job %s: executor failure", job_id)
                _finish(ctx, job_id, status="failed",
                        message=f"job process failed: {type(e).__name__}: {e}",
                        log_line=f"job process failed: {e}")
            return
        execute_job(ctx, job_id)


def _finish(ctx: AppContext, job_id: int, **values: Any) -> None:
    with ctx.sessions() as s:
        values.setdefault("finished_at", utcnow())
        job = s.get(Job, job_id)
        line = values.pop("log_line", None)
        if line:
            job.log = service.append_log(job, line)
        for k, v in values.items():
            setattr(job, k, v)
        s.commit()


def execute_job(ctx: AppContext, job_id: int) -> None:
    """Run a job already marked ``running`` and record its outcome (any process)."""
    from app.jobs import kinds  # noqa: F401 - registers the job kinds

    with ctx.sessions() as s:
        job = s.get(Job, job_id)
        jc = JobContext(ctx=ctx, job_id=job.id, kind=job.kind, scene_id=job.scene_id,
                        params=dict(job.params or {}))
    fn = KINDS.get(jc.kind)
    if fn is None:
        _finish(ctx, job_id, status="failed", message=f"unknown job kind {jc.kind!r}")
        return
    try:
        result = fn(jc)
    except JobCancelled:
        _finish(ctx, job_id, status="cancelled", message="cancelled", log_line="cancelled")
        _on_failure(jc, "cancelled")
    except (PipelineMissing, OccuflyError) as e:
        _finish(ctx, job_id, status="failed", message=str(e), log_line=f"failed: {e}")
        _on_failure(jc, str(e))
    except Exception as e:  # a bug: keep the traceback in the job log
        log.exception("job %s (%s) crashed", job_id, jc.kind)
        tb = traceback.format_exc(limit=8)
        _finish(ctx, job_id, status="failed", message=f"internal error: {type(e).__name__}: {e}",
                log_line=tb)
        _on_failure(jc, str(e))
    else:
        _finish(ctx, job_id, status="done", progress=1.0, message="done",
                result=_jsonable(result or {}), log_line="done")


def run_job_process(settings, job_id: int) -> None:  # noqa: ANN001
    """Entry point on the job executor (a spawned process or a Dask worker)."""
    from app import db
    from app.annotations.lifting import LiftingManager
    from app.context import AppContext
    from app.storage import BlobStore

    engine = db.make_engine(settings.database_url, pooled=False)
    holder: list = []
    ctx = AppContext(settings=settings, engine=engine, sessions=db.make_sessionmaker(engine),
                     store=BlobStore(settings.mask_store_dir),
                     lifting=LiftingManager(lambda: holder[0], enabled=False),
                     jobs=None)  # type: ignore[arg-type]
    holder.append(ctx)
    try:
        execute_job(ctx, job_id)
    finally:
        engine.dispose()


def _on_failure(jc: JobContext, message: str) -> None:
    hook = getattr(KINDS.get(jc.kind), "on_failure", None)
    if hook is not None:
        try:
            hook(jc, message)
        except Exception:  # noqa: BLE001 - never mask the job's own failure
            log.exception("failure hook of job %s", jc.job_id)


def _jsonable(obj: Any) -> Any:
    import numpy as np

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
