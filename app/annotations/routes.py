from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path as FsPath
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Form, Header, Path, Query, Request, Response, UploadFile

from app import pipeline
from app.annotations import interchange, service
from app.annotations.schemas import PNG, EffortOut, LabelsStatus, VersionOut
from app.audit import service as audit
from app.deps import (
    AdminUser,
    AnnotatorUser,
    ClientIp,
    CtxDep,
    CurrentUser,
    FrameDep,
    SceneDep,
    SessionDep,
)
from app.errors import Invalid, PayloadTooLarge
from app.scenes import service as scenes
from app.scenes.models import Scene
from app.scenes.schemas import FrameOut
from occufly.io.mask_interchange import load_class_map

router = APIRouter(prefix="/api", tags=["annotations"])

# who may call what (see app/access.py; tests/app/test_security.py walks them all). Object
# checks on top: an annotator writes only a frame leased to them and reads masks of frames
# they hold or worked on.
ACCESS = {
    "POST /api/scenes/{sid}/next": "annotator",
    "POST /api/frames/{fid}/release": "annotator",
    "POST /api/frames/{fid}/reopen": "annotator",
    "GET /api/frames/{fid}/mask": "member",
    "PUT /api/frames/{fid}/mask": "annotator",
    "GET /api/frames/{fid}/mask/versions": "member",
    "GET /api/frames/{fid}/mask/versions/{vid}": "member",
    "POST /api/frames/{fid}/mask/versions/{vid}/restore": "annotator",
    "GET /api/frames/{fid}/prefill": "member",
    "GET /api/scenes/{sid}/labels/status": "member",
    "GET /api/scenes/{sid}/effort": "admin",
    "POST /api/scenes/{sid}/masks/import": "admin",
    "GET /api/scenes/{sid}/masks/export": "admin",
}

PNG_BODY = {"requestBody": {"required": True, **PNG}}


async def png_body(request: Request) -> bytes:
    """The raw request body, refused with 413 beyond the configured upload limit."""
    limit = request.app.state.ctx.settings.max_upload_bytes
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit:
        raise PayloadTooLarge(f"mask upload of {declared} bytes exceeds the limit of {limit} bytes")
    chunks, total = [], 0
    async for chunk in request.stream():
        total += len(chunk)
        if total > limit:
            raise PayloadTooLarge(f"mask upload exceeds the limit of {limit} bytes")
        chunks.append(chunk)
    data = b"".join(chunks)
    if not data:
        raise Invalid("empty body: send the mask as image/png")
    return data


BodyDep = Annotated[bytes, Depends(png_body)]
VidPath = Annotated[int, Path(ge=1, le=2**31 - 1)]


@router.post("/scenes/{sid}/next", response_model=FrameOut,
             responses={204: {"description": "no frame left to annotate"}})
def next_frame(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AnnotatorUser,
               skip: Annotated[list[int] | None, Query(max_length=1000)] = None):
    """Lease the next frame; ``?skip=<id>`` (repeatable) leaves those frames for later."""
    frame = service.next_frame(session=session, ctx=ctx, scene=scene, user=user, skip=skip)
    if frame is None:
        return Response(status_code=204)
    return scenes.frame_out(session=session, frame=frame)


@router.post("/frames/{fid}/release", response_model=FrameOut)
def release_frame(frame: FrameDep, session: SessionDep, user: AnnotatorUser):
    frame = service.release(session=session, frame=frame, user=user)
    return scenes.frame_out(session=session, frame=frame)


@router.post("/frames/{fid}/reopen", response_model=FrameOut,
             responses={409: {"description": "the frame is not submitted or was reviewed"}})
def reopen_frame(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: AnnotatorUser):
    """Take a submitted frame back (lease renewed) while no reviewer has decided on it."""
    frame = service.reopen(session=session, ctx=ctx, frame=frame, user=user)
    return scenes.frame_out(session=session, frame=frame)


def _png(ctx, sha256: str, version_id: int, number: int | None = None) -> Response:  # noqa: ANN001
    headers = {"ETag": f'"{version_id}"', "Cache-Control": "private, no-cache",
               "X-Mask-Version": str(version_id),
               # stored bytes: never a document (nosniff, sandboxing CSP), issue 24
               **scenes.data_headers(f"mask_version_{version_id}.png")}
    if number is not None:
        headers["X-Mask-Number"] = str(number)  # the per-frame version number
    return Response(ctx.store.get(sha256, owner=f"mask version {version_id}"),
                    media_type="image/png", headers=headers)


@router.get("/frames/{fid}/mask", response_class=Response, responses={200: PNG})
def get_mask(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: CurrentUser):
    service.check_read(session, frame, user)
    v = service.current_version(session=session, frame=frame)
    return _png(ctx, v.sha256, v.id, service.version_number(session, v))


