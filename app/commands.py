"""The web-app commands' handlers: ``serve``, ``lifting-worker``, ``db``, ``users``,
``backup``, ``restore``, ``scene-export``, ``demo`` (their parsers: :mod:`app.cli`, which
imports this module only when one of them runs).

Settings come from ``OCCUFLY_*`` environment variables (see ``app/config.py``), e.g.
``OCCUFLY_DATABASE_URL``, ``OCCUFLY_DATA_DIR``, ``OCCUFLY_SECRET_KEY``.
"""

from __future__ import annotations

import argparse
import getpass
import os
import secrets
import subprocess
import sys
from pathlib import Path

import uvicorn
from sqlalchemy import select
from sqlalchemy.engine import make_url

from app import db, security
from app.backup import backup, restore
from app.bootstrap import build_context
from app.config import Settings
from app.demo import DemoSteps
from app.demo import seed as seed_demo
from app.errors import DomainError
from app.jobs import service as jobs
from app.jobs.schemas import ExportIn
from app.lifting.worker import main
from app.main import create_app
from app.scenes.models import Scene
from app.serving import tune_allocator, uvicorn_options
from app.users import service
from occufly.errors import InputFormatError, OccuflyError


def _backup(args: argparse.Namespace) -> dict:
    return backup(_settings(), Path(args.dir), images=not args.no_images)


def _restore(args: argparse.Namespace) -> dict:
    s = _settings()
    security.configure(time_cost=s.argon2_time_cost, memory_kib=s.argon2_memory_kib)
    return restore(s, Path(args.dir))


def _scene_export(args: argparse.Namespace) -> dict:
    """The admin page's export as a command: an export job with the same policy field."""
    settings = _settings()
    ctx = build_context(settings, lifting="off")
    try:
        with ctx.sessions() as s:
            key = str(args.scene)
            scene = s.get(Scene, int(key)) if key.isdigit() else None
            scene = scene or s.scalar(select(Scene).where(Scene.name == key))
            if scene is None:
                raise OccuflyError(f"scene {key!r}: no scene with that id or name")
            if scene.status != "ready":
                raise OccuflyError(f"scene {key!r} is {scene.status}, not ready")
            include = ["accepted", "submitted", "imported"] if args.include_unreviewed else ["accepted"]
            params = ExportIn(layout=args.layout, include=include).model_dump()
            job = jobs.create(session=s, kind="export", scene_id=scene.id, params=params, user_id=None)
            jid = job.id
        ctx.jobs.start()  # heartbeats: a server sharing the database must not sweep the job
        ctx.jobs.submit(jid)
        ctx.jobs.wait(jid, timeout=24 * 3600)
        with ctx.sessions() as s:
            job = jobs.get(session=s, job_id=jid)
            status, message, result = job.status, job.message, job.result or {}
        if status != "done":
            raise OccuflyError(f"export job {jid} {status}: {message}")
        review = result.get("review") or {}
        return {"job_id": jid, "output": result.get("output"), "files": result.get("files"),
                "include": include, "took": review.get("took"),
                "unreviewed_frames": review.get("unreviewed_frames"),
                "left_out": review.get("left_out"), "quality": result.get("quality")}
    finally:
        ctx.jobs.shutdown()
        ctx.engine.dispose()


def _settings():
    return Settings.from_env()


MAX_WORKERS = 64


def _serve(args: argparse.Namespace) -> int:
    if not 1 <= args.workers <= MAX_WORKERS:
        raise InputFormatError(f"--workers must be between 1 and {MAX_WORKERS}, got {args.workers}")
    if args.workers > 1:
        return _serve_workers(args)
    settings = _settings()
    # header-read/keep-alive timeouts, head size cap, no permessage-deflate, proxy headers
    # only with --proxy-headers from OCCUFLY_TRUSTED_PROXIES (app.serving)
    opts = uvicorn_options(settings, proxy_headers=args.proxy_headers)
    tune_allocator()  # freed request temporaries kept for the next request (app.serving)
    app = create_app(settings)
    uvicorn.run(app, host=args.host, port=args.port, log_level="info", **opts)
    return 0


def _serve_workers(args: argparse.Namespace) -> int:
    """N stateless API processes (uvicorn workers, each ``app.main.app_from_env``) plus the
    lifting worker as a child that dies with this process."""
    settings = _settings()  # configuration errors surface once, here
    opts = uvicorn_options(settings, proxy_headers=args.proxy_headers)
    db.upgrade(settings.database_url)  # once, before N processes start
    env = os.environ  # inherited by the uvicorn workers (spawned) and the lifting worker
    env["OCCUFLY_AUTO_UPGRADE"] = "0"
    env["OCCUFLY_DIE_WITH_PARENT"] = str(os.getpid())  # no orphan serves on after kill -9
    if settings.lifting != "off":
        env["OCCUFLY_LIFTING"] = "external"
    worker = None
    if settings.lifting != "off" and not args.no_lifting_worker:
        worker = subprocess.Popen([sys.executable, "-m", "app.lifting"], env=dict(env))
    try:
        uvicorn.run("app.main:app_from_env", factory=True, workers=args.workers,
                    host=args.host, port=args.port, log_level="info", **opts)
    finally:
        if worker is not None:
            worker.terminate()
            try:
                worker.wait(30)
            except subprocess.TimeoutExpired:
                worker.kill()
    return 0


