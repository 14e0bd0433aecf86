"""Reviewers' label corrections: audited, versioned 3D edits and what follows from them.

An edit relabels a set of points to one class (0 = unlabelled). Its database row holds who,
when, the class, the comment, the from-label histogram and its state (``active``, ``undone``,
``reverted``, ``dropped``); its point ids are a compact file in the scene workspace
(:meth:`occufly.workspace.Workspace.correction_edit`). The net effect of the active edits
(applied in id order: the newest wins on a point) is the override layer every reader of labels
applies (:func:`occufly.lifting.load_labels`).

Writes are ordered so that a ``kill -9`` at any moment leaves an edit applied entirely or not
at all:

1. the edit's point file (atomic; an orphan file without a row is never read),
2. the row, committed (from here on the edit exists),
3. the net layer (atomic), which records the ids of the edits it reflects (``applied``).

:func:`repair` compares that record with the active rows and, when they disagree (a crash
between 2 and 3, or an undo/revert between its commit and its layer write), rebuilds the
layer from the active edits' point files. It runs before every change, when the app starts
and whenever the layer is read through this module. All changes of one scene's layer run
under an exclusive file lock (``corrections/.lock``), so API processes never interleave.

Incremental cost: a new edit reads the layer, merges its M points in (O(M log K + K) for K
corrected points) and writes it; an undo or revert re-resolves only the edit's own points
against the older active edits. Nothing here reads or writes an O(scene) array.
"""

from __future__ import annotations

import contextlib
import fcntl
import io
import logging
import os
import signal
from collections.abc import Iterator

import numpy as np
from PIL import Image
from scipy.ndimage import binary_closing, binary_dilation
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from app.annotations import service as annotations
from app.annotations.models import MaskVersion
from app.annotations.service import check_read
from app.audit import service as audit
from app.blobs import claim_blob
from app.context import AppContext
from app.corrections.models import CorrectionEdit, MaskProposal
from app.db import utcnow
from app.errors import Conflict, Forbidden, Invalid, NotFound, PayloadTooLarge
from app.notifications.service import notify
from app.pipeline import encode_png, stored_mask_ids
from app.review.models import ReviewItem
from app.review.service import items_out
from app.scenes.membership import check_member
from app.scenes.models import Frame, Scene
from app.users.models import User
from occufly.lifting import corrections as lib
from occufly.workspace import Workspace

log = logging.getLogger("occufly.corrections")

FAULT_ENV = "OCCUFLY_CORRECTIONS_FAULT"  # tests: SIGKILL this process at a named step


def _fault(step: str) -> None:
    if os.environ.get(FAULT_ENV) == step:
        os.kill(os.getpid(), signal.SIGKILL)


