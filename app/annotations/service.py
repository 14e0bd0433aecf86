"""Frame leases (``next``), versioned masks with optimistic concurrency, live-lifting hooks.

Concurrency rules (race free on SQLite and PostgreSQL alike, no SELECT ... FOR UPDATE):
- ``next`` claims a frame with one conditional UPDATE whose WHERE re-checks that the frame
  is still free; the database serialises concurrent UPDATEs of a row, so exactly one
  annotator's UPDATE matches.
- A mask PUT inserts its version row and then moves the frame's ``current_version_id`` with
  ``UPDATE ... WHERE current_version_id = <If-Match>`` in the same transaction. If that
  matches no row, someone else won: the version is kept with kind ``conflict`` (so the
  loser's upload stays recoverable) and the request gets 409.

Provenance (docs/provenance.md): a version's ``kind`` is its state. Only a frame's voting
version (``Frame.voting_version_id``: its newest submitted / accepted / imported version,
unless a rejected one is newer) is lifted; the lifting queue carries only changes of it. A
draft save never reaches the queue: it informs its own frame's editor only.
"""

from __future__ import annotations

import hashlib
import io
import threading
from collections import OrderedDict
from datetime import timedelta
from pathlib import Path

import numpy as np
from PIL import Image
from sqlalchemy import and_, case, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.annotations.models import STORED_KINDS, VOTING_KINDS, MaskVersion, Prefill
from app.blobs import claim_blob, release_blobs
from app.context import AppContext
from app.db import utcnow
from app.errors import (
    Conflict,
    Forbidden,
    InsufficientStorage,
    Invalid,
    NotFound,
    PreconditionRequired,
    StaleVersion,
)
from app.limits import INT32_MAX
from app.scenes.models import Frame, Scene
from app.users.models import User
from occufly import render
from occufly.errors import WorkspaceError
from occufly.io import masks
from occufly.lifting import load_labels
from occufly.workspace import Workspace

CLAIMABLE = ("unassigned", "in_progress", "rejected")


# ---- leases ---------------------------------------------------------------------------------
def _claimable(user_id: int, now):
    return and_(Frame.selected.is_(True), Frame.state.in_(CLAIMABLE),
                or_(Frame.assignee_id.is_(None), Frame.assignee_id == user_id,
                    Frame.lease_expires_at.is_(None), Frame.lease_expires_at < now))


def next_frame(*, session: Session, ctx: AppContext, scene: Scene, user: User,
               skip: list[int] | None = None) -> Frame | None:
    """Lease the caller's next frame: own held/rejected frames first, then free ones in the
    selection's hand-out order (``Frame.handout_rank``, see app.scenes.service.handout_order:
    the frames over what nobody has painted yet first), unranked ones after, by index.

    ``skip``: frame ids not to hand out now (the annotator pressed Skip on them).
    """
    now = utcnow()
    mine = case((Frame.assignee_id == user.id, 0), else_=1)
    rejected_first = case((Frame.state == "rejected", 0), else_=1)
    candidates = list(session.scalars(
        select(Frame.id).where(Frame.scene_id == scene.id, _claimable(user.id, now),
                               Frame.id.notin_(skip or []))
        .order_by(mine, rejected_first, case((Frame.handout_rank.is_(None), 1), else_=0),
                  Frame.handout_rank, Frame.index).limit(32)))
    expires = now + timedelta(seconds=ctx.settings.lease_seconds)
    for fid in candidates:
        res = session.execute(
            update(Frame).where(Frame.id == fid, _claimable(user.id, now))
            .values(assignee_id=user.id, lease_expires_at=expires,
                    state=case((Frame.state == "unassigned", "in_progress"), else_=Frame.state))
            .execution_options(synchronize_session=False))
        session.commit()
        if res.rowcount == 1:
            frame = session.get(Frame, fid)
            session.refresh(frame)
            return frame
    return None


