"""Label corrections (3D edits, undo/redo/revert), proposed 2D mask changes, review items seen
from a frame, and the guarded re-import (notifications: app.notifications)."""

from __future__ import annotations

import io
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Depends, Header, Request, Response
from PIL import Image
from pydantic import BaseModel
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from app.annotations import service as annotations
from app.annotations.routes import png_body
from app.audit import service as audit
from app.corrections import service
from app.corrections.models import CorrectionEdit
from app.corrections.parsing import ParsedEdit, parse_edit, read_body
from app.corrections.schemas import (
    DeclineIn,
    DisagreeOut,
    EditIn,
    EditOut,
    FrameEditOut,
    LayerOut,
    ProjectedItemOut,
    ProposalIn,
    ProposalOut,
    StackOut,
)
from app.deps import (
    AdminUser,
    AnnotatorUser,
    ClientIp,
    CtxDep,
    CurrentUser,
    FrameDep,
    ReviewerUser,
    SceneDep,
    SessionDep,
)
from app.errors import NotFound
from app.jobs import service as jobs
from app.jobs.models import Job
from app.limits import IdPath
from app.notifications.service import notify_frame_people
from app.pipeline import encode_png, stored_mask_ids
from app.review.service import projected_for
from app.scenes.models import Frame, Scene

router = APIRouter(prefix="/api", tags=["corrections"])
PNG = {200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}}}

ACCESS = {
    "POST /api/scenes/{sid}/corrections": "reviewer",
    "GET /api/scenes/{sid}/corrections": "reviewer",
    "GET /api/scenes/{sid}/corrections/layer": "reviewer",
    "GET /api/scenes/{sid}/corrections/stack": "reviewer",
    "POST /api/scenes/{sid}/corrections/undo": "reviewer",
    "POST /api/scenes/{sid}/corrections/redo": "reviewer",
    "POST /api/scenes/{sid}/corrections/{eid}/revert": "admin",
    "GET /api/scenes/{sid}/corrections/{eid}/frames": "reviewer",
    "POST /api/scenes/{sid}/corrections/{eid}/proposals": "reviewer",
    "GET /api/frames/{fid}/proposals": "member",
    "GET /api/frames/{fid}/proposals/{pid}/overlay": "member",
    "POST /api/frames/{fid}/proposals/{pid}/take": "annotator",
    "POST /api/frames/{fid}/proposals/{pid}/decline": "annotator",
    "GET /api/frames/{fid}/projected-items": "member",
    "GET /api/frames/{fid}/corrections": "reviewer",
    "POST /api/scenes/{sid}/reimport": "admin",
    "PUT /api/frames/{fid}/reviewer-correction": "reviewer",
}


def _edit_of(session, scene, eid: int) -> CorrectionEdit:  # noqa: ANN001
    e = session.get(CorrectionEdit, eid)
    if e is None or e.scene_id != scene.id:
        raise NotFound(f"correction {eid} is not in scene {scene.id}")
    return e


def _proposal_of(session, frame, pid: int, user):  # noqa: ANN001, ANN202
    p = service.get_proposal(session=session, proposal_id=pid, user=user)
    if p.frame_id != frame.id:
        raise NotFound(f"proposal {pid} is not about frame {frame.id}")
    return p


async def edit_body(request: Request, ctx: CtxDep, _user: ReviewerUser,
                    _scene: SceneDep) -> ParsedEdit:
    """The correction's body, parsed without a Python object per point (app.corrections.parsing);
    the body itself is capped by app.bodylimit before it is read. Read only once the caller is
    known to be a reviewer of the scene (``_user``, ``_scene``: an anonymous or foreign request
    is a 401 / 403 before its body is read, not a 422 about it)."""
    cap = ctx.settings.max_correction_points
    body = await read_body(request.stream(), cap)
    return await run_in_threadpool(parse_edit, body, cap)


EDIT_BODY_DOC = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": EditIn.model_json_schema()}}}}


@router.post("/scenes/{sid}/corrections", response_model=EditOut, status_code=201,
             openapi_extra=EDIT_BODY_DOC)
def create_edit(body: Annotated[ParsedEdit, Depends(edit_body)], scene: SceneDep,
                session: SessionDep, ctx: CtxDep, user: ReviewerUser, ip: ClientIp):
    """Relabel points (``point_ids`` or the compact ``point_ids_b64``) to ``to_class``."""
    e = service.create_edit(session=session, ctx=ctx, scene=scene, user=user,
                            point_ids=body.point_ids, to_class=body.to_class,
                            comment=body.comment, frame_id=body.frame_id)
    out = service.edit_out(session, e)
    audit.record(session, "correction", actor=user, scene_id=scene.id, frame_id=body.frame_id,
                 client_ip=ip, detail={"edit": e.id, "to": e.to_class, "points": e.n_points})
    return out


