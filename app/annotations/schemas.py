from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel


class VersionOut(BaseModel):
    version: int  # global id (ETag / If-Match)
    number: int | None = None  # 1-based per-frame number (what people see: "version 3")
    frame_id: int
    kind: str  # the state: draft submitted accepted rejected conflict imported
    author: str | None
    created_at: datetime
    sha256: str
    size_bytes: int
    width: int
    height: int
    base_version: int | None
    restored_from: int | None
    source: str | None = None  # None = painted in the editor; "import:cvat", ...
    decided_at: datetime | None = None  # when a reviewer accepted / rejected this version


class LabelsStatus(BaseModel):
    lifting_available: bool
    included_versions: dict[str, int | None]  # frame id -> version counted in the point votes
    filled_versions: dict[str, int | None]  # frame id -> version in the filled/denoised labels
    pending_fill: bool
    pending_frames: int
    fill_running: bool
    last_error: str | None
    class_histogram: dict[str, int]
    labels_source: str | None
    lag_s: float = 0.0  # seconds since the scene's oldest entry still waiting to be lifted


class EffortRow(BaseModel):
    n: int  # submission order in the scene
    version: int
    frame_id: int
    frame: str
    frame_index: int
    author: str | None
    created_at: datetime
    pixels: int
    painted_px: int  # a class or 255: what painting from an empty mask costs
    changed_px: int  # differs from the prefill started from (= painted_px without one)
    prefilled: bool
    painted_share: float | None
    changed_share: float | None
    changed_of_painted: float | None
    resubmissions: int = 0  # later submissions of this frame, not counted again


class EffortTotals(BaseModel):
    submissions: int
    prefilled: int
    resubmissions: int = 0
    painted_px: int
    changed_px: int
    reduction_x: float | None
    median_changed_of_painted_from_6th: float | None


class EffortOut(BaseModel):
    scene_id: int
    submissions: list[EffortRow]
    totals: EffortTotals


#: OpenAPI content of a PNG request or response body
PNG = {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}}
