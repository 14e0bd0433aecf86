"""What the import form reaches on the server (issue 28): a folder browser confined to the
import roots, and the upload of a project folder as a zip.

Routes (admin only; their own router, included by app/main.py):

* ``GET  /api/imports/browse?path=...`` -- the folders (and files) of one folder under an
  import root; without ``path`` the roots themselves. A path outside every root is 403 (it
  names the roots); an entry whose real location (symlinks followed) is outside the roots is
  never listed.
* ``POST /api/imports/upload?name=...`` -- the request body is a zip of a project folder,
  streamed to ``<data dir>/uploads/.incoming`` (never held in memory), at most
  ``OCCUFLY_MAX_IMPORT_UPLOAD_MB``; it is extracted into ``<data dir>/uploads/<name>`` only if
  every entry is a plain file or folder with a relative name (no ``..``, no absolute or
  drive-letter names, no symlinks, no encrypted entries), at most 100,000 entries and at most
  four times the upload cap once extracted (declared and actually written sizes both
  checked). Anything else is refused with nothing left behind. ``<data dir>/uploads`` is an
  import root of its own (:func:`import_roots`).
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import uuid
import zipfile
from pathlib import Path, PurePosixPath
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response
from fastapi import Path as PathParam
from sqlalchemy import select
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.audit import service as audit
from app.config import Settings
from app.deps import AdminUser, ClientIp, CtxDep, SessionDep
from app.errors import (
    Conflict,
    Forbidden,
    InsufficientStorage,
    Invalid,
    NotFound,
    PayloadTooLarge,
)
from app.jobs.models import Job
from app.scenes.models import Scene
from app.scenes.service import import_roots, upload_dir
from occufly.fsutil import PathNotConfined, confined

router = APIRouter(prefix="/api", tags=["scenes"])

ACCESS = {"GET /api/imports/browse": "admin",
          "POST /api/imports/upload": "admin",
          "GET /api/imports/uploads": "admin",
          "DELETE /api/imports/uploads/{name}": "admin"}

MAX_ENTRIES = 1000  # listed per folder (folders first, then files, by name)
MAX_ZIP_ENTRIES = 100_000
EXTRACT_FACTOR = 4  # extracted content may be at most this many times the upload cap
#: ... and at most this many times the zip actually uploaded (at least INFLATE_FLOOR): a
#: project folder is photos and point clouds, which deflate little (issue 36: a 2 MB zip
#: kept 2 GiB)
INFLATE_FACTOR = 10
INFLATE_FLOOR = 64 << 20
CHUNK = 1 << 20
FOLDER_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")


def roots_text(settings: Settings) -> str:
    return ", ".join(str(r) for r in import_roots(settings))


# ---- folder browser -------------------------------------------------------------------------
def browse(settings: Settings, raw: str | None) -> dict:
    roots = import_roots(settings)
    if not raw:
        return {"path": None, "parent": None, "roots": [str(r) for r in roots],
                "entries": [{"name": str(r), "path": str(r), "kind": "dir", "root": True,
                             "exists": r.is_dir()} for r in roots], "truncated": False}
    if "\x00" in raw:
        raise Invalid("path: contains a NUL byte")
    p = Path(raw)
    if not p.is_absolute() or ".." in p.parts:
        raise Invalid(f"path: give an absolute folder inside the import roots ({roots_text(settings)}), "
                      f"got {raw!r}")
    try:
        real = confined(p, roots)
    except PathNotConfined:
        raise Forbidden(f"path: {raw!r} is outside the allowed import roots "
                        f"({roots_text(settings)})") from None
    if not real.is_dir():
        raise NotFound(f"path: {raw!r} is not a folder")
    dirs, files = [], []
    with os.scandir(real) as it:
        for e in it:
            if e.name.startswith("."):
                continue
            try:
                target = confined(Path(e.path), roots)  # a symlink may point anywhere
            except (PathNotConfined, OSError):
                continue  # never show what lies outside the roots
            try:
                st = target.stat()
            except OSError:
                continue
            row = {"name": e.name, "path": str(real / e.name)}
            if stat.S_ISDIR(st.st_mode):
                dirs.append({**row, "kind": "dir"})
            elif stat.S_ISREG(st.st_mode) and st.st_nlink > 1:
                # a hard link may be a file from outside the roots: an import refuses it
                # (occufly.io.importer.refuse_hard_link); the browser says so
                files.append({**row, "kind": "file", "bytes": int(st.st_size), "hard_link": True,
                              "refused": "a hard link: imports refuse it, copy the file in"})
            elif stat.S_ISREG(st.st_mode):
                files.append({**row, "kind": "file", "bytes": int(st.st_size)})
    entries = sorted(dirs, key=lambda r: r["name"]) + sorted(files, key=lambda r: r["name"])
    real_roots = [Path(os.path.realpath(r)) for r in roots]
    up = real.parent  # None at a root: the browser goes back to the list of roots
    parent = (str(up) if real not in real_roots and any(up == r or r in up.parents
                                                         for r in real_roots) else None)
    return {"path": str(real), "parent": parent,
            "roots": [str(r) for r in roots], "entries": entries[:MAX_ENTRIES],
            "truncated": len(entries) > MAX_ENTRIES}


@router.get("/imports/browse")
def browse_route(ctx: CtxDep, _admin: AdminUser,
                 path: Annotated[str | None, Query(max_length=1024)] = None) -> dict:
    """The folders and files of ``path`` (a folder inside an import root); none: the roots."""
    return browse(ctx.settings, path)


# ---- upload ---------------------------------------------------------------------------------
def _member_parts(info: zipfile.ZipInfo) -> tuple[str, ...]:
    """The entry's path components, or Invalid naming it when it could leave the folder."""
    name = info.filename
    if "\x00" in name or "\\" in name:
        raise Invalid(f"zip entry {name!r}: backslashes and NUL bytes are not allowed in names")
    pp = PurePosixPath(name)
    parts = tuple(x for x in pp.parts if x not in ("", "."))
    if pp.is_absolute() or (parts and re.match(r"^[A-Za-z]:", parts[0])):
        raise Invalid(f"zip entry {name!r}: absolute names are not allowed")
    if ".." in parts:
        raise Invalid(f"zip entry {name!r}: '..' is not allowed (it would write outside the folder)")
    mode = (info.external_attr >> 16) & 0o170000
    if mode == stat.S_IFLNK:
        raise Invalid(f"zip entry {name!r} is a symbolic link; upload plain files only")
    if mode not in (0, stat.S_IFREG, stat.S_IFDIR):
        raise Invalid(f"zip entry {name!r} is not a plain file or folder")
    if info.flag_bits & 0x1:
        raise Invalid(f"zip entry {name!r} is encrypted")
    return parts