@router.get("/scenes/{sid}/corrections", response_model=list[EditOut])
def list_edits(scene: SceneDep, session: SessionDep, _user: ReviewerUser,
               state: Literal["active", "undone", "reverted", "dropped"] | None = None):
    return service.list_edits(session=session, scene=scene, state=state)


@router.get("/scenes/{sid}/corrections/layer", response_model=LayerOut)
def layer(scene: SceneDep, session: SessionDep, _user: ReviewerUser):
    return service.layer_summary(session=session, scene=scene)


@router.get("/scenes/{sid}/corrections/stack", response_model=StackOut)
def stack(scene: SceneDep, session: SessionDep, user: ReviewerUser):
    return service.stack(session=session, scene=scene, user=user)


@router.post("/scenes/{sid}/corrections/undo", response_model=EditOut)
def undo(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: ReviewerUser, ip: ClientIp):
    e = service.undo(session=session, ctx=ctx, scene=scene, user=user)
    audit.record(session, "correction_undo", actor=user, scene_id=scene.id, client_ip=ip,
                 detail={"edit": e.id})
    return service.edit_out(session, e)


@router.post("/scenes/{sid}/corrections/redo", response_model=EditOut)
def redo(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: ReviewerUser, ip: ClientIp):
    e = service.redo(session=session, ctx=ctx, scene=scene, user=user)
    audit.record(session, "correction_redo", actor=user, scene_id=scene.id, client_ip=ip,
                 detail={"edit": e.id})
    return service.edit_out(session, e)


@router.post("/scenes/{sid}/corrections/{eid}/revert", response_model=EditOut)
def revert(eid: IdPath, scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AdminUser,
           ip: ClientIp):
    _edit_of(session, scene, eid)
    e = service.revert(session=session, ctx=ctx, edit_id=eid, user=user)
    audit.record(session, "correction_revert", actor=user, scene_id=scene.id, client_ip=ip,
                 detail={"edit": e.id})
    return service.edit_out(session, e)


@router.get("/scenes/{sid}/corrections/{eid}/frames", response_model=list[DisagreeOut])
def disagreeing_frames(eid: IdPath, scene: SceneDep, session: SessionDep, ctx: CtxDep,
                       _user: ReviewerUser):
    return service.disagreeing_frames(session=session, ctx=ctx, edit=_edit_of(session, scene, eid))


@router.post("/scenes/{sid}/corrections/{eid}/proposals", response_model=ProposalOut,
             status_code=201)
def propose(eid: IdPath, body: ProposalIn, scene: SceneDep, session: SessionDep, ctx: CtxDep,
            user: ReviewerUser):
    edit = _edit_of(session, scene, eid)
    frame = session.get(Frame, body.frame_id)
    if frame is None or frame.scene_id != scene.id:
        raise NotFound(f"frame {body.frame_id} is not in scene {scene.id}")
    p = service.propose(session=session, ctx=ctx, edit=edit, frame=frame, user=user,
                        dilate=body.dilate)
    return service.proposal_out(session, p)


@router.get("/frames/{fid}/proposals", response_model=list[ProposalOut])
def list_proposals(frame: FrameDep, session: SessionDep, user: CurrentUser,
                   status: Literal["open", "taken", "declined"] | None = None):
    annotations.check_read(session, frame, user)
    return service.list_proposals(session=session, frame=frame, status=status)


@router.get("/frames/{fid}/proposals/{pid}/overlay", response_class=Response, responses=PNG)
def proposal_overlay(pid: IdPath, frame: FrameDep, session: SessionDep, ctx: CtxDep,
                     user: CurrentUser):
    """RGBA at the mask's size: the proposed class colour where the proposal changes the mask,
    transparent elsewhere."""
    p = _proposal_of(session, frame, pid, user)
    scene = session.get(Scene, frame.scene_id)
    tax = ctx.load_scene(scene.workspace).taxonomy
    ids = stored_mask_ids(ctx.store.get(p.sha256), tax)
    change = np.asarray(Image.open(io.BytesIO(ctx.store.get(p.change_sha256)))) > 0
    lut = np.zeros((256, 4), np.uint8)
    for c in tax.classes:
        lut[c.id, :3] = c.rgb
    lut[:, 3] = 200
    rgba = lut[ids]
    rgba[~change] = 0
    return Response(encode_png(rgba), media_type="image/png",
                    headers={"Cache-Control": "private, no-cache"})