@contextlib.contextmanager
def scene_lock(ws: str) -> Iterator[None]:
    """Exclusive lock over one scene's corrections (every API process on this host)."""
    w = Workspace(ws)
    w.corrections_dir.mkdir(parents=True, exist_ok=True)
    with open(w.corrections_dir / ".lock", "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _active(session: Session, scene_id: int) -> list[tuple[int, int]]:
    """(edit id, to_class) of the scene's active edits, oldest first."""
    return [(int(i), int(c)) for i, c in session.execute(
        select(CorrectionEdit.id, CorrectionEdit.to_class).where(
            CorrectionEdit.scene_id == scene_id, CorrectionEdit.state == "active")
        .order_by(CorrectionEdit.id))]


def _repair_locked(session: Session, scene: Scene) -> bool:
    ws = scene.workspace
    applied = lib.read_applied(ws)
    active = _active(session, scene.id)
    want = np.asarray([i for i, _c in active], np.int64)
    if applied is not None and np.array_equal(np.sort(applied), want):
        return False
    if applied is None and not active and not Workspace(ws).overrides_path.is_file():
        return False  # no corrections at all
    log.warning("scene %s: the label corrections layer reflects edits %s, the active edits are "
                "%s; rebuilding it", scene.id,
                None if applied is None else applied.tolist(), want.tolist())
    rebuilt = lib.rebuild_net((i, c, lib.read_edit_points(ws, i)) for i, c in active)
    lib.write_net(ws, rebuilt)
    return True


def repair(session: Session, scene: Scene) -> bool:
    """Make the net layer agree with the active edits; True when it had to be rebuilt."""
    if not scene.workspace or not Workspace(scene.workspace).exists():
        return False
    with scene_lock(scene.workspace):
        return _repair_locked(session, scene)


def repair_all(ctx: AppContext) -> list[int]:
    """:func:`repair` every ready scene that has edits (app start-up); ids of rebuilt scenes."""
    out = []
    with ctx.sessions() as s:
        ids = set(s.scalars(select(CorrectionEdit.scene_id).distinct()))
        for sid in sorted(ids):
            scene = s.get(Scene, sid)
            if scene is None or scene.status != "ready":
                continue
            try:
                if repair(s, scene):
                    out.append(sid)
            except Exception:  # noqa: BLE001 - one broken scene must not stop the app
                log.exception("scene %s: repairing label corrections failed", sid)
    return out


def _check_editor(user: User) -> None:
    if user.role not in ("reviewer", "admin"):
        raise Forbidden(f"only reviewers and admins correct labels; you are {user.role}")


def _check_class(ctx: AppContext, scene: Scene, to_class: int) -> None:
    tax = ctx.load_scene(scene.workspace).taxonomy
    if to_class != 0 and to_class not in {int(i) for i in tax.ids}:
        raise Invalid(f"class {to_class} is not in scene {scene.id}'s taxonomy "
                      f"(0 = unlabelled, or one of {sorted(int(i) for i in tax.ids)})")


def _publish(ctx: AppContext, scene: Scene, edit_id: int, action: str) -> None:
    if ctx.events is None:
        return
    try:  # the viewer and review refresh on labels_updated (the stamp covers the layer)
        ctx.events.publish("labels_updated", scene.id, stamp=Workspace(scene.workspace).stamp(),
                           corrections={"edit": edit_id, "action": action})
    except Exception:  # noqa: BLE001 - the edit is durable; a lost refresh is not an error
        log.exception("publishing labels_updated after a correction failed")


def create_edit(*, session: Session, ctx: AppContext, scene: Scene, user: User,
                point_ids, to_class: int, comment: str | None = None,  # noqa: ANN001
                frame_id: int | None = None) -> CorrectionEdit:
    """Relabel ``point_ids`` ((M,) ints, any order) of ``scene`` to ``to_class``."""
    _check_editor(user)
    _check_class(ctx, scene, int(to_class))
    if scene.status != "ready":
        raise Conflict(f"scene {scene.id} is {scene.status}, not ready")
    cap = ctx.settings.max_correction_points
    if len(point_ids) > cap:  # the API counts before parsing (app.corrections.parsing)
        raise PayloadTooLarge(f"point_ids: a correction names at most {cap} points "
                              f"(OCCUFLY_MAX_CORRECTION_POINTS), this one {len(point_ids)}")
    try:
        ids = lib.normalise_point_ids(point_ids, scene.n_points)
    except ValueError as e:
        raise Invalid(str(e)) from None
    if len(ids) == 0:
        raise Invalid("a correction needs at least one point id")
    if frame_id is not None:
        fr = session.get(Frame, frame_id)
        if fr is None or fr.scene_id != scene.id:
            raise NotFound(f"frame {frame_id} is not in scene {scene.id}")
    ws = scene.workspace
    with scene_lock(ws):
        _repair_locked(session, scene)
        net = lib.read_net(ws, scene.n_points)
        before = lib.labels_at(ws, ids, net)
        if before is None:
            before = np.zeros(len(ids), np.uint8)
        counts = np.bincount(before, minlength=256)
        hist = {str(i): int(counts[i]) for i in np.flatnonzero(counts)}
        edit = CorrectionEdit(scene_id=scene.id, author_id=user.id, created_at=utcnow(),
                              to_class=int(to_class), comment=comment or None,
                              n_points=int(len(ids)), from_hist=hist, frame_id=frame_id,
                              state="active", redoable=False)
        session.add(edit)
        session.flush()  # the id names the point file
        lib.write_edit_points(ws, edit.id, ids, int(to_class))
        _fault("after_points")
        # a new edit empties its author's redo stack in this scene
        session.execute(update(CorrectionEdit).where(
            CorrectionEdit.scene_id == scene.id, CorrectionEdit.author_id == user.id,
            CorrectionEdit.redoable.is_(True)).values(redoable=False)
            .execution_options(synchronize_session=False))
        session.commit()
        _fault("after_commit")
        lib.write_net(ws, lib.activate_edit(net, edit.id, ids, int(to_class)))
        _fault("after_layer")
    _publish(ctx, scene, edit.id, "edit")
    return edit


def _earlier(ws: str, session: Session, scene_id: int, below: int):
    for eid, cls in reversed(_active(session, scene_id)):
        if eid < below:
            yield eid, cls, (lambda eid=eid: lib.read_edit_points(ws, eid))


def _deactivate(session: Session, ctx: AppContext, scene: Scene, edit: CorrectionEdit,
                values: dict, action: str) -> CorrectionEdit:
    ws = scene.workspace
    with scene_lock(ws):
        _repair_locked(session, scene)
        net = lib.read_net(ws, scene.n_points)
        res = session.execute(update(CorrectionEdit).where(
            CorrectionEdit.id == edit.id, CorrectionEdit.state == "active").values(**values)
            .execution_options(synchronize_session=False))
        if res.rowcount != 1:
            session.rollback()
            raise Conflict(f"correction {edit.id} is no longer active")
        session.commit()
        _fault(f"after_commit_{action}")
        ids = lib.read_edit_points(ws, edit.id)
        lib.write_net(ws, lib.deactivate_edit(net, edit.id, ids,
                                              _earlier(ws, session, scene.id, edit.id)))
    session.refresh(edit)
    _publish(ctx, scene, edit.id, action)
    return edit


def _activate(session: Session, ctx: AppContext, scene: Scene, edit: CorrectionEdit,
              values: dict, action: str) -> CorrectionEdit:
    ws = scene.workspace
    with scene_lock(ws):
        _repair_locked(session, scene)
        net = lib.read_net(ws, scene.n_points)
        res = session.execute(update(CorrectionEdit).where(
            CorrectionEdit.id == edit.id, CorrectionEdit.state == "undone",
            CorrectionEdit.redoable.is_(True)).values(**values)
            .execution_options(synchronize_session=False))
        if res.rowcount != 1:
            session.rollback()
            raise Conflict(f"correction {edit.id} cannot be redone")
        session.commit()
        ids = lib.read_edit_points(ws, edit.id)
        lib.write_net(ws, lib.activate_edit(net, edit.id, ids, edit.to_class))
    session.refresh(edit)
    _publish(ctx, scene, edit.id, action)
    return edit


def undo(*, session: Session, ctx: AppContext, scene: Scene, user: User) -> CorrectionEdit:
    """Undo ``user``'s newest active edit in ``scene`` (their own undo stack)."""
    _check_editor(user)
    edit = session.scalar(select(CorrectionEdit).where(
        CorrectionEdit.scene_id == scene.id, CorrectionEdit.author_id == user.id,
        CorrectionEdit.state == "active").order_by(CorrectionEdit.id.desc()).limit(1))
    if edit is None:
        raise NotFound(f"you have no correction to undo in scene {scene.id}")
    return _deactivate(session, ctx, scene, edit, dict(state="undone", redoable=True,
                                                       undone_by_id=user.id, undone_at=utcnow()),
                       "undo")


def redo(*, session: Session, ctx: AppContext, scene: Scene, user: User) -> CorrectionEdit:
    """Redo ``user``'s most recently undone edit (until they make a new edit)."""
    _check_editor(user)
    edit = session.scalar(select(CorrectionEdit).where(
        CorrectionEdit.scene_id == scene.id, CorrectionEdit.author_id == user.id,
        CorrectionEdit.state == "undone", CorrectionEdit.redoable.is_(True))
        .order_by(CorrectionEdit.undone_at.desc(), CorrectionEdit.id.desc()).limit(1))
    if edit is None:
        raise NotFound(f"you have no undone correction to redo in scene {scene.id}")
    return _activate(session, ctx, scene, edit, dict(state="active", redoable=False,
                                                     undone_by_id=None, undone_at=None), "redo")


def revert(*, session: Session, ctx: AppContext, edit_id: int, user: User) -> CorrectionEdit:
    """An admin takes back anyone's active edit (kept in the history as ``reverted``)."""
    if user.role != "admin":
        raise Forbidden("only admins revert corrections; reviewers undo their own")
    edit = session.get(CorrectionEdit, edit_id)
    if edit is None:
        raise NotFound(f"correction {edit_id} does not exist")
    scene = session.get(Scene, edit.scene_id)
    return _deactivate(session, ctx, scene, edit, dict(state="reverted", redoable=False,
                                                       reverted_by_id=user.id,
                                                       reverted_at=utcnow()), "revert")


def edit_out(session: Session, e: CorrectionEdit, names: dict | None = None) -> dict:
    if names is None:
        names = dict(session.execute(select(User.id, User.username)).all())
    return dict(id=e.id, scene_id=e.scene_id, author=names.get(e.author_id),
                created_at=e.created_at, to_class=e.to_class, comment=e.comment,
                n_points=e.n_points, from_hist={int(k): int(v) for k, v in e.from_hist.items()},
                frame_id=e.frame_id, state=e.state, redoable=bool(e.redoable),
                undone_by=names.get(e.undone_by_id), undone_at=e.undone_at,
                reverted_by=names.get(e.reverted_by_id), reverted_at=e.reverted_at)


def list_edits(*, session: Session, scene: Scene, state: str | None = None) -> list[dict]:
    q = select(CorrectionEdit).where(CorrectionEdit.scene_id == scene.id)
    if state:
        q = q.where(CorrectionEdit.state == state)
    names = dict(session.execute(select(User.id, User.username)).all())
    return [edit_out(session, e, names) for e in session.scalars(q.order_by(CorrectionEdit.id))]


def stack(*, session: Session, scene: Scene, user: User) -> dict:
    """What ``user``'s undo / redo buttons would do in ``scene``."""
    undo_id = session.scalar(select(CorrectionEdit.id).where(
        CorrectionEdit.scene_id == scene.id, CorrectionEdit.author_id == user.id,
        CorrectionEdit.state == "active").order_by(CorrectionEdit.id.desc()).limit(1))
    redo_id = session.scalar(select(CorrectionEdit.id).where(
        CorrectionEdit.scene_id == scene.id, CorrectionEdit.author_id == user.id,
        CorrectionEdit.state == "undone", CorrectionEdit.redoable.is_(True))
        .order_by(CorrectionEdit.undone_at.desc(), CorrectionEdit.id.desc()).limit(1))
    return {"undo": undo_id, "redo": redo_id}


def layer_summary(*, session: Session, scene: Scene) -> dict:
    """The net layer as it stands (after a repair): corrected points per class."""
    repair(session, scene)
    net = lib.read_net(scene.workspace, scene.n_points)
    counts = np.bincount(net.labels, minlength=256) if len(net) else np.zeros(256, np.int64)
    return {"corrected_points": int(len(net)),
            "applied": [] if net.applied is None else [int(i) for i in net.applied],
            "per_class": {int(i): int(counts[i]) for i in np.flatnonzero(counts)}}


# ---- re-import ------------------------------------------------------------------------------
def active_count(session: Session, scene_id: int) -> int:
    return len(_active(session, scene_id))


def guard_reimport(*, session: Session, scene: Scene, drop: bool, user: User | None) -> int:
    """Before a re-import replaces the scene's points: refuse (409 naming the count) while
    active corrections exist, unless ``drop``; with ``drop`` they become ``dropped`` (kept in
    the history) and the layer is emptied. Returns the number dropped."""
    n = active_count(session, scene.id)
    if n == 0:
        return 0
    if not drop:
        raise Conflict(f"scene {scene.id} has {n} active label correction(s) made on its current "
                       "points; a re-import changes the points and would silently lose them. "
                       "Re-import with drop_corrections=true to drop them explicitly.",
                       corrections=n)
    session.execute(update(CorrectionEdit).where(
        CorrectionEdit.scene_id == scene.id, CorrectionEdit.state.in_(("active", "undone")))
        .values(state="dropped", redoable=False, reverted_by_id=getattr(user, "id", None),
                reverted_at=utcnow()).execution_options(synchronize_session=False))
    session.commit()
    if scene.workspace and Workspace(scene.workspace).exists():
        with scene_lock(scene.workspace):
            lib.write_net(scene.workspace, lib.NetLayer.empty())
    return n


# ---- 2D <-> 3D -----------------------------------------------------------------------------
def _voting_frames(session: Session, scene_id: int) -> list[tuple[Frame, object]]:
    """(frame, its voting mask version) of the frames that have one (``Frame.voting_version_id``:
    the newest submitted / accepted / imported version)."""
    rows = session.execute(select(Frame, MaskVersion).join(
        MaskVersion, MaskVersion.id == Frame.voting_version_id).where(
        Frame.scene_id == scene_id)).all()
    return [(f, v) for f, v in rows]


def _edit_pixels(ws_scene, frame_index: int, ids: np.ndarray, shape: tuple[int, int]):  # noqa: ANN001
    """(rows, cols) of the mask pixels (at the mask's ``shape``) the edit's points project to
    in frame ``frame_index`` (the visibility's correspondences: only points that frame sees)."""
    fids, uv, _depth = ws_scene.visibility.frame(frame_index)
    fids = np.asarray(fids, np.int64)
    pos = np.searchsorted(ids, fids)
    ok = pos < len(ids)
    ok[ok] = ids[pos[ok]] == fids[ok]
    if not ok.any():
        return None
    cam = ws_scene.frames[frame_index].camera
    h, w = shape
    sx, sy = w / cam.width, h / cam.height
    uvk = np.asarray(uv, np.float64)[ok]
    col = np.clip((uvk[:, 0] * sx).astype(np.int64), 0, w - 1)
    row = np.clip((uvk[:, 1] * sy).astype(np.int64), 0, h - 1)
    lin = np.unique(row * w + col)
    return lin // w, lin % w


def disagreeing_frames(*, session: Session, ctx: AppContext, edit: CorrectionEdit) -> list[dict]:
    """Frames whose voting mask disagrees with the corrected points: per frame the pixels the
    edit's points fall on, and how many of those the mask gives another class than the
    correction (0 = unlabelled counts as "no opinion" in the mask)."""
    scene = session.get(Scene, edit.scene_id)
    ws_scene = ctx.load_scene(scene.workspace)
    ids = lib.read_edit_points(scene.workspace, edit.id)
    out = []
    for frame, version in _voting_frames(session, scene.id):
        if frame.index >= len(ws_scene.frames):
            continue
        mask = stored_mask_ids(ctx.store.get(version.sha256), ws_scene.taxonomy)
        px = _edit_pixels(ws_scene, frame.index, ids, mask.shape)
        if px is None:
            continue
        vals = mask[px]
        disagree = int(((vals != edit.to_class) & (vals != 0) & (vals != 255)).sum())
        out.append(dict(frame_id=frame.id, index=frame.index, name=frame.name,
                        pixels=int(len(vals)), disagreeing_px=disagree,
                        version=version.id, state=frame.state))
    out.sort(key=lambda r: (-r["disagreeing_px"], r["index"]))
    return [r for r in out if r["disagreeing_px"] > 0]


def frame_corrections(*, session: Session, ctx: AppContext, frame: Frame) -> list[dict]:
    """The scene's active 3D corrections whose points ``frame`` sees, newest first: per edit
    (:func:`edit_out`) the mask pixels its points fall on (``pixels``), how many of those the
    frame's voting mask gives another class (``disagreeing_px``, as :func:`disagreeing_frames`)
    and how many a proposal would set to the edit's class before growing the region
    (``proposable_px``: every seen pixel not of that class, unpainted ones too), plus the id of
    the open proposal already filed from it for this frame (``open_proposal``). One decode of
    the frame's mask; each edit costs a search of its sorted point ids."""
    scene = session.get(Scene, frame.scene_id)
    ws_scene = ctx.load_scene(scene.workspace)
    if frame.index >= len(ws_scene.frames):
        return []
    version = (session.get(MaskVersion, frame.voting_version_id)
               if frame.voting_version_id is not None else None)
    mask = (stored_mask_ids(ctx.store.get(version.sha256), ws_scene.taxonomy)
            if version is not None else None)
    shape = mask.shape if mask is not None else (frame.height, frame.width)
    open_props = dict(session.execute(select(MaskProposal.edit_id, MaskProposal.id).where(
        MaskProposal.frame_id == frame.id, MaskProposal.status == "open")).all())
    names = dict(session.execute(select(User.id, User.username)).all())
    out = []
    for e in session.scalars(select(CorrectionEdit).where(
            CorrectionEdit.scene_id == frame.scene_id, CorrectionEdit.state == "active")
            .order_by(CorrectionEdit.id.desc())):
        px = _edit_pixels(ws_scene, frame.index, lib.read_edit_points(scene.workspace, e.id),
                          shape)
        if px is None:
            continue
        row = edit_out(session, e, names)
        row.update(pixels=int(len(px[0])), voting_version=version.id if version else None,
                   open_proposal=open_props.get(e.id))
        if mask is None:
            row.update(disagreeing_px=None, proposable_px=None)
        else:
            vals = mask[px]
            row.update(disagreeing_px=int(((vals != e.to_class) & (vals != 0)
                                           & (vals != 255)).sum()),
                       proposable_px=int((vals != e.to_class).sum()))
        out.append(row)
    return out


def _png(arr: np.ndarray) -> bytes:
    return encode_png(np.ascontiguousarray(arr, dtype=np.uint8))


def propose(*, session: Session, ctx: AppContext, edit: CorrectionEdit, frame: Frame,
            user: User, dilate: int = 1) -> MaskProposal:
    """Turn edit ``edit``'s projection into frame ``frame`` into a proposed mask change: the
    frame's voting mask with the pixels the edit's points fall on (grown by ``dilate``
    pixels, only where the mask disagrees) set to the correction's class."""
    _check_editor(user)
    if frame.scene_id != edit.scene_id:
        raise NotFound(f"frame {frame.id} is not in the scene of correction {edit.id}")
    if frame.state == "accepted":  # its annotator can never take it (issue 40, defect 3)
        raise Conflict(f"frame {frame.id} ({frame.name}) is accepted: its annotator cannot take "
                       "a proposal on an accepted mask. Fix the mask in 2D as a reviewer, or "
                       "reject the frame first so that it goes back to its annotator",
                       state=frame.state)
    votes = dict((f.id, v) for f, v in _voting_frames(session, frame.scene_id))
    if frame.id not in votes:
        raise Conflict(f"frame {frame.id} has no submitted mask to propose a change to")
    version = votes[frame.id]
    scene = session.get(Scene, frame.scene_id)
    ws_scene = ctx.load_scene(scene.workspace)
    mask = stored_mask_ids(ctx.store.get(version.sha256), ws_scene.taxonomy)
    ids = lib.read_edit_points(scene.workspace, edit.id)
    px = _edit_pixels(ws_scene, frame.index, ids, mask.shape)
    if px is None:
        raise Conflict(f"frame {frame.id} does not see the points of correction {edit.id}")
    change = np.zeros(mask.shape, bool)
    change[px] = True
    if dilate > 0:  # close the gaps between the projected points, then grow the region
        change = binary_closing(change, iterations=2 * int(dilate)) | change
        change = binary_dilation(change, iterations=int(dilate))
    change &= mask != edit.to_class
    if not change.any():
        raise Conflict(f"frame {frame.id}'s mask already agrees with correction {edit.id}")
    proposed = mask.copy()
    proposed[change] = edit.to_class
    p = MaskProposal(frame_id=frame.id, edit_id=edit.id, author_id=user.id, created_at=utcnow(),
                     sha256=claim_blob(session, ctx.store, _png(proposed)),
                     change_sha256=claim_blob(session, ctx.store,
                                              _png(change.astype(np.uint8) * 255)),
                     changed_px=int(change.sum()), status="open")
    session.add(p)
    session.flush()
    for uid in {frame.last_annotator_id, frame.assignee_id} - {None}:
        notify(session, user_id=uid, kind="proposal", scene_id=frame.scene_id,
               frame_id=frame.id,
               text=f"{user.username} proposes a change of {p.changed_px} px "
                    f"to the mask of {frame.name}")
    session.commit()
    return p


def get_proposal(*, session: Session, proposal_id: int, user: User) -> MaskProposal:
    p = session.get(MaskProposal, proposal_id)
    if p is None:
        raise NotFound(f"proposal {proposal_id} does not exist")
    check_read(session, session.get(Frame, p.frame_id), user)
    return p


def list_proposals(*, session: Session, frame: Frame, status: str | None = None) -> list[dict]:
    q = select(MaskProposal).where(MaskProposal.frame_id == frame.id)
    if status:
        q = q.where(MaskProposal.status == status)
    return [proposal_out(session, p) for p in session.scalars(q.order_by(MaskProposal.id))]


def proposal_out(session: Session, p: MaskProposal) -> dict:
    names = dict(session.execute(select(User.id, User.username)).all())
    return dict(id=p.id, frame_id=p.frame_id, edit_id=p.edit_id, author=names.get(p.author_id),
                created_at=p.created_at, changed_px=p.changed_px, status=p.status,
                reply=p.reply, decided_by=names.get(p.decided_by_id), decided_at=p.decided_at,
                taken_version=p.taken_version_id)


def take(*, session: Session, ctx: AppContext, proposal: MaskProposal, user: User,
         expected: int | None) -> MaskProposal:
    """The frame's annotator takes a proposal: a new draft = the current mask with the
    proposal's changed pixels set to the proposal (lease and If-Match rules of any save)."""

    if proposal.status != "open":
        raise Conflict(f"proposal {proposal.id} is {proposal.status}")
    frame = session.get(Frame, proposal.frame_id)
    scene = session.get(Scene, frame.scene_id)
    tax = ctx.load_scene(scene.workspace).taxonomy
    proposed = stored_mask_ids(ctx.store.get(proposal.sha256), tax)

    change = np.asarray(Image.open(io.BytesIO(ctx.store.get(proposal.change_sha256)))) > 0
    if frame.current_version_id is not None:
        cur = annotations.current_version(session=session, frame=frame)
        base = stored_mask_ids(ctx.store.get(cur.sha256), tax)
    else:
        base = np.zeros_like(proposed)
    if base.shape != proposed.shape:
        raise Conflict(f"frame {frame.id}'s mask is {base.shape[1]}x{base.shape[0]}, the proposal "
                       f"{proposed.shape[1]}x{proposed.shape[0]}")
    out = base.copy()
    out[change] = proposed[change]
    v = annotations.store_version(session=session, ctx=ctx, frame=frame, user=user,
                                  data=_png(out), kind="draft",
                                  expected=expected if expected is not None
                                  else frame.current_version_id)
    proposal = session.get(MaskProposal, proposal.id)
    proposal.status, proposal.decided_by_id, proposal.decided_at = "taken", user.id, utcnow()
    proposal.taken_version_id = v.id
    session.commit()
    return proposal


def decline(*, session: Session, proposal: MaskProposal, user: User, reply: str) -> MaskProposal:
    if proposal.status != "open":
        raise Conflict(f"proposal {proposal.id} is {proposal.status}")
    proposal.status, proposal.reply = "declined", reply
    proposal.decided_by_id, proposal.decided_at = user.id, utcnow()
    if proposal.author_id:
        frame = session.get(Frame, proposal.frame_id)
        notify(session, user_id=proposal.author_id, kind="declined",
               scene_id=frame.scene_id, frame_id=frame.id,
               text=f"{user.username} declined your proposal for {frame.name}: {reply}")
    session.commit()
    return proposal


# ---- review items seen from a frame --------------------------------------------------------
def projected_items(*, session: Session, ctx: AppContext, frame: Frame, user: User) -> list[dict]:
    """Open review items on 3D points that ``frame`` sees, each with the outline of its
    points in the frame (convex hull in pixels) -- what the annotator page draws."""
    scene = session.get(Scene, frame.scene_id)
    ws_scene = ctx.load_scene(scene.workspace)
    fids, uv, _d = ws_scene.visibility.frame(frame.index)
    fids = np.asarray(fids, np.int64)
    order = np.argsort(fids)
    sorted_ids = fids[order]
    seen = []  # (item, outline, visible points)
    for it in session.scalars(select(ReviewItem).where(
            ReviewItem.scene_id == frame.scene_id, ReviewItem.point_ids.is_not(None))
            .order_by(ReviewItem.id)):
        pts = np.asarray(it.point_ids or [], np.int64)
        if not len(pts):
            continue
        pos = np.searchsorted(sorted_ids, pts)
        ok = pos < len(sorted_ids)
        ok[ok] = sorted_ids[pos[ok]] == pts[ok]
        if not ok.any():
            continue
        seen.append((it, _hull(np.asarray(uv, np.float64)[order[pos[ok]]]), int(ok.sum())))
    out = items_out(session, [it for it, _o, _n in seen])
    for d, (_it, outline, n) in zip(out, seen, strict=True):
        d.pop("point_ids", None)
        d["outline"] = outline
        d["visible_points"] = n
    return out


def _hull(xy: np.ndarray) -> list[list[float]]:
    """Convex hull (monotone chain) of (n, 2) pixel positions, as [[x, y], ...]."""
    pts = np.unique(np.round(xy, 1), axis=0)
    if len(pts) <= 2:
        return pts.tolist()

    def cross(o, a, b):  # noqa: ANN001, ANN202
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    upper: list = []
    for p in pts:  # hull vertices only; O(n) over unique rounded positions
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return [[float(x), float(y)] for x, y in lower[:-1] + upper[:-1]]


# ---- the 3D viewer's hooks -----------------------------------------------------------------
def viewer_hooks(ctx: AppContext) -> dict:
    """relabel / undo / redo / stack / propose for ``app.viewer``
    (``ViewerService.corrections``); the viewer's user is re-read by id, so a role changed
    since the ticket counts."""

    def _user(s: Session, user) -> User:  # noqa: ANN001
        uid = user if isinstance(user, int) else getattr(user, "id", None)
        u = s.get(User, uid) if uid is not None else None
        if u is None or not u.active:
            raise Forbidden("log in again")
        return u

    def _member_scene(s: Session, scene_id, user) -> tuple[Scene, User]:  # noqa: ANN001
        """The scene (404) and the viewer's user, who must be an active member of it."""
        scene = s.get(Scene, int(scene_id))
        if scene is None:
            raise NotFound(f"scene {scene_id} does not exist")
        u = _user(s, user)
        check_member(s, u, scene.id)
        return scene, u

    def relabel(scene_id, point_ids, to_class, comment, user, frame_index=None) -> dict:  # noqa: ANN001
        with ctx.sessions() as s:
            scene, u = _member_scene(s, scene_id, user)
            fid = None if frame_index is None else s.scalar(select(Frame.id).where(
                Frame.scene_id == scene.id, Frame.index == int(frame_index)))
            e = create_edit(session=s, ctx=ctx, scene=scene, user=u, point_ids=point_ids,
                            to_class=int(to_class), comment=comment or None, frame_id=fid)
            out = edit_out(s, e)
            audit.record(s, "correction", actor=u, scene_id=scene.id, frame_id=fid,
                         detail={"edit": e.id, "to": e.to_class, "points": e.n_points,
                                 "via": "viewer"})
            return out

    def _stacked(which):  # noqa: ANN001, ANN202
        def run(scene_id, user) -> dict:  # noqa: ANN001
            with ctx.sessions() as s:
                scene = s.get(Scene, int(scene_id))
                u = _user(s, user)
                e = (undo if which == "undo" else redo)(session=s, ctx=ctx, scene=scene, user=u)
                out = edit_out(s, e)
                audit.record(s, f"correction_{which}", actor=u, scene_id=scene.id,
                             detail={"edit": e.id, "via": "viewer"})
                return out
        return run

    def stack_of(scene_id, user) -> dict:  # noqa: ANN001
        with ctx.sessions() as s:
            return stack(session=s, scene=s.get(Scene, int(scene_id)), user=_user(s, user))

    def propose_from_viewer(scene_id, edit_id, frame_index, user) -> dict:  # noqa: ANN001
        """The viewer's "File as proposal": correction ``edit_id``'s projection into the
        frame at ``frame_index`` as a proposal (:func:`propose`; its refusals pass through)."""
        with ctx.sessions() as s:
            scene, u = _member_scene(s, scene_id, user)
            e = s.get(CorrectionEdit, int(edit_id))
            if e is None or e.scene_id != scene.id:
                raise NotFound(f"correction {edit_id} is not in scene {scene.id}")
            if e.state != "active":
                raise Conflict(f"correction {e.id} is {e.state}: redo it to propose it")
            frame = s.scalar(select(Frame).where(Frame.scene_id == scene.id,
                                                 Frame.index == int(frame_index)))
            if frame is None:
                raise NotFound(f"frame index {frame_index} is not in scene {scene.id}")
            p = propose(session=s, ctx=ctx, edit=e, frame=frame, user=u)
            return dict(proposal_out(s, p), frame_name=frame.name)

    return {"relabel": relabel, "undo": _stacked("undo"), "redo": _stacked("redo"),
            "stack": stack_of, "propose": propose_from_viewer}
