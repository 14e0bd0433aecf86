"""The audit log: ``record(...)`` appends one event; ``query(...)`` reads them for admins.

Events are written in their own short transaction right after the action they describe has
committed, so a failed action leaves no event and an event never rolls an action back.
"""

from __future__ import annotations

import logging
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.audit.models import AuditEvent
from app.db import utcnow
from app.scenes.models import Frame, Scene
from app.users.models import User

log = logging.getLogger("occufly.audit")


def record(session: Session, action: str, *, actor=None, scene_id: int | None = None,  # noqa: ANN001
           frame_id: int | None = None, target: str | None = None, client_ip: str | None = None,
           detail: dict | None = None, actor_name: str | None = None) -> None:
    """Append an event. ``actor`` is a User (or None for the system / an anonymous caller)."""
    ev = AuditEvent(at=utcnow(), action=action[:32],
                    actor_id=getattr(actor, "id", None),
                    actor=(getattr(actor, "username", None) or actor_name or None),
                    scene_id=scene_id, frame_id=frame_id,
                    target=target[:256] if target else None,
                    client_ip=client_ip[:64] if client_ip else None, detail=detail or None)
    if ev.actor:
        ev.actor = ev.actor[:64]
    try:
        session.add(ev)
        session.commit()
    except Exception:  # noqa: BLE001 - the action already happened; never turn it into a 500
        session.rollback()
        log.exception("audit: could not record %s", action)


def query(*, session: Session, action: str | None = None, actor_id: int | None = None,
          scene_id: int | None = None, since: datetime | None = None,
          until: datetime | None = None, before_id: int | None = None,
          limit: int = 100) -> list[AuditEvent]:
    """Newest first; page with ``before_id`` (the smallest id of the previous page)."""
    q = select(AuditEvent)
    if action:
        q = q.where(AuditEvent.action.in_(action.split(",")))
    if actor_id is not None:
        q = q.where(AuditEvent.actor_id == actor_id)
    if scene_id is not None:
        q = q.where(AuditEvent.scene_id == scene_id)
    if since is not None:
        q = q.where(AuditEvent.at >= since)
    if until is not None:
        q = q.where(AuditEvent.at < until)
    if before_id is not None:
        q = q.where(AuditEvent.id < before_id)
    return list(session.scalars(q.order_by(AuditEvent.id.desc()).limit(limit)))


def out(ev: AuditEvent) -> dict:
    return dict(id=ev.id, at=ev.at, actor_id=ev.actor_id, actor=ev.actor, action=ev.action,
                scene_id=ev.scene_id, frame_id=ev.frame_id, target=ev.target,
                client_ip=ev.client_ip, detail=ev.detail)


USER_KEYS = ("user_id", "added", "removed", "user_ids")


def with_names(session: Session, rows: list[dict]) -> list[dict]:
    """Add ``scene_name``, ``frame_name`` and ``users`` (id -> name of the user ids in
    ``detail``) to event rows: one query per kind of name for the whole page."""
    sids = {r["scene_id"] for r in rows if r["scene_id"] is not None}
    fids = {r["frame_id"] for r in rows if r["frame_id"] is not None}
    uids: set[int] = set()
    for r in rows:
        d = r["detail"] or {}
        for k in USER_KEYS:
            v = d.get(k)
            for u in (v if isinstance(v, list) else [v]):
                if isinstance(u, int):
                    uids.add(u)
    scenes = dict(session.execute(select(Scene.id, Scene.name).where(Scene.id.in_(sids))).all()) if sids else {}
    frames = dict(session.execute(select(Frame.id, Frame.name).where(Frame.id.in_(fids))).all()) if fids else {}
    users = dict(session.execute(select(User.id, User.username).where(User.id.in_(uids))).all()) if uids else {}
    for r in rows:
        r["scene_name"] = scenes.get(r["scene_id"])
        r["frame_name"] = frames.get(r["frame_id"])
        d = r["detail"] or {}
        found = {}
        for k in USER_KEYS:
            v = d.get(k)
            for u in (v if isinstance(v, list) else [v]):
                if isinstance(u, int) and u in users:
                    found[str(u)] = users[u]
        r["users"] = found
    return rows
