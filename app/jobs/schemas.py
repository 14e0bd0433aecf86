from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, Field

from app.limits import Count


class JobOut(BaseModel):
    id: int
    kind: str
    scene_id: int | None
    status: str
    progress: float
    message: str
    log_tail: list[str]
    params: dict[str, Any]
    result: dict[str, Any] | None
    attempts: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class ExportIn(BaseModel):
    layout: Literal["occufly", "sscbench"] = "occufly"
    frames: list[Count] | None = Field(default=None, max_length=100000)  # frame indices
    # issue 23: the mask version states whose votes the exported labels count (accepted only
    # by default; submitted and imported versions are unreviewed and count only when named)
    include: list[Literal["accepted", "submitted", "imported"]] = Field(
        default=["accepted"], min_length=1, max_length=3)


class VoxelizeIn(BaseModel):
    voxel_size: float = Field(default=0.5, gt=0, le=100)


class EvalIn(BaseModel):
    frames: list[Count] | None = Field(default=None, max_length=100000)  # frame indices


#: a job id in a path: a positive 32-bit integer
JidPath = Annotated[int, Path(ge=1, le=2**31 - 1)]
