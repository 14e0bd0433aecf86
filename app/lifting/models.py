"""Tables of the lifting service: the durable queue, per-scene status and the event log."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import JSON, DateTime, ForeignKey, Index, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from app.db import Base, utcnow

QUEUE_STATES = ("pending", "applied", "superseded", "failed")
FILL_STATES = ("idle", "due", "running")
# how the live lifting decides a scene's votes (issue 37; LiftStatus.model): one annotator
# model for every painter (the robust decision's pooled matrix) or one confusion matrix per
# mask author (occufly.lifting.confusion). The descriptions are what the admin console shows;
# the figures are docs/lifting.md's (issue 37, seventh round). Region consistency
# (occufly.lifting.regions) is not offered here: on one benchmark scene it repainted true
# facades as roof and cost 1.05 accuracy points (the command line keeps it, --regions).
LIFT_MODELS = {
    "pooled": "The default: the robust decision with one confusion matrix fitted over every "
              "mask, whoever painted it. Best when the painters make the same kind of errors.",
    "per_author": "A confusion matrix per mask author, for a team where one painter "
                  "systematically swaps two classes (see Quality, per painter): where the others "
                  "see the same points, that painter is outvoted. On the benchmark scenes with "
                  "such a painter, +1.2 to +14.7 points of accuracy; where everyone is hurried "
                  "in the same way, little change in accuracy and up to 3.6 points of mIoU "
                  "lost. Fills take about 1.3x to 2x as long.",
}


class LiftQueueEntry(Base):
    """"Frame F of scene S has version V": inserted in the transaction that makes V current,
    so an acknowledged save is never missing from the queue (nothing is lost while the
    lifting worker is down). ``version_id`` None = the frame has no mask any more."""

    __tablename__ = "lift_queue"
    __table_args__ = (Index("ix_lift_queue_status_id", "status", "id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    frame_id: Mapped[int] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"))
    frame_index: Mapped[int] = mapped_column(Integer)
    version_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    status: Mapped[str] = mapped_column(String(16), default="pending")
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    applied_at: Mapped[datetime | None] = mapped_column(DateTime, nullable=True)
    # order in which the scene's owning worker processed its entries (1, 2, ... per scene)
    applied_seq: Mapped[int | None] = mapped_column(Integer, nullable=True)
    # the worker (EventBus.origin: host:pid:id) that processed the entry
    applied_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error: Mapped[str | None] = mapped_column(String(512), nullable=True)


class LiftStatus(Base):
    """What the lifting worker is doing for a scene (read by every API process)."""

    __tablename__ = "lift_status"

    scene_id: Mapped[int] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"),
                                          primary_key=True)
    fill_state: Mapped[str] = mapped_column(String(16), default="idle")
    fills: Mapped[int] = mapped_column(Integer, default=0)
    labels_stamp: Mapped[str | None] = mapped_column(String(64), nullable=True)
    last_error: Mapped[str | None] = mapped_column(String(512), nullable=True)
    updated_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    # LIFT_MODELS (migration 0014): set by an admin, read by the worker at every fill
    model: Mapped[str] = mapped_column(String(16), default="pooled", server_default="pooled")


class Event(Base):
    """An event published to every process (``labels_updated`` ...), kept for a while so a
    subscriber that polls (SQLite) or reconnects (PostgreSQL) misses nothing recent."""

    __tablename__ = "events"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    scene_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    payload: Mapped[dict] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow, index=True)
