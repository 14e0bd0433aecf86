"""An admin brings masks painted in another tool (CVAT, COCO, Label Studio, PNG) into a scene.

The archive is read and checked as a whole first (occufly.io.mask_interchange: unknown
classes, images that name no frame, wrong sizes are one 422 listing them all, and nothing is
stored); then each frame gets a version of kind ``imported`` through ``store_version`` --
authored by the uploading admin, with ``source`` "imported from CVAT" (and "by <name>" when
an external author is recorded) -- which votes and waits for review like a submitted one.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pydantic import BaseModel
from sqlalchemy import func, select
from sqlalchemy.orm import Session, aliased

from app.annotations import service
from app.annotations.models import MaskVersion
from app.context import AppContext
from app.errors import Conflict, InsufficientStorage, Invalid, NotFound, TooManyAttempts
from app.scenes.models import Frame, Scene
from app.users.models import User
from occufly.errors import check_name
from occufly.io import mask_interchange
from occufly.io.masks import decode_mask_png, encode_mask_png

SOURCE_MAX = 64  # MaskVersion.source
#: mask imports read at once on this host, whatever the number of API processes (each may
#: unpack up to mask_interchange.INFLATE_FACTOR times its upload and parse 16 MB annotation
#: files); one more is a 429 (issue 36). The slots are ``flock``-ed files under the data dir
#: (``locks/mask-import/slot<i>``): an flock belongs to one open file, so it excludes other
#: threads of this process as well as other processes, and the kernel drops it when its
#: holder dies (a killed import never keeps a slot)
MAX_CONCURRENT_IMPORTS = 2
IMPORT_RETRY_AFTER_S = 5


@contextmanager
def import_slot(data_dir: Path, slots: int = MAX_CONCURRENT_IMPORTS) -> Iterator[int]:
    """Hold one of ``slots`` host-wide import slots while the block runs (its number), or
    raise TooManyAttempts (429, Retry-After) when every slot is held."""
    folder = Path(data_dir) / "locks" / "mask-import"
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(slots):
        fd = os.open(folder / f"slot{i}", os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        try:
            yield i
        finally:
            os.close(fd)  # closing the file releases its lock
        return
    raise TooManyAttempts(f"{slots} mask imports are being read on this server; try again "
                          f"when one has finished", retry_after=IMPORT_RETRY_AFTER_S)


class ImportedFrame(BaseModel):
    frame_id: int
    frame: str  # the frame's image name
    item: str  # the image name in the archive
    version: int  # the version's id (ids count across all frames)
    number: int  # its 1-based number among the frame's versions ("v3", as the frame page says)
    kind: str


class MaskImportOut(BaseModel):
    format: str  # the format read (cvat resolved to cvat_images / cvat_mask)
    source: str  # what the versions' source says, e.g. "imported from CVAT"
    frames_imported: int
    frames: list[ImportedFrame]
    unchanged: list[str] = []  # frames whose current mask is already this one (not stored again)
    skipped_without_annotations: list[str]  # archive images with nothing painted
    classes: dict[str, int]  # archive class name -> raw id it was mapped to


def source_label(tool: str, author: str | None) -> str:
    base = f"imported from {tool}"
    if not author:
        return base
    author = check_name(author.strip(), "author")
    room = SOURCE_MAX - len(base) - len(" by ")
    if len(author) > room:
        raise Invalid(f"author: at most {room} characters (the version's source holds "
                      f"{SOURCE_MAX}: {base!r} + ' by ' + the author)")
    return f"{base} by {author}"


def _check_ready(scene: Scene) -> None:
    if scene.status != "ready" or not scene.workspace:
        raise Conflict(f"scene {scene.id} is {scene.status}; masks move in and out of ready "
                       f"scenes only")


def upload_name(filename: str | None, default: str) -> str:
    """A safe file name for an upload (what the client called it, for the messages and to
    keep its suffix): letters, digits, ``._-``, no leading dot."""
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(filename or "").name).lstrip(".")[:120]
    return name or default


def import_archive(*, session: Session, ctx: AppContext, scene: Scene, user: User,
                   archive: Path, fmt: str, class_map: dict | None = None,
                   author: str | None = None) -> MaskImportOut:
    """Read ``archive`` (a zip, or a folder) in ``fmt`` and store one ``imported`` version per
    frame it paints. Raises MaskImportError (422) listing every problem, storing nothing."""
    if fmt not in mask_interchange.FORMATS:
        raise Invalid(f"format must be one of {', '.join(mask_interchange.FORMATS)}, got "
                      f"{fmt!r}")
    _check_ready(scene)
    tool = mask_interchange.TOOL_NAMES[fmt]
    source = source_label(tool, author)  # checked before the archive is read
    ws_scene = ctx.load_scene(scene.workspace)
    try:
        with import_slot(ctx.settings.data_dir):
            res = mask_interchange.read_masks(archive, fmt, ws_scene.frames, ws_scene.taxonomy,
                                              class_map=class_map)
    except mask_interchange.MaskImportError as e:  # the page lists them one per line
        raise Invalid(str(e), problems=e.problems) from None
    except mask_interchange.InsufficientSpace as e:
        raise InsufficientStorage(str(e)) from None
    if not res.masks:
        raise Invalid(f"the {res.tool} archive paints no frame ({len(res.skipped_empty)} "
                      f"image(s) without annotations): nothing to import")
    rows = {f.index: f for f in session.scalars(select(Frame).where(Frame.scene_id == scene.id))}
    stored: list[tuple[Frame, MaskVersion, str]] = []
    unchanged: list[str] = []
    for fi, mask in sorted(res.masks.items()):
        frame = rows[fi]
        session.refresh(frame)
        data = encode_mask_png(mask)
        current = (session.get(MaskVersion, frame.current_version_id)
                   if frame.current_version_id else None)
        if current is not None and current.sha256 == hashlib.sha256(data).hexdigest():
            unchanged.append(frame.name)  # the same archive again: no second version
            continue
        v: MaskVersion = service.store_version(
            session=session, ctx=ctx, frame=frame, user=user, data=data,
            kind="imported", expected=frame.current_version_id, source=source)
        stored.append((frame, v, res.item_names[fi]))
    # each new version's number: its frame's versions up to it (one query for the archive)
    earlier = aliased(MaskVersion)
    numbers = dict(session.execute(
        select(MaskVersion.id, func.count(earlier.id))
        .join(earlier, (earlier.frame_id == MaskVersion.frame_id) & (earlier.id <= MaskVersion.id))
        .where(MaskVersion.id.in_([v.id for _, v, _ in stored]))
        .group_by(MaskVersion.id)).all()) if stored else {}
    out = [ImportedFrame(frame_id=frame.id, frame=frame.name, item=item, version=v.id,
                         number=int(numbers[v.id]), kind=v.kind) for frame, v, item in stored]
    return MaskImportOut(format=res.fmt, source=source, frames_imported=len(out), frames=out,
                         unchanged=unchanged,
                         skipped_without_annotations=res.skipped_empty, classes=res.classes)


EXPORT_KINDS = ("masks", "prefill")


def export_archive(*, session: Session, ctx: AppContext, scene: Scene, fmt: str, what: str,
                   out: Path) -> dict:
    """Write the scene's voting masks (``what="masks"``: each frame's mask that counts) or the
    3D prefill of its selected frames (``"prefill"``: the lifted labels rendered into them, as
    the annotator's "Prefill from 3D" shows; Label Studio gets them as predictions) as a zip
    in ``fmt`` at ``out``. Returns write_masks' summary."""
    if fmt not in mask_interchange.FORMATS:
        raise Invalid(f"format must be one of {', '.join(mask_interchange.FORMATS)}, got "
                      f"{fmt!r}")
    _check_ready(scene)
    ws_scene = ctx.load_scene(scene.workspace)
    masks = {}
    if what == "masks":
        for fi, v in sorted(service.voting_versions(session, scene.id).items()):
            masks[fi] = decode_mask_png(ctx.store.get(v.sha256), ws_scene.taxonomy,
                                        name=f"version {v.id}")
        if not masks:
            raise NotFound(f"scene {scene.id} has no submitted, accepted or imported mask yet")
    elif what == "prefill":
        frames = list(session.scalars(select(Frame).where(Frame.scene_id == scene.id,
                                                          Frame.selected.is_(True))
                                      .order_by(Frame.index)))
        if not frames:
            raise NotFound(f"scene {scene.id} has no selected frames to prefill")
        labels = service.current_labels(ctx, scene)
        if labels is None:
            raise NotFound(f"scene {scene.id} has no lifted labels yet, so no prefill")
        for f in frames:
            masks[f.index], _filled = service.prefill_image(ctx, scene, f, labels=labels)
    else:
        raise Invalid(f"what must be one of {', '.join(EXPORT_KINDS)}, got {what!r}")
    return mask_interchange.write_masks(out, fmt, masks, ws_scene.frames, ws_scene.taxonomy,
                                        prediction=what == "prefill")

