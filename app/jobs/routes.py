from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Response

from app.audit import service as audit
from app.deps import AdminUser, CtxDep, ReviewerUser, SceneDep, SessionDep
from app.errors import Conflict, Forbidden, Invalid, NotFound
from app.jobs import service
from app.jobs.schemas import EvalIn, ExportIn, JidPath, JobOut, VoxelizeIn
from app.limits import INT32_MAX
from app.review import provenance, quality_cache
from app.scenes.membership import check_member
from app.scenes.service import visible_scene_ids
from occufly.workspace import Workspace

router = APIRouter(prefix="/api", tags=["jobs"])

# who may call what (see app/access.py; tests/app/test_security.py walks them all)
ACCESS = {
    "GET /api/jobs": "staff",  # reviewers: the jobs of their scenes only
    "GET /api/jobs/{jid}": "staff",  # reviewers: 403 for a job of another scene
    "POST /api/jobs/{jid}/cancel": "admin",
    "POST /api/jobs/{jid}/resume": "admin",
    "POST /api/scenes/{sid}/voxelize": "admin",
    "POST /api/scenes/{sid}/export": "admin",
    "POST /api/scenes/{sid}/eval": "admin",
    "GET /api/scenes/{sid}/export/plan": "admin",
    "GET /api/scenes/{sid}/quality": "reviewer",
    "GET /api/scenes/{sid}/metrics": "reviewer",
}
# an export's output is downloaded as a compressed archive with its exact length
# (app/jobs/archive.py); the uncompressed tar stream of GET /api/jobs/{jid}/download, which
# shipped the exporter's .occufly_export bookkeeping and no length, was removed (issue 28)


@router.get("/jobs", response_model=list[JobOut])
def list_jobs(session: SessionDep, user: ReviewerUser,
              scene_id: Annotated[int | None, Query(ge=1, le=INT32_MAX)] = None):
    rows = service.list_jobs(session=session, scene_id=scene_id)
    visible = visible_scene_ids(session, user)
    if visible is not None:
        rows = [j for j in rows if j.scene_id in set(visible)]
    return [service.out(j) for j in rows]


@router.get("/jobs/{jid}", response_model=JobOut)
def get_job(jid: JidPath, session: SessionDep, user: ReviewerUser):
    job = service.get(session=session, job_id=jid)
    if user.role != "admin":
        if job.scene_id is None:
            raise Forbidden(f"job {jid} is not about one of your scenes")
        check_member(session, user, job.scene_id)
    return service.out(job)


@router.post("/jobs/{jid}/cancel", response_model=JobOut)
def cancel_job(jid: JidPath, session: SessionDep, _user: AdminUser):
    job = service.request_cancel(session=session, job=service.get(session=session, job_id=jid))
    return service.out(job)


@router.post("/jobs/{jid}/resume", response_model=JobOut)
def resume_job(jid: JidPath, session: SessionDep, ctx: CtxDep, _user: AdminUser):
    job = service.prepare_resume(session=session, job=service.get(session=session, job_id=jid))
    ctx.jobs.submit(job.id)
    return service.out(job)


IdemKey = Annotated[str | None, Header(alias="Idempotency-Key", max_length=128)]


def _start(session, ctx, scene, user, kind: str, params: dict,  # noqa: ANN001
           key: str | None = None, response: Response | None = None) -> dict:
    """Create and submit a job. With an ``Idempotency-Key``, the same key from the same user
    within a day returns the job it started (200) instead of a second one; the same key with
    another request is 422 (app.jobs.service.find_by_key)."""
    if key is not None:
        found = service.find_by_key(session=session, user_id=user.id, key=key, kind=kind,
                                    scene_id=scene.id, params=params)
        if found is not None:
            if response is not None:
                response.status_code = 200
            return service.out(found)
    if scene.status != "ready":
        raise Conflict(f"scene {scene.id} is {scene.status}, not ready")
    # issue 24: per-user job quota, export disk quota -- checked in the job's own transaction
    # under the user's database lock, so it holds across API processes (issue 36)
    job = service.create(session=session, kind=kind, scene_id=scene.id, params=params,
                         user_id=user.id, key=key, quota=ctx.settings)
    if getattr(job, "reused", False):
        if response is not None:
            response.status_code = 200
        return service.out(job)
    ctx.jobs.submit(job.id)
    audit.record(session, "export" if kind == "export" else "job", actor=user,
                 scene_id=scene.id, target=kind, detail={"job_id": job.id, "params": params})
    return service.out(job)