def release(*, session: Session, frame: Frame, user: User) -> Frame:
    if frame.assignee_id != user.id and user.role != "admin":
        raise Forbidden(f"frame {frame.id} is not leased to you")
    session.execute(update(Frame).where(Frame.id == frame.id).values(
        assignee_id=None, lease_expires_at=None,
        state=case((Frame.current_version_id.is_(None), "unassigned"), else_=Frame.state)))
    session.commit()
    session.refresh(frame)
    return frame


# ---- access ---------------------------------------------------------------------------------
def has_authored(session: Session, frame: Frame, user: User) -> bool:
    return session.scalar(select(MaskVersion.id).where(
        MaskVersion.frame_id == frame.id, MaskVersion.author_id == user.id).limit(1)) is not None


def check_read(session: Session, frame: Frame, user: User) -> None:
    """Annotators see the masks of frames they hold or worked on; reviewers/admins all."""
    if user.role in ("reviewer", "admin"):
        return
    if frame.assignee_id == user.id or frame.last_annotator_id == user.id:
        return
    if has_authored(session, frame, user):
        return
    raise Forbidden(f"frame {frame.id} is not assigned to you")


# ---- versions -------------------------------------------------------------------------------
def parse_if_match(raw: str | None) -> int | None:
    """'none' -> None, '12' / '"12"' / 'W/"12"' -> 12; missing -> 428."""
    if raw is None:
        raise PreconditionRequired(
            "If-Match header is required: the current mask version id, or 'none' for the first")
    v = raw.strip()
    if v.startswith("W/"):
        v = v[2:]
    v = v.strip('"').strip()
    if v.lower() == "none":
        return None
    if not v.isdigit() or len(v) > 10 or int(v) > INT32_MAX:
        raise Invalid(f"If-Match must be a mask version id (1..{INT32_MAX}) or 'none', got "
                      f"{raw[:40]!r}")
    return int(v)


# at most this many uploads are decoded at once per process: with the PNG header checked
# against the frame size first (occufly.io.masks.check_png_size), decoding memory is bounded
# by DECODE_SLOTS x the largest frame (x 4 bytes for RGBA), whatever the uploads claim
DECODE_SLOTS = threading.BoundedSemaphore(2)


def _decode_for_frame(ctx: AppContext, session: Session, frame: Frame, data: bytes,
                      info: dict | None = None):
    scene = session.get(Scene, frame.scene_id)
    gone = NotFound(f"frame {frame.id}: its scene {frame.scene_id} was deleted while the mask "
                    "was saved; nothing was stored")
    if scene is None:
        raise gone
    try:
        ws_scene = ctx.load_scene(scene.workspace)
    except (OSError, WorkspaceError):
        # the scene is being deleted (app.scenes.disk.delete_scene moves its workspace away
        # first, in one rename): a 404, not a 500; a workspace broken while its scene stands
        # stays an error
        if not Path(scene.workspace).is_dir():
            raise gone from None
        raise
    sf = ws_scene.frames[frame.index]
    name = f"mask upload for {frame.name}"
    masks.check_png_size(data, name=name, frame=sf)  # a bomb is refused before it waits
    with DECODE_SLOTS:
        return masks.read_mask(data, sf, ws_scene.taxonomy, name=name, info=info)


def storage_used(session: Session, *, user_id: int | None = None,
                 scene_id: int | None = None) -> int:
    """Bytes of mask versions (every kind, conflicts included) authored by ``user_id`` or
    belonging to ``scene_id``, as the quotas count them."""
    q = select(func.coalesce(func.sum(MaskVersion.size_bytes), 0))
    if user_id is not None:
        q = q.where(MaskVersion.author_id == user_id)
    if scene_id is not None:
        q = q.join(Frame, Frame.id == MaskVersion.frame_id).where(Frame.scene_id == scene_id)
    return int(session.scalar(q) or 0)


