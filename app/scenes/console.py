"""The admin console's cross-scene routes (issue 28): storage per scene, deleting scenes and
exports (with what it frees), export retention, and the overview of the work.

* ``GET    /api/storage`` -- bytes per scene (workspace, exports, image cache, masks) and
  the data dir's disk;
* ``GET    /api/scenes/{sid}/deletion`` -- what deleting the scene removes and frees, and
  what blocks it now; ``DELETE /api/scenes/{sid}?confirm=<scene name>`` deletes it;
* ``GET    /api/exports`` -- finished exports with their bytes;
  ``DELETE /api/jobs/{jid}/export`` deletes one (the job row stays, marked deleted);
  ``POST   /api/exports/retention`` applies ``OCCUFLY_EXPORT_KEEP_LAST`` /
  ``OCCUFLY_EXPORT_MAX_AGE_DAYS`` now (also done at start-up and after each export);
* ``GET    /api/overview`` -- per scene and per annotator: frames to do / in progress /
  submitted / accepted / rejected, submissions, time spent and throughput (from the audit
  log's mask saves), and the lifting lag.
"""

from __future__ import annotations

import shutil
from collections import defaultdict
from datetime import timedelta
from typing import Annotated

from fastapi import APIRouter, Query, Response
from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session

from app.annotations.models import MaskVersion
from app.audit import service as audit
from app.audit.models import AuditEvent
from app.db import utcnow
from app.deps import AdminUser, ClientIp, CtxDep, SceneDep, SessionDep
from app.errors import Invalid
from app.jobs.schemas import JidPath
from app.limits import INT32_MAX
from app.scenes import disk
from app.scenes.models import Frame, Scene
from app.users.models import User

router = APIRouter(prefix="/api", tags=["admin console"])

ACCESS = {
    "GET /api/storage": "admin",
    "GET /api/scenes/{sid}/deletion": "admin",
    "DELETE /api/scenes/{sid}": "admin",
    "GET /api/exports": "admin",
    "DELETE /api/jobs/{jid}/export": "admin",
    "POST /api/exports/retention": "admin",
    "GET /api/overview": "admin",
}

#: two mask saves of one person further apart than this are two sittings: the gap is not
#: counted as time spent (the editor autosaves a draft while someone paints)
IDLE_GAP = timedelta(minutes=5)
MIN_RATE_S = 60.0  # less recorded work than this: no throughput figure
WORK_ACTIONS = ("mask_save", "mask_submit", "mask_restore")
STATES = ("todo", "in_progress", "submitted", "accepted", "rejected")


@router.get("/storage")
def storage_route(session: SessionDep, ctx: CtxDep, _admin: AdminUser) -> dict:
    """Disk used per scene (workspace, exports and their archives, resized images, mask
    PNGs) and the data dir's file system."""
    scenes = [disk.scene_storage(ctx, session, s)
              for s in session.scalars(select(Scene).order_by(Scene.id))]
    du = shutil.disk_usage(ctx.settings.data_dir)
    return {"scenes": scenes, "total_bytes": sum(s["total_bytes"] for s in scenes),
            "data_dir": str(ctx.settings.data_dir),
            "disk": {"total_bytes": du.total, "used_bytes": du.used, "free_bytes": du.free},
            "retention": {"keep_last": ctx.settings.export_keep_last,
                          "max_age_days": ctx.settings.export_max_age_days}}


@router.get("/scenes/{sid}/deletion")
def deletion_preview(scene: SceneDep, session: SessionDep, ctx: CtxDep, _admin: AdminUser) -> dict:
    """What deleting the scene removes (workspace, exports, cached images, mask PNGs no other
    scene uses; never the import source) and the bytes it frees; ``blocked_by`` lists what
    stops it now."""
    return disk.deletion_preview(ctx, session, scene)


@router.delete("/scenes/{sid}", responses={409: {"description": "a job or the lifting "
                                                              "worker still uses the scene"}})
