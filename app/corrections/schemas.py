from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, Field

from app.limits import Count, Id, text


class EditMeta(BaseModel):
    """A correction's fields besides its points (app.corrections.parsing reads those)."""

    to_class: int = Field(ge=0, le=255)  # raw class id, 0 = unlabelled
    comment: text(10000) | None = None
    frame_id: Id | None = None  # the frame the reviewer was looking through, if any


class EditIn(EditMeta):
    """The body of POST /scenes/{sid}/corrections as documented (the route parses it with
    app.corrections.parsing, never as a Python list): exactly one of ``point_ids`` and
    ``point_ids_b64``, at most OCCUFLY_MAX_CORRECTION_POINTS points (413 beyond)."""

    point_ids: list[Count] | None = Field(default=None, min_length=1)
    point_ids_b64: str | None = Field(
        default=None, description="base64 of the point ids packed as little-endian uint32")


class EditOut(BaseModel):
    id: int
    scene_id: int
    author: str | None
    created_at: datetime
    to_class: int
    comment: str | None
    n_points: int
    from_hist: dict[int, int]
    frame_id: int | None
    state: Literal["active", "undone", "reverted", "dropped"]
    redoable: bool
    undone_by: str | None
    undone_at: datetime | None
    reverted_by: str | None
    reverted_at: datetime | None


class StackOut(BaseModel):
    undo: int | None
    redo: int | None


class LayerOut(BaseModel):
    corrected_points: int
    applied: list[int]
    per_class: dict[int, int]


class DisagreeOut(BaseModel):
    frame_id: int
    index: int
    name: str
    pixels: int
    disagreeing_px: int
    version: int
    state: str


class FrameEditOut(EditOut):
    """An active 3D correction as one frame sees it (GET /frames/{fid}/corrections)."""

    pixels: int  # mask pixels its points fall on in this frame
    voting_version: int | None  # the frame's voting mask compared (None: it has none)
    disagreeing_px: int | None  # of those, painted with another class (None: no voting mask)
    proposable_px: int | None  # of those, not of the edit's class (a proposal would set them)
    open_proposal: int | None  # the open proposal already filed from it for this frame


class ProposalIn(BaseModel):
    frame_id: Id
    dilate: int = Field(default=1, ge=0, le=16)


class ProposalOut(BaseModel):
    id: int
    frame_id: int
    edit_id: int | None
    author: str | None
    created_at: datetime
    changed_px: int
    status: str
    reply: str | None
    decided_by: str | None
    decided_at: datetime | None
    taken_version: int | None


class DeclineIn(BaseModel):
    reply: text(10000, 1)


class ProjectedItemOut(BaseModel):
    id: int
    scene_id: int
    frame_id: int | None
    status: str
    author: str | None
    n_points: int
    visible_points: int
    outline: list[list[float]]
    comments: list[dict]
