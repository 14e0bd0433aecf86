"""Disk used by scenes and exports, their deletion, and export retention (issue 28).

What a scene holds on disk: its workspace (``<data dir>/scenes/<name>``), the outputs of its
export jobs (``<data dir>/exports/job_<id>``) and their download archives
(``<data dir>/cache/archives/export_job_<id>.*``), its resized frame images
(``<data dir>/cache/images/<scene id>``) and the mask PNGs of its versions and prefills in
the content-addressed store (a blob another scene also uses is kept). The import source
folder is never touched: it is the admin's, not the app's.

Deleting a scene marks it ``deleting`` first (no job starts on a scene that is not ready),
refuses while a job of it is queued or running or the lifting worker still holds frames
of it, moves the workspace aside, removes the database rows (every table cascades from the
scene), then the files. Deleting an export removes its output folder and archives and keeps
the job row, its result marked ``deleted_at`` / ``freed_bytes`` (the download answers 404).

Retention (``OCCUFLY_EXPORT_KEEP_LAST``, ``OCCUFLY_EXPORT_MAX_AGE_DAYS``; 0 = off): the
finished exports of each scene beyond the newest N, and those older than D days, are
deleted at start-up and after every export job (the export kind's ``on_done``,
:mod:`app.review.jobs`).
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from datetime import timedelta
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from app.annotations.models import MaskVersion, Prefill
from app.blobs import release_blobs
from app.db import utcnow
from app.errors import Conflict, NotFound
from app.jobs.models import Job
from app.scenes.models import Frame, Scene
from app.scenes.service import own_workspace

if TYPE_CHECKING:  # annotations only: the services are handed the context
    from app.context import AppContext

log = logging.getLogger("occufly.storage")

ACTIVE = ("queued", "running")


def tree_bytes(path: Path) -> int:
    """Bytes of the regular files under ``path`` (symlinks not followed; 0 if missing)."""
    p = Path(path)
    if p.is_symlink():
        return 0
    if p.is_file():
        return p.stat().st_size
    total = 0
    for dirpath, _dirs, files in os.walk(p, followlinks=False):
        for f in files:
            fp = os.path.join(dirpath, f)
            try:
                st = os.lstat(fp)
            except OSError:
                continue
            if not os.path.islink(fp):
                total += st.st_size
    return total


# ---- exports --------------------------------------------------------------------------------
def export_dir(ctx: AppContext, job: Job) -> Path | None:
    """The export's output folder when it is the app's own (inside the exports folder)."""
    out = (job.result or {}).get("output")
    if not out:
        return None
    p = Path(out)
    base = ctx.settings.exports_dir.resolve()
    try:
        if not p.resolve().is_relative_to(base) or p.resolve() == base:
            return None
    except OSError:
        return None
    return p


def archive_files(ctx: AppContext, job_id: int) -> list[Path]:
    d = ctx.settings.data_dir / "cache" / "archives"
    return [p for p in (d / f"export_job_{job_id}.zip", d / f"export_job_{job_id}.tar.gz")
            if p.is_file()]


def export_row(ctx: AppContext, job: Job, scene_name: str | None) -> dict:
    res = job.result or {}
    d = export_dir(ctx, job)
    out_bytes = tree_bytes(d) if d is not None and d.is_dir() and not res.get("deleted_at") else 0
    arch = sum(p.stat().st_size for p in archive_files(ctx, job.id))
    return dict(job_id=job.id, scene_id=job.scene_id, scene=scene_name,
                layout=(job.params or {}).get("layout"), finished_at=job.finished_at,
                created_at=job.created_at, output=res.get("output"),
                output_bytes=int(out_bytes), archive_bytes=int(arch),
                bytes=int(out_bytes + arch), deleted_at=res.get("deleted_at"),
                freed_bytes=res.get("freed_bytes"))


def list_exports(ctx: AppContext, session: Session, scene_id: int | None = None) -> list[dict]:
    q = (select(Job, Scene.name).outerjoin(Scene, Scene.id == Job.scene_id)
         .where(Job.kind == "export", Job.status == "done").order_by(Job.id.desc()))
    if scene_id is not None:
        q = q.where(Job.scene_id == scene_id)
    return [export_row(ctx, j, name) for j, name in session.execute(q)]


def finished_export(session: Session, job_id: int) -> Job:
    job = session.get(Job, job_id)
    if job is None:
        raise NotFound(f"job {job_id} does not exist")
    if job.kind != "export" or job.status != "done":
        raise Conflict(f"job {job_id} is not a finished export ({job.kind}, {job.status})")
    return job


def delete_export(ctx: AppContext, session: Session, job: Job, *, reason: str = "admin") -> dict:
    """Remove the export's output folder and archives; the job row stays, marked deleted.
    Returns the export's row as it was with ``freed_bytes``."""
    scene = session.get(Scene, job.scene_id) if job.scene_id is not None else None
    row = export_row(ctx, job, scene.name if scene else None)
    if row["deleted_at"]:
        raise Conflict(f"export job {job.id} was deleted at {row['deleted_at']}")
    d = export_dir(ctx, job)
    if d is not None and d.exists():
        trash = ctx.settings.data_dir / "trash" / f"export_{job.id}_{uuid.uuid4().hex[:8]}"
        trash.parent.mkdir(parents=True, exist_ok=True)
        os.replace(d, trash)  # gone from its place at once; the bytes go below
        shutil.rmtree(trash, ignore_errors=True)
    for p in archive_files(ctx, job.id):
        p.unlink(missing_ok=True)
    job.result = {**(job.result or {}), "deleted_at": utcnow().isoformat(timespec="seconds"),
                  "freed_bytes": row["bytes"], "deleted_by": reason}
    session.commit()
    return {**row, "freed_bytes": row["bytes"], "deleted_at": job.result["deleted_at"]}


