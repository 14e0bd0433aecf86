"""The composition root: builds a process's :class:`~app.context.AppContext` (database,
mask store, event bus, lifting client, job runner) with explicit arguments, wires the event
subscriptions, and is the entry point that runs a job in an executor process. Everything
that starts a process (the app factory, the job executor's children, the lifting worker)
builds its context here, so no lower module imports ``app.main``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from app import db
from app.blobs import BlobStore
from app.config import Settings
from app.context import AppContext, SceneCache
from app.events import EventBus
from app.jobs import runner
from app.jobs.runner import JobRunner
from app.lifting.client import LiftingClient
from app.lifting.service import LiftingService
from app.review import jobs as review_jobs
from app.review import quality_cache
from app.review import service as review
from app.review.refresher import ReviewRefresher
from app.scenes import jobs as scene_jobs
from app.scenes.models import Scene

log = logging.getLogger("occufly.app")

# the domains' job kinds (app.jobs.registry): every process that builds a context -- the API,
# the job executor's children, the lifting worker -- has them, and the runner names none
JOB_KINDS = (scene_jobs, review_jobs)


def build_context(settings: Settings, *, lifting: str | None = None,
                  jobs: bool = True) -> AppContext:
    """The per-process context; ``lifting`` overrides ``settings.lifting`` (the job and
    lifting worker processes pass ``"off"`` / ``"external"``). The runner and the lifting
    client get what they use explicitly; the two callables that need the whole context (a
    job run in this process, the lifting service's subscribers) close over it."""
    engine = db.make_engine(settings.database_url)
    sessions = db.make_sessionmaker(engine)
    scenes = SceneCache()
    ctx = AppContext(
        settings=settings, engine=engine, sessions=sessions,
        store=BlobStore(settings.mask_store_dir),
        lifting=LiftingClient(sessions=sessions, load_scene=scenes.load,
                              make_service=lambda: build_lifting_service(ctx),
                              mode=lifting or settings.lifting),
        jobs=(JobRunner(settings.job_workers, settings=settings, sessions=sessions,
                        run_here=lambda job_id, attempt: runner.execute_job(ctx, job_id, attempt),
                        processes=settings.job_processes, entry=run_job_process)
              if jobs else None),
        events=EventBus(engine, sessions), scene_cache=scenes)
    return ctx


def build_lifting_service(ctx: AppContext) -> LiftingService:
    """The lifting service over ``ctx``'s database, store and scenes, with the subscribers of
    the scenes it owns (:data:`app.events.CATALOGUE`): the review's agreement refresh -- in a
    niced child process per refresh (:class:`app.review.refresher.ReviewRefresher`), or with
    ``review_refresh_process=False`` in the fill thread."""
    if ctx.settings.review_refresh_process:
        refresh = ReviewRefresher(ctx.settings, run_review_refresh,
                                  nice=ctx.settings.review_refresh_nice)
    else:
        def refresh(msg, stop):  # noqa: ANN001, ANN202
            review.refresh_after_fill(ctx, msg, stop)
    return LiftingService(
        settings=ctx.settings, engine=ctx.engine, sessions=ctx.sessions, store=ctx.store,
        load_scene=ctx.load_scene, bus=ctx.events, on_owned_labels=(refresh,))


def run_review_refresh(settings: Settings, scene_id: int, stop) -> None:  # noqa: ANN001
    """Entry point of the review refresh's child process (:mod:`app.review.refresher`): its
    own context (reads the votes and labels; runs no lifting, no jobs), one scene's refresh,
    then the scene's quality report of the new labels (the admin page's quality section finds
    it computed instead of starting minutes of work in an API process)."""
    ctx = build_context(settings, lifting="external", jobs=False)
    try:
        review.refresh_scene(ctx, scene_id, stop)
        if not stop.is_set():
            with ctx.sessions() as s:
                scene = s.get(Scene, scene_id)
                ws = None if scene is None else scene.workspace
            if ws is not None:
                quality_cache.compute_locked(ctx, scene_id, Path(ws))
    finally:
        ctx.engine.dispose()


def subscribe_api_process(ctx: AppContext) -> None:
    """An API process whose lifting runs elsewhere (another process owns it, or
    ``OCCUFLY_LIFTING=external``) keeps its own review cache warm on ``labels_updated``."""
    if ctx.lifting.service is None and ctx.events is not None and ctx.lifting.enabled:
        ctx.events.subscribe("labels_updated", review.warm_on_labels(ctx))


def run_job_process(settings, job_id: int, attempt: int | None = None) -> None:  # noqa: ANN001
    """Entry point on the job executor (a local worker process or a Dask worker)."""
    ctx = build_context(settings, lifting="off", jobs=False)
    try:
        runner.execute_job(ctx, job_id, attempt)
    finally:
        ctx.engine.dispose()
