from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse

from app.deps import AdminUser, CtxDep, CurrentUser, FrameDep, SceneDep, SessionDep
from app.errors import NotFound
from app.jobs import service as jobs
from app.jobs.schemas import JobOut
from app.scenes import service
from app.scenes.models import Scene
from app.scenes.schemas import FrameDetail, FrameOut, ImportIn, SceneDetail, SceneOut, SelectionIn

router = APIRouter(prefix="/api", tags=["scenes"])
CACHE = "private, max-age=86400"


@router.get("/scenes", response_model=list[SceneOut])
def list_scenes(session: SessionDep, _user: CurrentUser):
    from sqlalchemy import select

    return list(session.scalars(select(Scene).order_by(Scene.id)))


@router.post("/scenes/import", response_model=JobOut, status_code=202)
def import_scene(body: ImportIn, session: SessionDep, ctx: CtxDep, user: AdminUser):
    s = ctx.settings
    source = service.resolve_import_path(s, body.source)
    cloud = service.resolve_import_path(s, body.cloud, field="cloud") if body.cloud else None
    depth = (service.resolve_import_path(s, body.depth_maps, field="depth_maps")
             if body.depth_maps else None)
    scene = service.create_scene(session=session, settings=s, name=body.name, source=source)
    job = jobs.create(session=session, kind="import", scene_id=scene.id, user_id=user.id,
                      params={"source": str(source), "cloud": str(cloud) if cloud else None,
                              "depth_maps": str(depth) if depth else None})
    ctx.jobs.submit(job.id)
    return jobs.out(job)


@router.get("/scenes/{sid}", response_model=SceneDetail)
def get_scene(scene: SceneDep, session: SessionDep, ctx: CtxDep):
    out = SceneOut.model_validate(scene).model_dump()
    out["frame_states"] = service.frame_states(session=session, scene=scene)
    if scene.status == "ready":
        tax = ctx.load_scene(scene.workspace).taxonomy
        out["taxonomy"] = {"name": tax.name, "classes": [
            {"id": c.id, "name": c.name, "rgb": list(c.rgb), "group": c.group}
            for c in tax.classes]}
    return out


@router.post("/scenes/{sid}/selection", response_model=JobOut, status_code=202)
def run_selection(body: SelectionIn, scene: SceneDep, session: SessionDep, ctx: CtxDep,
                  user: AdminUser):
    _ready(scene)
    job = jobs.create(session=session, kind="selection", scene_id=scene.id, user_id=user.id,
                      params=body.model_dump())
    ctx.jobs.submit(job.id)
    return jobs.out(job)


@router.get("/scenes/{sid}/selection")
def get_selection(scene: SceneDep) -> dict:
    if not scene.selection:
        raise NotFound(f"scene {scene.id} has no frame selection yet")
    return scene.selection


@router.get("/scenes/{sid}/frames", response_model=list[FrameOut])
def list_frames(scene: SceneDep, session: SessionDep, user: CurrentUser,
                sort: Literal["index", "name", "disagreement"] = "index",
                state: Annotated[str | None, Query(max_length=200)] = None,
                selected: bool | None = None):
    rows = service.list_frames(session=session, scene_id=scene.id, sort=sort, state=state,
                               selected=selected)
    return [_hide_assignee(r, user) for r in rows]


@router.get("/frames/{fid}", response_model=FrameDetail)
def get_frame(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: CurrentUser):
    out = service.frame_out(session=session, frame=frame)
    scene = session.get(Scene, frame.scene_id)
    ws_scene = ctx.load_scene(scene.workspace)
    out["center"] = [float(x) for x in ws_scene.frames[frame.index].center]
    return _hide_assignee(out, user)


@router.get("/frames/{fid}/image", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}, "image/png": {}}},
                       304: {"description": "not modified"}})
def frame_image(frame: FrameDep, session: SessionDep, ctx: CtxDep, request: Request,
                size: Literal["full", "preview", "thumb"] = "full"):
    scene = session.get(Scene, frame.scene_id)
    src = service.image_file(ctx.load_scene(scene.workspace), scene.workspace, frame.index)
    path = src if size == "full" else service.resized_image(ctx.settings, src, scene.id,
                                                            frame.id, size)
    etag = service.file_etag(path)
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers={"ETag": etag, "Cache-Control": CACHE})
    return FileResponse(path, headers={"ETag": etag, "Cache-Control": CACHE})


def _ready(scene: Scene) -> None:
    from app.errors import Conflict

    if scene.status != "ready":
        raise Conflict(f"scene {scene.id} is {scene.status}, not ready")


def _hide_assignee(row: dict, user) -> dict:  # noqa: ANN001
    """Annotators do not learn who else works on which frame."""
    if user.role == "annotator":
        for key in ("assignee", "last_annotator"):
            if row.get(key) not in (None, user.username):
                row[key] = "another annotator"
    return row
