from __future__ import annotations

from datetime import datetime

from sqlalchemy import DateTime, ForeignKey, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, utcnow

#: a version's state (docs/provenance.md). ``draft``: autosaved, informs only its own frame's
#: editor; ``submitted``: handed in for review; ``accepted`` / ``rejected``: a reviewer decided
#: on it; ``conflict``: an upload that lost a race (kept, never current); ``imported``: brought
#: in from another tool by an admin.
VERSION_KINDS = ("draft", "submitted", "accepted", "rejected", "conflict", "imported")
#: the states whose newest version of a frame votes (Frame.voting_version_id) -- unless a
#: rejected version is newer: a rejection withdraws the frame's votes until the next submit
VOTING_KINDS = ("submitted", "accepted", "imported")
#: the kinds ``store_version`` creates (accept/reject turn a stored version into a decided one)
STORED_KINDS = ("draft", "submitted", "imported")


class MaskVersion(Base):
    """One stored mask upload. The PNG lives in the content-addressed store under ``sha256``."""

    __tablename__ = "mask_versions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    frame_id: Mapped[int] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(16))  # the state: one of VERSION_KINDS
    # where it came from: None / "editor" (painted here), "reviewer_correction", "import:cvat",
    # "import:coco", ... (free text, at most 64 characters)
    source: Mapped[str | None] = mapped_column(String(64), nullable=True)
    # who accepted / rejected this version, and when (None while nobody has decided on it)
    decided_by_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    decided_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    author_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    sha256: Mapped[str] = mapped_column(String(64), index=True)
    size_bytes: Mapped[int] = mapped_column(Integer)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    base_version_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    restored_from_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # annotation effort, recorded for submitted versions (issue 17): the prefill the author
    # started from (None = painted from an empty mask), the pixels carrying a class or 255 in
    # this mask (what painting from scratch costs) and the pixels that differ from the prefill
    prefill_id: Mapped[int | None] = mapped_column(
        ForeignKey("prefills.id", ondelete="SET NULL"), nullable=True)
    painted_px: Mapped[int | None] = mapped_column(Integer, nullable=True)
    changed_px: Mapped[int | None] = mapped_column(Integer, nullable=True)


class Prefill(Base):
    """One prefill handed to a user (``GET /frames/{fid}/prefill``): the rendered lifted labels
    as stored in the content store, so a later submit can count what the person changed."""

    __tablename__ = "prefills"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    frame_id: Mapped[int] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"), index=True)
    user_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    sha256: Mapped[str] = mapped_column(String(64), index=True)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    labelled_px: Mapped[int] = mapped_column(Integer)  # pixels the prefill gives a class
    masks: Mapped[int | None] = mapped_column(Integer, nullable=True)  # masks lifted into it
