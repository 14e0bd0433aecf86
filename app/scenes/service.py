"""Scenes and frames: import paths, frame rows from a workspace, selection, images."""

from __future__ import annotations

import io
import math
import os
import re
from pathlib import Path
from urllib.parse import quote

import numpy as np
from PIL import Image
from sqlalchemy import case, delete, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, aliased

from app import pipeline
from app.annotations.models import MaskVersion
from app.config import Settings
from app.errors import Conflict, Forbidden, Invalid, NotFound
from app.scenes.models import Frame, IdCounter, Scene, SceneMember
from app.users.models import User
from occufly.errors import OccuflyError, UnsafePathError
from occufly.fsutil import PathNotConfined, atomic_write_bytes, confined
from occufly.scene import Scene as WsScene


def resolve_import_path(settings: Settings, raw: str, *, field: str = "source") -> Path:
    """An existing path inside one of the allowed import roots (symlinks resolved).

    Relative paths are taken relative to the first root. Any ``..`` component is refused
    outright, as is a path whose real location is outside every root.
    """
    if "\x00" in raw:
        raise Invalid(f"{field}: path contains a NUL byte")
    p = Path(raw)
    if ".." in p.parts:
        raise Forbidden(f"{field}: '..' is not allowed in import paths ({raw!r})")
    if not p.is_absolute():
        p = settings.import_roots[0] / p
    allowed = import_roots(settings)
    roots = [r.resolve() for r in allowed]
    named = ", ".join(str(r) for r in allowed)  # the admin learns where imports may come from
    try:
        real = p.resolve(strict=True)
    except (FileNotFoundError, OSError):
        # do not reveal whether something exists outside the roots
        if not any(_inside(p.absolute(), r) for r in roots):
            raise Forbidden(f"{field}: {raw!r} is outside the allowed import roots ({named})") from None
        raise Invalid(f"{field}: {raw!r} does not exist") from None
    if not any(_inside(real, r) for r in roots):
        raise Forbidden(f"{field}: {raw!r} is outside the allowed import roots ({named})")
    return real


def upload_dir(settings: Settings) -> Path:
    """Where zips uploaded from the import form are extracted (app/scenes/imports.py)."""
    return settings.data_dir / "uploads"


def import_roots(settings: Settings) -> list[Path]:
    """Where an import may read from: ``OCCUFLY_IMPORT_ROOTS`` and the uploads folder."""
    up = upload_dir(settings)
    return [*settings.import_roots, *([] if up in settings.import_roots else [up])]


def _inside(path: Path, root: Path) -> bool:
    try:
        path.relative_to(root)
        return True
    except ValueError:
        return False


SCENE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")


def workspace_path(settings: Settings, name: str) -> Path:
    """The workspace folder of scene ``name``: exactly one level below the workspaces folder.

    ``name`` must be one safe path component (no '.', '..', separators, hidden or dash-led
    names); anything else is refused before a folder is touched.
    """
    if not SCENE_NAME.match(name) or name in (".", ".."):
        raise Invalid(f"scene name {name!r} is not allowed: use 1-128 letters, digits, '_', '.' "
                      "or '-', starting with a letter, digit or '_'")
    root = settings.workspaces_dir.absolute()
    ws = root / name
    if ws.parent != root or ws.name != name:
        raise Invalid(f"scene name {name!r} does not name a folder inside {root}")
    return ws


def own_workspace(settings: Settings, scene: Scene) -> Path:
    """The scene's workspace, checked to be its own folder before anything renames or replaces
    it: a direct child of the workspaces folder, named after the scene (raises Forbidden)."""
    ws = Path(scene.workspace)
    try:
        expected = workspace_path(settings, scene.name)
    except Invalid as e:
        raise Forbidden(f"scene {scene.id}: refusing to write its workspace ({e.detail})") from None
    if ws.absolute() != expected or ws.is_symlink():
        raise Forbidden(f"scene {scene.id}: workspace {ws} is not {expected}; refusing to replace it")
    return expected


def _next_scene_id(session: Session) -> int | None:
    """On SQLite the id after the highest ever handed out (``id_counters``; the UPDATE takes
    the write lock, so two creations never get one id); None elsewhere (PostgreSQL's sequence
    never reuses an id). SQLite alone would give max(id) + 1: a deleted newest scene's id."""
    if session.get_bind().dialect.name != "sqlite":
        return None

    top = select(func.coalesce(func.max(Scene.id), 0)).scalar_subquery()
    got = session.execute(
        update(IdCounter).where(IdCounter.name == "scenes")
        .values(last_id=func.max(IdCounter.last_id, top) + 1)
        .returning(IdCounter.last_id)).scalar()
    if got is None:  # a database created without migration 0012's seed row
        got = int(session.scalar(select(func.coalesce(func.max(Scene.id), 0)))) + 1
        session.add(IdCounter(name="scenes", last_id=got))
    return int(got)