def delete_scene(scene: SceneDep, session: SessionDep, ctx: CtxDep, admin: AdminUser,
                 ip: ClientIp, confirm: Annotated[str, Query(max_length=128, description=(
                     "the scene's name, typed by the admin to confirm"))]) -> dict:
    """Delete the scene, its frames, masks, jobs, exports and workspace."""
    if confirm != scene.name:
        raise Invalid(f"confirm: type the scene's name {scene.name!r} to delete it")
    sid, name = scene.id, scene.name
    out = disk.delete_scene(ctx, session, scene)
    audit.record(session, "scene_delete", actor=admin, scene_id=sid, target=name, client_ip=ip,
                 detail={"freed_bytes": out["freed_bytes"], "frames": out["frames"],
                         "mask_versions": out["mask_versions"], "exports": out["exports"]})
    return out


@router.get("/exports")
def list_exports(session: SessionDep, ctx: CtxDep, _admin: AdminUser,
                 scene_id: Annotated[int | None, Query(ge=1, le=INT32_MAX)] = None) -> list[dict]:
    """Finished exports, newest first, with the bytes their output and archives take."""
    return disk.list_exports(ctx, session, scene_id)


@router.delete("/jobs/{jid}/export")
def delete_export(jid: JidPath, session: SessionDep, ctx: CtxDep, admin: AdminUser,
                  ip: ClientIp) -> dict:
    """Delete a finished export's output and archives (answers what it freed)."""
    job = disk.finished_export(session, jid)
    out = disk.delete_export(ctx, session, job, reason=f"admin {admin.username}")
    audit.record(session, "export_delete", actor=admin, scene_id=job.scene_id,
                 target=f"export job {jid}", client_ip=ip,
                 detail={"job_id": jid, "freed_bytes": out["freed_bytes"]})
    return out


@router.post("/exports/retention")
def apply_retention(session: SessionDep, ctx: CtxDep, admin: AdminUser, ip: ClientIp,
                    response: Response) -> dict:
    """Apply the export retention settings now; answers what was deleted."""
    deleted = disk.apply_export_retention(ctx)
    if deleted:
        audit.record(session, "export_retention", actor=admin, client_ip=ip,
                     detail={"job_ids": [d["job_id"] for d in deleted],
                             "freed_bytes": sum(d["freed_bytes"] or 0 for d in deleted)})
    return {"keep_last": ctx.settings.export_keep_last,
            "max_age_days": ctx.settings.export_max_age_days, "deleted": deleted,
            "freed_bytes": sum(d["freed_bytes"] or 0 for d in deleted)}


# ---- overview -------------------------------------------------------------------------------
def _state_of(state: str, selected: bool) -> str | None:
    if state == "unassigned":
        return "todo" if selected else None
    return state if state in STATES else None


def time_spent(session: Session, scene_ids: list[int]) -> dict[tuple[int, int], dict]:
    """(scene id, user id) -> {seconds, first_at, last_at}: the sum of the gaps between one
    person's consecutive mask saves in a scene, gaps above IDLE_GAP left out."""
    rows = session.execute(select(AuditEvent.scene_id, AuditEvent.actor_id, AuditEvent.at)
                           .where(AuditEvent.action.in_(WORK_ACTIONS),
                                  AuditEvent.scene_id.in_(scene_ids),
                                  AuditEvent.actor_id.is_not(None))
                           .order_by(AuditEvent.scene_id, AuditEvent.actor_id, AuditEvent.at))
    out: dict[tuple[int, int], dict] = {}
    prev: dict[tuple[int, int], object] = {}
    for sid, uid, at in rows:
        k = (sid, uid)
        d = out.setdefault(k, {"seconds": 0.0, "first_at": at, "last_at": at})
        p = prev.get(k)
        if p is not None and at - p <= IDLE_GAP:
            d["seconds"] += (at - p).total_seconds()
        d["last_at"] = at
        prev[k] = at
    return out


