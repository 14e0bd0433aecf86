from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from app.limits import Count, Id, text


class ReviewDecisionIn(BaseModel):
    decision: Literal["accept", "reject"]
    comment: text(10000) | None = None
    # the mask version the reviewer looked at (required, issue 40: a decision names what it
    # decides on); a version that is not the frame's current one is refused with 409
    version: Id


class ReviewUndoIn(BaseModel):
    """Take back ``decision`` made on mask ``version`` (the frame is submitted again)."""

    model_config = ConfigDict(extra="forbid")
    decision: Literal["accept", "reject"]
    version: Id


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


class NeighbourOut(BaseModel):
    frame_id: int
    name: str
    frame_index: int
    shared_points: int  # points both frames voted
    disagree_points: int  # of them, voted a different class
    disagree_share: float
    overruled_share: float | None  # of those, the share the independent labels overrule it on


class AgreementOut(BaseModel):
    # leave-one-out agreement; None when status is "not_enough_independent_views"
    agreement: float | None
    status: Literal["ok", "not_enough_independent_views"] = "ok"
    loo_agreement: float | None = None  # the LOO value even below the coverage threshold
    self_agreement: float | None = None  # the old circular figure (labels lifted from this mask)
    independent_coverage: float = 0.0
    painted_share: float = 0.0
    independent_pixels: int = 0
    painted_pixels: int = 0
    min_independent_coverage: float = 0.5
    # the review list's ranking score (higher = look first; occufly.lifting.loo.review_score)
    # and its parts: agreement over the confidently, independently labelled area (painted
    # or not), that area's share of the frame, the shift test's gain
    review_score: float | None = None
    area_agreement: float | None = None
    area_share: float = 0.0
    shift_gain: float = 0.0
    pixels: int  # = independent_pixels
    per_class: dict[str, object]  # from the LOO rendering
    version: int
    # the frames whose votes contradict this one's, most disagreeing points first
    # (occufly.lifting.loo.disagreeing_neighbours): overruled_share near 1 = the other frames
    # overrule that neighbour (likely the wrong one), near 0 = they side with it
    neighbours: list[NeighbourOut] = []


class SuspectMarkIn(BaseModel):
    """A reviewer's verdict on a suspect: done, dismissed, or null to reopen it."""

    model_config = ConfigDict(extra="forbid")
    status: Literal["done", "dismissed"] | None