def create_scene(*, session: Session, settings: Settings, name: str, source: Path) -> Scene:
    ws = workspace_path(settings, name)
    scene = Scene(name=name, status="importing", workspace=str(ws), source=str(source),
                  id=_next_scene_id(session))
    session.add(scene)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        raise Conflict(f"a scene named {name!r} already exists") from None
    return scene


def sync_frames(*, session: Session, scene: Scene, ws_scene: WsScene) -> None:
    """(Re)create the frame rows of ``scene`` from its workspace (an import or a re-import)."""
    session.execute(delete(Frame).where(Frame.scene_id == scene.id))
    rows = []
    for i, f in enumerate(ws_scene.frames):
        rows.append(dict(
            scene_id=scene.id, index=i, name=f.name, width=f.camera.width, height=f.camera.height,
            altitude=None if math.isnan(f.altitude) else float(f.altitude),
            nominal_altitude=f.nominal_altitude, selected=False, state="unassigned"))
    if rows:
        session.execute(Frame.__table__.insert(), rows)
    scene.n_frames = len(ws_scene.frames)
    scene.n_points = ws_scene.n_points
    scene.n_selected = 0
    scene.coverage = None
    scene.status = "ready"
    session.commit()


def handout_order(ws_scene: WsScene, frames) -> list[int]:
    """The order in which "next" hands out the selected ``frames`` (workspace frame indices):
    each next frame is the one that sees the most points no earlier frame of the order sees
    (ties: lower index). The frames over what nobody has painted yet come first, so every
    later frame is mostly covered by the lifted labels of the earlier ones and its prefill
    leaves little to change. It is not free: on ``small`` (17 frames) the median left to change
    from the 6th frame on is 4.6 % (index order: 9.1 %), but the whole selection paints 12 %
    more pixels than in index order (4.77x vs 5.36x less than from scratch), because the
    first frames are spread apart and each starts from little. Measured by
    bench/bench_annotation_effort.py (``--compare-index-order``), which uses this order."""
    frames = sorted(set(int(i) for i in frames))
    if len(frames) < 2:
        return frames
    vis = ws_scene.visibility
    ids = {f: np.unique(vis.frame_ids(f)) for f in frames}
    seen = np.zeros(ws_scene.n_points, dtype=bool)
    new = {f: len(ids[f]) for f in frames}  # upper bounds of each frame's new points (lazy)
    order: list[int] = []
    left = set(frames)
    while left:
        # lazy greedy: a frame's count of new points only falls, so re-count the best bound
        # until it stays the best (exact greedy result, far fewer counts)
        while True:
            f = min(left, key=lambda g: (-new[g], g))
            n = int(np.count_nonzero(~seen[ids[f]]))
            if n == new[f]:
                break
            new[f] = n
        order.append(f)
        left.discard(f)
        seen[ids[f]] = True
    return order


def apply_selection(*, session: Session, scene: Scene, result: dict,
                    ws_scene: WsScene | None = None) -> None:
    """Mark the selected frames; with ``ws_scene``, rank them by :func:`handout_order` (kept
    in ``result["handout_order"]``)."""
    chosen = sorted(set(int(i) for i in result["frames"]))
    session.execute(update(Frame).where(Frame.scene_id == scene.id)
                    .values(selected=False, handout_rank=None))
    if chosen:
        session.execute(update(Frame).where(Frame.scene_id == scene.id, Frame.index.in_(chosen))
                        .values(selected=True))
    if chosen and ws_scene is not None:
        order = handout_order(ws_scene, chosen)
        result = {**result, "handout_order": order}
        rank = case({int(f): r for r, f in enumerate(order)}, value=Frame.index)
        session.execute(update(Frame).where(Frame.scene_id == scene.id, Frame.index.in_(order))
                        .values(handout_rank=rank).execution_options(synchronize_session=False))
    scene.n_selected = len(chosen)
    scene.coverage = float(result.get("coverage")) if result.get("coverage") is not None else None
    scene.selection = result
    session.commit()


def frame_states(*, session: Session, scene: Scene) -> dict[str, int]:
    rows = session.execute(select(Frame.state, func.count()).where(Frame.scene_id == scene.id)
                           .group_by(Frame.state))
    return {state: int(n) for state, n in rows}


