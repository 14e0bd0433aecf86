"""Database-tracked jobs: create, read, cancel, resume, start-up recovery."""

from __future__ import annotations

import hashlib
import json
import os
import time
from datetime import timedelta
from pathlib import Path

from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.db import utcnow
from app.errors import Conflict, InsufficientStorage, Invalid, NotFound, TooManyAttempts
from app.jobs.models import Job, JobRequestKey
from app.shared_limits import JOB_QUOTA, serialise

LOG_LINES = 200


IDEMPOTENCY_TTL = timedelta(days=1)


def _request_hash(kind: str, scene_id: int | None, params: dict) -> str:
    raw = json.dumps({"kind": kind, "scene": scene_id, "params": params}, sort_keys=True,
                     default=str)
    return hashlib.sha256(raw.encode()).hexdigest()


def find_by_key(*, session: Session, user_id: int, key: str, kind: str, scene_id: int | None,
                params: dict) -> Job | None:
    """The job ``user_id`` started with ``key`` within a day (None: none); 422 when that key
    came with another request. An older key is forgotten (it may start a new job)."""
    row = session.scalar(select(JobRequestKey).where(JobRequestKey.user_id == user_id,
                                                     JobRequestKey.key == key))
    if row is None:
        return None
    if row.created_at < utcnow() - IDEMPOTENCY_TTL:
        session.delete(row)
        session.commit()
        return None
    if row.request_hash != _request_hash(kind, scene_id, params):
        raise Invalid(f"Idempotency-Key {key[:40]!r} was used for another request (job "
                      f"{row.job_id}); send a new key for a new request")
    return session.get(Job, row.job_id)


# ---- quotas (issue 24: 40 export requests in 5 s wrote 11 GB) --------------------------------
# The count and the job's insert are one transaction serialised in the database per user
# (app.shared_limits.serialise: an advisory lock on PostgreSQL, the write lock on SQLite), so
# the quota holds across API processes (issue 36; before, a process-local lock serialised one
# process's requests only: N processes let in up to N x the quota in a race). No process lock
# is kept: the database lock already serialises the threads of one process.
_EXPORTS_SIZE: dict[str, tuple[float, int]] = {}
EXPORTS_SIZE_TTL_S = 10.0


def folder_bytes(root: Path) -> int:
    """Bytes of the files under ``root`` (symlinks not followed), 0 when it does not exist."""
    total = 0
    stack = [Path(root)]
    while stack:
        try:
            entries = list(os.scandir(stack.pop()))
        except OSError:
            continue
        for e in entries:
            try:
                if e.is_dir(follow_symlinks=False):
                    stack.append(Path(e.path))
                elif e.is_file(follow_symlinks=False):
                    total += e.stat(follow_symlinks=False).st_size
            except OSError:
                continue
    return total


def exports_bytes(exports_dir: Path, *, fresh: bool = False) -> int:
    """:func:`folder_bytes` of the exports folder, cached for EXPORTS_SIZE_TTL_S."""
    key = str(exports_dir)
    now = time.monotonic()
    hit = _EXPORTS_SIZE.get(key)
    if hit is not None and not fresh and now - hit[0] < EXPORTS_SIZE_TTL_S:
        return hit[1]
    n = folder_bytes(exports_dir)
    _EXPORTS_SIZE[key] = (now, n)
    return n


def check_quota(*, session: Session, settings, user_id: int, kind: str) -> None:  # noqa: ANN001
    """Before a job is created: 429 when the user already has ``active_jobs_per_user`` jobs
    queued or running (Retry-After 10 s); for an export, 507 when the exports folder already
    takes ``export_quota_bytes``. On its own it is an early answer (nothing created yet); the
    binding check is the one :func:`create` makes with ``quota=`` in its transaction."""
    active = session.scalar(select(func.count()).select_from(Job).where(
        Job.created_by_id == user_id, Job.status.in_(("queued", "running")))) or 0
    if active >= settings.active_jobs_per_user:
        raise TooManyAttempts(
            f"job quota: you have {active} jobs queued or running; at most "
            f"{settings.active_jobs_per_user} at a time (OCCUFLY_ACTIVE_JOBS_PER_USER) -- wait for "
            "one to finish or cancel one", retry_after=10, active_jobs=int(active),
            quota=settings.active_jobs_per_user)
    if kind == "export":
        used = exports_bytes(settings.exports_dir)
        if used >= settings.export_quota_bytes:
            raise InsufficientStorage(
                f"export quota: the exports folder takes {used} bytes, the quota is "
                f"{settings.export_quota_bytes} bytes (OCCUFLY_EXPORT_QUOTA_MB); delete old "
                "exports first", used_bytes=used, quota_bytes=settings.export_quota_bytes)


