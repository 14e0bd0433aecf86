from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field


class ReviewDecisionIn(BaseModel):
    decision: Literal["accept", "reject"]
    comment: str | None = Field(default=None, max_length=10000)


class ReviewItemIn(BaseModel):
    frame_id: int | None = Field(default=None, ge=1, le=2**31 - 1)
    pixel: list[int] | None = Field(default=None, min_length=2, max_length=2)
    point_ids: list[int] | None = Field(default=None, max_length=1_000_000)
    comment: str = Field(min_length=1, max_length=10000)


class CommentIn(BaseModel):
    text: str = Field(min_length=1, max_length=10000)


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
