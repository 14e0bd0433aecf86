from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query, Response

from app.audit import service as audit
from app.deps import ClientIp, CtxDep, CurrentUser, FrameDep, ReviewerUser, SceneDep, SessionDep
from app.errors import Forbidden
from app.limits import INT32_MAX
from app.review import service
from app.review.schemas import (
    AgreementOut,
    CommentIn,
    ItemPatch,
    ReviewDecisionIn,
    ReviewItemIn,
    ReviewItemOut,
    ReviewUndoIn,
    SuspectMarkIn,
)
from app.scenes import service as scenes
from app.scenes.models import Scene
from app.scenes.schemas import FrameOut

router = APIRouter(prefix="/api", tags=["review"])
PNG = {200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}}}}
RidPath = Annotated[int, Path(ge=1, le=2**31 - 1)]

# who may call what (see app/access.py; tests/app/test_security.py walks them all). Review
# items: annotators see and comment on those about frames they hold or worked on.
ACCESS = {
    "GET /api/frames/{fid}/render": "reviewer",
    "GET /api/frames/{fid}/disagreement": "reviewer",
    "GET /api/frames/{fid}/agreement": "reviewer",
    "GET /api/scenes/{sid}/suspects": "reviewer",
    "PUT /api/scenes/{sid}/suspects/{key}/mark": "reviewer",
    "POST /api/frames/{fid}/review": "reviewer",
    "POST /api/frames/{fid}/review/undo": "reviewer",
    "GET /api/scenes/{sid}/review-items": "member",
    "POST /api/scenes/{sid}/review-items": "reviewer",
    "POST /api/review-items/{rid}/comments": "member",
    "PATCH /api/review-items/{rid}": "member",
}


@router.get("/frames/{fid}/render", response_class=Response, responses=PNG)
def render(frame: FrameDep, session: SessionDep, ctx: CtxDep, _user: ReviewerUser,
           downscale: Annotated[int, Query(ge=1, le=64)] = 1):
    scene = session.get(Scene, frame.scene_id)
    return Response(service.render_png(ctx, scene, frame, downscale=downscale),
                    media_type="image/png",
                    headers={"Cache-Control": "private, no-cache"})


@router.get("/frames/{fid}/disagreement", response_class=Response, responses=PNG)
def disagreement(frame: FrameDep, session: SessionDep, ctx: CtxDep, _user: ReviewerUser):
    scene = session.get(Scene, frame.scene_id)
    return Response(service.disagreement_png(ctx, session, scene, frame), media_type="image/png",
                    headers={"Cache-Control": "private, no-cache"})


@router.get("/scenes/{sid}/suspects")
def suspects(scene: SceneDep, ctx: CtxDep, _user: ReviewerUser):
    """Contested regions of the scene's labels, largest first (issue 23)."""
    return service.suspects(ctx, scene)


SuspectKey = Annotated[str, Path(pattern=r"^[pr][0-9]{1,12}$",
                                  description="the suspect's key from GET .../suspects")]


@router.put("/scenes/{sid}/suspects/{key}/mark")
def mark_suspect(key: SuspectKey, body: SuspectMarkIn, scene: SceneDep, session: SessionDep,
                 user: ReviewerUser, ip: ClientIp):
    """Mark a suspect done / dismissed (shared by the scene's reviewers), or clear the mark
    (``status`` null); the same mark twice is a no-op."""
    before = service.suspect_marks(session, scene.id).get(key)
    mark = service.set_suspect_mark(session=session, scene=scene, key=key, status=body.status,
                                    user=user)
    if (before and before["status"]) != (mark and mark["status"]):
        audit.record(session, "suspect_mark", actor=user, scene_id=scene.id, target=key,
                     client_ip=ip, detail={"status": body.status})
    return {"key": key, "mark": mark}


@router.get("/frames/{fid}/agreement", response_model=AgreementOut)
def agreement(frame: FrameDep, session: SessionDep, ctx: CtxDep, _user: ReviewerUser):
    scene = session.get(Scene, frame.scene_id)
    out = service.frame_agreement(ctx, session, scene, frame)
    service.prefetch_next(ctx, session, scene, frame)  # N finds the next frames computed
    return out


@router.post("/frames/{fid}/review", response_model=FrameOut)
def review_frame(body: ReviewDecisionIn, frame: FrameDep, session: SessionDep, ctx: CtxDep,
                 user: ReviewerUser, ip: ClientIp):
    frame = service.decide(session=session, ctx=ctx, frame=frame, user=user,
                           decision=body.decision, comment=body.comment, version=body.version)
    if getattr(frame, "decision_noop", False):  # the same decision again: nothing to record
        return scenes.frame_out(session=session, frame=frame)
    audit.record(session, f"review_{body.decision}", actor=user, scene_id=frame.scene_id,
                 frame_id=frame.id, client_ip=ip,
                 detail={"version": frame.reviewed_version_id, "comment": bool(body.comment)})
    return scenes.frame_out(session=session, frame=frame)


@router.post("/frames/{fid}/review/undo", response_model=FrameOut)
def undo_review(body: ReviewUndoIn, frame: FrameDep, session: SessionDep, ctx: CtxDep,
                user: ReviewerUser, ip: ClientIp):
    """Take back a decision (the page's Undo): the frame waits for review again."""
    frame = service.undo_decision(session=session, ctx=ctx, frame=frame, user=user,
                                  decision=body.decision, version=body.version)
    audit.record(session, "review_undo", actor=user, scene_id=frame.scene_id,
                 frame_id=frame.id, client_ip=ip,
                 detail={"version": body.version, "decision": body.decision})
    return scenes.frame_out(session=session, frame=frame)


@router.get("/scenes/{sid}/review-items", response_model=list[ReviewItemOut])
def list_items(scene: SceneDep, session: SessionDep, user: CurrentUser,
               status: Literal["open", "resolved"] | None = None,
               frame_id: Annotated[int | None, Query(ge=1, le=INT32_MAX)] = None):
    return service.list_items(session=session, scene=scene, user=user, status=status,
                              frame_id=frame_id)


@router.post("/scenes/{sid}/review-items", response_model=ReviewItemOut, status_code=201)
def create_item(body: ReviewItemIn, scene: SceneDep, session: SessionDep, ctx: CtxDep,
                user: ReviewerUser):
    item = service.create_item(session=session, scene=scene, user=user, frame_id=body.frame_id,
                               pixel=body.pixel, point_ids=body.point_ids, comment=body.comment,
                               settings=ctx.settings)
    return service.item_out(session, item)


@router.post("/review-items/{rid}/comments", response_model=ReviewItemOut, status_code=201)
def add_comment(rid: RidPath, body: CommentIn, session: SessionDep, ctx: CtxDep,
                user: CurrentUser):
    item = service.get_item(session=session, item_id=rid, user=user)
    service.add_comment(session=session, item=item, user=user, text=body.text,
                        settings=ctx.settings)
    return service.item_out(session, item)


@router.patch("/review-items/{rid}", response_model=ReviewItemOut)
def patch_item(rid: RidPath, body: ItemPatch, session: SessionDep, user: CurrentUser):
    item = service.get_item(session=session, item_id=rid, user=user)
    if user.role == "annotator" and body.status == "resolved":
        raise Forbidden("only reviewers and admins resolve review items")
    service.set_status(session=session, item=item, status=body.status)
    return service.item_out(session, item)
