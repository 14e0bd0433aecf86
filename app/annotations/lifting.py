"""Live lifting: each stored mask version updates the scene's point votes in the background.

One vote thread per scene owns that scene's :class:`occufly.lifting.LiftState` (which is
not safe for concurrent writers); a second thread per scene runs kNN fill + denoise on a
snapshot of the vote majority taken under the state lock, so a long fill never delays the
next mask's votes. A notification only says "frame F of scene S changed"; the
worker then reads the frame's *current* version from the database, so notifications may
arrive out of order or be coalesced without ever applying an older mask over a newer one.
After votes change, kNN fill + denoise is rerun once the scene has been quiet for
``fill_debounce_s`` seconds.

:meth:`LiftingManager.apply` is the single call into the lifting library.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from app.context import AppContext

log = logging.getLogger("occufly.lifting")


@dataclass
class _SceneWorker:
    scene_id: int
    dirty_frames: set[int] = field(default_factory=set)  # frame ids
    cond: threading.Condition = field(default_factory=threading.Condition)
    busy: bool = False
    fill_due: float | None = None
    filling: bool = False
    state: object | None = None
    last_error: str | None = None
    thread: threading.Thread | None = None
    fill_thread: threading.Thread | None = None
    state_lock: threading.Lock = field(default_factory=threading.Lock)
    fills: int = 0
    included: dict | None = None  # snapshot of state.included_versions(), updated by the worker
    decoded: dict = field(default_factory=dict)  # frame id -> (version id, (h, w) uint8 mask)


class LiftingManager:
    def __init__(self, ctx_getter, *, debounce_s: float = 5.0, enabled: bool = True) -> None:
        self._ctx_getter = ctx_getter
        self.debounce_s = debounce_s
        self.enabled = enabled
        self._workers: dict[int, _SceneWorker] = {}
        self._lock = threading.Lock()
        self._stop = False

    @property
    def ctx(self) -> AppContext:
        return self._ctx_getter()

    # ---- public -----------------------------------------------------------------------------
    def notify(self, scene_id: int, frame_id: int, *, version_id: int | None = None,
               mask=None) -> None:  # noqa: ANN001
        """Frame ``frame_id`` changed; ``mask`` (the decoded upload of ``version_id``) saves the
        worker a second PNG decode."""
        if not self.enabled or self._stop:
            return
        w = self._worker(scene_id)
        with w.cond:
            if mask is not None and version_id is not None:
                w.decoded[frame_id] = (version_id, mask)
            w.dirty_frames.add(frame_id)
            w.cond.notify_all()

    def status(self, scene_id: int) -> dict:
        w = self._workers.get(scene_id)
        if w is None:
            return {"pending_fill": False, "pending_frames": 0, "fill_running": False,
                    "last_error": None}
        with w.cond:
            return {"pending_fill": w.fill_due is not None or w.filling,
                    "pending_frames": len(w.dirty_frames) + (1 if w.busy else 0),
                    "fill_running": w.filling, "last_error": w.last_error}

    def included_versions(self, scene_id: int, workspace: str) -> dict[int, str | None] | None:
        """frame_index -> version tag counted in the votes, or None without lifting."""
        if not self.enabled:
            return None
        w = self._worker(scene_id)
        if w.included is None:
            state = self._state(w, workspace)
            if state is None:
                return None
        with w.cond:
            return dict(w.included or {})

    def state_for(self, scene_id: int, workspace: str):
        """The scene's LiftState shared with its worker (opened once), or None without lifting."""
        if not self.enabled:
            from app import pipeline

            return pipeline.open_lift_state(workspace, self.ctx.load_scene(workspace))
        return self._state(self._worker(scene_id), workspace)

    def wait_idle(self, scene_id: int, timeout: float = 10.0, *, include_fill: bool = False) -> bool:
        w = self._workers.get(scene_id)
        if w is None:
            return True
        end = time.monotonic() + timeout
        with w.cond:
            while w.dirty_frames or w.busy or (include_fill and (w.fill_due or w.filling)):
                left = end - time.monotonic()
                if left <= 0:
                    return False
                w.cond.wait(min(left, 0.05))
        return True

    def stop(self) -> None:
        self._stop = True
        for w in list(self._workers.values()):
            with w.cond:
                w.cond.notify_all()
        for w in list(self._workers.values()):
            for t in (w.thread, w.fill_thread):
                if t is not None:
                    t.join(timeout=60)

    # ---- internals --------------------------------------------------------------------------
    def _worker(self, scene_id: int) -> _SceneWorker:
        with self._lock:
            w = self._workers.get(scene_id)
            if w is None:
                w = _SceneWorker(scene_id)
                w.thread = threading.Thread(target=self._loop, args=(w,), daemon=True,
                                            name=f"occufly-lift-{scene_id}")
                w.fill_thread = threading.Thread(target=self._fill_loop, args=(w,), daemon=True,
                                                 name=f"occufly-fill-{scene_id}")
                self._workers[scene_id] = w
                w.thread.start()
                w.fill_thread.start()
            return w

    def _state(self, w: _SceneWorker, workspace: str):
        from app import pipeline

        if w.state is None:
            with w.cond:
                if w.state is None:
                    w.state = pipeline.open_lift_state(workspace, self.ctx.load_scene(workspace))
                    if w.state is not None:
                        w.included = dict(w.state.included_versions())
        return w.state

    def _loop(self, w: _SceneWorker) -> None:
        """Vote thread: apply changed frames as soon as they are notified."""
        while not self._stop:
            with w.cond:
                while not self._stop and not w.dirty_frames:
                    w.cond.wait(1.0)
                if self._stop:
                    return
                frames = sorted(w.dirty_frames)
                w.dirty_frames.clear()
                w.busy = True
            try:
                if self._apply_frames(w, frames):
                    with w.cond:
                        w.fill_due = time.monotonic() + self.debounce_s
                w.last_error = None
            except Exception as e:  # noqa: BLE001 - keep the worker alive, report in status
                log.exception("live lifting for scene %s", w.scene_id)
                w.last_error = f"{type(e).__name__}: {e}"
            finally:
                with w.cond:
                    w.busy = False
                    w.cond.notify_all()

    def _fill_loop(self, w: _SceneWorker) -> None:
        """Fill thread: rerun fill + denoise once votes have been quiet for ``debounce_s``."""
        while not self._stop:
            with w.cond:
                while not self._stop and (w.fill_due is None or w.busy or w.dirty_frames
                                          or time.monotonic() < w.fill_due):
                    wait = 1.0 if w.fill_due is None else max(0.01, w.fill_due - time.monotonic())
                    w.cond.wait(min(wait, 1.0))
                if self._stop:
                    return
                w.fill_due = None
                w.filling = True
            try:
                self._fill(w)
            except Exception as e:  # noqa: BLE001
                log.exception("fill/denoise for scene %s", w.scene_id)
                w.last_error = f"{type(e).__name__}: {e}"
            finally:
                with w.cond:
                    w.filling = False
                    w.cond.notify_all()

    def _apply_frames(self, w: _SceneWorker, frame_ids: list[int]) -> int:
        from sqlalchemy import select

        from app.annotations.models import MaskVersion
        from app.scenes.models import Frame, Scene

        ctx = self.ctx
        with ctx.sessions() as s:
            scene = s.get(Scene, w.scene_id)
            rows = s.execute(select(Frame.index, Frame.current_version_id, MaskVersion.sha256,
                                    Frame.id)
                             .outerjoin(MaskVersion, MaskVersion.id == Frame.current_version_id)
                             .where(Frame.id.in_(frame_ids))).all()
            workspace = scene.workspace
        state = self._state(w, workspace)
        if state is None:
            return 0
        changed = 0
        try:
            for index, version_id, sha, fid in rows:
                with w.cond:
                    hit = w.decoded.pop(fid, None)
                mask = hit[1] if hit is not None and hit[0] == version_id else None
                with w.state_lock:
                    changed += self.apply(state, ctx, index, version_id, sha, mask=mask)
        finally:
            snapshot = dict(state.included_versions())
            with w.cond:
                w.included = snapshot
        return changed

    @staticmethod
    def apply(state, ctx: AppContext, frame_index: int, version_id: int | None,
              sha256: str | None, *, mask=None) -> int:  # noqa: ANN001
        """Make ``state`` count exactly frame ``frame_index``'s version ``version_id``."""
        tag = None if version_id is None else str(version_id)
        if state.included_versions().get(frame_index) == tag and (
                tag is not None or frame_index not in state.included_versions()):
            return 0
        if version_id is None:
            state.remove_mask(frame_index)
            return 1
        if mask is None:
            from app.pipeline import stored_mask_ids

            mask = stored_mask_ids(ctx.store.get(sha256), state.scene.taxonomy)
        state.set_mask(frame_index, mask, version=tag, name=f"mask version {version_id}")
        return 1

    def _fill(self, w: _SceneWorker) -> None:
        """Snapshot the vote majority under the state lock, then fill/denoise without it."""
        import numpy as np

        state = w.state
        if state is None:
            return
        try:
            from occufly.lifting import fill_and_denoise, save_result
            snapshot = state._direct  # noqa: SLF001 - the first step of state.fill_and_denoise
        except (ImportError, AttributeError):
            with w.state_lock:  # older lifting: whole fill under the lock
                state.fill_and_denoise()
            w.fills += 1
            return
        with w.state_lock:
            direct, margin, top = snapshot()
            versions = {str(k): v for k, v in state.included_versions().items()}
        scene = state.scene
        result = fill_and_denoise(np.asarray(scene.xyz), direct, scene.taxonomy,
                                  vote_margin=margin, vote_top=top)
        result.stats["annotated_frames"] = len(versions)
        result.stats["versions"] = versions
        save_result(state.ws, result)
        w.fills += 1
        self._refresh_agreement(w)

    MAX_AGREEMENT_FRAMES = 200

    def _refresh_agreement(self, w: _SceneWorker) -> None:
        """Recompute the stored per-frame agreement (the frame list's disagreement sort) of
        submitted/reviewed frames against the new labels; off the vote path, best effort."""
        from sqlalchemy import select

        from app.review.service import frame_agreement
        from app.scenes.models import Frame, Scene

        ctx = self.ctx
        with ctx.sessions() as s:
            scene = s.get(Scene, w.scene_id)
            frames = list(s.scalars(
                select(Frame).where(Frame.scene_id == w.scene_id,
                                    Frame.current_version_id.is_not(None),
                                    Frame.state.in_(("submitted", "accepted", "rejected")))
                .order_by(Frame.index).limit(self.MAX_AGREEMENT_FRAMES)))
            for f in frames:
                if self._stop:
                    return
                try:
                    frame_agreement(ctx, s, scene, f)
                except Exception:  # noqa: BLE001 - a frame that cannot be rendered keeps its value
                    log.warning("agreement of frame %s failed", f.id, exc_info=True)
                    s.rollback()