def extract_zip(zpath: Path, dest: Path, *, max_bytes: int) -> dict:
    """Check every entry of ``zpath`` (see the module docstring), then extract into ``dest``
    (which must not exist); on any error nothing is left at ``dest``."""
    try:
        zf = zipfile.ZipFile(zpath)
    except zipfile.BadZipFile:
        raise Invalid("the upload is not a zip file") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_ZIP_ENTRIES:
            raise Invalid(f"the zip has {len(infos)} entries; at most {MAX_ZIP_ENTRIES} are accepted")
        plan = [(i, _member_parts(i)) for i in infos]
        declared = sum(i.file_size for i, _ in plan if not i.is_dir())
        if declared > max_bytes:
            raise PayloadTooLarge(f"the zip would extract to {declared} bytes; at most {max_bytes} "
                                  f"are accepted ({INFLATE_FACTOR} times the zip's size, at "
                                  f"least {INFLATE_FLOOR >> 20} MB, at most {EXTRACT_FACTOR} "
                                  f"times OCCUFLY_MAX_IMPORT_UPLOAD_MB)")
        dest.parent.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(dest.parent).free
        if declared + (256 << 20) > free:
            raise InsufficientStorage(f"the zip would extract to {declared} bytes; the server's "
                                      f"uploads folder has {free} bytes free; nothing was written")
        if not any(parts for _, parts in plan):
            raise Invalid("the zip is empty")
        dest.mkdir(parents=True)
        written = 0
        try:
            for info, parts in plan:
                if not parts:
                    continue
                target = dest.joinpath(*parts)
                if info.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                n = 0
                with zf.open(info) as src, open(target, "xb") as out:
                    while chunk := src.read(CHUNK):
                        n += len(chunk)
                        written += len(chunk)
                        if n > info.file_size or written > max_bytes:
                            raise PayloadTooLarge(f"zip entry {info.filename!r} is larger than it "
                                                  "declares; refused")
                        out.write(chunk)
        except (FileExistsError, IsADirectoryError, NotADirectoryError):
            shutil.rmtree(dest, ignore_errors=True)
            raise Invalid(f"zip entry {info.filename!r} clashes with another entry (the same "
                          "name twice, or one name for a file and a folder)") from None
        except zipfile.BadZipFile as e:
            shutil.rmtree(dest, ignore_errors=True)
            raise Invalid(f"the zip is damaged: {e}") from None
        except BaseException:
            shutil.rmtree(dest, ignore_errors=True)
            raise
    files = sum(1 for i, parts in plan if parts and not i.is_dir())
    tops = {parts[0] for _, parts in plan if parts}
    source = dest / next(iter(tops)) if len(tops) == 1 and (dest / next(iter(tops))).is_dir() else dest
    return {"path": str(dest), "source": str(source), "files": files, "bytes": written}


