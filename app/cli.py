"""Web-app commands: ``serve``, ``lifting-worker``, ``db upgrade|current``, ``users
create|list``, ``backup``, ``restore``, ``scene-export``, ``demo``.

Registered with the ``occufly`` command line through the ``occufly.commands`` entry point
(pyproject.toml), so the library never imports the app. Every ``occufly`` command builds this
parser, so this module imports nothing of the app: the handlers (:mod:`app.commands`, which
import FastAPI, SQLAlchemy, uvicorn and the app -- about 2 s of CPU) are loaded only when one
of these commands runs. Before (issue 38's survey bench): ``occufly select`` on the small scene
took 3.4 s of CPU, 2.3 s of it this import.

Settings come from ``OCCUFLY_*`` environment variables (see ``app/config.py``), e.g.
``OCCUFLY_DATABASE_URL``, ``OCCUFLY_DATA_DIR``, ``OCCUFLY_SECRET_KEY``.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from typing import Any

from occufly.cli import command


def _handler(name: str) -> Callable[[argparse.Namespace], Any]:
    """The handler ``name`` of :mod:`app.commands`, imported when the command runs."""
    def run(args: argparse.Namespace) -> Any:
        return getattr(importlib.import_module("app.commands"), name)(args)

    run.__name__ = run.__qualname__ = name
    return run


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "serve", _handler("_serve"), help="run the web app (uvicorn) on the configured database")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=1,
                   help="API processes on one port (default 1). With N > 1 the processes are "
                        "stateless uvicorn workers over the same database and the lifting "
                        "worker runs as its own child process")
    p.add_argument("--proxy-headers", action="store_true",
                   help="behind a TLS-terminating reverse proxy: believe X-Forwarded-Proto/-For "
                        "from OCCUFLY_TRUSTED_PROXIES (required), so cookies are sent Secure")
    p.add_argument("--no-lifting-worker", action="store_true",
                   help="with --workers N > 1: do not start the lifting worker here (run "
                        "'occufly lifting-worker' elsewhere, e.g. its own container)")

    command(sub, "lifting-worker", _handler("_lifting_worker"),
            help="run the lifting service (queued mask versions -> votes, fill, events) as its "
                 "own process; one per data directory")

    p = command(sub, "db", _handler("_db"), help="database schema: 'upgrade' to the newest, 'current' revision")
    p.add_argument("action", choices=["upgrade", "current"])

    p = command(sub, "users", _handler("_users"), help="manage users: 'create NAME --role R', 'list'")
    p.add_argument("action", choices=["create", "list"])
    p.add_argument("name", nargs="?")
    p.add_argument("--role", choices=["annotator", "reviewer", "admin"])
    p.add_argument("--password", help="default: $OCCUFLY_NEW_PASSWORD, else prompt (or generate "
                                      "one when stdin is not a terminal)")

    p = command(sub, "backup", _handler("_backup"), help="back up the database, mask store and scene "
                                              "workspaces into a new folder (safe while serving)")
    p.add_argument("dir", help="the backup folder to create (must not exist or be empty)")
    p.add_argument("--no-images", action="store_true",
                   help="do not copy frame images that live outside the workspaces (the "
                        "import folders); they are recorded with their sha256 and the backup "
                        "is marked incomplete: a restore needs them at the same paths")
    p = command(sub, "restore", _handler("_restore"), help="restore a backup folder into this fresh data "
                                                "directory and database")
    p.add_argument("dir", help="a folder written by 'occufly backup'")

    p = command(sub, "scene-export", _handler("_scene_export"),
                help="export a scene of the app's database (an export job, run here): its "
                     "accepted mask versions only, unless --include-unreviewed")
    p.add_argument("scene", help="scene id or name")
    p.add_argument("--layout", choices=("occufly", "sscbench"), default="occufly")
    p.add_argument("--include-unreviewed", action="store_true",
                   help="also take in submitted and imported mask versions (not reviewed); "
                        "default: accepted versions only (issue 23, docs/provenance.md)")

    p = command(sub, "demo", _handler("_demo"), help="synthesize a scene, import it, select frames, create "
                                        "one user per role, and serve")
    p.add_argument("--preset", default="small", help="synthetic preset (tiny|small|bench)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--source", help="import this reconstruction instead of synthesizing")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--no-serve", action="store_true", help="seed only")
    p.add_argument("--dev", action="store_true",
                   help="well-known passwords occufly-<role> (default: random ones, printed)")