PREFILL_ID_DOC = ("on a submit: the X-Prefill-Id of the prefill this mask was painted over, "
                  "while the editor still holds it ('none' or absent: painted without one, or "
                  "the prefill was undone); only a named prefill counts in the effort figures")


@router.put("/frames/{fid}/mask", response_model=VersionOut, openapi_extra=PNG_BODY,
            responses={409: {"description": "stale If-Match; upload kept as a conflict version"},
                       413: {"description": "too large"}, 428: {"description": "no If-Match"}})
def put_mask(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: AnnotatorUser,
             body: BodyDep, ip: ClientIp, kind: Literal["draft", "submitted"] = "draft",
             if_match: Annotated[str | None, Header(max_length=100)] = None,
             x_prefill_id: Annotated[str | None, Header(max_length=12, pattern=r"^(\d{1,10}|none)$",
                                                      description=PREFILL_ID_DOC)] = None):
    """Save a mask version: the annotator holding the frame's lease, or an admin."""
    expected = service.parse_if_match(if_match)
    prefill_id = int(x_prefill_id) if x_prefill_id and x_prefill_id != "none" else None
    v = service.store_version(session=session, ctx=ctx, frame=frame, user=user, data=body,
                              kind=kind, expected=expected, prefill_id=prefill_id)
    _audit_version(session, user, frame, v, ip, "mask_submit" if kind == "submitted" else "mask_save")
    return service.version_out(v, user.username, number=service.version_number(session, v))


def _audit_version(session, user, frame, v, ip: str, action: str) -> None:  # noqa: ANN001
    audit.record(session, action, actor=user, scene_id=frame.scene_id, frame_id=frame.id,
                 client_ip=ip, detail={"version": v.id, "kind": v.kind, "sha256": v.sha256,
                                       "restored_from": v.restored_from_id})


@router.get("/frames/{fid}/mask/versions", response_model=list[VersionOut])
def list_versions(frame: FrameDep, session: SessionDep, user: CurrentUser):
    service.check_read(session, frame, user)
    return service.list_versions(session=session, frame=frame)


@router.get("/frames/{fid}/mask/versions/{vid}", response_class=Response, responses={200: PNG})
def get_version(frame: FrameDep, vid: VidPath,
                session: SessionDep, ctx: CtxDep, user: CurrentUser):
    service.check_read(session, frame, user)
    v = service.get_version(session=session, frame=frame, version_id=vid)
    return _png(ctx, v.sha256, v.id, service.version_number(session, v))


@router.post("/frames/{fid}/mask/versions/{vid}/restore", response_model=VersionOut,
             responses={409: {"description": "stale If-Match"}})
def restore_version(frame: FrameDep, vid: VidPath, session: SessionDep, ctx: CtxDep,
                    user: AnnotatorUser, ip: ClientIp,
                    kind: Literal["draft", "submitted"] = "draft",
                    if_match: Annotated[str | None, Header(max_length=100)] = None):
    """Make an old version current again (a new version): lease holder or admin only."""
    expected = service.parse_if_match(if_match) if if_match is not None else None
    v = service.restore(session=session, ctx=ctx, frame=frame, user=user, version_id=vid,
                        expected=expected, kind=kind)
    _audit_version(session, user, frame, v, ip, "mask_restore")
    return service.version_out(v, user.username, number=service.version_number(session, v))


@router.get("/frames/{fid}/prefill", response_class=Response, responses={200: PNG})
def prefill(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: CurrentUser,
            downscale: Annotated[int, Query(ge=1, le=64)] = 1):
    """Lifted labels rendered into the frame: single-channel raw ids (0 = nothing known);
    holes between rendered points are closed from the nearest rendered pixel (the confidence
    image marks those pixels as low confidence)."""
    service.check_read(session, frame, user)
    scene = session.get(Scene, frame.scene_id)
    img, _filled = service.prefill_image(ctx, scene, frame, downscale=downscale)
    data = pipeline.encode_png(img)
    headers = {"Cache-Control": "private, no-cache"}
    masks = ctx.lifting.included_versions(scene.id, scene.workspace)
    own = service.prefill_holds_own_mask(scene, frame, masks)
    if own:  # the labels repeat this frame's own mask: starting from it saves no painting
        headers["X-Prefill-Own-Mask"] = "1"
    elif user.role in ("annotator", "admin"):  # who may submit: their submit counts changes
        p = service.record_prefill(session, ctx, frame, user, img, data,
                                   masks=None if masks is None else len(masks))
        headers["X-Prefill-Id"] = str(p.id)
    return Response(data, media_type="image/png", headers=headers)


