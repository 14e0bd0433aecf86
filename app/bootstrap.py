"""The composition root: builds a process's :class:`~app.context.AppContext` (database,
mask store, lifting client, job runner, event bus) and the entry point that runs a job in an
executor process. Everything that starts a process (the app factory, the job executor's
children, the lifting worker) builds its context here, so no lower module imports
``app.main``.
"""

from __future__ import annotations

from app import db
from app.config import Settings
from app.context import AppContext
from app.jobs import runner
from app.jobs.runner import JobRunner
from app.lifting.client import LiftingClient
from app.lifting.events import EventBus
from app.review import jobs as review_jobs
from app.scenes import jobs as scene_jobs
from app.storage import BlobStore

# the domains' job kinds (app.jobs.registry): every process that builds a context -- the API,
# the job executor's children, the lifting worker -- has them, and the runner names none
JOB_KINDS = (scene_jobs, review_jobs)


def build_context(settings: Settings, *, lifting: str | None = None,
                  jobs: bool = True) -> AppContext:
    """The per-process context; ``lifting`` overrides ``settings.lifting`` (the job and
    lifting worker processes pass ``"off"`` / ``"external"``)."""
    engine = db.make_engine(settings.database_url)
    sessions = db.make_sessionmaker(engine)
    holder: list[AppContext] = []
    ctx = AppContext(
        settings=settings, engine=engine, sessions=sessions,
        store=BlobStore(settings.mask_store_dir),
        lifting=LiftingClient(lambda: holder[0], mode=lifting or settings.lifting),
        jobs=(JobRunner(settings.job_workers, processes=settings.job_processes,
                        entry=run_job_process) if jobs else None),
        events=EventBus(engine, sessions))
    holder.append(ctx)
    if ctx.jobs is not None:
        ctx.jobs.bind(ctx)
    return ctx


def run_job_process(settings, job_id: int, attempt: int | None = None) -> None:  # noqa: ANN001
    """Entry point on the job executor (a local worker process or a Dask worker)."""
    ctx = build_context(settings, lifting="off", jobs=False)
    try:
        runner.execute_job(ctx, job_id, attempt)
    finally:
        ctx.engine.dispose()
