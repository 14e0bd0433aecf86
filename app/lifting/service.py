"""The lifting worker: applies queued mask versions to each scene's votes, fills, publishes.

It consumes the ``lift_queue`` table (:mod:`app.lifting.queue`), in id order, which for one
frame is version order (a version can only become current after the one it replaces
committed). Per scene it owns the workspace's :class:`occufly.lifting.LiftState` (one writer:
a lock file in the data directory admits a single worker per data directory). For each batch
it keeps, per frame, the newest entry; older entries of the same frame in the batch are
``superseded`` (their votes would be replaced at once). An entry is applied exactly once:

- ``LiftState.apply_frame`` replaces the frame's votes and records the version tag on disk
  (crash-safe, repaired by ``LiftState.open``);
- the entry is marked ``applied`` afterwards; a worker killed in between finds the entry still
  pending on restart, sees the state already counts that version and only marks it.

After votes change, kNN fill + denoise runs in a per-scene thread once the scene has been
quiet for ``debounce_s`` (on a snapshot of the vote majority, so votes go on meanwhile). The
scene's ``lift_status.fill_state`` is ``due``/``running`` until the labels are written, so a
worker killed in the middle of a fill reruns it on restart; the fill is deterministic, so the
labels end identical to an uninterrupted run. Each fill publishes
``labels_updated(scene, stamp)`` (:mod:`app.lifting.events`); the review agreement of
submitted/reviewed frames is refreshed by a subscriber of that event in this process.

Wake-ups: PostgreSQL ``NOTIFY occufly_lift`` (sent in the save's transaction), an in-process
:meth:`LiftingService.wake` (embedded mode), and a poll every ``poll_s`` (SQLite, and a
safety net everywhere).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import func, select, update

from app.db import utcnow
from app.lifting.events import LIFT_CHANNEL, EventBus, Message, listen
from app.lifting.models import LiftQueueEntry, LiftStatus
from occufly.errors import OccuflyError

if TYPE_CHECKING:
    from app.context import AppContext

log = logging.getLogger("occufly.lifting")

LOCK_NAME = "lifting.lock"


class LiftingBusy(OccuflyError):
    """Another lifting worker already owns this data directory."""


@dataclass
class _Scene:
    scene_id: int
    workspace: str
    state: object  # occufly.lifting.LiftState
    lock: threading.Lock = field(default_factory=threading.Lock)  # updates vs snapshot
    fill_due: float | None = None
    filling: bool = False
    applying: bool = False
    fills: int = 0
    thread: threading.Thread | None = None


class LiftingService:
    RETRY_S = 5.0  # a scene whose entries cannot be applied is retried after this long

    def __init__(self, ctx: AppContext, bus: EventBus, *, debounce_s: float | None = None,
                 poll_s: float = 0.5, batch: int = 256) -> None:
        self.ctx = ctx
        self.bus = bus
        self.debounce_s = ctx.settings.fill_debounce_s if debounce_s is None else debounce_s
        self.poll_s = poll_s
        self.batch = batch
        self._scenes: dict[int, _Scene] = {}
        self._scenes_lock = threading.Lock()
        self._cv = threading.Condition()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._hints: dict[tuple[int, int], object] = {}  # (frame id, version id) -> mask
        self._seq = 0
        self._backoff: dict[int, float] = {}  # scene id -> monotonic time to retry it
        self._lock_fd: int | None = None
        self.applied = 0  # entries applied by this process (tests, benchmarks)

    # ---- lifecycle --------------------------------------------------------------------------
    def acquire(self) -> None:
        """Take the data directory's worker lock or raise :class:`LiftingBusy`."""
        import fcntl

        path = Path(self.ctx.settings.data_dir) / LOCK_NAME
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise LiftingBusy(f"{path}: another lifting worker is running for this data "
                              "directory") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd

    def start(self) -> None:
        if self._lock_fd is None:
            self.acquire()
        with self.ctx.sessions() as s:
            self._seq = s.scalar(select(func.max(LiftQueueEntry.applied_seq))) or 0
        self.bus.subscribe("labels_updated", self._refresh_agreement)
        self._recover()
        t = threading.Thread(target=self._vote_loop, name="occufly-lift-votes", daemon=True)
        t.start()
        self._threads.append(t)
        if self.bus.is_postgres:
            t = threading.Thread(target=listen, name="occufly-lift-listen", daemon=True,
                                 args=(self.ctx.engine, (LIFT_CHANNEL,)),
                                 kwargs=dict(stop=self._stop, on_wake=self._wake.set,
                                             timeout_s=self.poll_s))
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        with self._cv:
            self._cv.notify_all()
        for t in self._threads + [sc.thread for sc in self._scenes.values() if sc.thread]:
            t.join(timeout=60)
        for sc in self._scenes.values():
            close = getattr(sc.state, "close", None)
            if close is not None:
                close()
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def run_forever(self) -> None:
        """Standalone worker: run until SIGTERM/SIGINT."""
        import signal

        def _term(_sig, _frm) -> None:  # noqa: ANN001
            self._stop.set()
            self._wake.set()

        signal.signal(signal.SIGTERM, _term)
        signal.signal(signal.SIGINT, _term)
        self.start()
        log.info("lifting worker %s running (pid %s)", self.bus.origin, os.getpid())
        while not self._stop.wait(1.0):
            pass
        self.stop()

    def wake(self) -> None:
        self._wake.set()

    def hint(self, frame_id: int, version_id: int, mask) -> None:  # noqa: ANN001
        """The decoded upload of ``version_id`` (embedded mode: saves a second PNG decode)."""
        with self._cv:
            if len(self._hints) > 64:
                self._hints.clear()
            self._hints[(frame_id, version_id)] = mask

    # ---- status (this process) ------------------------------------------------------------
    def busy(self, scene_id: int) -> dict:
        sc = self._scenes.get(scene_id)
        if sc is None:
            return {"applying": False, "fill_due": False, "filling": False}
        with self._cv:
            return {"applying": sc.applying, "fill_due": sc.fill_due is not None,
                    "filling": sc.filling}

    # ---- recovery ---------------------------------------------------------------------------
    def _recover(self) -> None:
        """Scenes whose fill was due or running when the last worker stopped fill again; so do
        scenes whose stored labels count other versions than the votes."""
        from app.scenes.models import Scene
        from occufly.workspace import Workspace

        with self.ctx.sessions() as s:
            rows = s.execute(select(LiftStatus.scene_id, LiftStatus.fill_state, Scene.workspace)
                             .join(Scene, Scene.id == LiftStatus.scene_id)).all()
        for sid, fill_state, ws in rows:
            try:
                sc = self._scene(sid, ws)
            except Exception:  # noqa: BLE001 - a broken workspace must not stop the others
                log.exception("lifting: cannot open the state of scene %s", sid)
                continue
            counted = {str(k): v for k, v in sc.state.included_versions().items()}
            stale = Workspace(ws).lift_stats().get("versions") != counted and bool(counted)
            if fill_state in ("due", "running") or stale:
                log.info("lifting: scene %s resumes an unfinished fill", sid)
                self._schedule_fill(sc, delay=0.0)

    # ---- votes ------------------------------------------------------------------------------
    def _vote_loop(self) -> None:
        while not self._stop.is_set():
            try:
                n = self.process_pending()
            except Exception:  # noqa: BLE001 - database away: retry after a pause
                log.exception("lifting: processing the queue failed")
                n = 0
                self._stop.wait(1.0)
            if n == 0:
                self._wake.wait(self.poll_s)
                self._wake.clear()

    def process_pending(self) -> int:
        """Apply up to ``batch`` pending entries; returns how many were processed."""
        from app.annotations.models import MaskVersion
        from app.scenes.models import Scene

        now = time.monotonic()
        waiting = [sid for sid, t in self._backoff.items() if t > now]
        q = (select(LiftQueueEntry.id, LiftQueueEntry.scene_id, LiftQueueEntry.frame_id,
                    LiftQueueEntry.frame_index, LiftQueueEntry.version_id, MaskVersion.sha256,
                    Scene.workspace)
             .outerjoin(MaskVersion, MaskVersion.id == LiftQueueEntry.version_id)
             .join(Scene, Scene.id == LiftQueueEntry.scene_id)
             .where(LiftQueueEntry.status == "pending"))
        if waiting:  # a scene that just failed must not hold up the others
            q = q.where(LiftQueueEntry.scene_id.not_in(waiting))
        with self.ctx.sessions() as s:
            rows = s.execute(q.order_by(LiftQueueEntry.id).limit(self.batch)).all()
        by_scene: dict[int, list] = {}
        for r in rows:
            by_scene.setdefault(r.scene_id, []).append(r)
        for sid, entries in by_scene.items():
            if self._stop.is_set():
                break
            try:
                self._apply_scene(sid, entries)
                self._backoff.pop(sid, None)
            except Exception as e:  # noqa: BLE001 - e.g. a workspace being re-imported
                log.exception("lifting: scene %s; retrying in %.0f s", sid, self.RETRY_S)
                self._backoff[sid] = time.monotonic() + self.RETRY_S
                try:
                    with self.ctx.sessions() as s:
                        self._set_status(s, sid, last_error=f"{type(e).__name__}: {e}")
                        s.commit()
                except Exception:  # noqa: BLE001 - the database itself is away
                    log.warning("lifting: cannot record the error of scene %s", sid)
        return len(rows)

    def _apply_scene(self, scene_id: int, entries: list) -> None:
        sc = self._scene(scene_id, entries[0].workspace)
        newest: dict[int, object] = {}
        for r in entries:  # id order = version order per frame
            newest[r.frame_index] = r
        outcome: dict[int, tuple[str, str | None]] = {}
        for r in entries:
            if newest[r.frame_index] is not r:
                outcome[r.id] = ("superseded", None)
        changed = False
        with self._cv:
            sc.applying = True
        try:
            for fi, r in newest.items():
                try:
                    changed |= self._apply_entry(sc, r)
                    outcome[r.id] = ("applied", None)
                except OccuflyError as e:  # a mask the scene cannot take: report, go on
                    log.warning("lifting: entry %s (frame %s v%s): %s", r.id, fi, r.version_id, e)
                    outcome[r.id] = ("failed", str(e)[:500])
            with self.ctx.sessions() as s:
                now = utcnow()
                for r in entries:
                    self._seq += 1
                    st, err = outcome[r.id]
                    s.execute(update(LiftQueueEntry).where(LiftQueueEntry.id == r.id).values(
                        status=st, error=err, applied_at=now, applied_seq=self._seq))
                errors = [e for st, e in outcome.values() if e]
                self._set_status(s, scene_id, fill_state="due" if changed else None,
                                 last_error=errors[-1] if errors else None, clear_error=not errors)
                s.commit()
            self.applied += sum(1 for st, _ in outcome.values() if st == "applied")
        finally:
            with self._cv:
                sc.applying = False
                self._cv.notify_all()
        if changed:
            self._schedule_fill(sc)

    def _apply_entry(self, sc: _Scene, r) -> bool:  # noqa: ANN001
        """Make the state count exactly entry ``r``'s version; False if it already did."""
        state = sc.state
        fi = int(r.frame_index)
        tag = None if r.version_id is None else str(r.version_id)
        if tag is None:
            if fi not in state.included_versions():
                return False
            with sc.lock:
                state.remove_frame(fi)
            return True
        if state.version_of(fi) == tag and fi in state.included_versions():
            return False  # counted before a restart: exactly once
        with self._cv:
            mask = self._hints.pop((r.frame_id, r.version_id), None)
        if mask is None:
            from app.pipeline import stored_mask_ids

            mask = stored_mask_ids(self.ctx.store.get(r.sha256), state.scene.taxonomy)
        with sc.lock:
            state.apply_frame(fi, mask, version=tag, name=f"mask version {r.version_id}")
        return True

    def _scene(self, scene_id: int, workspace: str) -> _Scene:
        with self._scenes_lock:
            sc = self._scenes.get(scene_id)
            if sc is not None and sc.workspace == str(workspace):
                return sc
            from occufly.lifting import LiftState

            state = LiftState.open(Path(workspace), self.ctx.load_scene(str(workspace)))
            sc = _Scene(scene_id, str(workspace), state)
            sc.thread = threading.Thread(target=self._fill_loop, args=(sc,), daemon=True,
                                         name=f"occufly-fill-{scene_id}")
            self._scenes[scene_id] = sc
            sc.thread.start()
            return sc

    def _set_status(self, s, scene_id: int, *, fill_state: str | None = None,  # noqa: ANN001
                    last_error: str | None = None, clear_error: bool = False,
                    bump_fills: bool = False, **values) -> None:
        row = s.get(LiftStatus, scene_id)
        if row is None:
            row = LiftStatus(scene_id=scene_id, fill_state="idle", fills=0)
            s.add(row)
        if fill_state is not None and not (fill_state == "due" and row.fill_state == "running"):
            row.fill_state = fill_state  # a running fill stays "running"; it reschedules itself
        if last_error is not None:
            row.last_error = last_error[:500]
        elif clear_error:
            row.last_error = None
        if bump_fills:
            row.fills = (row.fills or 0) + 1
        for k, v in values.items():
            setattr(row, k, v)
        row.updated_at = utcnow()

    # ---- fill -------------------------------------------------------------------------------
    def _schedule_fill(self, sc: _Scene, delay: float | None = None) -> None:
        with self._cv:
            sc.fill_due = time.monotonic() + (self.debounce_s if delay is None else delay)
            self._cv.notify_all()

    def _fill_loop(self, sc: _Scene) -> None:
        while not self._stop.is_set():
            with self._cv:
                while not self._stop.is_set() and (
                        sc.fill_due is None or sc.applying or time.monotonic() < sc.fill_due):
                    wait = 1.0 if sc.fill_due is None else max(0.01, sc.fill_due - time.monotonic())
                    self._cv.wait(min(wait, 1.0))
                if self._stop.is_set():
                    return
                sc.fill_due = None
                sc.filling = True
            error = None
            try:
                with self.ctx.sessions() as s:
                    self._set_status(s, sc.scene_id, fill_state="running")
                    s.commit()
                self._fill(sc)
            except Exception as e:  # noqa: BLE001 - keep the worker alive, report in status
                log.exception("lifting: fill/denoise of scene %s", sc.scene_id)
                error = f"{type(e).__name__}: {e}"
            finally:
                with self._cv:
                    sc.filling = False
                    again = sc.fill_due is not None
                try:
                    with self.ctx.sessions() as s:
                        self._set_status(s, sc.scene_id, fill_state="due" if again else "idle",
                                         last_error=error)
                        s.commit()
                except Exception:  # noqa: BLE001
                    log.exception("lifting: status of scene %s", sc.scene_id)
                with self._cv:
                    self._cv.notify_all()

    def _fill(self, sc: _Scene) -> None:
        """Snapshot the vote majority under the update lock, fill/denoise without it, publish."""
        from occufly.workspace import Workspace

        with sc.lock:
            snap = sc.state.snapshot()
        sc.state.fill_and_denoise(snapshot=snap)
        sc.fills += 1
        stamp = Workspace(sc.workspace).stamp()
        with self.ctx.sessions() as s:
            self._set_status(s, sc.scene_id, labels_stamp=stamp, bump_fills=True)
            s.commit()
        self.bus.publish("labels_updated", sc.scene_id, stamp=stamp,
                         versions={str(k): v for k, v in sorted(snap.versions.items())},
                         fills=sc.fills)

    # ---- subscribers ------------------------------------------------------------------------
    MAX_AGREEMENT_FRAMES = 200

    def _refresh_agreement(self, msg: Message) -> None:
        """Recompute the stored per-frame agreement (the frame list's disagreement sort) of
        submitted/reviewed frames against the new labels; best effort."""
        from app.review.service import frame_agreement
        from app.scenes.models import Frame, Scene

        with self.ctx.sessions() as s:
            scene = s.get(Scene, msg.scene_id)
            if scene is None:
                return
            frames = list(s.scalars(
                select(Frame).where(Frame.scene_id == scene.id,
                                    Frame.current_version_id.is_not(None),
                                    Frame.state.in_(("submitted", "accepted", "rejected")))
                .order_by(Frame.index).limit(self.MAX_AGREEMENT_FRAMES)))
            for f in frames:
                if self._stop.is_set():
                    return
                try:
                    frame_agreement(self.ctx, s, scene, f)
                except Exception:  # noqa: BLE001 - a frame that cannot be rendered keeps its value
                    log.warning("agreement of frame %s failed", f.id, exc_info=True)
                    s.rollback()
