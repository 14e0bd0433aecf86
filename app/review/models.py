from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, DateTime, ForeignKey, Integer, String, Text, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, utcnow


class ReviewItem(Base):
    """An issue pinned to a frame pixel and/or a set of 3D point ids, with a comment thread."""

    __tablename__ = "review_items"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    frame_id: Mapped[int | None] = mapped_column(
        ForeignKey("frames.id", ondelete="CASCADE"), nullable=True, index=True)
    pixel_x: Mapped[int | None] = mapped_column(Integer, nullable=True)
    pixel_y: Mapped[int | None] = mapped_column(Integer, nullable=True)
    point_ids: Mapped[list | None] = mapped_column(JSON, nullable=True)
    status: Mapped[str] = mapped_column(String(16), default="open")
    author_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    resolved_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)


class ReviewComment(Base):
    __tablename__ = "review_comments"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    item_id: Mapped[int] = mapped_column(
        ForeignKey("review_items.id", ondelete="CASCADE"), index=True)
    # indexed (migration 0013): the per-user comment quota counts a user's last hour
    author_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True, index=True)
    text: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class SuspectMark(Base):
    """A reviewer's verdict on one suspect (contested region) of a scene: done (looked at and
    fixed) or dismissed (nothing wrong). Shared by the scene's reviewers; ``key`` is the
    suspect's stable key (its smallest point id, ``p<id>``), so a mark survives re-rankings."""

    __tablename__ = "suspect_marks"
    __table_args__ = (UniqueConstraint("scene_id", "key", name="uq_suspect_marks_scene_id_key"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    key: Mapped[str] = mapped_column(String(32))
    status: Mapped[str] = mapped_column(String(16))
    author_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
