"""What an API process knows of lifting (``ctx.lifting``): enqueue, wake, status, read-only votes.

Nothing here holds lifting state: the queue and status live in the database, the votes and
labels in the workspace (read read-only). With ``mode="embedded"`` (the default of a single
``occufly serve``) this process also runs the :class:`~app.lifting.service.LiftingService`
in threads; with ``"external"`` a separate ``occufly lifting-worker`` does (``occufly serve
--workers N`` starts one); ``"off"`` disables live lifting.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from sqlalchemy import func, select, text

from app.db import utcnow
from app.events import LIFT_CHANNEL
from app.lifting.models import LIFT_MODELS, LiftQueueEntry, LiftStatus
from app.lifting.service import LiftingBusy, LiftingService
from occufly.errors import WorkspaceError
from occufly.lifting import VoteStore

if TYPE_CHECKING:
    from sqlalchemy.orm import Session, sessionmaker

    from occufly.scene import Scene

log = logging.getLogger("occufly.lifting")

MODES = ("embedded", "external", "off")


class LiftingClient:
    def __init__(self, *, sessions: sessionmaker[Session], load_scene: Callable[[str], Scene],
                 make_service: Callable[[], LiftingService], mode: str = "embedded") -> None:
        """sessions: the database; load_scene: the process's scene cache; make_service: builds
        the lifting service this process runs in embedded mode (the composition root's
        :func:`app.bootstrap.build_lifting_service`)."""
        if mode not in MODES:
            raise ValueError(f"lifting mode must be one of {MODES}, got {mode!r}")
        self.sessions = sessions
        self.load_scene = load_scene
        self.make_service = make_service
        self.mode = mode
        self.service: LiftingService | None = None

    @property
    def enabled(self) -> bool:
        return self.mode != "off"

    # ---- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        """Embedded mode: run the lifting service in this process, unless another worker
        already owns the data directory (then this process only enqueues)."""
        if self.mode != "embedded" or self.service is not None:
            return

        svc = self.make_service()
        try:
            svc.acquire()
        except LiftingBusy as e:
            log.info("%s; this process only enqueues", e)
            return
        svc.start()
        self.service = svc

    def stop(self) -> None:
        if self.service is not None:
            self.service.stop()
            self.service = None

    # ---- the save path ----------------------------------------------------------------------
    def enqueue(self, session, frame, version_id: int | None) -> None:  # noqa: ANN001
        """Queue "frame has version V" in the caller's transaction (commit makes it durable
        together with the save; on PostgreSQL the worker is woken by NOTIFY at commit)."""
        if not self.enabled:
            return
        session.add(LiftQueueEntry(scene_id=frame.scene_id, frame_id=frame.id,
                                   frame_index=frame.index, version_id=version_id,
                                   status="pending"))
        if session.get_bind().dialect.name == "postgresql":
            session.execute(text("SELECT pg_notify(:c, :p)"),
                            {"c": LIFT_CHANNEL, "p": str(frame.scene_id)})

    def notify(self, scene_id: int, frame_id: int, *, version_id: int | None = None,
               mask=None) -> None:  # noqa: ANN001
        """After the commit: wake an in-process worker (``mask``, the decoded upload of
        ``version_id``, saves it a second decode)."""
        svc = self.service
        if svc is None:
            return
        if mask is not None and version_id is not None:
            svc.offer_decoded(frame_id, version_id, mask)
        svc.wake()

    # ---- how the votes are decided (issue 37) ------------------------------------------------
    def model(self, session, scene_id: int) -> str:  # noqa: ANN001
        """The scene's annotator model (:data:`~app.lifting.models.LIFT_MODELS`)."""
        row = session.get(LiftStatus, scene_id)
        return row.model if row is not None and row.model in LIFT_MODELS else "pooled"

    def set_model(self, session, scene_id: int, model: str) -> bool:  # noqa: ANN001
        """Set the scene's annotator model in the caller's transaction; True if it changed.
        A scene that has been lifted is marked due, so the worker that takes it fills again
        (the caller publishes ``lifting_model_changed`` after the commit: its owner fills at
        once)."""
        if model not in LIFT_MODELS:
            raise ValueError(f"model must be one of {sorted(LIFT_MODELS)}, got {model!r}")
        row = session.get(LiftStatus, scene_id)
        if row is None:  # nothing lifted yet: the first fill uses it
            session.add(LiftStatus(scene_id=scene_id, fill_state="idle", fills=0, model=model,
                                   updated_at=utcnow()))
            return model != "pooled"
        if row.model == model:
            return False
        row.model = model
        if self.enabled and row.fills:
            if row.fill_state != "running":
                row.fill_state = "due"
        row.updated_at = utcnow()
        return True

    # ---- status -----------------------------------------------------------------------------
    def status(self, scene_id: int) -> dict:
        with self.sessions() as s:
            pending = s.scalar(select(func.count()).select_from(LiftQueueEntry).where(
                LiftQueueEntry.scene_id == scene_id, LiftQueueEntry.status == "pending")) or 0
            row = s.get(LiftStatus, scene_id)
            oldest = s.scalar(select(func.min(LiftQueueEntry.created_at)).where(
                LiftQueueEntry.scene_id == scene_id, LiftQueueEntry.status == "pending"))
        # lag: seconds since the oldest entry of the scene still waiting to be lifted (0 = none)

        lag_s = max(0.0, (utcnow() - oldest).total_seconds()) if oldest is not None else 0.0
        fill_state = row.fill_state if row is not None else "idle"
        busy = self.service.busy(scene_id) if self.service is not None else {}
        return {"pending_fill": fill_state in ("due", "running") or bool(busy.get("fill_due")),
                "pending_frames": int(pending),
                "fill_running": fill_state == "running",
                "last_error": row.last_error if row is not None else None,
                "lag_s": round(lag_s, 1),
                "model": row.model if row is not None and row.model in LIFT_MODELS else "pooled"}

    def wait_idle(self, scene_id: int, timeout: float = 10.0, *, include_fill: bool = False) -> bool:
        """Until the scene's queue is empty (and, with ``include_fill``, its fill finished and
        the review's after-fill refresh with it)."""
        end = time.monotonic() + timeout
        while True:
            st = self.status(scene_id)
            busy = self.service.busy(scene_id) if self.service is not None else {}
            idle = st["pending_frames"] == 0 and not busy.get("applying")
            if include_fill:  # the fill and what follows it (the review's refresh)
                idle = idle and not st["pending_fill"] and not busy.get("filling") \
                    and not busy.get("refreshing")
            if idle:
                return True
            if time.monotonic() >= end:
                return False
            time.sleep(0.05)

    # ---- read-only views of the votes -------------------------------------------------------
    def state_for(self, scene_id: int, workspace: str):  # noqa: ARG002
        """The scene's vote state opened read-only, or None (no state yet / mid-update)."""
        scene = self.load_scene(str(workspace))
        for _ in range(20):  # an update in progress marks the state dirty for milliseconds
            try:
                return VoteStore.open(workspace, scene, read_only=True)
            except WorkspaceError as e:
                if "no lifting state" in str(e):
                    return None
                time.sleep(0.05)
        return None

    def included_versions(self, scene_id: int, workspace: str) -> dict[int, str | None] | None:
        """frame_index -> version tag counted in the votes ({} before the first; None when
        lifting is off)."""
        if not self.enabled:
            return None
        state = self.state_for(scene_id, workspace)
        if state is None:
            return {}
        try:
            return dict(state.included_versions())
        finally:
            close = getattr(state, "close", None)
            if close is not None:
                close()
