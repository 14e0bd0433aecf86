"""The lifting worker: applies queued mask versions to each scene's votes, fills, publishes.

It consumes the ``lift_queue`` table (:class:`app.lifting.models.LiftQueueEntry`), in id order, which for one
frame is version order (a version can only become current after the one it replaces
committed). Per scene one worker owns the workspace's :class:`occufly.lifting.VoteStore`
(one writer per scene):

- PostgreSQL: a session-level advisory lock ``(PG_SCENE_LOCK, scene id)`` held on the worker's
  own connection. Any number of workers, on any hosts sharing the data volume, split the
  scenes: each live worker holds a slot lock ``(PG_SLOT_LOCK, n)``, a scene belongs to the
  live slot that wins its rendezvous hash, and a worker hands back an idle scene that hashes
  to another (new) worker. A worker that dies (``kill -9``, host lost) drops its connection;
  PostgreSQL releases its locks and the survivors take its scenes over (the vote state repairs
  itself on open, an interrupted fill reruns).
- SQLite: one worker per data directory (a lock file in it, single host) owns every scene.

For each batch it keeps, per frame, the newest entry; older entries of the same frame (in the
batch or still pending after it) are ``superseded`` without decoding them. The masks of a
batch are decoded and projected in a thread pool (PNG decoding and the numpy projection
release the GIL) and applied to the votes one at a time, in queue order. An entry is applied
exactly once:

- ``VoteStore.apply_frame`` replaces the frame's votes and records the version tag on disk
  (crash-safe, repaired by ``VoteStore.open``);
- the entry is marked ``applied`` (with a per-scene ``applied_seq`` and ``applied_by``, the
  worker) afterwards; a worker killed in between leaves the entry pending, and whichever
  worker owns the scene next sees the state already counts that version and only marks it.

Each applied batch publishes one ``votes_applied(scene, seq, versions)`` event. After votes
change, kNN fill + denoise runs in a per-scene thread once the scene has been quiet for
``debounce_s`` (at the latest ``MAX_WAIT_DEBOUNCES`` debounces after the first change, so a
busy scene is not starved) on a snapshot of the vote majority, so votes go on meanwhile. The
scene's ``lift_status.fill_state`` is ``due``/``running`` until the labels are written, so a
worker killed in the middle of a fill reruns it on restart (or on the worker that takes the
scene over); the fill is deterministic, so the labels end identical to an uninterrupted run.
Each fill publishes ``labels_updated(scene, stamp, seq)`` once (:mod:`app.events`);
the review agreement of submitted/reviewed frames is refreshed by a subscriber of that event
in the worker owning the scene.

Wake-ups: PostgreSQL ``NOTIFY occufly_lift`` (sent in the save's transaction), an in-process
:meth:`LiftingService.wake` (embedded mode), and a poll every ``poll_s`` (SQLite, and a
safety net everywhere).
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import psycopg
from sqlalchemy import func, select, update

from app.annotations.models import MaskVersion
from app.db import utcnow
from app.events import (
    LIFT_CHANNEL,
    EventBus,
    Message,
    listen,
    psycopg_dsn,
    stop_channel_name,
    wake_listener,
)
from app.lifting.models import LIFT_MODELS, LiftQueueEntry, LiftStatus
from app.pipeline import stored_mask_ids
from app.scenes.models import Scene
from occufly.errors import OccuflyError
from occufly.lifting import LiftParams, RobustParams, VoteStore
from occufly.lifting.confusion import ConfusionParams, load_frame_votes
from occufly.lifting.incremental import IncrementalFill
from occufly.workspace import Workspace

if TYPE_CHECKING:
    from collections.abc import Callable

    from sqlalchemy.engine import Engine
    from sqlalchemy.orm import Session, sessionmaker

    from app.blobs import BlobStore
    from app.config import Settings
    from occufly.scene import Scene as WorkspaceScene

    # a subscriber of the scenes this worker owns: (event, the service's stop event)
    OwnedSubscriber = Callable[[Message, threading.Event], None]

log = logging.getLogger("occufly.lifting")

LOCK_NAME = "lifting.lock"
# PostgreSQL advisory lock keys (two-int form): (PG_SCENE_LOCK, scene id) = the worker that
# owns the scene's vote state; (PG_SLOT_LOCK, n) = a live worker's slot
PG_SCENE_LOCK = 0x4F43
PG_SLOT_LOCK = 0x4F44
MAX_SLOTS = 4096


class LiftingBusy(OccuflyError):
    """Another lifting worker already owns this data directory (SQLite: one per host)."""


def preferred_slot(scene_id: int, slots: list[int]) -> int | None:
    """The live worker slot a scene belongs to: rendezvous (highest random weight) hashing, so
    a worker joining or leaving moves only the scenes that hash to it."""
    if not slots:
        return None
    def weight(n: int) -> bytes:
        return hashlib.blake2b(f"{scene_id}:{n}".encode(), digest_size=8).digest()

    return max(slots, key=lambda n: (weight(n), n))


class PgLocks:
    """The session-level advisory locks of one worker, on one dedicated autocommit connection
    (the locks live as long as it does: a killed worker's are released by the server)."""

    def __init__(self, engine, name: str = "") -> None:  # noqa: ANN001
        self.dsn = psycopg_dsn(engine)
        self.name = name  # the connection's application_name (pg_stat_activity)
        self.conn = None
        self.slot: int | None = None
        self._mu = threading.Lock()

    def connect(self) -> int:
        with self._mu:
            self.conn = psycopg.connect(self.dsn, autocommit=True,
                                        application_name=f"occufly-lifting {self.name}"[:63])
            for n in range(MAX_SLOTS):
                if self.conn.execute("SELECT pg_try_advisory_lock(%s, %s)",
                                     (PG_SLOT_LOCK, n)).fetchone()[0]:
                    self.slot = n
                    return n
        raise LiftingBusy(f"{MAX_SLOTS} lifting workers already run on this database")

    def alive(self) -> bool:
        with self._mu:
            if self.conn is None:
                return False
            try:
                self.conn.execute("SELECT 1")
                return True
            except Exception:  # noqa: BLE001 - connection lost: every lock with it
                return False

    def try_scene(self, scene_id: int) -> bool:
        with self._mu:
            return bool(self.conn.execute("SELECT pg_try_advisory_lock(%s, %s)",
                                          (PG_SCENE_LOCK, int(scene_id))).fetchone()[0])

    def release_scene(self, scene_id: int) -> None:
        with self._mu:
            self.conn.execute("SELECT pg_advisory_unlock(%s, %s)", (PG_SCENE_LOCK, int(scene_id)))

    def live_slots(self) -> list[int]:
        with self._mu:
            rows = self.conn.execute(
                "SELECT objid FROM pg_locks WHERE locktype = 'advisory' AND classid = %s "
                "AND objsubid = 2 AND granted AND database = (SELECT oid FROM pg_database "
                "WHERE datname = current_database())", (PG_SLOT_LOCK,)).fetchall()
        return sorted(int(r[0]) for r in rows)

    def close(self) -> None:
        with self._mu:
            if self.conn is not None:
                try:
                    self.conn.close()
                except Exception:  # noqa: BLE001
                    pass
            self.conn = None
            self.slot = None


@dataclass
class _SceneWork:
    """What this worker holds for one scene it owns: the open vote store, its update lock, the
    pending fill's timing and the last applied queue entry."""

    scene_id: int
    workspace: str
    state: object  # occufly.lifting.VoteStore
    lock: threading.Lock = field(default_factory=threading.Lock)  # updates vs snapshot
    fill_due: float | None = None
    first_due: float | None = None  # when the pending fill was first asked for
    # a fill decided with the held robust model (issue 37, eighth round): when the quiet scene
    # is filled again with the model refitted (Settings.fill_settle_s)
    settle_due: float | None = None
    filling: bool = False
    seq: int = 0  # applied_seq of the last entry this worker processed for the scene
    incremental: object | None = None  # occufly.lifting.incremental.IncrementalFill
    closed: bool = False  # handed back to another worker: the fill thread ends
    applying: bool = False
    fills: int = 0
    thread: threading.Thread | None = None


def _next_due(sc: _SceneWork) -> float | None:
    """When the scene's fill thread runs next: the pending fill, else the settle fill."""
    return sc.fill_due if sc.fill_due is not None else sc.settle_due


def lower_thread_priority(nice: int) -> None:
    """Add ``nice`` to the calling thread's niceness (Linux: a thread is a task with its own
    nice value; the threads it starts inherit it). The fill is the lifting worker's heavy,
    latency-tolerant work (seconds of CPU per submit); a save waits for its request thread,
    so on a busy host the fill yields the CPU to it. No-op where it is not supported."""
    if nice <= 0 or not hasattr(os, "setpriority"):
        return
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except OSError:  # not permitted / not supported: run at the normal priority
        log.info("lifting: could not lower the fill thread's priority", exc_info=True)


AUTHOR_CHUNK = 500  # version ids per IN (...) query


def version_painters(session: Session, version_ids) -> dict[int, tuple[int | None, str | None]]:  # noqa: ANN001
    """version id -> (who painted it, its source): the author, or None for a version
    imported from another tool (``source`` ``import:...``: the importing admin did not paint
    it) or without an author -- the one rule of who painted a mask (the lifting's painters,
    the quality report's per-painter sums)."""
    ids = sorted({int(v) for v in version_ids})
    out: dict[int, tuple[int | None, str | None]] = {}
    for i in range(0, len(ids), AUTHOR_CHUNK):
        for vid, uid, src in session.execute(
                select(MaskVersion.id, MaskVersion.author_id, MaskVersion.source)
                .where(MaskVersion.id.in_(ids[i:i + AUTHOR_CHUNK]))):
            out[vid] = (None if (src or "").startswith("import:") else uid, src)
    return out


def decision_for(session: Session, scene_id: int, versions: dict
                 ) -> tuple[str, LiftParams | None, dict | None]:
    """How a fill of scene ``scene_id`` counting ``versions`` (frame index -> mask version id
    or tag) decides its votes: (model, LiftParams or None for the default, frame -> who
    painted it or None) from the scene's annotator model (``LiftStatus.model``, set by an
    admin). The live worker and an export's relift both use it, so an export's labels are
    decided as the live ones are.

    The painter of a frame is the author of the version its votes count; a version imported
    from another tool (``source`` ``import:...``: the importing admin is not who painted it)
    or without an author is a painter of its own."""
    model = session.scalar(select(LiftStatus.model).where(LiftStatus.scene_id == scene_id))
    if model not in LIFT_MODELS or model == "pooled":
        return "pooled", None, None
    tags = {int(f): int(v) for f, v in versions.items() if v is not None and str(v).isdigit()}
    info = version_painters(session, tags.values())
    rp = RobustParams(confusion=ConfusionParams())  # per_author
    return model, LiftParams(robust_params=rp), {
        f: uid for f, v in tags.items() if (uid := info.get(v, (None, None))[0]) is not None}


class LiftingService:
    RETRY_S = 5.0  # a scene whose entries cannot be applied is retried after this long
    TAKEOVER_S = 5.0  # a scene waiting this long is taken by any worker, not only its own
    MAX_WAIT_DEBOUNCES = 3  # a fill waits at most this many debounces after the first change

    def __init__(self, *, settings: Settings, engine: Engine, sessions: sessionmaker[Session],
                 store: BlobStore, load_scene: Callable[[str], WorkspaceScene], bus: EventBus,
                 on_owned_labels: tuple[OwnedSubscriber, ...] = (),
                 debounce_s: float | None = None, poll_s: float = 0.5, batch: int = 256,
                 decode_threads: int | None = None) -> None:
        """on_owned_labels: ``labels_updated`` subscribers for the scenes this worker owns
        (the composition root's; e.g. the review's agreement refresh), called with the event
        and this service's stop event in the fill's thread; one that hands its work to the
        background has ``busy(scene_id)`` (:meth:`busy`'s ``refreshing``; ``wait_idle`` with
        ``include_fill`` waits for it) and ``close()`` (called by :meth:`stop`)."""
        self.settings = settings
        self.engine = engine
        self.sessions = sessions
        self.store = store
        self.load_scene = load_scene
        self.bus = bus
        self.on_owned_labels = tuple(on_owned_labels)
        self.debounce_s = settings.fill_debounce_s if debounce_s is None else debounce_s
        self.poll_s = poll_s
        self._stop_channel = stop_channel_name()  # ends the LISTEN thread's wait on stop()
        self.batch = batch
        self._scenes: dict[int, _SceneWork] = {}
        self._scenes_lock = threading.Lock()
        self._cv = threading.Condition()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._decoded: dict[tuple[int, int], object] = {}  # (frame id, version id) -> mask
        self._backoff: dict[int, float] = {}  # scene id -> monotonic time to retry it
        self._lock_fd: int | None = None
        self._pg: PgLocks | None = None  # PostgreSQL: advisory locks (scenes, worker slot)
        self._locked: set[int] = set()  # PostgreSQL: the scenes whose lock this worker holds
        self.decode_threads = decode_threads or max(1, min(4, os.cpu_count() or 1))
        self._pool: ThreadPoolExecutor | None = None
        self.applied = 0  # entries applied by this process (tests, benchmarks)
        self.name = bus.origin  # lift_queue.applied_by

    # ---- lifecycle --------------------------------------------------------------------------
    @property
    def distributed(self) -> bool:
        """PostgreSQL: scenes are shared between workers by advisory locks."""
        return self.bus.is_postgres

    def acquire(self) -> None:
        """PostgreSQL: open the advisory-lock connection and take a worker slot (any number of
        workers, on any host). SQLite: take the data directory's worker lock or raise
        :class:`LiftingBusy` (one worker per data directory, on one host)."""
        if self.distributed:
            if self._pg is None:
                self._pg = PgLocks(self.engine, self.name)
                slot = self._pg.connect()
                log.info("lifting worker %s: PostgreSQL advisory locks, slot %s", self.name, slot)
            return

        path = Path(self.settings.data_dir) / LOCK_NAME
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise LiftingBusy(f"{path}: another lifting worker is running for this data "
                              "directory (SQLite: one lifting worker per data directory, on "
                              "one host; use PostgreSQL to run several)") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd
        log.info("lifting worker %s: SQLite, single-host file lock %s (one worker owns every "
                 "scene)", self.name, path)

    def start(self) -> None:
        if self._lock_fd is None and self._pg is None:
            self.acquire()
        self._pool = ThreadPoolExecutor(self.decode_threads, thread_name_prefix="occufly-decode")
        for fn in self.on_owned_labels:
            self.bus.subscribe("labels_updated", self._owned_only(fn))
        # an admin changed how a scene's votes are decided: its owner fills again at once
        self.bus.subscribe("lifting_model_changed", self._owned_only(self._on_model_changed))
        if not self.distributed:
            self._recover()
        t = threading.Thread(target=self._vote_loop, name="occufly-lift-votes", daemon=True)
        t.start()
        self._threads.append(t)
        if self.bus.is_postgres:
            t = threading.Thread(target=listen, name="occufly-lift-listen", daemon=True,
                                 args=(self.engine, (LIFT_CHANNEL,)),
                                 kwargs=dict(stop=self._stop, on_wake=self._wake.set,
                                             timeout_s=self.poll_s,
                                             stop_channel=self._stop_channel))
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self.bus.is_postgres and self._threads:
            wake_listener(self.engine, self._stop_channel)
        with self._cv:
            self._cv.notify_all()
        for t in self._threads + [sc.thread for sc in self._scenes.values() if sc.thread]:
            t.join(timeout=60)
        for fn in self.on_owned_labels:  # a subscriber's background work (a child process)
            close = getattr(fn, "close", None)
            if close is not None:
                close()
        for sc in self._scenes.values():
            close = getattr(sc.state, "close", None)
            if close is not None:
                close()
        self._scenes.clear()
        self._locked.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        if self._pg is not None:
            self._pg.close()  # releases the slot and every scene lock
            self._pg = None

    def run_forever(self) -> None:
        """Standalone worker: run until SIGTERM/SIGINT."""
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

    def offer_decoded(self, frame_id: int, version_id: int, mask) -> None:  # noqa: ANN001
        """The decoded upload of ``version_id`` (embedded mode: saves a second PNG decode)."""
        with self._cv:
            if len(self._decoded) > 64:
                self._decoded.clear()
            self._decoded[(frame_id, version_id)] = mask

    # ---- status (this process) ------------------------------------------------------------
    def busy(self, scene_id: int) -> dict:
        sc = self._scenes.get(scene_id)
        if sc is None:
            return {"applying": False, "fill_due": False, "filling": False,
                    "refreshing": self.refreshing(scene_id)}
        with self._cv:
            out = {"applying": sc.applying, "fill_due": sc.fill_due is not None,
                   "filling": sc.filling}
        out["refreshing"] = self.refreshing(scene_id)
        return out

    def refreshing(self, scene_id: int) -> bool:
        """Whether a subscriber that works in the background (one with a ``busy(scene_id)``,
        e.g. :class:`app.review.refresher.ReviewRefresher`) still works on the scene."""
        return any(getattr(fn, "busy", None) is not None and fn.busy(scene_id)
                   for fn in self.on_owned_labels)

    # ---- recovery ---------------------------------------------------------------------------
    def _recover(self) -> None:
        """SQLite (this worker owns every scene): recover each scene with a status row."""
        with self.sessions() as s:
            sids = list(s.scalars(select(LiftStatus.scene_id)))
        for sid in sids:
            self._recover_scene(sid)

    def _recover_scene(self, sid: int) -> None:
        """A scene whose fill was due or running when its last owner stopped fills again; so
        does a scene whose stored labels count other versions than the votes."""
        with self.sessions() as s:
            row = s.execute(select(LiftStatus.fill_state, Scene.workspace)
                            .join(Scene, Scene.id == LiftStatus.scene_id)
                            .where(LiftStatus.scene_id == sid)).first()
        if row is None:
            return
        fill_state, ws = row
        try:
            sc = self._scene(sid, ws)
        except Exception:  # noqa: BLE001 - a broken workspace must not stop the others
            log.exception("lifting: cannot open the state of scene %s", sid)
            return
        counted = {str(k): v for k, v in sc.state.included_versions().items()}
        stale = Workspace(ws).lift_stats().get("versions") != counted and bool(counted)
        if fill_state in ("due", "running") or stale:
            log.info("lifting: scene %s resumes an unfinished fill", sid)
            self._schedule_fill(sc, delay=0.0)

    # ---- scene ownership (PostgreSQL) --------------------------------------------------------
    def owned(self) -> set[int] | None:
        """PostgreSQL: the scene ids whose lock this worker holds; SQLite: None (all)."""
        if not self.distributed:
            return None
        with self._scenes_lock:
            return set(self._locked)

    def _claim(self) -> None:
        """Take the scenes with work that belong to this worker (or that waited too long for
        theirs), hand back idle ones that belong to another live worker."""
        pg = self._pg
        if pg is None:
            return
        if not pg.alive():  # every lock went with the connection: another worker may own them
            log.warning("lifting: the advisory-lock connection was lost; dropping %d scenes",
                        len(self._scenes))
            for sid in self.owned() or ():
                self._drop_scene(sid, unlock=False)
            pg.close()
            pg.connect()
        slots = pg.live_slots()
        now = utcnow()
        with self.sessions() as s:
            waiting = dict(s.execute(select(LiftQueueEntry.scene_id,
                                            func.min(LiftQueueEntry.created_at))
                                     .where(LiftQueueEntry.status == "pending")
                                     .group_by(LiftQueueEntry.scene_id)).all())
            for sid in s.scalars(select(LiftStatus.scene_id).where(
                    LiftStatus.fill_state.in_(("due", "running")))):
                waiting.setdefault(sid, None)
        mine = self.owned()
        for sid, oldest in waiting.items():
            if sid in mine or self._stop.is_set():
                continue
            overdue = oldest is not None and (now - oldest).total_seconds() > self.TAKEOVER_S
            if preferred_slot(sid, slots) != pg.slot and not overdue:
                continue
            if not pg.try_scene(sid):
                continue  # another worker owns it
            log.info("lifting worker %s (slot %s) takes scene %s", self.name, pg.slot, sid)
            with self._scenes_lock:
                self._locked.add(sid)
            self._recover_scene(sid)
        for sid in mine:
            if preferred_slot(sid, slots) == pg.slot or sid in waiting:
                continue
            sc = self._scenes.get(sid)
            if sc is None or not (sc.applying or sc.filling or sc.fill_due is not None):
                log.info("lifting worker %s hands scene %s to slot %s", self.name, sid,
                         preferred_slot(sid, slots))
                self._drop_scene(sid)

    def _drop_scene(self, sid: int, *, unlock: bool = True) -> None:
        with self._scenes_lock:
            sc = self._scenes.pop(sid, None)
            self._locked.discard(sid)
        if sc is not None:
            with self._cv:
                sc.closed = True
                self._cv.notify_all()
            if sc.thread is not None and sc.thread is not threading.current_thread():
                sc.thread.join(timeout=60)
            close = getattr(sc.state, "close", None)
            if close is not None:
                close()
        if unlock and self._pg is not None:
            try:
                self._pg.release_scene(sid)
            except Exception:  # noqa: BLE001 - connection lost: released with it
                log.warning("lifting: releasing scene %s", sid, exc_info=True)

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
        """Apply up to ``batch`` pending entries of the scenes this worker owns; returns how
        many were processed."""
        self._claim()
        owned = self.owned()
        if owned is not None and not owned:
            return 0
        now = time.monotonic()
        waiting = [sid for sid, t in self._backoff.items() if t > now]
        q = (select(LiftQueueEntry.id, LiftQueueEntry.scene_id, LiftQueueEntry.frame_id,
                    LiftQueueEntry.frame_index, LiftQueueEntry.version_id, MaskVersion.sha256,
                    Scene.workspace)
             .outerjoin(MaskVersion, MaskVersion.id == LiftQueueEntry.version_id)
             .join(Scene, Scene.id == LiftQueueEntry.scene_id)
             .where(LiftQueueEntry.status == "pending"))
        if owned is not None:
            q = q.where(LiftQueueEntry.scene_id.in_(sorted(owned)))
        if waiting:  # a scene that just failed must not hold up the others
            q = q.where(LiftQueueEntry.scene_id.not_in(waiting))
        with self.sessions() as s:
            rows = s.execute(q.order_by(LiftQueueEntry.id).limit(self.batch)).all()
            newest_pending = {}
            if len(rows) == self.batch:  # entries beyond the batch may supersede some in it
                frames = sorted({r.frame_id for r in rows})
                newest_pending = dict(s.execute(
                    select(LiftQueueEntry.frame_id, func.max(LiftQueueEntry.id))
                    .where(LiftQueueEntry.status == "pending",
                           LiftQueueEntry.frame_id.in_(frames))
                    .group_by(LiftQueueEntry.frame_id)).all())
        by_scene: dict[int, list] = {}
        for r in rows:
            by_scene.setdefault(r.scene_id, []).append(r)
        for sid, entries in by_scene.items():
            if self._stop.is_set():
                break
            try:
                self._apply_scene(sid, entries, newest_pending)
                self._backoff.pop(sid, None)
            except Exception as e:  # noqa: BLE001 - e.g. a workspace being re-imported
                log.exception("lifting: scene %s; retrying in %.0f s", sid, self.RETRY_S)
                self._backoff[sid] = time.monotonic() + self.RETRY_S
                try:
                    with self.sessions() as s:
                        self._set_status(s, sid, last_error=f"{type(e).__name__}: {e}")
                        s.commit()
                except Exception:  # noqa: BLE001 - the database itself is away
                    log.warning("lifting: cannot record the error of scene %s", sid)
        return len(rows)

    def _apply_scene(self, scene_id: int, entries: list, newest_pending: dict | None = None
                     ) -> None:
        sc = self._scene(scene_id, entries[0].workspace)
        newest: dict[int, object] = {}
        for r in entries:  # id order = version order per frame
            newest[r.frame_index] = r
        outcome: dict[int, tuple[str, str | None]] = {}
        for r in entries:
            later = (newest_pending or {}).get(r.frame_id)
            if newest[r.frame_index] is not r or (later is not None and later > r.id):
                outcome[r.id] = ("superseded", None)  # never decoded
        todo = sorted((r for r in newest.values() if r.id not in outcome), key=lambda r: r.id)
        changed = False
        with self._cv:
            sc.applying = True
        try:
            # decode + project in the pool (a window of a few masks ahead), apply in order
            window = self.decode_threads + 1
            futs: dict[int, object] = {}

            def submit(i: int) -> None:
                if i < len(todo) and self._pool is not None:
                    futs[i] = self._pool.submit(self._votes_of, sc, todo[i])

            for i in range(window):
                submit(i)
            for i, r in enumerate(todo):
                fut = futs.pop(i, None)
                try:
                    votes = fut.result() if fut is not None else self._votes_of(sc, r)
                    changed |= self._apply_entry(sc, r, votes)
                    outcome[r.id] = ("applied", None)
                except OccuflyError as e:  # a mask the scene cannot take: report, go on
                    log.warning("lifting: entry %s (frame %s v%s): %s", r.id, r.frame_index,
                                r.version_id, e)
                    outcome[r.id] = ("failed", str(e)[:500])
                finally:
                    submit(i + window)
            with self.sessions() as s:
                now = utcnow()
                seq = s.scalar(select(func.max(LiftQueueEntry.applied_seq)).where(
                    LiftQueueEntry.scene_id == scene_id)) or 0
                for r in entries:
                    seq += 1
                    st, err = outcome[r.id]
                    s.execute(update(LiftQueueEntry).where(LiftQueueEntry.id == r.id).values(
                        status=st, error=err, applied_at=now, applied_seq=seq,
                        applied_by=self.name[:64]))
                errors = [e for st, e in outcome.values() if e]
                self._set_status(s, scene_id, fill_state="due" if changed else None,
                                 last_error=errors[-1] if errors else None, clear_error=not errors)
                s.commit()
            sc.seq = seq
            self.applied += sum(1 for st, _ in outcome.values() if st == "applied")
        finally:
            with self._cv:
                sc.applying = False
                self._cv.notify_all()
        self.bus.publish("votes_applied", scene_id, seq=seq, applied_by=self.name,
                         versions={str(r.frame_index): (None if r.version_id is None
                                                        else str(r.version_id))
                                   for r in todo if outcome[r.id][0] == "applied"})
        if changed:
            self._schedule_fill(sc)

    def _votes_of(self, sc: _SceneWork, r):  # noqa: ANN001
        """The votes of entry ``r``'s mask (pool thread: decode + projection, reads only), or
        None when there is nothing to decode (no mask any more, or already counted)."""
        state = sc.state
        fi = int(r.frame_index)
        if r.version_id is None:
            return None
        tag = str(r.version_id)
        if state.version_of(fi) == tag and fi in state.included_versions():
            return None
        with self._cv:
            mask = self._decoded.pop((r.frame_id, r.version_id), None)
        if mask is None:
            mask = stored_mask_ids(self.store.get(r.sha256), state.scene.taxonomy)
        return state.frame_votes(fi, mask, name=f"mask version {r.version_id}")

    def _apply_entry(self, sc: _SceneWork, r, votes=None) -> bool:  # noqa: ANN001
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
        if votes is None:
            votes = self._votes_of(sc, r)
        with sc.lock:
            state.apply_frame(fi, None, votes=votes, version=tag,
                              name=f"mask version {r.version_id}")
        return True

    def _scene(self, scene_id: int, workspace: str) -> _SceneWork:
        with self._scenes_lock:
            sc = self._scenes.get(scene_id)
            if sc is not None and sc.workspace == str(workspace):
                return sc
            if sc is not None:  # re-imported elsewhere: the old state's fill thread ends
                sc.closed = True

            state = VoteStore.open(Path(workspace), self.load_scene(str(workspace)))
            sc = _SceneWork(scene_id, str(workspace), state)
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
    def _schedule_fill(self, sc: _SceneWork, delay: float | None = None) -> None:
        """Fill once the scene has been quiet for ``debounce_s`` (``delay``), but no later than
        ``MAX_WAIT_DEBOUNCES`` debounces after the first change it covers."""
        now = time.monotonic()
        with self._cv:
            if sc.first_due is None:
                sc.first_due = now
            due = now + (self.debounce_s if delay is None else delay)
            sc.fill_due = min(due, sc.first_due + self.MAX_WAIT_DEBOUNCES * self.debounce_s)
            self._cv.notify_all()

    def _fill_loop(self, sc: _SceneWork) -> None:
        lower_thread_priority(self.settings.fill_nice)
        while not self._stop.is_set() and not sc.closed:
            with self._cv:
                while not self._stop.is_set() and not sc.closed and (
                        _next_due(sc) is None or sc.applying or time.monotonic() < _next_due(sc)):
                    due = _next_due(sc)
                    wait = 1.0 if due is None else max(0.01, due - time.monotonic())
                    self._cv.wait(min(wait, 1.0))
                if self._stop.is_set() or sc.closed:
                    return
                settling = sc.fill_due is None  # woken by the settle timer alone
                sc.fill_due = None
                sc.first_due = None
                sc.settle_due = None
                sc.filling = True
            error = None
            try:
                with self.sessions() as s:
                    self._set_status(s, sc.scene_id, fill_state="running")
                    s.commit()
                if settling and sc.incremental is not None:
                    sc.incremental.held.clear()  # the quiet scene: fit the model again
                self._fill(sc)
            except Exception as e:  # noqa: BLE001 - keep the worker alive, report in status
                log.exception("lifting: fill/denoise of scene %s", sc.scene_id)
                error = f"{type(e).__name__}: {e}"
            finally:
                with self._cv:
                    sc.filling = False
                    again = sc.fill_due is not None
                try:
                    with self.sessions() as s:
                        self._set_status(s, sc.scene_id, fill_state="due" if again else "idle",
                                         last_error=error)
                        s.commit()
                except Exception:  # noqa: BLE001
                    log.exception("lifting: status of scene %s", sc.scene_id)
                with self._cv:
                    self._cv.notify_all()

    def _fill(self, sc: _SceneWork) -> None:
        """Snapshot the vote majority, fill/denoise, publish. The snapshot's pass over the counts
        runs without the update lock (a survey's: about a second, 5-7 s before it was
        compiled); the rows a vote update writes meanwhile are recomputed under the lock at
        the end (:meth:`VoteStore.snapshot_begin`), so no submit waits for the pass."""
        with sc.lock:
            sc.state.snapshot_begin()
        try:
            rows = sc.state.snapshot_rows()
        except BaseException:
            with sc.lock:
                sc.state.snapshot_cancel()
            raise
        with sc.lock:
            snap = sc.state.snapshot_finish(rows)
            seq = sc.seq
        if sc.incremental is None:  # the first fill of this worker is a full one
            sc.incremental = IncrementalFill(sc.state.scene.xyz, sc.state.scene.taxonomy)
        _model, params, annotators = self._decision(sc, snap)
        res = sc.state.fill_and_denoise(snapshot=snap, incremental=sc.incremental,
                                        params=params, annotators=annotators)
        inc = res.stats.get("incremental") or {}
        log.info("lifting: scene %s filled in %.2f s (%s)", sc.scene_id,
                 res.stats.get("seconds", 0.0) or 0.0,
                 f"incremental: {inc.get('updated_points')} points updated of "
                 f"{inc.get('region_points')} in context" if inc.get("incremental") else "full")
        sc.fills += 1
        settle = self.settings.fill_settle_s
        with self._cv:
            sc.settle_due = (time.monotonic() + settle
                             if res.stats.get("robust_warm") and settle > 0 else None)
        stamp = Workspace(sc.workspace).stamp()
        with self.sessions() as s:
            self._set_status(s, sc.scene_id, labels_stamp=stamp, bump_fills=True)
            s.commit()
        self.bus.publish("labels_updated", sc.scene_id, stamp=stamp,
                         versions={str(k): v for k, v in sorted(snap.versions.items())},
                         fills=sc.fills, seq=seq, applied_by=self.name)

    # ---- how the votes are decided (issue 37) ------------------------------------------------
    def _decision(self, sc: _SceneWork, snap) -> tuple[str, LiftParams | None, dict | None]:  # noqa: ANN001
        """The scene's annotator model as this fill's parameters (:func:`decision_for`, read
        at every fill); the models that read every frame's votes get them here, consistent
        with ``snap``'s counts (:meth:`_frame_votes`)."""
        with self.sessions() as s:
            model, params, annotators = decision_for(s, sc.scene_id, snap.versions)
        if params is not None:
            snap.frame_votes = self._frame_votes(sc, snap)
        return model, params, annotators

    def _frame_votes(self, sc: _SceneWork, snap) -> dict[int, tuple]:  # noqa: ANN001
        """Every counted frame's stored votes, as ``snap`` counts them: the files are read
        without the update lock, then a frame whose version changed meanwhile (its file now
        holds the newer votes; the counts the older) is left out of the per-frame model --
        its votes still count, and the change schedules the next fill, which has it."""
        frames = sorted(f for f in snap.versions)
        got = load_frame_votes(sc.state.ws, frames)
        with sc.lock:
            now = sc.state.included_versions()
        return {f: v for f, v in got.items() if now.get(f) == snap.versions.get(f)}

    def _on_model_changed(self, msg: Message, stop: threading.Event) -> None:  # noqa: ARG002
        """An admin changed a scene's annotator model: fill it again with the new one."""
        with self.sessions() as s:
            ws = s.scalar(select(Scene.workspace).where(Scene.id == msg.scene_id))
        if ws is None or not Workspace(ws).lifting_dir.is_dir():
            return  # deleted, or nothing voted yet: the first fill uses the model
        try:
            sc = self._scene(int(msg.scene_id), ws)
        except Exception:  # noqa: BLE001 - a broken workspace must not stop the others
            log.exception("lifting: cannot open the state of scene %s", msg.scene_id)
            return
        self._schedule_fill(sc, delay=0.0)

    # ---- subscribers ------------------------------------------------------------------------
    def _owned_only(self, fn: OwnedSubscriber) -> Callable[[Message], None]:
        """``fn`` for the scenes this worker owns (every worker gets every event; the one
        owning the scene acts), handed this service's stop event; best effort."""

        def on_event(msg: Message) -> None:
            owned = self.owned()
            if msg.scene_id is None or (owned is not None and msg.scene_id not in owned):
                return
            try:
                fn(msg, self._stop)
            except Exception:  # noqa: BLE001 - a subscriber never stops the lifting
                log.warning("labels_updated subscriber %s failed", fn, exc_info=True)

        return on_event
