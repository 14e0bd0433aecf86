"""The job kinds' registry and what a kind's code is handed: the domains declare their kinds
here (:func:`kind`), the runner (:mod:`app.jobs.runner`) looks them up by name and never
imports or names one.

A kind is a function ``run(jc: JobContext) -> dict | None`` with its record
(:class:`JobKind`): whether it runs on the job executor (``remote``: a separate process, or
the Dask cluster), what happens when it fails (``on_failure``) and after its outcome is
recorded ``done`` (``on_done``), and the event published then (``done_event``, one of
:data:`app.events.CATALOGUE`). The domains' kinds: :mod:`app.scenes.jobs` (import,
selection, voxelize) and :mod:`app.review.jobs` (export, eval); the composition root
(:mod:`app.bootstrap`) imports both, so every process that builds a context has them.

Fencing: claiming a job increments ``jobs.attempts``; that number is the attempt's token.
Every write of an attempt -- progress, log, the outcome -- is an ``UPDATE ... WHERE attempts =
<token> AND status = 'running'``; a write that matches nothing raises :class:`StaleAttempt`
and the attempt stops. Output folders are written under an attempt-private name
(:meth:`JobContext.output_dir`) and moved into place when that attempt records ``done``.
Progress is written at most every 0.3 s; cancellation is cooperative (the progress callback
raises :class:`JobCancelled` once a cancel was requested).
"""

from __future__ import annotations

import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import update

from app.jobs import service
from app.jobs.models import Job
from occufly.parallel import get_executor

if TYPE_CHECKING:
    from app.context import AppContext


class JobCancelled(Exception):
    pass


class StaleAttempt(Exception):
    """This attempt is no longer the job's current one: it must not write anything."""


def fenced(job_id: int, attempt: int):  # noqa: ANN201 - an UPDATE statement
    """``UPDATE jobs`` of attempt ``attempt`` only, while it is running."""
    return update(Job).where(Job.id == job_id, Job.attempts == attempt, Job.status == "running")


@dataclass
class JobContext:
    """What a running attempt's kind function gets: the process's context, the job's row
    values, progress / log writers fenced by the attempt, and attempt-private outputs."""

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
            if s.execute(fenced(self.job_id, self.attempt).values(**values)).rowcount != 1:
                s.rollback()
                raise StaleAttempt(f"job {self.job_id} attempt {self.attempt} is stale")
            s.commit()
        self._last_msg = message

    def log(self, line: str) -> None:
        with self._lock, self.ctx.sessions() as s:
            job = self._current(s)
            if s.execute(fenced(self.job_id, self.attempt).values(
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

    def executor(self):  # noqa: ANN201 - occufly.parallel's executor
        """Fan-out executor inside a job: Dask when configured, else a local pool whose
        workers die with this job process."""
        return get_executor(self.ctx.settings.dask_address, die_with_caller=True)


Run = Callable[[JobContext], "dict | None"]


@dataclass(frozen=True)
class JobKind:
    """A job kind as its domain declares it."""

    name: str
    run: Run
    remote: bool = False  # on the job executor (a process of its own / Dask), not in-thread
    on_failure: Callable[[JobContext, str], None] | None = None  # failed or cancelled
    on_done: Callable[[JobContext], None] | None = None  # after ``done`` is recorded
    done_event: str | None = None  # published (scene, workspace stamp) after ``done``


KINDS: dict[str, JobKind] = {}


def kind(name: str, *, remote: bool = False,
         on_failure: Callable[[JobContext, str], None] | None = None,
         on_done: Callable[[JobContext], None] | None = None,
         done_event: str | None = None) -> Callable[[Run], Run]:
    """Register the decorated function as job kind ``name`` (one declaration per name)."""
    def deco(fn: Run) -> Run:
        if name in KINDS and KINDS[name].run is not fn:
            raise ValueError(f"job kind {name!r} is declared twice")
        KINDS[name] = JobKind(name=name, run=fn, remote=remote, on_failure=on_failure,
                              on_done=on_done, done_event=done_event)
        return fn

    return deco


def jsonable(obj: Any) -> Any:
    """``obj`` with numpy values, paths and NaN made JSON-safe (a job's stored result)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and obj != obj:
        return None
    if hasattr(obj, "__fspath__"):
        return str(obj)
    return obj
