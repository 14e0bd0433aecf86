from __future__ import annotations

from fastapi import APIRouter

from app.deps import CurrentUser, SessionDep
from app.notifications import service
from app.notifications.schemas import NotificationsOut, ReadIn

router = APIRouter(prefix="/api", tags=["notifications"])

ACCESS = {
    "GET /api/notifications": "user",
    "POST /api/notifications/read": "user",
}


@router.get("/notifications", response_model=NotificationsOut)
def notifications(session: SessionDep, user: CurrentUser, unread: bool = False):
    return service.list_notifications(session=session, user=user, unread=unread)


@router.post("/notifications/read")
def read_notifications(body: ReadIn, session: SessionDep, user: CurrentUser) -> dict:
    return {"marked": service.mark_read(session=session, user=user, ids=body.ids)}
