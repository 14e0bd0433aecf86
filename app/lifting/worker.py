"""The lifting worker as its own process: ``occufly lifting-worker`` or ``python -m app.lifting``.

Settings come from the same ``OCCUFLY_*`` environment as the API processes (database, data
directory). PostgreSQL: start as many as you like, on any host mounting the data volume; they
share the scenes through advisory locks (:mod:`app.lifting.service`). SQLite: one per data
directory on one host -- a second one exits 2 with a message.
"""

from __future__ import annotations

import logging
import os
import sys

from app import db
from app.bootstrap import build_context, build_lifting_service
from app.config import Settings
from app.lifting.service import LiftingBusy
from occufly.errors import OccuflyError
from occufly.parallel import die_with_parent


def main(argv: list[str] | None = None) -> int:  # noqa: ARG001

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    parent = os.environ.get("OCCUFLY_DIE_WITH_PARENT")
    if parent and parent.isdigit():  # started by `occufly serve --workers N`
        die_with_parent(int(parent))
    try:
        settings = Settings.from_env()
    except OccuflyError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if settings.auto_upgrade:
        db.upgrade(settings.database_url)
    ctx = build_context(settings, lifting="external", jobs=False)
    svc = build_lifting_service(ctx)
    try:
        svc.acquire()
    except LiftingBusy as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        svc.run_forever()
    finally:
        ctx.events.close()
        ctx.engine.dispose()
    return 0
