"""Reviewers' label corrections (issue 25): versioned 3D edits and proposed 2D mask changes
(notifications: :mod:`app.notifications`)."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, Boolean, DateTime, ForeignKey, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, utcnow

EDIT_STATES = ("active", "undone", "reverted", "dropped")


class CorrectionEdit(Base):
    """One relabel of a set of points: who, when, to which class, from which classes
    (``from_hist``: raw id -> points, as they were just before the edit), its state. The
    point ids live in ``Workspace.correction_edit(id)``; the net effect of the active edits
    in ``Workspace.overrides_path``."""

    __tablename__ = "correction_edits"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    author_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True, index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    to_class: Mapped[int] = mapped_column(Integer)  # raw id, 0 = unlabelled
    comment: Mapped[str | None] = mapped_column(Text, nullable=True)
    n_points: Mapped[int] = mapped_column(Integer)
    from_hist: Mapped[dict] = mapped_column(JSON, default=dict)
    frame_id: Mapped[int | None] = mapped_column(
        ForeignKey("frames.id", ondelete="SET NULL"), nullable=True)  # the view it was made in
    state: Mapped[str] = mapped_column(String(16), default="active", index=True)
    redoable: Mapped[bool] = mapped_column(Boolean, default=False)  # on its author's redo stack
    undone_by_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    undone_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    reverted_by_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    reverted_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)


class MaskProposal(Base):
    """A reviewer's proposed change of one frame's mask (from a 3D correction's projection):
    ``sha256`` a PNG of proposed raw ids, ``change_sha256`` a PNG of the change mask (255 where
    the proposal applies), both in the content store."""

    __tablename__ = "mask_proposals"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    frame_id: Mapped[int] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"), index=True)
    edit_id: Mapped[int | None] = mapped_column(
        ForeignKey("correction_edits.id", ondelete="SET NULL"), nullable=True)
    author_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    sha256: Mapped[str] = mapped_column(String(64))
    change_sha256: Mapped[str] = mapped_column(String(64))
    changed_px: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16), default="open")  # open / taken / declined
    reply: Mapped[str | None] = mapped_column(Text, nullable=True)
    decided_by_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    decided_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    taken_version_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