def check_storage_quota(session: Session, ctx: AppContext, frame: Frame, user: User,
                        nbytes: int) -> None:
    """507 before a byte is stored when this version would take the author's mask storage
    past ``user_quota_bytes`` or the scene's past ``scene_quota_bytes`` (conflict versions of
    a user who lost the lease count too)."""
    s = ctx.settings
    used = storage_used(session, user_id=user.id)
    if used + nbytes > s.user_quota_bytes:
        raise InsufficientStorage(
            f"storage quota: {user.username}'s mask versions take {used} bytes; this one "
            f"({nbytes} bytes) would pass the per-user quota of {s.user_quota_bytes} bytes "
            "(OCCUFLY_USER_QUOTA_MB); nothing was stored -- ask an admin",
            quota="user", used_bytes=used, quota_bytes=s.user_quota_bytes)
    used = storage_used(session, scene_id=frame.scene_id)
    if used + nbytes > s.scene_quota_bytes:
        raise InsufficientStorage(
            f"storage quota: scene {frame.scene_id}'s mask versions take {used} bytes; this one "
            f"({nbytes} bytes) would pass the per-scene quota of {s.scene_quota_bytes} bytes "
            "(OCCUFLY_SCENE_QUOTA_MB); nothing was stored -- ask an admin",
            quota="scene", used_bytes=used, quota_bytes=s.scene_quota_bytes)


def _insert_version(session: Session, ctx: AppContext, frame_id: int, sha256: str) -> None:
    """Flush the new version's row. A frame deleted with its scene while this save ran
    (issue 36 attack pass: a foreign-key failure was a 500) is a 404 with nothing stored:
    the transaction is rolled back and the blob it claimed released unless referenced."""
    try:
        session.flush()
    except IntegrityError:
        session.rollback()
        if session.get(Frame, frame_id) is not None:
            raise
        if ctx.store.exists(sha256):  # kept by no row of this save: released unless used
            claim_blob(session, ctx.store, sha256=sha256, owner=f"frame {frame_id}")
            session.commit()
            release_blobs(session, ctx.store, {sha256})
        raise NotFound(f"frame {frame_id} was deleted (with its scene) while this mask was "
                       "being saved; nothing was stored") from None


