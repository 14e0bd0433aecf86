from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse
from sqlalchemy import select

from app.audit import service as audit
from app.deps import AdminUser, ClientIp, CtxDep, CurrentUser, FrameDep, SceneDep, SessionDep
from app.errors import Conflict, DomainError, NotFound
from app.jobs import service as jobs
from app.jobs.schemas import JobOut
from app.limits import IdPath
from app.scenes import service
from app.scenes.models import Scene
from app.scenes.schemas import (
    FrameDetail,
    FrameOut,
    ImportIn,
    MemberOut,
    MembersIn,
    NextFramesIn,
    SceneDetail,
    SceneOut,
    SelectionIn,
)
from occufly.fsutil import image_content_type
from occufly.io.crs import parse_crs

router = APIRouter(prefix="/api", tags=["scenes"])
CACHE = "private, max-age=86400"

# who may call what (see app/access.py; tests/app/test_security.py walks them all)
ACCESS = {
    "GET /api/scenes": "user",  # filtered: annotators/reviewers see their scenes only
    "POST /api/scenes/import": "admin",
    "GET /api/scenes/{sid}": "member",
    "POST /api/scenes/{sid}/selection": "admin",
    "GET /api/scenes/{sid}/selection": "member",
    "POST /api/scenes/{sid}/next-frames": "admin",
    "GET /api/scenes/{sid}/frames": "member",
    "GET /api/frames/{fid}": "member",
    "GET /api/frames/{fid}/image": "member",
    "GET /api/scenes/{sid}/members": "admin",
    "PUT /api/scenes/{sid}/members": "admin",
    "POST /api/scenes/{sid}/members": "admin",
    "DELETE /api/scenes/{sid}/members/{uid}": "admin",
}


@router.get("/scenes", response_model=list[SceneOut])
def list_scenes(session: SessionDep, user: CurrentUser):
    q = select(Scene).order_by(Scene.id)
    ids = service.visible_scene_ids(session, user)
    if ids is not None:
        q = q.where(Scene.id.in_(ids))
    return list(session.scalars(q))


@router.post("/scenes/import", response_model=JobOut, status_code=202)
def import_scene(body: ImportIn, session: SessionDep, ctx: CtxDep, user: AdminUser, ip: ClientIp):
    s = ctx.settings
    source = service.resolve_import_path(s, body.source)
    cloud = service.resolve_import_path(s, body.cloud, field="cloud") if body.cloud else None
    depth = (service.resolve_import_path(s, body.depth_maps, field="depth_maps")
             if body.depth_maps else None)
    images = service.resolve_import_path(s, body.images, field="images") if body.images else None
    if body.crs:  # a CRS pyproj cannot read is a 4xx now, not a failed job later
        parse_crs(body.crs, "crs")
    if body.members:  # check the ids before anything is created
        service.check_member_ids(session=session, user_ids=body.members)
    service.check_source_paths(s, source)  # a workspace's image paths, before a job exists
    jobs.check_quota(session=session, settings=s, user_id=user.id, kind="import")  # issue 24
    scene = service.create_scene(session=session, settings=s, name=body.name, source=source)
    if body.members:
        service.set_members(session=session, scene=scene, user_ids=body.members, replace=True)
    try:  # the binding quota check, in the job's transaction (holds across API processes)
        job = jobs.create(session=session, kind="import", scene_id=scene.id, user_id=user.id,
                          params={"source": str(source), "cloud": str(cloud) if cloud else None,
                                  "depth_maps": str(depth) if depth else None,
                                  "format": body.format,
                                  "images": str(images) if images else None,
                                  "crs": body.crs, "scale": body.scale}, quota=s)
    except DomainError:  # lost the race for the last place: the new scene goes again
        session.delete(scene)
        session.commit()
        raise
    ctx.jobs.submit(job.id)
    audit.record(session, "import", actor=user, scene_id=scene.id, target=scene.name,
                 client_ip=ip, detail={"source": str(source), "job_id": job.id,
                                       "members": body.members or []})
    return jobs.out(job)