def _lifting_worker(_args: argparse.Namespace) -> int:
    return main([])


def _db(args: argparse.Namespace) -> dict:
    s = _settings()
    if args.action == "upgrade":
        db.upgrade(s.database_url)
    return {"database": _redact(s.database_url), "revision": db.current_revision(s.database_url)}


def _users(args: argparse.Namespace) -> dict | list:
    s = _settings()
    db.upgrade(s.database_url)
    security.configure(time_cost=s.argon2_time_cost, memory_kib=s.argon2_memory_kib)
    engine = db.make_engine(s.database_url, pooled=False)
    try:
        with db.make_sessionmaker(engine)() as session:
            if args.action == "list":
                return {"users": [{"id": u.id, "username": u.username, "role": u.role}
                                  for u in service.list_users(session=session)]}
            if not args.name or not args.role:
                raise OccuflyError("users create needs NAME and --role annotator|reviewer|admin")
            password, generated = _password(args)
            try:
                user = service.create_user(session=session, username=args.name,
                                           password=password, role=args.role)
            except Exception as e:  # domain errors (duplicate, short password) -> one line
                if isinstance(e, DomainError):
                    raise OccuflyError(f"users create {args.name}: {e.detail}") from None
                raise
            out = {"id": user.id, "username": user.username, "role": user.role}
            if generated:
                out["password"] = password
            return out
    finally:
        engine.dispose()


def _password(args: argparse.Namespace) -> tuple[str, bool]:
    if args.password:
        return args.password, False
    if os.environ.get("OCCUFLY_NEW_PASSWORD"):
        return os.environ["OCCUFLY_NEW_PASSWORD"], False
    if sys.stdin.isatty():
        return getpass.getpass(f"password for {args.name}: "), False
    return secrets.token_urlsafe(12), True


def demo(*, preset: str = "small", seed: int = 0, source: str | None = None,
         host: str = "127.0.0.1", port: int = 8000, serve: bool = True,
         dev: bool = False) -> dict:
    """The README's main command: synthesize ``preset``, import it, select frames, create one
    user per role (random passwords printed; ``dev``: the well-known ``occufly-<role>``), then
    serve on ``host:port``.

    Without ``OCCUFLY_SECRET_KEY`` the demo runs in development mode with a random secret.
    """
    env = dict(os.environ)
    if not env.get("OCCUFLY_SECRET_KEY"):
        env.setdefault("OCCUFLY_ENV", "development")
        env["OCCUFLY_SECRET_KEY"] = secrets.token_urlsafe(32)
    settings = Settings.from_env(env)
    app = create_app(settings)
    # each step (synthesize, users, import, select) prints as it starts and ends, with its time
    info = seed_demo(settings, Path(source) if source else None, preset=preset,
                     seed_value=seed, app=app, dev_passwords=dev,
                     steps=DemoSteps(sys.stderr, total=4 if source is None else 3))
    print(f"OccuFly Studio demo: scene {info['scene_id']} from {info['source']}", file=sys.stderr)
    sel = info["selection"]
    if sel.get("frames") is not None:
        print(f"  selected {len(sel['frames'])} frames (coverage {sel['coverage']:.3f})",
              file=sys.stderr)
    print("  log in with:", file=sys.stderr)
    for user, pw in info["users"].items():
        shown = pw if pw is not None else "(existing account, password unchanged)"
        print(f"    {user:10s} password {shown}", file=sys.stderr)
    if serve:
        import uvicorn  # the web server, for serving only: every other command starts without it

        print(f"  open http://{host}:{port}/", file=sys.stderr)
        opts = uvicorn_options(settings)
        tune_allocator()
        uvicorn.run(app, host=host, port=port, log_level="info", **opts)
    else:
        from app.main import close  # the app factory's module, loaded by demo's app already

        close(app)
    return info


def _demo(args: argparse.Namespace) -> dict | int:
    info = demo(preset=args.preset, seed=args.seed, source=args.source, host=args.host,
                port=args.port, serve=not args.no_serve, dev=args.dev)
    return info if args.no_serve else 0


def _redact(url: str) -> str:
    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001
        return url
