"""Executes jobs: a small pool of supervisor threads in the server process.

Each job kind is a function ``run(jc: JobContext) -> dict | None`` registered in
:data:`KINDS` (see ``app/jobs/kinds.py``). Pipeline fan-out inside a job (e.g. per-frame
export) goes to the pipeline executor (``occufly.parallel.get_executor``: a local process
pool, or Dask when ``OCCUFLY_DASK_ADDRESS`` is set), obtained in one place:
:meth:`JobContext.executor`.

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
    def __init__(self, workers: int = 2) -> None:
        self.pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="occufly-job")
        self.ctx: AppContext | None = None
        self.futures: dict[int, Future] = {}
        self._closed = False

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

    def _finish(self, job_id: int, **values: Any) -> None:
        with self.ctx.sessions() as s:
            values.setdefault("finished_at", utcnow())
            job = s.get(Job, job_id)
            line = values.pop("log_line", None)
            if line:
                job.log = service.append_log(job, line)
            for k, v in values.items():
                setattr(job, k, v)
            s.commit()

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
            job = s.scalar(select(Job).where(Job.id == job_id))
            jc = JobContext(ctx=ctx, job_id=job.id, kind=job.kind, scene_id=job.scene_id,
                            params=dict(job.params or {}))
        fn = KINDS.get(jc.kind)
        if fn is None:
            self._finish(job_id, status="failed", message=f"unknown job kind {jc.kind!r}")
            return
        try:
            result = fn(jc)
        except JobCancelled:
            self._finish(job_id, status="cancelled", message="cancelled", log_line="cancelled")
            _on_failure(jc, "cancelled")
        except PipelineMissing as e:
            self._finish(job_id, status="failed", message=str(e), log_line=f"failed: {e}")
            _on_failure(jc, str(e))
        except OccuflyError as e:
            self._finish(job_id, status="failed", message=str(e), log_line=f"failed: {e}")
            _on_failure(jc, str(e))
        except Exception as e:  # a bug: keep the traceback in the job log
            log.exception("job %s (%s) crashed", job_id, jc.kind)
            tb = traceback.format_exc(limit=8)
            self._finish(job_id, status="failed", message=f"internal error: {type(e).__name__}: {e}",
                         log_line=tb)
            _on_failure(jc, str(e))
        else:
            self._finish(job_id, status="done", progress=1.0, message="done",
                         result=_jsonable(result or {}), log_line="done")


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