def list_frames(*, session: Session, scene_id: int, sort: str = "index",
                state: str | None = None, selected: bool | None = None,
                frame_ids: list[int] | None = None) -> list[dict]:
    assignee = aliased(User)
    last = aliased(User)
    author = aliased(User)
    # the current version's source and who stored it: an imported mask names its tool and
    # author and the admin who uploaded it (issue 40, defect 5)
    q = (select(Frame, assignee.username, last.username, MaskVersion.source, author.username)
         .outerjoin(assignee, assignee.id == Frame.assignee_id)
         .outerjoin(last, last.id == Frame.last_annotator_id)
         .outerjoin(MaskVersion, MaskVersion.id == Frame.current_version_id)
         .outerjoin(author, author.id == MaskVersion.author_id)
         .where(Frame.scene_id == scene_id))
    if state:
        q = q.where(Frame.state.in_(state.split(",")))
    if selected is not None:
        q = q.where(Frame.selected == selected)
    if frame_ids is not None:
        q = q.where(Frame.id.in_(frame_ids))
    if sort == "name":
        q = q.order_by(Frame.name)
    elif sort == "disagreement":
        # the ranking score (occufly.lifting.loo.review_score), highest first -- frames
        # without enough independent views for an agreement figure are ranked by it too;
        # then frames without a score by LOO agreement, worst first; then never scored
        q = q.order_by(Frame.review_score.is_(None), Frame.review_score.desc(),
                       Frame.agreement.is_(None), Frame.agreement,
                       Frame.independent_coverage.is_(None), Frame.independent_coverage,
                       Frame.index)
    else:
        q = q.order_by(Frame.index)
    return [frame_dict(f, a, la, source=src, author=au)
            for f, a, la, src, au in session.execute(q)]


def frame_dict(f: Frame, assignee: str | None, last_annotator: str | None = None, *,
               source: str | None = None, author: str | None = None) -> dict:
    return dict(id=f.id, scene_id=f.scene_id, index=f.index, name=f.name, width=f.width,
                height=f.height, altitude=f.altitude, nominal_altitude=f.nominal_altitude,
                selected=f.selected, state=f.state, assignee=assignee,
                lease_expires_at=f.lease_expires_at, current_version=f.current_version_id,
                agreement=f.agreement, last_annotator=last_annotator,
                handout_rank=f.handout_rank, self_agreement=f.self_agreement,
                independent_coverage=f.independent_coverage, painted_share=f.painted_share,
                review_score=f.review_score, current_source=source, current_author=author)


def frame_out(*, session: Session, frame: Frame) -> dict:
    return list_frames(session=session, scene_id=frame.scene_id, frame_ids=[frame.id])[0]


def image_file(ws_scene: WsScene, workspace: str, index: int, *, roots) -> Path:  # noqa: ANN001
    """The frame's image, resolved (symlinks followed) and confined to ``roots`` (the import
    roots and the data dir): a path from scene.json outside them is refused with 404."""
    f = ws_scene.frames[index]
    if not f.image_path:
        raise NotFound(f"frame {f.name} has no image in the workspace")
    p = Path(f.image_path)
    if not p.is_absolute():
        p = Path(workspace) / p
    try:
        p = confined(p, roots)
    except PathNotConfined:
        raise NotFound(f"image of frame {f.name} lies outside the import roots") from None
    if not p.is_file():
        raise NotFound(f"image of frame {f.name} is missing ({p.name})")
    if p.stat().st_nlink > 1:  # a hard link made after the import (occufly.io.importer)
        raise NotFound(f"image of frame {f.name} is a hard link ({p.name}); hard links in the "
                       "import roots are not served -- copy the file in instead")
    return p


def check_source_paths(settings: Settings, source: Path) -> None:
    """A workspace source whose scene.json names an image outside the import roots
    (``/etc/passwd``, ``../../occufly.db``, the data dir, a symlink out), a non-image, or a
    frame name with markup or control characters: 403/422 naming scene.json and the path."""
    try:
        pipeline.check_workspace_source(source, import_roots(settings))
    except UnsafePathError as e:
        raise Forbidden(str(e)) from None
    except OccuflyError as e:
        raise Invalid(str(e)) from None


def image_roots(settings: Settings) -> list[Path]:
    """Where a served frame image may live: the import roots (with the uploads folder) and the
    scene workspaces (images a restore put there). Not the rest of the data dir: it holds the
    database, the mask store, the caches and the exports (issue 24)."""
    return [*import_roots(settings), settings.workspaces_dir]


SIZES = {"preview": 1600, "thumb": 256}

#: served with every file whose bytes came from outside the app (frame images, stored masks):
#: even opened as a document, such a response runs nothing and loads nothing (issue 24)
DATA_CSP = "default-src 'none'; sandbox"