@router.post("/frames/{fid}/proposals/{pid}/take", response_model=ProposalOut)
def take(pid: IdPath, frame: FrameDep, session: SessionDep, ctx: CtxDep, user: AnnotatorUser,
         if_match: Annotated[str | None, Header(max_length=100)] = None):
    p = _proposal_of(session, frame, pid, user)
    expected = annotations.parse_if_match(if_match) if if_match else None
    p = service.take(session=session, ctx=ctx, proposal=p, user=user, expected=expected)
    return service.proposal_out(session, p)


@router.post("/frames/{fid}/proposals/{pid}/decline", response_model=ProposalOut)
def decline(pid: IdPath, body: DeclineIn, frame: FrameDep, session: SessionDep,
            user: AnnotatorUser):
    p = _proposal_of(session, frame, pid, user)
    p = service.decline(session=session, proposal=p, user=user, reply=body.reply)
    return service.proposal_out(session, p)


@router.get("/frames/{fid}/projected-items", response_model=list[ProjectedItemOut])
def projected_items(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: CurrentUser):
    annotations.check_read(session, frame, user)

    return projected_for(session, user,
                    service.projected_items(session=session, ctx=ctx, frame=frame, user=user))


@router.get("/frames/{fid}/corrections", response_model=list[FrameEditOut])
def frame_corrections(frame: FrameDep, session: SessionDep, ctx: CtxDep, _user: ReviewerUser):
    """The scene's active 3D corrections this frame sees, newest first, each with what a
    proposal from it would change in the frame's voting mask (the reviewer page's "Propose
    from 3D")."""
    return service.frame_corrections(session=session, ctx=ctx, frame=frame)


class ReimportIn(BaseModel):
    # required: the admin says explicitly what happens to reviewers' corrections
    drop_corrections: bool


@router.post("/scenes/{sid}/reimport", status_code=202)
def reimport(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AdminUser, ip: ClientIp,
             body: ReimportIn) -> dict:
    """Import the scene's source again into its workspace (same parameters as its first
    import). 409 naming their count while active corrections exist, unless
    ``drop_corrections`` is true (they are then kept in the history as ``dropped``)."""
    first = session.scalar(select(Job).where(Job.scene_id == scene.id, Job.kind == "import")
                           .order_by(Job.id).limit(1))
    if first is None:
        raise NotFound(f"scene {scene.id} has no import to repeat")
    # the job quota (issue 24/36): answered before any correction is dropped; the binding
    # check is the one in the job's transaction (it holds across API processes)
    jobs.check_quota(session=session, settings=ctx.settings, user_id=user.id, kind="import")
    dropped = service.guard_reimport(session=session, scene=scene, drop=body.drop_corrections,
                                     user=user)
    job = jobs.create(session=session, kind="import", scene_id=scene.id, user_id=user.id,
                      params={**(first.params or {}), "drop_corrections": body.drop_corrections},
                      quota=ctx.settings)
    ctx.jobs.submit(job.id)
    audit.record(session, "reimport", actor=user, scene_id=scene.id, client_ip=ip,
                 detail={"job_id": job.id, "dropped_corrections": dropped})
    return {**jobs.out(job), "dropped_corrections": dropped}


@router.put("/frames/{fid}/reviewer-correction", status_code=201,
            openapi_extra={"requestBody": {"required": True, "content": {
                "image/png": {"schema": {"type": "string", "format": "binary"}}}}},
            responses={409: {"description": "stale If-Match"}})
def reviewer_correction(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: ReviewerUser,
                        ip: ClientIp, body: Annotated[bytes, Depends(png_body)],
                        if_match: Annotated[str | None, Header(max_length=100)] = None) -> dict:
    """A reviewer corrects the frame's mask directly: a new *submitted* version authored by the
    reviewer, ``source = "reviewer_correction"`` (it votes like any submitted version). If-Match
    names the version corrected (default: the current one). The frame's annotator is told."""
    expected = annotations.parse_if_match(if_match) if if_match else frame.current_version_id
    v = annotations.store_version(session=session, ctx=ctx, frame=frame, user=user, data=body,
                                  kind="submitted", expected=expected,
                                  source="reviewer_correction")
    session.refresh(frame)
    notify_frame_people(session, frame=frame, actor=user, kind="corrected",
                                text=f"{user.username} corrected the mask of {frame.name}")
    session.commit()
    audit.record(session, "mask_reviewer_correction", actor=user, scene_id=frame.scene_id,
                 frame_id=frame.id, client_ip=ip, detail={"version": v.id, "sha256": v.sha256})
    return annotations.version_out(v, user.username,
                                   number=annotations.version_number(session, v))