def create(*, session: Session, kind: str, scene_id: int | None, params: dict,
           user_id: int | None, key: str | None = None, quota=None) -> Job:  # noqa: ANN001
    """Add a queued job. ``quota`` (the settings): the user's job quota is checked in the
    transaction that adds the job, under the user's lock in the database (see above), so
    concurrent requests in any number of API processes cannot all see room for one more."""
    if quota is not None and user_id is not None:
        # held from here to the commit below (PostgreSQL reads each statement afresh; on
        # SQLite the write lock makes this transaction the only writer); a refusal rolls back
        # the caller's uncommitted changes with it
        serialise(session, JOB_QUOTA, user_id)
        try:
            if key is not None:  # the same key's request that held the lock before us won
                found = find_by_key(session=session, user_id=user_id, key=key, kind=kind,
                                    scene_id=scene_id, params=params)
                if found is not None:
                    session.commit()
                    found.reused = True  # the caller must not submit it again
                    return found
                serialise(session, JOB_QUOTA, user_id)  # again: an expired key was committed
            check_quota(session=session, settings=quota, user_id=user_id, kind=kind)
        except Exception:
            session.rollback()  # releases the lock
            raise
    # heartbeat_at now: a queued job no runner has claimed yet is not "lost" until STALE_S has
    # passed -- a sweep between this commit and the runner's submit() would interrupt it
    job = Job(kind=kind, scene_id=scene_id, params=params, status="queued", created_by_id=user_id,
              progress=0.0, message="queued", log="", heartbeat_at=utcnow())
    session.add(job)
    if key is not None and user_id is not None:
        session.flush()
        session.add(JobRequestKey(user_id=user_id, key=key, job_id=job.id, created_at=utcnow(),
                                  request_hash=_request_hash(kind, scene_id, params)))
        try:
            session.commit()
        except IntegrityError:  # the same key raced in from a second request: its job wins
            session.rollback()
            found = find_by_key(session=session, user_id=user_id, key=key, kind=kind,
                                scene_id=scene_id, params=params)
            if found is None:
                raise
            found.reused = True  # the caller must not submit it again
            return found
        return job
    session.commit()
    return job


def get(*, session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise NotFound(f"job {job_id} does not exist")
    return job


def list_jobs(*, session: Session, scene_id: int | None = None, limit: int = 200) -> list[Job]:
    q = select(Job).order_by(Job.id.desc()).limit(limit)
    if scene_id is not None:
        q = q.where(Job.scene_id == scene_id)
    return list(session.scalars(q))


def out(job: Job) -> dict:
    lines = job.log.splitlines() if job.log else []
    return dict(id=job.id, kind=job.kind, scene_id=job.scene_id, status=job.status,
                progress=job.progress, message=job.message, log_tail=lines[-20:],
                params=job.params or {}, result=job.result, attempts=job.attempts,
                created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at)


def request_cancel(*, session: Session, job: Job) -> Job:
    if job.status in ("done", "failed", "cancelled"):
        raise Conflict(f"job {job.id} is already {job.status}")
    if job.status in ("queued", "interrupted"):
        session.execute(update(Job).where(Job.id == job.id, Job.status == job.status)
                        .values(status="cancelled", finished_at=utcnow(), message="cancelled",
                                cancel_requested=True))
    else:
        session.execute(update(Job).where(Job.id == job.id).values(cancel_requested=True,
                                                                    message="cancelling"))
    session.commit()
    session.refresh(job)
    return job


def prepare_resume(*, session: Session, job: Job) -> Job:
    """interrupted/failed/cancelled -> queued (the caller then submits it)."""
    res = session.execute(
        update(Job).where(Job.id == job.id,
                          Job.status.in_(("interrupted", "failed", "cancelled")))
        .values(status="queued", cancel_requested=False, message="resumed", finished_at=None,
                heartbeat_at=utcnow()))
    session.commit()
    if res.rowcount != 1:
        session.refresh(job)
        raise Conflict(f"job {job.id} is {job.status}; only interrupted, failed or cancelled "
                       "jobs can be resumed")
    session.refresh(job)
    return job


def mark_interrupted(*, session: Session, stale_s: float = 15.0,
                     alive_owner: str | None = None) -> list[int]:
    """Queued/running jobs whose runner is gone can no longer finish: those no runner holds
    (no heartbeat) or whose runner has not beaten for ``stale_s`` (another API process may
    still be running the rest). ``alive_owner``: the caller's own runner, never swept."""
    limit = utcnow() - timedelta(seconds=stale_s)
    lost = or_(Job.heartbeat_at.is_(None), Job.heartbeat_at < limit)
    q = select(Job.id).where(Job.status.in_(("running", "queued")), lost)
    if alive_owner is not None:
        q = q.where(or_(Job.owner.is_(None), Job.owner != alive_owner))
    ids = list(session.scalars(q))
    if ids:
        session.execute(update(Job).where(Job.id.in_(ids), Job.status.in_(("running", "queued")),
                                          lost).values(
            status="interrupted", owner=None, message="interrupted: the server stopped while "
            "this job was running; resume it to run again"))
        session.commit()
    return ids


def append_log(job: Job, line: str) -> str:
    lines = (job.log.splitlines() if job.log else []) + [line]
    return "\n".join(lines[-LOG_LINES:])