@router.get("/scenes/{sid}/members", response_model=list[MemberOut])
def list_members(scene: SceneDep, session: SessionDep, _admin: AdminUser):
    return service.members(session=session, scene=scene)


def _change_members(session, scene, admin, ip, user_ids, replace: bool):  # noqa: ANN001, ANN202
    change = service.set_members(session=session, scene=scene, user_ids=user_ids, replace=replace)
    if change["added"] or change["removed"]:
        audit.record(session, "membership", actor=admin, scene_id=scene.id, target=scene.name,
                     client_ip=ip, detail=change)
    return service.members(session=session, scene=scene)


@router.put("/scenes/{sid}/members", response_model=list[MemberOut])
def replace_members(body: MembersIn, scene: SceneDep, session: SessionDep, admin: AdminUser,
                    ip: ClientIp):
    """Exactly these users (annotators/reviewers) are the scene's members afterwards."""
    return _change_members(session, scene, admin, ip, body.user_ids, True)


@router.post("/scenes/{sid}/members", response_model=list[MemberOut])
def add_members(body: MembersIn, scene: SceneDep, session: SessionDep, admin: AdminUser,
                ip: ClientIp):
    """Add these users to the scene's members."""
    return _change_members(session, scene, admin, ip, body.user_ids, False)


@router.delete("/scenes/{sid}/members/{uid}", status_code=204, response_class=Response)
def remove_member(uid: IdPath, scene: SceneDep, session: SessionDep, admin: AdminUser,
                  ip: ClientIp) -> Response:
    service.remove_member(session=session, scene=scene, user_id=uid)
    audit.record(session, "membership", actor=admin, scene_id=scene.id, target=scene.name,
                 client_ip=ip, detail={"added": [], "removed": [uid]})
    return Response(status_code=204)


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
                      params=body.model_dump(), quota=ctx.settings)  # issue 36: every job kind
    ctx.jobs.submit(job.id)
    return jobs.out(job)


@router.post("/scenes/{sid}/next-frames", response_model=JobOut, status_code=202)
def run_next_frames(body: NextFramesIn, scene: SceneDep, session: SessionDep, ctx: CtxDep,
                    user: AdminUser):
    """Issue 37: a job proposing ``k`` more frames to paint (its result: the frames, best
    first, each with the contested / uncertain points it sees and their classes)."""
    _ready(scene)
    job = jobs.create(session=session, kind="next_frames", scene_id=scene.id, user_id=user.id,
                      params=body.model_dump(), quota=ctx.settings)  # issue 36: every job kind
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
                state: Annotated[str | None, Query(max_length=200,
                                                   pattern=r"^[a-z_]+(,[a-z_]+)*$")] = None,
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
                size: Literal["full", "preview", "thumb"] = "full", download: bool = False):
    """The frame's photo (``?download=1``: as an attachment), its type decided from its bytes,
    with nosniff and a sandboxing CSP."""
    scene = session.get(Scene, frame.scene_id)
    src = service.image_file(ctx.load_scene(scene.workspace), scene.workspace, frame.index,
                             roots=service.image_roots(ctx.settings))

    if image_content_type(src) is None:  # decided from content, never from the name
        raise NotFound(f"image of frame {frame.id} is not a PNG, JPEG, TIFF or WebP file")
    path = src if size == "full" else service.resized_image(ctx.settings, src, scene.id,
                                                            frame.id, size)
    etag = service.file_etag(path)
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers={"ETag": etag, "Cache-Control": CACHE})
    name = frame.name if size == "full" else f"{Path(frame.name).stem}_{size}.jpg"
    return FileResponse(path, media_type=image_content_type(path), headers={
        "ETag": etag, "Cache-Control": CACHE,
        **service.data_headers(name, download=download)})


def _ready(scene: Scene) -> None:
    if scene.status != "ready":
        raise Conflict(f"scene {scene.id} is {scene.status}, not ready")


def _hide_assignee(row: dict, user) -> dict:  # noqa: ANN001
    """Annotators do not learn who else works on which frame."""
    if user.role == "annotator":
        for key in ("assignee", "last_annotator"):
            if row.get(key) not in (None, user.username):
                row[key] = "another annotator"
    return row
