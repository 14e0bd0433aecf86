from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, DateTime, ForeignKey, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, utcnow

AUDIT_ACTIONS = (
    "login", "login_failed", "logout", "mask_save", "mask_submit", "mask_restore", "review_accept",
    "review_reject", "review_undo", "import", "export", "job", "user_create", "user_update",
    "password_change", "password_reset", "user_unlock", "session_revoke", "membership", "backup",
    "lifting_model",
)


class AuditEvent(Base):
    """Who did what, when: one row per security- or data-relevant action (append only)."""

    __tablename__ = "audit_events"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    at: Mapped[datetime] = mapped_column(DateTime, default=utcnow, index=True)
    actor_id: Mapped[int | None] = mapped_column(
        ForeignKey("users.id", ondelete="SET NULL"), nullable=True, index=True)
    actor: Mapped[str | None] = mapped_column(String(64), nullable=True)  # name at the time
    action: Mapped[str] = mapped_column(String(32), index=True)
    scene_id: Mapped[int | None] = mapped_column(Integer, nullable=True, index=True)
    frame_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    target: Mapped[str | None] = mapped_column(String(256), nullable=True)
    client_ip: Mapped[str | None] = mapped_column(String(64), nullable=True)
    detail: Mapped[dict | None] = mapped_column(JSON, nullable=True)