def store_version(*, session: Session, ctx: AppContext, frame: Frame, user: User, data: bytes,
                  kind: str, expected: int | None, restored_from: int | None = None,
                  sha256: str | None = None, size: tuple[int, int] | None = None,
                  source: str | None = None, prefill_id: int | None = None) -> MaskVersion:
    """Validate, store and (if ``expected`` is still current) make current a new version.

    kind: ``draft`` (an autosave: never lifted), ``submitted`` (handed in for review) or
    ``imported`` (an admin brings a mask from another tool; ``source`` e.g. ``"import:cvat"``).
    A submitted or imported version becomes the frame's voting version and is queued for
    lifting; a draft leaves the voting version (and so every other consumer) unchanged.
    source: where the mask came from (None = painted in the editor), at most 64 characters.
    prefill_id: the prefill (``X-Prefill-Id`` of GET /frames/{fid}/prefill) this submitted
    mask was painted over, as the editor still holds it (None: none, or it was undone); only
    a named prefill counts in the effort figures (:func:`_record_effort`).

    Raises StaleVersion (409) after keeping the upload as a ``conflict`` version.
    """
    if kind not in STORED_KINDS:
        raise Invalid(f"kind must be one of {', '.join(STORED_KINDS)}, got {kind!r}")
    if source is not None and (not isinstance(source, str) or len(source) > 64):
        raise Invalid("source must be a string of at most 64 characters")
    reviewer_fix = (user.role == "reviewer" and source == "reviewer_correction"
                    and kind == "submitted")  # a reviewer corrects a 2D mask (issue 25)
    if user.role not in ("annotator", "admin") and not reviewer_fix:
        raise Forbidden(f"frame {frame.id}: only the annotator holding its lease (or an admin) "
                        f"writes its mask; reviewers accept or reject")
    if kind == "imported" and user.role != "admin":
        raise Forbidden(f"frame {frame.id}: only an admin imports masks")
    if user.role == "annotator" and frame.assignee_id != user.id:
        if not has_authored(session, frame, user):
            raise Forbidden(f"frame {frame.id} is not leased to you; ask for it with 'next'")
        lost_lease = True
    else:
        lost_lease = False
    mask = None
    if sha256 is None:
        info: dict = {}
        mask = _decode_for_frame(ctx, session, frame, data, info)  # MaskError -> 422, nothing stored
        h, w = mask.shape
        # stored canonically (issue 24): the decoded class ids re-encoded as an 8-bit PNG
        # without ancillary chunks -- bytes after IEND, text chunks, palettes, 16-bit or
        # colour encodings of the upload are never kept. An upload that is canonical already
        # (the editor's: 8-bit grey, IHDR/IDAT/IEND, nothing after the stream) is kept as it
        # is -- it decodes to the same ids -- which saves the re-encode (issue 29: save p95)
        if not info["canonical"]:  # told by the decode (occufly.io.masks.decode_mask_png)
            data = masks.encode_mask_png(mask)
        check_storage_quota(session, ctx, frame, user, len(data))
        # claimed in this transaction: a concurrent scene deletion cannot remove the blob
        # between here and the commit (app/blobs.py, issue 36)
        sha256 = claim_blob(session, ctx.store, data)
        nbytes = len(data)
    else:
        w, h = size
        nbytes = len(data)
        check_storage_quota(session, ctx, frame, user, nbytes)
        claim_blob(session, ctx.store, sha256=sha256, owner=f"mask version {restored_from}")
    version = MaskVersion(frame_id=frame.id, kind="conflict" if lost_lease else kind,
                          author_id=user.id, sha256=sha256, size_bytes=nbytes, width=w, height=h,
                          base_version_id=expected, restored_from_id=restored_from,
                          source=source, created_at=utcnow())
    if kind == "submitted" and not lost_lease:
        _record_effort(session, ctx, frame, user, version, mask, prefill_id)
    session.add(version)
    _insert_version(session, ctx, frame.id, sha256)
    if lost_lease:
        session.commit()
        raise Conflict(f"frame {frame.id} is no longer leased to you (it is {frame.state}); your "
                       f"upload was kept as conflict version {version.id}", reason="lease",
                       frame_state=frame.state, current_version=frame.current_version_id,
                       conflict_version=version.id)
    now = utcnow()
    values: dict = {"current_version_id": version.id}
    votes = kind in VOTING_KINDS
    if votes:  # submitted / imported: waits for review, and votes from now on
        values.update(state="submitted", lease_expires_at=None, assignee_id=None,
                      last_annotator_id=user.id if user.role == "annotator" else
                      Frame.last_annotator_id, agreement=None, voting_version_id=version.id)
    elif user.role == "annotator":
        values.update(state="in_progress", last_annotator_id=user.id,
                      lease_expires_at=now + timedelta(seconds=ctx.settings.lease_seconds))
    else:  # an admin's draft: an accepted frame no longer shows what was reviewed
        values.update(state=case((Frame.state == "accepted", "in_progress"), else_=Frame.state))
    cond = (Frame.current_version_id.is_(None) if expected is None
            else Frame.current_version_id == expected)
    res = session.execute(update(Frame).where(Frame.id == frame.id, cond).values(**values)
                          .execution_options(synchronize_session=False))
    if res.rowcount != 1:
        version.kind = "conflict"
        session.commit()
        current = session.scalar(select(Frame.current_version_id).where(Frame.id == frame.id))
        raise StaleVersion(
            f"mask of frame {frame.id} changed: If-Match {expected if expected is not None else 'none'}"
            f" is not the current version {current}; your upload was kept as conflict version "
            f"{version.id}", reason="stale", current_version=current,
            current_number=_number_of(session, frame.id, current), conflict_version=version.id)
    if votes:  # only a change of the voting version is lifted; a draft never is
        ctx.lifting.enqueue(session, frame, version.id)  # durable: commits with the save
    session.commit()
    if votes:
        ctx.lifting.notify(frame.scene_id, frame.id, version_id=version.id, mask=mask)
    return version


