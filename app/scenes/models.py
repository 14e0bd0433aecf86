from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, Boolean, DateTime, Float, ForeignKey, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, utcnow

FRAME_STATES = ("unassigned", "in_progress", "submitted", "accepted", "rejected")


class Scene(Base):
    __tablename__ = "scenes"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(128), unique=True)
    status: Mapped[str] = mapped_column(String(16), default="importing")  # importing|ready|failed
    workspace: Mapped[str] = mapped_column(String(1024))
    source: Mapped[str | None] = mapped_column(String(1024), nullable=True)
    n_frames: Mapped[int] = mapped_column(Integer, default=0)
    n_points: Mapped[int] = mapped_column(Integer, default=0)
    n_selected: Mapped[int] = mapped_column(Integer, default=0)
    coverage: Mapped[float | None] = mapped_column(Float, nullable=True)
    selection: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Frame(Base):
    __tablename__ = "frames"
    __table_args__ = (UniqueConstraint("scene_id", "index"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    index: Mapped[int] = mapped_column(Integer)
    name: Mapped[str] = mapped_column(String(512))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    altitude: Mapped[float | None] = mapped_column(Float, nullable=True)
    nominal_altitude: Mapped[int | None] = mapped_column(Integer, nullable=True)
    selected: Mapped[bool] = mapped_column(Boolean, default=False)
    state: Mapped[str] = mapped_column(String(16), default="unassigned")
    assignee_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True, index=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    current_version_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    last_annotator_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    agreement: Mapped[float | None] = mapped_column(Float, nullable=True)
    # issue 23 (migration 0007): agreement is the leave-one-out one; the old self-agreement,
    # the share of painted pixels with independent evidence and the painted share beside it
    self_agreement: Mapped[float | None] = mapped_column(Float, nullable=True)
    independent_coverage: Mapped[float | None] = mapped_column(Float, nullable=True)
    painted_share: Mapped[float | None] = mapped_column(Float, nullable=True)
    # migration 0011: the review list's ranking score (occufly.lifting.loo.review_score;
    # higher = look first; None = not scored yet or no independent labels in the frame)
    review_score: Mapped[float | None] = mapped_column(Float, nullable=True)
    reviewed_by_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    reviewed_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    # the mask version the last accept/reject decided on (an export names it per frame)
    reviewed_version_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # the version whose votes count for this frame (the newest submitted / accepted / imported
    # one, None after a rejection or before any submit; app.annotations.service, provenance)
    voting_version_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # position in which "next" hands the selected frames out (app.scenes.service.handout_order;
    # None: not selected, or selected before this column existed -> after the ranked, by index)
    handout_rank: Mapped[int | None] = mapped_column(Integer, nullable=True)


class SceneMember(Base):
    """An annotator or reviewer assigned to a scene: they see only their scenes (admins all)."""

    __tablename__ = "scene_members"
    __table_args__ = (UniqueConstraint("scene_id", "user_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class IdCounter(Base):
    """The last id handed out per table where SQLite would reuse one (issue 36: a new scene
    took a deleted scene's id, and the audit log mixed the two); migration 0012."""

    __tablename__ = "id_counters"

    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    last_id: Mapped[int] = mapped_column(Integer)
