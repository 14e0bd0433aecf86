from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Query
from pydantic import BaseModel

from app.audit import service
from app.deps import AdminUser, SessionDep
from app.limits import INT32_MAX

router = APIRouter(prefix="/api", tags=["audit"])

ACCESS = {"GET /api/audit": "admin"}


class AuditOut(BaseModel):
    id: int
    at: datetime
    actor_id: int | None
    actor: str | None
    action: str
    scene_id: int | None
    frame_id: int | None
    target: str | None
    client_ip: str | None
    detail: dict | None
    # issue 28: what the ids name, as every other page shows them (None: deleted since)
    scene_name: str | None = None
    frame_name: str | None = None
    users: dict[str, str] = {}  # user ids in ``detail`` (user_id, added, removed) -> name


OptId = Annotated[int | None, Query(ge=1, le=INT32_MAX)]


@router.get("/audit", response_model=list[AuditOut])
def list_events(session: SessionDep, _admin: AdminUser,
                action: Annotated[str | None, Query(max_length=400, pattern=r"^[a-z_,]+$")] = None,
                actor_id: OptId = None, scene_id: OptId = None,
                since: datetime | None = None, until: datetime | None = None,
                before_id: OptId = None,
                limit: Annotated[int, Query(ge=1, le=1000)] = 100):
    """Audit events, newest first (filters combine; page with ``before_id``), with the names
    of the scene, frame and users their ids refer to."""
    return service.with_names(session, [service.out(e) for e in service.query(
        session=session, action=action, actor_id=actor_id, scene_id=scene_id,
        since=_naive(since), until=_naive(until), before_id=before_id, limit=limit)])


def _naive(t: datetime | None) -> datetime | None:
    """Timestamps are stored as naive UTC; an aware query time is converted."""
    if t is None or t.tzinfo is None:
        return t
    return t.astimezone(UTC).replace(tzinfo=None)