def set_voting(*, session: Session, ctx: AppContext, frame: Frame, version_id: int | None) -> bool:
    """Make ``version_id`` (None: no votes) the frame's voting version and queue the change
    in the caller's transaction (the caller commits); False (nothing queued) when it already
    is. The caller has checked the version's state (VOTING_KINDS) and owns the frame row."""
    old = session.scalar(select(Frame.voting_version_id).where(Frame.id == frame.id))
    if old == version_id:
        return False
    session.execute(update(Frame).where(Frame.id == frame.id)
                    .values(voting_version_id=version_id)
                    .execution_options(synchronize_session=False))
    ctx.lifting.enqueue(session, frame, version_id)
    return True


def voting_versions(session: Session, scene_id: int) -> dict[int, MaskVersion]:
    """frame index -> the frame's voting version (frames without one left out)."""
    rows = session.execute(select(Frame.index, MaskVersion)
                           .join(MaskVersion, MaskVersion.id == Frame.voting_version_id)
                           .where(Frame.scene_id == scene_id)).all()
    return {int(i): v for i, v in rows}


# ---- annotation effort (issue 17) ----------------------------------------------------------
def record_prefill(session: Session, ctx: AppContext, frame: Frame, user: User, img: np.ndarray,
                   png: bytes, *, masks: int | None = None) -> Prefill:
    """Keep the prefill handed to ``user`` (its PNG in the content store) so that the submit
    of this frame can count how much the person changed. The same prefill handed again (same
    frame, user and image) is the row already kept: a GET writes nothing then (issue 24 --
    every call used to add a row, so a loop of GETs grew the table without bound)."""
    digest = hashlib.sha256(png).hexdigest()
    same = session.scalar(select(Prefill).where(
        Prefill.frame_id == frame.id, Prefill.user_id == user.id, Prefill.sha256 == digest,
        Prefill.masks.is_(None) if masks is None else Prefill.masks == masks)
        .order_by(Prefill.id.desc()).limit(1))
    if same is not None and ctx.store.exists(digest):
        return same
    p = Prefill(frame_id=frame.id, user_id=user.id, sha256=claim_blob(session, ctx.store, png),
                width=int(img.shape[1]), height=int(img.shape[0]),
                labelled_px=int(np.count_nonzero(img)), masks=masks, created_at=utcnow())
    session.add(p)
    session.commit()
    return p


def prefill_holds_own_mask(scene: Scene, frame: Frame, included: dict | None) -> bool:
    """Whether the lifted labels a prefill of ``frame`` renders hold the frame's own mask:
    its votes are among the lifting state's versions (``included``, frame index -> tag) or
    the kNN fill's. Such a prefill gives the frame back its own work (a reopened or rejected
    frame); it is not recorded, so it never counts as painting saved by the 3D labels."""
    if included and frame.index in included:
        return True
    versions = Workspace(scene.workspace).lift_stats().get("versions") or {}  # labels.json only
    return str(frame.index) in {str(k) for k in versions}


def _decode_ids_png(data: bytes) -> np.ndarray:
    """(h, w) uint8 of a single-channel PNG this module wrote (a prefill)."""
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im, dtype=np.uint8)


