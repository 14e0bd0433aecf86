"""Who may work on a scene: admins on every scene, annotators and reviewers on the scenes an
admin assigned them (``scene_members``). Used by the services and by the HTTP dependencies
(:mod:`app.deps`) alike."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.errors import Forbidden, NotFound
from app.scenes.models import Scene, SceneMember
from app.users.models import User


def is_member(session: Session, user: User, scene_id: int) -> bool:
    """Admins see every scene; annotators and reviewers the scenes they are assigned to."""
    if user.role == "admin":
        return True
    return session.scalar(select(SceneMember.id).where(
        SceneMember.scene_id == scene_id, SceneMember.user_id == user.id)) is not None


def check_member(session: Session, user: User, scene_id: int) -> None:
    """:class:`Forbidden` unless ``user`` may work on the scene; :class:`NotFound` when the
    scene is gone or being deleted. A deletion removes the members with the scene, and on
    PostgreSQL each statement sees what has committed by then: a request that found the scene
    or its frame a moment earlier then finds no membership, and the user must read that the
    scene is gone, not that they are no member of it."""
    if not is_member(session, user, scene_id):
        status = session.scalar(select(Scene.status).where(Scene.id == scene_id))
        if status is None or status == "deleting":
            raise NotFound(f"scene {scene_id} does not exist (it was deleted)")
        raise Forbidden(f"you are not a member of scene {scene_id}; an admin assigns scenes")
