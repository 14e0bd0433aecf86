"""Database-tracked jobs: create, read, cancel, resume, start-up recovery."""

from __future__ import annotations

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from app.db import utcnow
from app.errors import Conflict, NotFound
from app.jobs.models import Job

LOG_LINES = 200


def create(*, session: Session, kind: str, scene_id: int | None, params: dict,
           user_id: int | None) -> Job:
    job = Job(kind=kind, scene_id=scene_id, params=params, status="queued", created_by_id=user_id,
              progress=0.0, message="queued", log="")
    session.add(job)
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
    from datetime import timedelta

    from sqlalchemy import or_

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