def _record_effort(session: Session, ctx: AppContext, frame: Frame, user: User,
                   version: MaskVersion, mask: np.ndarray | None,
                   prefill_id: int | None = None) -> None:
    """Fill ``version``'s effort columns: the prefill the submit names (``prefill_id``: one
    handed to this author for this frame, else 422; None = painted without one -- a prefill
    the editor undid is not named), the mask's painted pixels (a class or 255: what painting
    from an empty mask costs) and the pixels where the mask differs from that prefill
    (everything painted when there is none). A prefill of another resolution is compared
    after nearest-neighbour resampling. Prefills rendered from labels that held this frame's
    own mask are never recorded (app.annotations.routes.prefill), so they cannot be named."""
    pre = None
    if prefill_id is not None:
        pre = session.get(Prefill, prefill_id)
        if pre is None or pre.frame_id != frame.id or pre.user_id != user.id:
            raise Invalid(f"X-Prefill-Id {prefill_id} is not a prefill of frame {frame.name} "
                          f"handed to {user.username}; send the id GET /api/frames/{frame.id}"
                          f"/prefill answered, or none")
    if mask is None:
        mask = _decode_for_frame(ctx, session, frame, ctx.store.get(version.sha256))
    mask = np.asarray(mask)
    version.painted_px = int(np.count_nonzero(mask))
    img = None
    if pre is not None and ctx.store.exists(pre.sha256):
        img = _decode_ids_png(ctx.store.get(pre.sha256))
        if img.shape != mask.shape:  # nearest-neighbour resampling to the mask's grid
            H, W = mask.shape
            img = img[(np.arange(H) * img.shape[0]) // H][:, (np.arange(W) * img.shape[1]) // W]
    if img is None:
        version.prefill_id, version.changed_px = None, version.painted_px
    else:
        version.prefill_id = pre.id
        version.changed_px = int(np.count_nonzero(img != mask))


def effort(*, session: Session, scene: Scene) -> dict:
    """The scene's frames in the order of their first submission, each with the share of its
    pixels painted (from scratch) and changed versus the prefill its author started from; plus
    totals. A frame counts once: its later submissions (after a reopen or a rejection, or a
    restore submitted again) start from the frame's own mask, so counting their painted
    pixels again would count the frame twice; each row says how many it left out
    (``resubmissions``)."""
    rows = session.execute(
        select(MaskVersion, Frame.name, Frame.index, User.username)
        .join(Frame, Frame.id == MaskVersion.frame_id)
        .outerjoin(User, User.id == MaskVersion.author_id)
        .where(Frame.scene_id == scene.id,
               MaskVersion.kind.in_(("submitted", "accepted", "rejected")),
               MaskVersion.painted_px.is_not(None))
        .order_by(MaskVersion.id)).all()
    out = []
    first: dict[int, dict] = {}
    for v, name, index, author in rows:
        if v.frame_id in first:
            first[v.frame_id]["resubmissions"] += 1
            continue
        px = v.width * v.height
        n = len(out) + 1
        out.append(dict(n=n, version=v.id, resubmissions=0, frame_id=v.frame_id, frame=name, frame_index=index,
                        author=author, created_at=v.created_at, pixels=px,
                        painted_px=v.painted_px, changed_px=v.changed_px,
                        prefilled=v.prefill_id is not None,
                        painted_share=v.painted_px / px if px else None,
                        changed_share=v.changed_px / px if px else None,
                        changed_of_painted=(v.changed_px / v.painted_px if v.painted_px else None)))
        first[v.frame_id] = out[-1]
    painted = sum(r["painted_px"] for r in out)
    changed = sum(r["changed_px"] for r in out)
    later = [r["changed_of_painted"] for r in out[5:] if r["changed_of_painted"] is not None]
    totals = dict(submissions=len(out), prefilled=sum(r["prefilled"] for r in out),
                  resubmissions=sum(r["resubmissions"] for r in out),
                  painted_px=painted, changed_px=changed,
                  reduction_x=painted / changed if changed else None,
                  median_changed_of_painted_from_6th=float(np.median(later)) if later else None)
    return dict(scene_id=scene.id, submissions=out, totals=totals)


def restore(*, session: Session, ctx: AppContext, frame: Frame, user: User, version_id: int,
            expected: int | None, kind: str = "draft") -> MaskVersion:
    old = get_version(session=session, frame=frame, version_id=version_id)
    data = ctx.store.get(old.sha256, owner=f"mask version {old.id}")
    if expected is None:
        expected = frame.current_version_id
    return store_version(session=session, ctx=ctx, frame=frame, user=user, data=data, kind=kind,
                         expected=expected, restored_from=old.id, sha256=old.sha256,
                         size=(old.width, old.height), source=old.source)


def get_version(*, session: Session, frame: Frame, version_id: int) -> MaskVersion:
    v = session.get(MaskVersion, version_id)
    if v is None or v.frame_id != frame.id:
        raise NotFound(f"frame {frame.id} has no mask version {version_id}")
    return v


def current_version(*, session: Session, frame: Frame) -> MaskVersion:
    if frame.current_version_id is None:
        raise NotFound(f"frame {frame.id} has no mask yet")
    return get_version(session=session, frame=frame, version_id=frame.current_version_id)


def list_versions(*, session: Session, frame: Frame) -> list[dict]:
    rows = session.execute(select(MaskVersion, User.username)
                           .outerjoin(User, User.id == MaskVersion.author_id)
                           .where(MaskVersion.frame_id == frame.id).order_by(MaskVersion.id))
    return [version_out(v, name, number=i) for i, (v, name) in enumerate(rows, 1)]


def _number_of(session: Session, frame_id: int, version_id: int | None) -> int | None:
    """1-based position of a version among its frame's versions (ids are global)."""
    if version_id is None:
        return None
    return int(session.scalar(select(func.count(MaskVersion.id)).where(
        MaskVersion.frame_id == frame_id, MaskVersion.id <= version_id)) or 0)


def version_number(session: Session, v: MaskVersion) -> int:
    return _number_of(session, v.frame_id, v.id)


def reopen(*, session: Session, ctx: AppContext, frame: Frame, user: User) -> Frame:
    """Take a submitted frame back to edit it, while no reviewer has decided on it yet."""
    if frame.state != "submitted":
        raise Conflict(f"frame {frame.id} is {frame.state}; only a submitted frame that is "
                       f"still waiting for review can be reopened")
    if user.role == "annotator" and frame.last_annotator_id != user.id:
        raise Forbidden(f"frame {frame.id} was submitted by someone else")
    res = session.execute(update(Frame).where(Frame.id == frame.id, Frame.state == "submitted")
                          .values(state="in_progress", assignee_id=user.id,
                                  lease_expires_at=utcnow() + timedelta(
                                      seconds=ctx.settings.lease_seconds))
                          .execution_options(synchronize_session=False))
    session.commit()
    if res.rowcount != 1:
        raise Conflict(f"frame {frame.id} was reviewed meanwhile; it cannot be reopened")
    session.refresh(frame)
    return frame


def version_out(v: MaskVersion, author: str | None, *, number: int | None = None) -> dict:
    return dict(version=v.id, number=number, frame_id=v.frame_id, kind=v.kind, author=author,
                created_at=v.created_at, sha256=v.sha256, size_bytes=v.size_bytes, width=v.width,
                height=v.height, base_version=v.base_version_id, restored_from=v.restored_from_id,
                source=v.source, decided_at=v.decided_at)


# ---- lifted labels --------------------------------------------------------------------------
# The class histogram of a scene's labels per workspace stamp and counted versions. Every
# editor polls labels/status (every 5 s); on a survey (32 M points) the histogram is a pass
# over 32 M labels -- before the first fill, the vote majority of the whole (32 M, C) vote
# table, about 5 GB of temporaries per call in each API process. Both change only with the
# files the stamp covers (labels, lifting state) or the versions the votes count.
_HIST_LOCK = threading.Lock()
_HIST: OrderedDict = OrderedDict()
_HIST_SIZE = 8


def _labels_histogram(ctx: AppContext, scene: Scene, included_idx: dict | None
                      ) -> tuple[str | None, dict[str, int], dict]:
    """(labels source "filled" / "direct" / None, {raw id: points} without 0, {frame index:
    version tag} the fill counted), cached per (workspace, stamp, counted versions)."""
    key = (str(scene.workspace), Workspace(scene.workspace).stamp(),
           tuple(sorted((int(k), str(v)) for k, v in (included_idx or {}).items())))
    with _HIST_LOCK:
        if key in _HIST:
            _HIST.move_to_end(key)
            return _HIST[key]
    source, labels, filled = None, None, {}
    res = load_labels(scene.workspace)
    if res is not None:
        labels, source = np.asarray(res.labels), "filled"
        filled = dict(res.stats.get("versions") or {})
    elif included_idx:
        labels, source = current_labels(ctx, scene), "direct"
    hist: dict[str, int] = {}
    if labels is not None:
        counts = np.bincount(labels, minlength=256)
        hist = {str(i): int(c) for i, c in enumerate(counts) if c and i != 0}
    val = (source, hist, filled)
    with _HIST_LOCK:
        _HIST[key] = val
        while len(_HIST) > _HIST_SIZE:
            _HIST.popitem(last=False)
    return val


def labels_status(*, session: Session, ctx: AppContext, scene: Scene) -> dict:
    available = True  # the lifting library is part of every installation
    st = ctx.lifting.status(scene.id)
    included_idx = ctx.lifting.included_versions(scene.id, scene.workspace)
    idx_to_id = dict(session.execute(select(Frame.index, Frame.id)
                                     .where(Frame.scene_id == scene.id)).all())
    included = {}
    for index, tag in (included_idx or {}).items():
        if index in idx_to_id:
            included[str(idx_to_id[index])] = int(tag) if tag and tag.isdigit() else None
    source, hist, filled_idx = _labels_histogram(ctx, scene, included_idx)
    filled: dict[str, int | None] = {}
    for index, tag in filled_idx.items():
        if int(index) in idx_to_id:
            filled[str(idx_to_id[int(index)])] = int(tag) if tag and str(tag).isdigit() else None
    return dict(lifting_available=available, included_versions=included,
                filled_versions=filled,
                pending_fill=st["pending_fill"], pending_frames=st["pending_frames"],
                fill_running=st["fill_running"], last_error=st["last_error"],
                lag_s=st.get("lag_s", 0.0),
                class_histogram=hist, labels_source=source)


def current_labels(ctx: AppContext, scene: Scene):
    """(N,) uint8 lifted labels: filled/denoised if available, else direct votes, else None."""

    res = load_labels(scene.workspace)
    if res is not None:
        return np.asarray(res.labels)
    state = ctx.lifting.state_for(scene.id, scene.workspace)
    return None if state is None else state.direct_labels()


def rendered(ctx: AppContext, scene: Scene, frame: Frame, *, downscale: int = 1) -> np.ndarray:
    """(H/s, W/s) uint8 lifted labels rendered into the frame (s = ``downscale``): the plain
    rendering the 2D agreement is measured against (holes between splats stay 0)."""
    labels = current_labels(ctx, scene)
    if labels is None:
        raise NotFound(f"scene {scene.id} has no lifted labels yet")
    ws_scene = ctx.load_scene(scene.workspace)
    img, _depth = render.render_labels(ws_scene, labels, frame.index, scale=1.0 / downscale)
    return np.asarray(img, dtype=np.uint8)


def prefill_image(ctx: AppContext, scene: Scene, frame: Frame, *, downscale: int = 1,
                  labels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What "Prefill from 3D" shows: the lifted labels (or ``labels``, per point) rendered
    into the frame with the holes between splats closed (occufly.render.render_prefill).
    Returns ((H/s, W/s) uint8 ids, bool "hole filled": pixels no point reached, labelled from
    the nearest rendered pixel -- the confidence image marks them as low confidence)."""
    if labels is None:
        labels = current_labels(ctx, scene)
    if labels is None:
        raise NotFound(f"scene {scene.id} has no lifted labels yet")
    ws_scene = ctx.load_scene(scene.workspace)
    img, _depth, filled = render.render_prefill(ws_scene, labels, frame.index,
                                                  scale=1.0 / downscale)
    return np.asarray(img, dtype=np.uint8), filled
