"""Tell people (in the caller's transaction) and let them read what they were told."""

from __future__ import annotations

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from app.db import utcnow
from app.notifications.models import Notification
from app.scenes.models import Frame
from app.users.models import User


def notify(session: Session, *, user_id: int | None, kind: str, text: str,
           scene_id: int | None = None, frame_id: int | None = None,
           item_id: int | None = None) -> None:
    """Queue a notification (committed with the caller's transaction)."""
    if user_id is None:
        return
    session.add(Notification(user_id=user_id, kind=kind, text=text, scene_id=scene_id,
                             frame_id=frame_id, item_id=item_id, created_at=utcnow()))


def notify_frame_people(session: Session, *, frame: Frame, actor: User, kind: str,
                        text: str, item_id: int | None = None) -> None:
    """Tell the frame's annotator(s) (last annotator, assignee), not the actor."""
    for uid in {frame.last_annotator_id, frame.assignee_id} - {None, actor.id}:
        notify(session, user_id=uid, kind=kind, text=text, scene_id=frame.scene_id,
               frame_id=frame.id, item_id=item_id)


def list_notifications(*, session: Session, user: User, unread: bool = False,
                       limit: int = 100) -> dict:
    q = select(Notification).where(Notification.user_id == user.id)
    if unread:
        q = q.where(Notification.read_at.is_(None))
    rows = list(session.scalars(q.order_by(Notification.id.desc()).limit(limit)))
    n_unread = session.scalar(select(func.count()).select_from(Notification).where(
        Notification.user_id == user.id, Notification.read_at.is_(None))) or 0
    return {"unread": int(n_unread),
            "items": [dict(id=n.id, kind=n.kind, text=n.text, scene_id=n.scene_id,
                           frame_id=n.frame_id, item_id=n.item_id, created_at=n.created_at,
                           read_at=n.read_at) for n in rows]}


def mark_read(*, session: Session, user: User, ids: list[int] | None) -> int:
    q = update(Notification).where(Notification.user_id == user.id,
                                   Notification.read_at.is_(None))
    if ids is not None:
        q = q.where(Notification.id.in_(ids))
    res = session.execute(q.values(read_at=utcnow()).execution_options(synchronize_session=False))
    session.commit()
    return int(res.rowcount or 0)