@router.post("/imports/upload", status_code=201,
             # the zip's bytes as the body (sent as application/zip; any type is read as bytes)
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}},
             responses={409: {"description": "an upload of that name exists"},
                        413: {"description": "over OCCUFLY_MAX_IMPORT_UPLOAD_MB"}})
async def upload_route(request: Request, ctx: CtxDep, session: SessionDep, admin: AdminUser,
                       ip: ClientIp,
                       name: Annotated[str, Query(min_length=1, max_length=128)]) -> dict:
    """Upload a zip of a project folder; it is extracted to ``<data dir>/uploads/<name>`` and
    the answer's ``source`` is the folder to import (the zip's single top folder, if any)."""
    s = ctx.settings
    if not FOLDER_NAME.match(name):
        raise Invalid(f"name {name!r}: use 1-128 letters, digits, '_', '.' or '-', starting with "
                      "a letter, digit or '_'")
    cap = s.max_import_upload_bytes
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > cap:
        raise PayloadTooLarge(f"upload of {declared} bytes exceeds OCCUFLY_MAX_IMPORT_UPLOAD_MB "
                              f"({cap} bytes)")
    root = upload_dir(s)
    dest = root / name
    if dest.exists():
        raise Conflict(f"an upload named {name!r} exists already ({dest}); choose another name")
    incoming = root / ".incoming"
    incoming.mkdir(parents=True, exist_ok=True)
    tmp = incoming / f"{uuid.uuid4().hex}.zip"
    work = incoming / f"{tmp.stem}.d"
    total = 0
    try:
        with open(tmp, "xb") as fh:
            async for chunk in request.stream():
                total += len(chunk)
                if total > cap:
                    raise PayloadTooLarge(f"upload exceeds OCCUFLY_MAX_IMPORT_UPLOAD_MB ({cap} bytes)")
                await run_in_threadpool(fh.write, chunk)
        if not total:
            raise Invalid("empty body: send the zip of a project folder as application/zip")
        limit = min(EXTRACT_FACTOR * cap, max(INFLATE_FLOOR, INFLATE_FACTOR * total))
        out = await run_in_threadpool(extract_zip, tmp, work, max_bytes=limit)
        try:
            os.rename(work, dest)  # atomic on one file system; fails if dest appeared meanwhile
        except OSError:
            raise Conflict(f"an upload named {name!r} exists already ({dest})") from None
    finally:
        tmp.unlink(missing_ok=True)
        shutil.rmtree(work, ignore_errors=True)
    out = {k: (v.replace(str(work), str(dest), 1) if isinstance(v, str) else v)
           for k, v in out.items()}
    out["upload_bytes"] = total
    audit.record(session, "import_upload", actor=admin, target=name, client_ip=ip,
                 detail={"path": out["path"], "files": out["files"], "bytes": out["bytes"],
                         "upload_bytes": total})
    return out


