"""The FastAPI application factory: ``create_app(settings)``.

Start-up (inside :func:`create_app`, so a test that builds a second app over the same
database sees exactly what a restarted server does): Alembic upgrade to head, then every job
the previous process left ``running``/``queued`` is marked ``interrupted`` (resumable via
``POST /api/jobs/{id}/resume``).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
import os
import threading
from contextlib import asynccontextmanager

from fastapi import FastAPI, routing
from fastapi.staticfiles import StaticFiles
from sqlalchemy import select, text

from app import db, errors, security
from app.annotations.confidence import router as confidence_router
from app.annotations.models import MaskVersion
from app.annotations.routes import router as annotations_router
from app.annotations.smart import router as smart_router
from app.audit.routes import router as audit_router
from app.bodylimit import BodyLimitMiddleware
from app.bootstrap import build_context, subscribe_api_process
from app.config import Settings
from app.context import AppContext
from app.corrections.routes import router as corrections_router
from app.corrections.service import repair_all, viewer_hooks
from app.deps import is_member, token_from
from app.docs_offline import mount_docs, mount_site
from app.jobs import service as jobs_service
from app.jobs.archive import router as archive_router
from app.jobs.routes import router as jobs_router
from app.lifting.routes import router as lifting_router
from app.notifications.routes import router as notifications_router
from app.pipeline import stored_mask_ids
from app.review import service as review
from app.review.routes import router as review_router
from app.scenes.console import router as console_router
from app.scenes.disk import apply_export_retention
from app.scenes.imports import router as imports_router
from app.scenes.models import Frame, Scene
from app.scenes.routes import router as scenes_router
from app.shared_limits import SocketLeases
from app.users import service as users
from app.users.models import User
from app.users.routes import router as users_router
from occufly.parallel import die_with_parent

log = logging.getLogger("occufly.app")


def app_from_env() -> FastAPI:
    """The app of one API process configured from ``OCCUFLY_*`` (uvicorn ``--factory``; what
    each of ``occufly serve --workers N``'s processes runs). With ``OCCUFLY_DIE_WITH_PARENT``
    (set by ``serve --workers``) the process exits when that supervisor is gone, so no
    orphaned API process keeps serving after a ``kill -9``."""
    parent = os.environ.get("OCCUFLY_DIE_WITH_PARENT", "")
    if parent.isdigit():
        die_with_parent(int(parent))
    from app.serving import tune_allocator  # uvicorn's modules: loaded by serving processes only

    tune_allocator()  # freed request temporaries kept for the next request (app.serving)
    return create_app(Settings.from_env())


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    security.configure(time_cost=settings.argon2_time_cost, memory_kib=settings.argon2_memory_kib)
    if settings.auto_upgrade:
        db.upgrade(settings.database_url)
    ctx = build_context(settings)
    with ctx.sessions() as s:
        interrupted = jobs_service.mark_interrupted(session=s)
    if interrupted:
        log.warning("jobs %s were interrupted by a server stop; resume them via the API",
                    interrupted)
    repair_all(ctx)  # a correction a kill -9 left half-written is applied entirely or not at all
    apply_export_retention(ctx)  # OCCUFLY_EXPORT_KEEP_LAST / _MAX_AGE_DAYS (0 = keep all)
    ctx.jobs.start()
    ctx.lifting.start()
    subscribe_api_process(ctx)  # the worker runs elsewhere: keep the review cache warm
    review.warm_process_start(ctx)  # a survey's first review not 2-3 s (the process's state)

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        yield
        close(_app)

    app = FastAPI(title="OccuFly Studio", version="0.1.0", lifespan=lifespan,
                  docs_url=None,  # /docs served offline by app.docs_offline (issue 26)
                  description="Annotation, lifting, review and export of drone-survey SSC "
                              "ground truth. Auth: session cookie `occufly_session` or "
                              "`Authorization: Bearer <token>` from POST /api/auth/login.")
    app.state.ctx = ctx
    errors.install(app)  # domain errors and the (NaN-safe) 422 handler
    # body caps by route before a byte is read (413); inside the security headers' middleware
    app.add_middleware(BodyLimitMiddleware, get_ctx=lambda: ctx)
    app.add_middleware(security.SecurityMiddleware, get_ctx=lambda: ctx)  # CSRF, headers

    for r in (users_router, scenes_router, annotations_router, confidence_router, smart_router,
              review_router, jobs_router, archive_router, audit_router, corrections_router,
              notifications_router, imports_router, console_router, lifting_router):  # the last two: issue 28's admin console
        app.include_router(r)
    _share_included_routers(app)

    @app.get("/api/health", tags=["meta"])
    def health() -> dict:
        with ctx.sessions() as s:
            s.execute(text("SELECT 1"))
        return {"status": "ok", "database": ctx.engine.dialect.name}

    _mount_viewer(app, ctx)
    mount_docs(app)  # Swagger UI from the swagger-ui-bundle package, no CDN (issue 26)
    mount_site(app, lambda: ctx.settings.docs_site_dir)  # the documentation site (issue 40)
    _mount_frontend(app, settings)
    return app


# FastAPI (0.16x) resolves an included router's routes -- every endpoint's dependencies and
# their pydantic models -- lazily, once per app, on the first requests: 0.1-0.5 s of CPU per
# app. The routers are module objects and their resolution depends on nothing of the app (no
# dependency overrides are used here), so a process that builds many apps (the tests: one per
# test) resolves each router once and shares it.
_INCLUDED: dict[int, object] = {}
_INCLUDED_LOCK = threading.Lock()


def _share_included_routers(app: FastAPI) -> None:
    """Swap each router ``app`` included for the one the first app of this process included
    (its routes already resolved). The shared copy names no app as its dependency-overrides
    provider: ``app.dependency_overrides`` is not supported (nothing here uses it). A FastAPI
    without the lazily resolved ``_IncludedRouter`` leaves the app as it is."""
    included = getattr(routing, "_IncludedRouter", None)
    if included is None:
        return
    with _INCLUDED_LOCK:
        routes = app.router.routes
        for i, route in enumerate(routes):
            if type(route) is not included:
                continue
            key = id(route.original_router)
            shared = _INCLUDED.get(key)
            ctx = dataclasses.replace(route.include_context, dependency_overrides_provider=None)
            if shared is None or shared.include_context != ctx:
                shared = included(original_router=route.original_router, include_context=ctx)
                _INCLUDED[key] = shared
            routes[i] = shared


def close(app: FastAPI) -> None:
    """Stop background work and release the database (idempotent)."""
    ctx: AppContext = app.state.ctx
    ctx.jobs.shutdown(wait=True)
    ctx.lifting.stop()
    # the viewer's socket leases stop renewing and their rows go (app.shared_limits); the 3D
    # server's threads are daemons that end with the process, as before (stopping viser here
    # cost 6 s per closed app in the tests)
    leases = getattr(getattr(app.state, "viewer", None), "socket_leases", None)
    if leases is not None:
        leases.close()
    if ctx.events is not None:
        ctx.events.close()
    ctx.engine.dispose()


def authorize_viewer(ctx: AppContext):
    """authorize(request_or_websocket) -> bool for the 3D viewer: a logged-in reviewer/admin,
    and for a reviewer the requested scene (``?scene=`` or the viewer's scene cookie) must be
    one they are a member of."""

    def authorize(conn) -> bool:  # noqa: ANN001
        token = token_from(conn)
        if not token:
            return False
        with ctx.sessions() as s:
            user = users.user_for_token(session=s, settings=ctx.settings, token=token)
            if user is None or user.role not in ("reviewer", "admin"):
                return False
            query = getattr(conn, "query_params", None) or {}
            cookies = getattr(conn, "cookies", None) or {}
            scene = query.get("scene") or cookies.get("occufly_viewer_scene")
            if scene is not None and user.role != "admin":
                return scene.isdigit() and len(scene) < 10 and is_member(s, user, int(scene))
            return True

    return authorize


def viewer_callbacks(ctx: AppContext) -> dict:
    """The optional hooks of ``app.viewer.mount``: who is asking, which scenes, frame states,
    current masks, and filing review items from 3D (scene ids are ``str(scene.id)``)."""

    def identify(conn):  # noqa: ANN001, ANN202
        token = token_from(conn)
        if not token:
            return None
        with ctx.sessions() as s:
            return users.user_for_token(session=s, settings=ctx.settings, token=token)

    def scenes() -> dict:
        with ctx.sessions() as s:
            return {str(sc.id): (sc.name, sc.workspace)
                    for sc in s.scalars(select(Scene).where(Scene.status == "ready"))}

    def frame_states(scene_id) -> dict:  # noqa: ANN001
        from app.viewer.scene_builder import viewer_state  # the viewer is optional (viser)

        with ctx.sessions() as s:
            rows = s.execute(select(Frame.index, Frame.selected, Frame.state)
                             .where(Frame.scene_id == int(scene_id))).all()
        return {i: viewer_state(sel, st) for i, sel, st in rows}

    def frame_mask(scene_id, frame_index):  # noqa: ANN001, ANN202
        with ctx.sessions() as s:
            row = s.execute(select(MaskVersion.sha256, Scene.workspace).join(
                Frame, Frame.current_version_id == MaskVersion.id).join(
                Scene, Scene.id == Frame.scene_id).where(
                Frame.scene_id == int(scene_id), Frame.index == int(frame_index))).first()
        if row is None:
            return None
        return stored_mask_ids(ctx.store.get(row[0]), ctx.load_scene(row[1]).taxonomy)

    def frame_index(scene_id, frame_id):  # noqa: ANN001, ANN202 - ?frame=<frame id> -> index
        if not str(frame_id).isdigit() or not str(scene_id).isdigit():
            return None
        with ctx.sessions() as s:
            return s.scalar(select(Frame.index).where(Frame.scene_id == int(scene_id),
                                                      Frame.id == int(frame_id)))

    def suspect_points(scene_id, key):  # noqa: ANN001, ANN202 - ?suspect=<key> -> point ids
        if not str(scene_id).isdigit() or len(str(scene_id)) >= 10:
            return None
        with ctx.sessions() as s:
            scene = s.get(Scene, int(scene_id))
            if scene is None:
                return None
            s.expunge(scene)
        return review.suspect_points(ctx, scene, str(key))

    def can_open(user, scene_id) -> bool:  # noqa: ANN001 - the dropdown of a reviewer
        """Whether ``user`` may see ``scene_id`` now: the user is read again (the ticket's
        copy is as old as the socket), so a demotion, deactivation or removal from the scene
        ends an open viewer's access (ViewerService re-checks every client 4 times a second)."""
        uid = getattr(user, "id", None)
        if uid is None:
            return False
        with ctx.sessions() as s:
            fresh = s.get(User, uid)
            if fresh is None or not fresh.active or fresh.role not in ("reviewer", "admin"):
                return False
            if fresh.role == "admin" or scene_id is None:  # None: no scene open yet
                return True
            return str(scene_id).isdigit() and len(str(scene_id)) < 10 and \
                is_member(s, fresh, int(scene_id))


    return {"identify": identify, "scenes": scenes, "frame_states": frame_states,
            "frame_mask": frame_mask, "on_review_item": review.make_viewer_callback(ctx),
            "frame_index": frame_index, "suspect_points": suspect_points, "can_open": can_open,
            "corrections": viewer_hooks(ctx),
            # the per-user socket cap counted in the database, across API processes (issue 36)
            "socket_leases": SocketLeases(ctx.sessions)}


def _mount_viewer(app: FastAPI, ctx: AppContext) -> None:
    try:
        import app.viewer as viewer  # optional: viser missing -> no /viewer/
    except ImportError:
        return
    mount = getattr(viewer, "mount", None)
    if mount is None:
        return

    hooks = viewer_callbacks(ctx)
    if ctx.events is not None:  # refresh open viewers on labels_updated / grid_updated
        hooks["subscribe"] = ctx.events.subscribe
    app.state.on_review_item = hooks["on_review_item"]
    params = inspect.signature(mount).parameters
    accepts_all = any(p.kind is p.VAR_KEYWORD for p in params.values())
    kw = {k: v for k, v in hooks.items() if accepts_all or k in params}
    mount(app, settings=ctx.settings, authorize=authorize_viewer(ctx), **kw)
    if getattr(app.state, "viewer", None) is not None:  # resolves "Open in 3D" (?frame=<id>)
        app.state.viewer.frame_index = hooks["frame_index"]
        app.state.viewer.suspect_points = hooks["suspect_points"]


def _mount_frontend(app: FastAPI, settings: Settings) -> None:

    if settings.frontend_dir.is_dir():
        app.mount("/", StaticFiles(directory=settings.frontend_dir, html=True), name="frontend")