def content_disposition(name: str, *, download: bool = False) -> str:
    """``inline`` (or ``attachment``) with the file name reduced to safe ASCII for the
    quoted form and given exactly (RFC 5987 ``filename*``) for browsers that read it."""
    plain = re.sub(r"[^A-Za-z0-9._-]", "_", name)[:120] or "file"
    return (f"{'attachment' if download else 'inline'}; filename=\"{plain}\"; "
            f"filename*=UTF-8''{quote(name[:200], safe='')}")


def data_headers(name: str, *, download: bool = False) -> dict[str, str]:
    """Headers of a response carrying bytes that came from a file or an upload."""
    return {"Content-Disposition": content_disposition(name, download=download),
            "X-Content-Type-Options": "nosniff", "Content-Security-Policy": DATA_CSP}


def resized_image(settings: Settings, src: Path, scene_id: int, frame_id: int, size: str) -> Path:
    """A cached JPEG no larger than SIZES[size] on its long side (rebuilt if the source changes)."""
    st = src.stat()
    out = settings.data_dir / "cache" / "images" / str(scene_id) / (
        f"{frame_id}_{size}_{st.st_mtime_ns}_{st.st_size}.jpg")
    if out.is_file():
        return out

    try:
        with Image.open(src) as im:
            im.draft("RGB", (SIZES[size], SIZES[size]))  # JPEG: decode at the reduced size
            im = im.convert("RGB")
            im.thumbnail((SIZES[size], SIZES[size]))
            buf = io.BytesIO()
            im.save(buf, format="JPEG", quality=85)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        # a truncated or corrupt file with an image's magic bytes, or one too large to
        # decode: 422 naming the frame, not a 500 (issue 24)
        raise Invalid(f"image of frame {frame_id} ({src.name}) cannot be decoded for a "
                      f"{size}: {type(e).__name__}: {str(e)[:200]}") from None
    atomic_write_bytes(out, buf.getvalue())
    return out


def file_etag(p: Path) -> str:
    st = os.stat(p)
    return f'"{st.st_mtime_ns:x}-{st.st_size:x}"'


# ---- membership -----------------------------------------------------------------------------
def members(*, session: Session, scene: Scene) -> list[dict]:
    rows = session.execute(select(User).join(SceneMember, SceneMember.user_id == User.id)
                           .where(SceneMember.scene_id == scene.id).order_by(User.id)).scalars()
    return [dict(user_id=u.id, username=u.username, role=u.role, active=u.active) for u in rows]


def check_member_ids(*, session: Session, user_ids: list[int]) -> list[int]:
    """The distinct ids, sorted; 422 naming unknown users or admins (who see every scene)."""
    wanted = sorted(set(int(u) for u in user_ids))
    found = dict(session.execute(select(User.id, User.role).where(User.id.in_(wanted))).all()) if wanted else {}
    missing = [u for u in wanted if u not in found]
    if missing:
        raise Invalid(f"user_ids: no such user(s) {missing[:20]}")
    admins = [u for u in wanted if found[u] == "admin"]
    if admins:
        raise Invalid(f"user_ids: {admins[:20]} are admins, who see every scene without membership")
    return wanted


def set_members(*, session: Session, scene: Scene, user_ids: list[int], replace: bool) -> dict:
    """Assign users to the scene (``replace``: exactly these). Returns {added, removed}."""
    wanted = check_member_ids(session=session, user_ids=user_ids)
    current = set(session.scalars(select(SceneMember.user_id).where(SceneMember.scene_id == scene.id)))
    add = [u for u in wanted if u not in current]
    remove = sorted(current - set(wanted)) if replace else []
    for u in add:
        session.add(SceneMember(scene_id=scene.id, user_id=u))
    if remove:
        session.execute(delete(SceneMember).where(SceneMember.scene_id == scene.id,
                                                  SceneMember.user_id.in_(remove)))
    try:
        session.commit()
    except IntegrityError:  # a concurrent assignment added the same member first
        session.rollback()
    return {"added": add, "removed": remove}


def remove_member(*, session: Session, scene: Scene, user_id: int) -> None:
    res = session.execute(delete(SceneMember).where(SceneMember.scene_id == scene.id,
                                                    SceneMember.user_id == user_id))
    session.commit()
    if res.rowcount != 1:
        raise NotFound(f"user {user_id} is not a member of scene {scene.id}")


def visible_scene_ids(session: Session, user: User) -> list[int] | None:
    """Scene ids the user may see; None = all (admins)."""
    if user.role == "admin":
        return None
    return list(session.scalars(select(SceneMember.scene_id).where(SceneMember.user_id == user.id)))
