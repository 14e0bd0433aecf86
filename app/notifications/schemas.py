from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from app.limits import Id


class NotificationOut(BaseModel):
    id: int
    kind: str
    text: str
    scene_id: int | None
    frame_id: int | None
    item_id: int | None
    created_at: datetime
    read_at: datetime | None


class NotificationsOut(BaseModel):
    unread: int
    items: list[NotificationOut]


class ReadIn(BaseModel):
    ids: list[Id] | None = Field(default=None, max_length=1000)  # None: all
