from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.limits import Id, line

SCENE_NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$"


class SceneOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    name: str
    status: str
    n_frames: int
    n_points: int
    n_selected: int
    coverage: float | None
    created_at: datetime


class TaxonomyClass(BaseModel):
    id: int
    name: str
    rgb: list[int]
    group: str


class TaxonomyOut(BaseModel):
    name: str
    classes: list[TaxonomyClass]


class SceneDetail(SceneOut):
    taxonomy: TaxonomyOut | None = None
    frame_states: dict[str, int] = {}


class ImportIn(BaseModel):
    # a scene name is its workspace folder's name: one safe path component (letters, digits,
    # '_', '.', '-'; not starting with '.' or '-', so never '.', '..' or a hidden name)
    name: str = Field(min_length=1, max_length=128, pattern=SCENE_NAME_PATTERN)
    source: line(1024, 1)
    cloud: line(1024) | None = None
    depth_maps: line(1024) | None = None
    format: Literal["colmap", "odm", "metashape", "pix4d"] | None = Field(
        default=None, description="project kind (detected from the files when omitted): a COLMAP "
        "model, an OpenDroneMap project, a Metashape camera XML or a Pix4D project")
    images: line(1024) | None = Field(default=None, description="image folder (default: the "
                                      "project's images/)")
    crs: line(4096) | None = Field(default=None, description="CRS of the cloud when its file "
                                   "declares none: EPSG:n, WKT or PROJ")
    scale: float | None = Field(default=None, gt=0, le=1e6, allow_inf_nan=False,
                                description="metres per model unit of a COLMAP model that is "
                                "neither georeferenced nor geotagged (1 if it is metric "
                                "already); without it such a model is refused")
    members: list[Id] | None = Field(default=None, max_length=1000,
                                     description="user ids assigned to the scene at import")


class MembersIn(BaseModel):
    user_ids: list[Id] = Field(max_length=10000)


class MemberOut(BaseModel):
    user_id: int
    username: str
    role: str
    active: bool


class SelectionIn(BaseModel):
    # metres, or "auto" (greedy only): the edge of 23-28 m giving the fewest frames at the target
    cell: Annotated[float, Field(gt=0, le=10000)] | Literal["auto"] = 25.0
    mode: Literal["stratified", "greedy"] = "stratified"
    target_coverage: float = Field(default=0.99, gt=0, le=1)
    altitude: int | None = Field(default=None, ge=0, le=100000)

    @model_validator(mode="after")
    def _auto_needs_greedy(self) -> SelectionIn:
        if self.cell == "auto" and self.mode != "greedy":
            raise ValueError("cell 'auto' needs mode 'greedy' (it compares cells at the target coverage)")
        return self


class NextFramesIn(BaseModel):
    # issue 37: how many more frames to propose for painting (the frames whose masks would
    # most settle the contested and uncertain labels)
    k: int = Field(default=5, ge=1, le=200)


class FrameOut(BaseModel):
    id: int
    scene_id: int
    index: int
    name: str
    width: int
    height: int
    altitude: float | None
    nominal_altitude: int | None
    selected: bool
    state: str
    assignee: str | None
    lease_expires_at: datetime | None
    current_version: int | None
    agreement: float | None
    last_annotator: str | None = None  # who painted it (assignee is cleared on submit)
    handout_rank: int | None = None  # 0-based place in the hand-out order (selected frames)
    # issue 23: agreement above is leave-one-out; None with a coverage below the setting
    self_agreement: float | None = None
    independent_coverage: float | None = None
    painted_share: float | None = None
    review_score: float | None = None  # the review list's ranking score (higher = look first)
    # the current mask version's source (None: painted here; "imported from COCO by ...") and
    # the user who stored it (for an import: the admin who uploaded it)
    current_source: str | None = None
    current_author: str | None = None


class FrameDetail(FrameOut):
    center: list[float] | None = None