@router.get("/overview")
def overview(session: SessionDep, ctx: CtxDep, _admin: AdminUser) -> dict:
    """Per scene and per annotator: frames to do (selected, nobody started them), in
    progress, submitted, accepted, rejected; submissions (``resubmissions`` of a frame
    apart), time spent (mask saves of one person less than 5 minutes apart, summed) and
    frames submitted per hour of it (from a minute of it on); per scene the lifting lag (seconds the oldest waiting
    mask has waited) and the frames still waiting to be lifted."""
    scenes = list(session.scalars(select(Scene).where(Scene.status != "deleting")
                                  .order_by(Scene.id)))
    sids = [s.id for s in scenes]
    users = {u.id: u for u in session.scalars(select(User))}
    counts: dict[int, dict[str, int]] = defaultdict(lambda: dict.fromkeys(STATES, 0))
    per_user: dict[tuple[int, int], dict] = {}

    def urow(sid: int, uid: int) -> dict:
        k = (sid, uid)
        if k not in per_user:
            per_user[k] = {**dict.fromkeys(STATES[1:], 0), "submissions": 0, "frames_submitted": 0,
                           "resubmissions": 0}
        return per_user[k]

    for sid, state, selected, assignee, last in session.execute(
            select(Frame.scene_id, Frame.state, Frame.selected, Frame.assignee_id,
                   Frame.last_annotator_id).where(Frame.scene_id.in_(sids))):
        st = _state_of(state, bool(selected))
        if st is None:
            continue
        counts[sid][st] += 1
        who = assignee if st == "in_progress" and assignee is not None else last
        if st != "todo" and who is not None:
            urow(sid, who)[st] += 1
    for sid, uid, n, nf in session.execute(
            select(Frame.scene_id, MaskVersion.author_id, func.count(MaskVersion.id),
                   func.count(func.distinct(MaskVersion.frame_id)))
            .join(Frame, Frame.id == MaskVersion.frame_id)
            .where(Frame.scene_id.in_(sids), MaskVersion.author_id.is_not(None),
                   MaskVersion.kind.in_(("submitted", "accepted", "rejected")),
                   # an imported mask (accepted or not) is no one's annotation work here: the
                   # admin who uploaded it is not an annotator (issue 40, defect 5)
                   or_(MaskVersion.source.is_(None),
                       MaskVersion.source.not_like("imported%")))
            .group_by(Frame.scene_id, MaskVersion.author_id)):
        r = urow(sid, uid)
        r["submissions"], r["frames_submitted"] = int(n), int(nf)
        r["resubmissions"] = int(n) - int(nf)
    spent = time_spent(session, sids)
    for k in spent:
        urow(*k)

    def per_hour(frames: int, sec: float) -> float | None:
        # under a minute of recorded work says nothing about a rate (None, not 12000/h)
        return round(frames / (sec / 3600), 2) if sec >= MIN_RATE_S else None

    def finish(r: dict, sec: float) -> dict:
        return {**r, "time_spent_s": round(sec, 1),
                "frames_per_hour": per_hour(r["frames_submitted"], sec)}

    scene_rows = []
    for s in scenes:
        lift = ctx.lifting.status(s.id)
        people = []
        for (sid, uid), r in sorted(per_user.items(), key=lambda kv: kv[0]):
            if sid != s.id:
                continue
            u = users.get(uid)
            t = spent.get((sid, uid), {})
            people.append({"user_id": uid, "username": u.username if u else f"user {uid}",
                           "role": u.role if u else None,
                           "last_active_at": t.get("last_at"),
                           **finish(r, t.get("seconds", 0.0))})
        total_s = sum(p["time_spent_s"] for p in people)
        submitted = sum(p["frames_submitted"] for p in people)
        scene_rows.append({
            "scene_id": s.id, "scene": s.name, "status": s.status, "frames": s.n_frames,
            "selected": s.n_selected, **counts[s.id],
            "submissions": sum(p["submissions"] for p in people),
            "time_spent_s": round(total_s, 1),
            "frames_per_hour": per_hour(submitted, total_s),
            "lift_lag_s": lift.get("lag_s", 0.0), "lift_pending_frames": lift.get("pending_frames", 0),
            "lift_error": lift.get("last_error"), "annotators": people})
    # per annotator over every scene
    tot: dict[int, dict] = {}
    secs: dict[int, float] = defaultdict(float)
    for (sid, uid), r in per_user.items():
        t = tot.setdefault(uid, {**dict.fromkeys(STATES[1:], 0), "submissions": 0,
                                 "frames_submitted": 0, "resubmissions": 0, "scenes": 0})
        for k2 in r:
            t[k2] += r[k2]
        t["scenes"] += 1
        secs[uid] += spent.get((sid, uid), {}).get("seconds", 0.0)
    people = [{"user_id": uid, "username": users[uid].username if uid in users else f"user {uid}",
               "role": users[uid].role if uid in users else None, **finish(t, secs[uid])}
              for uid, t in sorted(tot.items())]
    return {"generated_at": utcnow(), "idle_gap_s": IDLE_GAP.total_seconds(),
            "scenes": scene_rows, "annotators": people}
