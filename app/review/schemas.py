from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field

from app.limits import Count, Id, text


class ReviewDecisionIn(BaseModel):
    decision: Literal["accept", "reject"]
    comment: text(10000) | None = None
    # the mask version the reviewer looked at; if the frame moved on since, 409 (optional:
    # without it the decision is about the version current at that moment)
    version: Id | None = None


class ReviewItemIn(BaseModel):
    frame_id: Id | None = None
    pixel: list[Count] | None = Field(default=None, min_length=2, max_length=2)
    point_ids: list[Count] | None = Field(default=None, max_length=1_000_000)
    comment: text(10000, 1)


class CommentIn(BaseModel):
    text: text(10000, 1)


class ItemPatch(BaseModel):
    status: Literal["open", "resolved"]


class CommentOut(BaseModel):
    id: int
    author: str | None
    text: str
    created_at: datetime


class ReviewItemOut(BaseModel):
    id: int
    scene_id: int
    frame_id: int | None
    pixel: list[int] | None
    point_ids: list[int] | None
    n_points: int
    status: str
    author: str | None
    created_at: datetime
    resolved_at: datetime | None
    comments: list[CommentOut]


class AgreementOut(BaseModel):
    agreement: float | None
    pixels: int
    per_class: dict[str, object]
    version: int
