"""Scenes and frames: import paths, frame rows from a workspace, selection, images."""

from __future__ import annotations

import math
import os
from pathlib import Path

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, aliased

from app.config import Settings
from app.errors import Conflict, Forbidden, Invalid, NotFound
from app.scenes.models import Frame, Scene
from app.users.models import User
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
    roots = [r.resolve() for r in settings.import_roots]
    try:
        real = p.resolve(strict=True)
    except (FileNotFoundError, OSError):
        # do not reveal whether something exists outside the roots
        if not any(_inside(p.absolute(), r) for r in roots):
            raise Forbidden(f"{field}: {raw!r} is outside the allowed import roots") from None
        raise Invalid(f"{field}: {raw!r} does not exist") from None
    if not any(_inside(real, r) for r in roots):
        raise Forbidden(f"{field}: {raw!r} is outside the allowed import roots")
    return real


def _inside(path: Path, root: Path) -> bool:
    try:
        path.relative_to(root)
        return True
    except ValueError:
        return False


def create_scene(*, session: Session, settings: Settings, name: str, source: Path) -> Scene:
    ws = settings.workspaces_dir / name
    scene = Scene(name=name, status="importing", workspace=str(ws), source=str(source))
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


def apply_selection(*, session: Session, scene: Scene, result: dict) -> None:
    chosen = sorted(set(int(i) for i in result["frames"]))
    session.execute(update(Frame).where(Frame.scene_id == scene.id).values(selected=False))
    if chosen:
        session.execute(update(Frame).where(Frame.scene_id == scene.id, Frame.index.in_(chosen))
                        .values(selected=True))
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
    q = (select(Frame, assignee.username, last.username)
         .outerjoin(assignee, assignee.id == Frame.assignee_id)
         .outerjoin(last, last.id == Frame.last_annotator_id)
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
        q = q.order_by(Frame.agreement.is_(None), Frame.agreement, Frame.index)
    else:
        q = q.order_by(Frame.index)
    return [frame_dict(f, a, la) for f, a, la in session.execute(q)]


def frame_dict(f: Frame, assignee: str | None, last_annotator: str | None = None) -> dict:
    return dict(id=f.id, scene_id=f.scene_id, index=f.index, name=f.name, width=f.width,
                height=f.height, altitude=f.altitude, nominal_altitude=f.nominal_altitude,
                selected=f.selected, state=f.state, assignee=assignee,
                lease_expires_at=f.lease_expires_at, current_version=f.current_version_id,
                agreement=f.agreement, last_annotator=last_annotator)


def frame_out(*, session: Session, frame: Frame) -> dict:
    return list_frames(session=session, scene_id=frame.scene_id, frame_ids=[frame.id])[0]


def image_file(ws_scene: WsScene, workspace: str, index: int) -> Path:
    f = ws_scene.frames[index]
    if not f.image_path:
        raise NotFound(f"frame {f.name} has no image in the workspace")
    p = Path(f.image_path)
    if not p.is_absolute():
        p = Path(workspace) / p
    if not p.is_file():
        raise NotFound(f"image of frame {f.name} is missing ({p.name})")
    return p


SIZES = {"preview": 1600, "thumb": 256}


def resized_image(settings: Settings, src: Path, scene_id: int, frame_id: int, size: str) -> Path:
    """A cached JPEG no larger than SIZES[size] on its long side (rebuilt if the source changes)."""
    from PIL import Image

    from occufly.fsutil import atomic_write_bytes

    st = src.stat()
    out = settings.data_dir / "cache" / "images" / str(scene_id) / (
        f"{frame_id}_{size}_{st.st_mtime_ns}_{st.st_size}.jpg")
    if out.is_file():
        return out
    import io

    with Image.open(src) as im:
        im = im.convert("RGB")
        im.thumbnail((SIZES[size], SIZES[size]))
        buf = io.BytesIO()
        im.save(buf, format="JPEG", quality=85)
    atomic_write_bytes(out, buf.getvalue())
    return out


def get_scene_or_404(session: Session, scene_id: int) -> Scene:
    scene = session.get(Scene, scene_id)
    if scene is None:
        raise NotFound(f"scene {scene_id} does not exist")
    return scene


def file_etag(p: Path) -> str:
    st = os.stat(p)
    return f'"{st.st_mtime_ns:x}-{st.st_size:x}"'