def apply_export_retention(ctx: AppContext, scene_id: int | None = None) -> list[dict]:
    """Delete the finished exports retention no longer keeps (see the module docstring);
    returns what was deleted. Nothing happens while both settings are 0."""
    keep = int(ctx.settings.export_keep_last or 0)
    age = float(ctx.settings.export_max_age_days or 0)
    if keep <= 0 and age <= 0:
        return []
    limit = utcnow() - timedelta(days=age) if age > 0 else None
    deleted = []
    with ctx.sessions() as s:
        q = select(Job).where(Job.kind == "export", Job.status == "done").order_by(Job.id.desc())
        if scene_id is not None:
            q = q.where(Job.scene_id == scene_id)
        seen: dict[int | None, int] = {}
        for job in list(s.scalars(q)):
            if (job.result or {}).get("deleted_at"):
                continue
            rank = seen.get(job.scene_id, 0)
            seen[job.scene_id] = rank + 1
            when = job.finished_at or job.created_at
            too_many = keep > 0 and rank >= keep
            too_old = limit is not None and when is not None and when < limit
            if too_many or too_old:
                why = f"retention: {'beyond the newest ' + str(keep) if too_many else ''}" \
                      f"{' and ' if too_many and too_old else ''}" \
                      f"{'older than ' + str(age) + ' days' if too_old else ''}"
                try:
                    deleted.append(delete_export(ctx, s, job, reason=why))
                except Exception:  # noqa: BLE001 - one export that cannot go must not stop the rest
                    s.rollback()
                    log.exception("retention: could not delete export job %s", job.id)
    if deleted:
        log.info("export retention deleted %d export(s), %d bytes", len(deleted),
                 sum(d["freed_bytes"] or 0 for d in deleted))
    return deleted


# ---- scenes ---------------------------------------------------------------------------------
def _scene_blobs(session: Session, scene_id: int) -> set[str]:
    frames = select(Frame.id).where(Frame.scene_id == scene_id)
    shas = set(session.scalars(select(MaskVersion.sha256).where(MaskVersion.frame_id.in_(frames))))
    shas |= set(session.scalars(select(Prefill.sha256).where(Prefill.frame_id.in_(frames))))
    return shas


def _shared_blobs(session: Session, scene_id: int, shas: set[str]) -> set[str]:
    """Those of ``shas`` another scene's versions or prefills also use."""
    if not shas:
        return set()
    others = select(Frame.id).where(Frame.scene_id != scene_id)
    out: set[str] = set()
    wanted = sorted(shas)
    for i in range(0, len(wanted), 500):
        part = wanted[i:i + 500]
        out |= set(session.scalars(select(MaskVersion.sha256).where(
            MaskVersion.sha256.in_(part), MaskVersion.frame_id.in_(others))))
        out |= set(session.scalars(select(Prefill.sha256).where(
            Prefill.sha256.in_(part), Prefill.frame_id.in_(others))))
    return out


