"""Downloadable export archives: a compressed zip or tar.gz of a finished export job's output,
without the exporter's internal bookkeeping (``.occufly_export/`` and any other ``.occufly*``
entry), built once next to the data dir's cache and served with its exact size.

Routes (its own router, included by app/main.py):

* ``GET  /api/jobs/{jid}/archive/info?format=zip|tar.gz`` -- files and bytes of the content,
  and the archive's size when it is built (``ready``);
* ``POST /api/jobs/{jid}/archive?format=...`` -- build it (idempotent), answer the info;
* ``GET  /api/jobs/{jid}/archive?format=...`` -- the archive (``Content-Length`` set; built
  first when needed), as ``<export name>.zip`` / ``.tar.gz``.
"""

from __future__ import annotations

import os
import tarfile
import zipfile
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Query
from fastapi.responses import FileResponse
from starlette.concurrency import run_in_threadpool

from app.deps import AdminUser, CtxDep, SessionDep
from app.errors import DISK_FULL_ERRNOS, Conflict, InsufficientStorage, NotFound
from app.jobs import service
from app.jobs.schemas import JidPath

router = APIRouter(prefix="/api", tags=["jobs"])

Format = Literal["zip", "tar.gz"]
FormatQ = Annotated[Format, Query(description="zip or tar.gz")]
HIDDEN_PREFIX = ".occufly"  # the exporter's resume / manifest bookkeeping


def export_root(ctx, session, jid: int) -> Path:  # noqa: ANN001
    job = service.get(session=session, job_id=jid)
    if job.kind != "export" or job.status != "done":
        raise Conflict(f"job {jid} is not a finished export")
    if (job.result or {}).get("deleted_at"):
        raise NotFound(f"export job {jid} was deleted at {job.result['deleted_at']}: "
                       f"nothing to download")
    root = Path((job.result or {}).get("output", ""))
    base = ctx.settings.exports_dir.resolve()
    if not root.is_dir() or not root.resolve().is_relative_to(base):
        raise NotFound(f"the output of job {jid} is no longer on disk")
    return root.resolve()


def content(root: Path) -> list[tuple[Path, str]]:
    """(file, name in the archive) of every regular file to ship, sorted; symlinks and the
    ``.occufly*`` bookkeeping entries are left out."""
    out = []
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(HIDDEN_PREFIX))
        for f in sorted(filenames):
            p = Path(dirpath) / f
            if f.startswith(HIDDEN_PREFIX) or p.is_symlink() or not p.is_file():
                continue
            out.append((p, f"{root.name}/{p.relative_to(root).as_posix()}"))
    return out


def archive_path(ctx, jid: int, fmt: str) -> Path:  # noqa: ANN001
    return ctx.settings.data_dir / "cache" / "archives" / f"export_job_{jid}.{fmt}"


def build(root: Path, dest: Path, fmt: str) -> Path:
    """Write the archive to ``dest`` atomically (a partial file never has the final name)."""
    files = content(root)
    if not files:
        raise NotFound(f"export {root.name} has no files to download")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.part")
    try:
        if fmt == "zip":
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6,
                                 allowZip64=True) as z:
                for p, name in files:
                    z.write(p, name)
        else:
            with tarfile.open(tmp, "w:gz", compresslevel=6) as t:
                for p, name in files:
                    t.add(p, arcname=name, recursive=False)
        os.replace(tmp, dest)
    except OSError as e:
        if e.errno not in DISK_FULL_ERRNOS:
            raise
        raise InsufficientStorage(  # the partial archive is removed below (issue 36)
            f"disk full while writing the archive {dest.name} of export {root.name} (in "
            f"{dest.parent}): nothing was kept -- an admin must free space, then try again"
        ) from None
    finally:
        tmp.unlink(missing_ok=True)
    return dest


def info(ctx, root: Path, jid: int, fmt: str) -> dict:  # noqa: ANN001
    files = content(root)
    dest = archive_path(ctx, jid, fmt)
    fresh = dest.is_file() and all(p.stat().st_mtime <= dest.stat().st_mtime for p, _ in files)
    return {"job_id": jid, "format": fmt, "name": f"{root.name}.{fmt}", "files": len(files),
            "content_bytes": int(sum(p.stat().st_size for p, _ in files)),
            "ready": fresh, "archive_bytes": dest.stat().st_size if fresh else None,
            "url": f"/api/jobs/{jid}/archive?format={fmt}"}


@router.get("/jobs/{jid}/archive/info")
def archive_info(jid: JidPath, session: SessionDep, ctx: CtxDep, _user: AdminUser,
                 format: FormatQ = "tar.gz") -> dict:  # noqa: A002 - the query's name
    return info(ctx, export_root(ctx, session, jid), jid, format)


@router.post("/jobs/{jid}/archive")
async def archive_build(jid: JidPath, session: SessionDep, ctx: CtxDep,
                        _user: AdminUser, format: FormatQ = "tar.gz") -> dict:  # noqa: A002
    root = export_root(ctx, session, jid)
    if not info(ctx, root, jid, format)["ready"]:
        await run_in_threadpool(build, root, archive_path(ctx, jid, format), format)
    return info(ctx, root, jid, format)


@router.get("/jobs/{jid}/archive", response_class=FileResponse,
                   responses={200: {"content": {"application/zip": {}, "application/gzip": {}}}})
async def archive_download(jid: JidPath, session: SessionDep, ctx: CtxDep,
                           _user: AdminUser, format: FormatQ = "tar.gz"):  # noqa: A002, ANN201
    root = export_root(ctx, session, jid)
    dest = archive_path(ctx, jid, format)
    if not info(ctx, root, jid, format)["ready"]:
        await run_in_threadpool(build, root, dest, format)
    return FileResponse(dest, filename=f"{root.name}.{format}",
                        media_type="application/zip" if format == "zip" else "application/gzip")


# app/access.py: who may call what
ACCESS = {"GET /api/jobs/{jid}/archive/info": "admin",
          "POST /api/jobs/{jid}/archive": "admin",
          "GET /api/jobs/{jid}/archive": "admin"}