@router.post("/scenes/{sid}/voxelize", response_model=JobOut, status_code=202)
def voxelize(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AdminUser,
             response: Response, key: IdemKey = None, body: VoxelizeIn | None = None):
    return _start(session, ctx, scene, user, "voxelize", (body or VoxelizeIn()).model_dump(), key,
                  response)


@router.post("/scenes/{sid}/export", response_model=JobOut, status_code=202)
def export(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AdminUser,
           response: Response, key: IdemKey = None, body: ExportIn | None = None):
    return _start(session, ctx, scene, user, "export", (body or ExportIn()).model_dump(), key,
                  response)


@router.get("/scenes/{sid}/export/plan")
def export_plan(scene: SceneDep, session: SessionDep, _user: AdminUser,
                include: Annotated[str, Query(max_length=64)] = "accepted") -> dict:
    """What an export with ``include`` (comma-separated version states) would take: per frame
    the version, and the frames it leaves out (drafts, unreviewed, rejected) -- what the admin
    page lists before asking to confirm (issue 23)."""
    try:
        plan = provenance.export_plan(session, scene.id, [v for v in include.split(",") if v])
    except ValueError as e:
        raise Invalid(str(e)) from None

    # labels lifted from this app's masks (an export that takes none of them has nothing to
    # export); False for labels written into the workspace otherwise (exported as they are)
    from_masks = bool(Workspace(scene.workspace).lift_stats().get("versions"))
    return {**plan, "took": provenance.plan_text(plan), "labels_from_masks": from_masks}


@router.get("/scenes/{sid}/quality")
def scene_quality(scene: SceneDep, session: SessionDep, ctx: CtxDep, _user: ReviewerUser,
                  response: Response) -> dict:
    """The quality report of the scene's live labels (docs/quality-json.md), computed in the
    background per labels stamp (app.review.quality_cache): the current report, or the last
    one with ``stale`` and ``computing`` while the current is computed, or 202
    ``{"computing": true}`` before the first; 404 before the first fill."""
    w = Workspace(scene.workspace)
    if not (w.has_labels() and w.lifting_state.is_file()):
        raise NotFound(f"scene {scene.id} has no lifted labels yet: nothing to report")
    q = quality_cache.scene_quality(ctx, scene)
    if q is None:
        response.status_code = 202
        return {"computing": True, "stale": False,
                "message": f"the quality report of scene {scene.id} is being computed (one "
                           "leave-one-out decision per annotated frame); ask again shortly"}
    # who painted what, from the report's frames (issue 37: the admin's choice of model)
    return {**q, "painters": provenance.painters(session, q)}


@router.post("/scenes/{sid}/eval", response_model=JobOut, status_code=202)
def evaluate(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AdminUser,
             response: Response, key: IdemKey = None, body: EvalIn | None = None):
    return _start(session, ctx, scene, user, "eval", (body or EvalIn()).model_dump(), key,
                  response)


@router.get("/scenes/{sid}/metrics")
def metrics(scene: SceneDep, session: SessionDep, _user: ReviewerUser) -> dict:
    jobs = [j for j in service.list_jobs(session=session, scene_id=scene.id)
            if j.kind == "eval" and j.status == "done"]
    if not jobs:
        raise NotFound(f"scene {scene.id} has no evaluation yet; run POST /api/scenes/{scene.id}/eval")
    return {"job_id": jobs[0].id, "finished_at": jobs[0].finished_at, **(jobs[0].result or {})}