def scene_storage(ctx: AppContext, session: Session, scene: Scene, *, exclusive: bool = False) -> dict:
    """Bytes the scene takes: workspace, exports (+ archives), image cache, mask store
    (``exclusive``: only blobs no other scene uses, i.e. what deleting it frees)."""
    ws = tree_bytes(Path(scene.workspace))
    exports = [r for r in list_exports(ctx, session, scene.id) if not r["deleted_at"]]
    exp = sum(r["bytes"] for r in exports)
    cache = tree_bytes(ctx.settings.data_dir / "cache" / "images" / str(scene.id))
    shas = _scene_blobs(session, scene.id)  # each stored PNG once (versions may share one)
    if exclusive:
        shas -= _shared_blobs(session, scene.id, shas)
    masks = sum(ctx.store.path(h).stat().st_size for h in shas if ctx.store.exists(h))
    return dict(scene_id=scene.id, scene=scene.name, status=scene.status,
                workspace_bytes=int(ws), exports=len(exports), export_bytes=int(exp),
                cache_bytes=int(cache), mask_bytes=int(masks),
                total_bytes=int(ws + exp + cache + masks))


def deletion_preview(ctx: AppContext, session: Session, scene: Scene) -> dict:
    """What deleting ``scene`` removes and frees, and what stops it now (``blocked_by``)."""
    st = scene_storage(ctx, session, scene, exclusive=True)
    frames = select(Frame.id).where(Frame.scene_id == scene.id)
    versions = int(session.scalar(select(func.count(MaskVersion.id))
                                  .where(MaskVersion.frame_id.in_(frames))) or 0)
    blocked = []
    active = list(session.scalars(select(Job.id).where(Job.scene_id == scene.id,
                                                       Job.status.in_(ACTIVE))))
    if active:
        blocked.append(f"job(s) {', '.join(map(str, active))} of this scene are queued or "
                       "running: cancel them or wait")
    lift = ctx.lifting.status(scene.id)
    if lift.get("pending_frames"):
        blocked.append(f"the lifting worker still has {lift['pending_frames']} frame(s) of this "
                       "scene to lift: wait a moment")
    return {**st, "frames": scene.n_frames, "mask_versions": versions,
            "workspace": scene.workspace, "source_kept": scene.source,
            "freed_bytes": st["total_bytes"], "blocked_by": blocked}


def delete_scene(ctx: AppContext, session: Session, scene: Scene) -> dict:
    preview = deletion_preview(ctx, session, scene)
    if preview["blocked_by"]:
        raise Conflict(f"scene {scene.name} cannot be deleted now: " + "; ".join(preview["blocked_by"]),
                       blocked_by=preview["blocked_by"])
    res = session.execute(update(Scene).where(Scene.id == scene.id, Scene.status != "deleting")
                          .values(status="deleting").execution_options(synchronize_session=False))
    session.commit()
    if res.rowcount != 1:
        raise Conflict(f"scene {scene.name} is being deleted already")
    session.refresh(scene)
    sid, name = scene.id, scene.name
    exports = [export_dir(ctx, j) for j in session.scalars(
        select(Job).where(Job.scene_id == sid, Job.kind == "export"))]
    archives = [p for j in session.scalars(select(Job.id).where(Job.scene_id == sid))
                for p in archive_files(ctx, j)]
    shas = _scene_blobs(session, sid)
    trash_root = ctx.settings.data_dir / "trash"
    trash_root.mkdir(parents=True, exist_ok=True)
    moved = []
    try:
        ws = own_workspace(ctx.settings, scene)  # never a folder that is not the scene's own
    except Exception:  # noqa: BLE001 - a workspace that is not ours is left where it is
        ws = None
    for p in [ws, *exports]:
        if p is not None and p.exists():
            t = trash_root / f"{p.name}_{uuid.uuid4().hex[:8]}"
            os.replace(p, t)
            moved.append(t)
    session.delete(scene)  # frames, versions, prefills, jobs, members, queues cascade
    session.commit()
    ctx.scene_cache.pop(str(scene.workspace), None)
    # the scene's rows are gone: a blob goes only if no row references it once its row is
    # locked -- a concurrent save of the same bytes in another scene keeps it (issue 36)
    release_blobs(session, ctx.store, shas)
    for t in moved:
        shutil.rmtree(t, ignore_errors=True)
    for p in archives:
        p.unlink(missing_ok=True)
    shutil.rmtree(ctx.settings.data_dir / "cache" / "images" / str(sid), ignore_errors=True)
    return {**preview, "status": "deleted", "scene": name}