@router.get("/scenes/{sid}/effort", response_model=EffortOut)
def effort(scene: SceneDep, session: SessionDep, _user: AdminUser):
    """Annotation effort of the scene's submitted masks, in submission order: the share of
    pixels painted (from scratch) and changed versus the prefill the author started from."""
    return service.effort(session=session, scene=scene)


@router.get("/scenes/{sid}/labels/status", response_model=LabelsStatus)
def labels_status(scene: SceneDep, session: SessionDep, ctx: CtxDep, _user: CurrentUser):
    return service.labels_status(session=session, ctx=ctx, scene=scene)


MAX_MAPPING_BYTES = 1 << 20


@router.post("/scenes/{sid}/masks/import", response_model=interchange.MaskImportOut,
             responses={422: {"description": "the archive cannot be imported: every unknown "
                                             "class, unmatched image and wrong size is listed; "
                                             "nothing was stored"}})
def import_masks(scene: SceneDep, session: SessionDep, ctx: CtxDep, user: AdminUser,
                 ip: ClientIp, archive: UploadFile,
                 format: Annotated[Literal["cvat", "cvat_images", "cvat_mask", "coco",  # noqa: A002
                                           "coco_panoptic", "labelstudio", "png"], Form()],
                 mapping: UploadFile | None = None,
                 author: Annotated[str | None, Form(max_length=64)] = None):
    """Masks painted in another tool (a CVAT, COCO, Label Studio or PNG export, zipped) as
    ``imported`` versions of the frames they paint, authored by the caller (``author``: an
    external author recorded in the versions' source); they vote and wait for review.
    ``mapping``: a JSON/YAML file {archive class name: taxonomy class name | id | "ignore" |
    "unpainted"} where the names differ."""
    with tempfile.TemporaryDirectory(prefix="occufly-mask-import-") as tmp:
        name = interchange.upload_name(archive.filename, "archive.zip")
        path = FsPath(tmp) / name
        with open(path, "wb") as f:
            shutil.copyfileobj(archive.file, f)
        if path.stat().st_size == 0:
            raise Invalid(f"archive {name!r} is empty; expected a zip of the tool's export")
        class_map = None
        if mapping is not None and mapping.filename:
            mname = interchange.upload_name(mapping.filename, "mapping.json")
            data = mapping.file.read(MAX_MAPPING_BYTES + 1)
            if len(data) > MAX_MAPPING_BYTES:
                raise PayloadTooLarge(f"mapping {mname!r} is larger than {MAX_MAPPING_BYTES} bytes")
            suffix = FsPath(mname).suffix.lower()
            mpath = FsPath(tmp) / ("mapping" + (suffix if suffix in (".yaml", ".yml") else ".json"))
            mpath.write_bytes(data)
            class_map = load_class_map(mpath)
        out = interchange.import_archive(session=session, ctx=ctx, scene=scene, user=user,
                                         archive=path, fmt=format, class_map=class_map,
                                         author=author)
    audit.record(session, "mask_import", actor=user, scene_id=scene.id, target=name,
                 client_ip=ip, detail={"format": out.format, "source": out.source,
                                       "frames": out.frames_imported,
                                       "versions": [f.version for f in out.frames]})
    session.commit()
    return out


@router.get("/scenes/{sid}/masks/export", response_class=Response,
            responses={200: {"content": {"application/zip": {}},
                             "description": "a zip in the tool's format"}})
def export_masks(scene: SceneDep, session: SessionDep, ctx: CtxDep, _user: AdminUser,
                 format: Literal["cvat", "cvat_images", "cvat_mask", "coco",  # noqa: A002
                                 "coco_panoptic", "labelstudio", "png"] = "cvat",
                 what: Literal["masks", "prefill"] = "masks"):
    """The scene's masks that count (``what=masks``: each frame's voting version) or the 3D
    prefill of its selected frames (``what=prefill``; Label Studio: as predictions) as a zip
    for CVAT, COCO, Label Studio or plain PNGs, one item per frame."""
    with tempfile.TemporaryDirectory(prefix="occufly-mask-export-") as tmp:
        safe = re.sub(r"[^A-Za-z0-9._-]+", "_", scene.name).strip("._") or f"scene{scene.id}"
        name = f"{safe}_{what}_{format}.zip"
        path = FsPath(tmp) / "out.zip"
        interchange.export_archive(session=session, ctx=ctx, scene=scene, fmt=format,
                                   what=what, out=path)
        data = path.read_bytes()
    return Response(data, media_type="application/zip",
                    headers={"Content-Disposition": f'attachment; filename="{name}"'})