# ---- uploads kept on the server (issue 36: none could be listed or deleted) -------------------
def _users_of(session: Session, folder: Path) -> dict[str, list[int]]:
    """{upload folder name: ids of the scenes whose source or import paths lie in it}."""
    root = str(folder)
    out: dict[str, list[int]] = {}

    def note(path: object, sid: int) -> None:
        if isinstance(path, str) and (path == root or path.startswith(root + os.sep)):
            name = path[len(root) + 1:].split(os.sep, 1)[0]
            if name and sid not in out.setdefault(name, []):
                out[name].append(sid)

    for sid, source in session.execute(select(Scene.id, Scene.source)).all():
        note(source, sid)
    for sid, params in session.execute(select(Job.scene_id, Job.params).where(
            Job.kind == "import", Job.scene_id.is_not(None))).all():
        for v in (params or {}).values():
            note(v, sid)
    live = set(session.scalars(select(Scene.id)))
    return {k: sorted(i for i in v if i in live) for k, v in out.items()}


def _folder_size(path: Path) -> tuple[int, int]:
    files = size = 0
    for dirpath, _dirs, names in os.walk(path):
        for n in names:
            try:
                size += os.lstat(os.path.join(dirpath, n)).st_size
                files += 1
            except OSError:
                continue
    return files, size


@router.get("/imports/uploads")
def list_uploads(ctx: CtxDep, session: SessionDep, _admin: AdminUser) -> list[dict]:
    """The project folders uploaded as zips (``<data dir>/uploads``): name, files, bytes,
    when, and the scenes that import from them (such an upload is not deleted)."""
    root = upload_dir(ctx.settings)
    if not root.is_dir():
        return []
    users = _users_of(session, root)
    out = []
    for p in sorted(root.iterdir()):
        if p.name.startswith(".") or not p.is_dir() or p.is_symlink():
            continue
        files, size = _folder_size(p)
        out.append({"name": p.name, "path": str(p), "files": files, "bytes": size,
                    "modified": p.stat().st_mtime, "scenes": users.get(p.name, [])})
    return out


@router.delete("/imports/uploads/{name}", status_code=204,
               responses={409: {"description": "a scene imports from it"}})
def delete_upload(ctx: CtxDep, session: SessionDep, admin: AdminUser, ip: ClientIp,
                  name: Annotated[str, PathParam(min_length=1, max_length=128)]) -> Response:
    """Delete an uploaded project folder, unless a scene imports from it (409 naming them:
    their frames' images may be served from it)."""
    if not FOLDER_NAME.match(name):
        raise Invalid(f"name {name!r}: not an upload name (letters, digits, '_', '.', '-')")
    root = upload_dir(ctx.settings)
    dest = root / name
    if not dest.is_dir() or dest.is_symlink():
        raise NotFound(f"no upload named {name!r} in {root}")
    scenes = _users_of(session, root).get(name, [])
    if scenes:
        raise Conflict(f"upload {name!r} is the source of scene(s) {', '.join(map(str, scenes))}; "
                       f"delete those scenes first")
    files, size = _folder_size(dest)
    trash = root / ".incoming" / f"{uuid.uuid4().hex}.del"
    trash.parent.mkdir(parents=True, exist_ok=True)
    os.rename(dest, trash)  # gone from the listing at once; removed below
    shutil.rmtree(trash, ignore_errors=True)
    audit.record(session, "upload_delete", actor=admin, target=name, client_ip=ip,
                 detail={"files": files, "bytes": size})
    session.commit()
    return Response(status_code=204)
