"""Events between processes: ``publish(kind, scene_id, **payload)`` / ``subscribe(kind, fn)``.

Every event is a row of the ``events`` table (so a subscriber that was briefly away misses
nothing recent) and, on PostgreSQL, a ``NOTIFY occufly_events`` sent in the same transaction,
so subscribers (one ``LISTEN`` connection per process) learn of it at once (each
notification wakes the listener as it arrives). On SQLite the
table is polled (``poll_s``, default 0.25 s). Subscribers in the publishing process are called
synchronously by :meth:`EventBus.publish`; other processes' subscribers are called from the
bus's listener thread, in event-id order. Events are kept ``keep_s`` seconds (default 1 h).

Every event there is, who publishes it and who subscribes, is :data:`CATALOGUE`; publishing a
kind it does not list is a ``ValueError``. Subscriptions are wired where the long-lived
services are built (:mod:`app.bootstrap`, and the viewer mount in :mod:`app.main`).

Several processes publish (every lifting worker, API processes for corrections), so on
PostgreSQL an id can commit after a higher one: :meth:`EventBus.poll` re-reads the last
``LOOKBACK`` ids and delivers each id once.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import timedelta

import psycopg
from sqlalchemy import delete, func, select, text
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.db import utcnow
from app.lifting.models import Event

log = logging.getLogger("occufly.events")

CHANNEL = "occufly_events"
LIFT_CHANNEL = "occufly_lift"  # "frame queued for lifting" wake-ups (payload: scene id)


@dataclass(frozen=True)
class EventKind:
    """One entry of the catalogue: the payload's fields, who publishes, who subscribes."""

    payload: str
    publishers: tuple[str, ...]
    subscribers: tuple[str, ...]


CATALOGUE: dict[str, EventKind] = {
    "labels_updated": EventKind(
        payload="scene_id, stamp (Workspace.stamp() after the write), versions (frame index "
                "-> version tag counted), fills (count for the scene), seq, applied_by",
        publishers=("app.lifting.service.LiftingService (after each fill)",
                    "app.corrections.service (a correction, undo or redo changed the layer)"),
        subscribers=("app.review.service.refresh_after_fill -- in the process whose lifting "
                     "service owns the scene (wired by app.bootstrap.build_lifting_service)",
                     "app.review.service.warm_on_labels -- API processes without a lifting "
                     "service (app.bootstrap.subscribe_api_process)",
                     "app.viewer (open viewers reload labels; wired by app.main's viewer mount)")),
    "votes_applied": EventKind(
        payload="scene_id, seq (the scene's last lift_queue.applied_seq), versions (frame "
                "index -> version tag applied), applied_by: once per applied batch",
        publishers=("app.lifting.service.LiftingService",),
        subscribers=("tests and benchmarks (votes lag); no app component",)),
    "lifting_model_changed": EventKind(
        payload="scene_id, model (app.lifting.models.LIFT_MODELS): an admin changed how the "
                "scene's votes are decided",
        publishers=("app.lifting.routes (PUT /api/scenes/{id}/lifting)",),
        subscribers=("app.lifting.service.LiftingService -- the worker owning the scene fills "
                     "it again at once (a scene nobody owns is marked due and taken)",)),
    "grid_updated": EventKind(
        payload="scene_id, stamp, job (the voxelize job's id)",
        publishers=("app.jobs.runner for the voxelize kind's done_event (app.scenes.jobs)",),
        subscribers=("app.viewer (open viewers reload the scene grid)",)),
}


@dataclass(frozen=True)
class Message:
    id: int
    kind: str
    scene_id: int | None
    payload: dict = field(default_factory=dict)


def psycopg_dsn(engine: Engine) -> str:
    """A libpq DSN for the engine's PostgreSQL database (for a raw LISTEN connection)."""
    return engine.url.set(drivername="postgresql").render_as_string(hide_password=False)


def listen(engine: Engine, channels: tuple[str, ...], *, stop: threading.Event,
           on_wake: Callable[[], None], timeout_s: float = 1.0,
           stop_channel: str | None = None) -> None:
    """Block until ``stop``: call ``on_wake()`` at once for every NOTIFY on ``channels`` and at
    least every ``timeout_s`` (so a lost connection costs at most one poll interval). A NOTIFY
    on ``stop_channel`` (:func:`wake_listener`, after setting ``stop``) ends the wait at once
    instead of at the next heartbeat. PostgreSQL only; reconnects with back-off."""
    delay = 0.5
    listened = channels + ((stop_channel,) if stop_channel else ())
    while not stop.is_set():
        try:
            with psycopg.connect(psycopg_dsn(engine), autocommit=True) as conn:
                for ch in listened:
                    conn.execute(f"LISTEN {ch}")
                delay = 0.5
                on_wake()  # anything published while we were not listening
                while not stop.is_set():
                    # each notification wakes the subscriber as it arrives (the generator
                    # itself returns only at its timeout: waking after it, as before, made
                    # every NOTIFY wait up to timeout_s)
                    for _n in conn.notifies(timeout=timeout_s):
                        if stop.is_set():
                            break
                        on_wake()
                    on_wake()
        except Exception as e:  # noqa: BLE001 - the database restarts; keep listening
            if stop.is_set():
                return
            log.warning("LISTEN %s: %s; reconnecting in %.1f s", channels, e, delay)
            stop.wait(delay)
            delay = min(delay * 2, 10.0)


def stop_channel_name() -> str:
    """A channel of one listener's own, to end its wait (:func:`wake_listener`)."""
    return f"occufly_stop_{uuid.uuid4().hex}"


def wake_listener(engine: Engine, channel: str) -> None:
    """NOTIFY ``channel`` (best effort): a :func:`listen` thread whose ``stop`` is set and
    whose ``stop_channel`` this is returns now rather than at its next heartbeat."""
    try:
        with engine.connect() as c:
            c.execute(text("SELECT pg_notify(:c, '')"), {"c": channel})
            c.commit()
    except Exception:  # noqa: BLE001 - the database is away: the heartbeat ends the wait
        log.debug("could not wake the listener on %s", channel, exc_info=True)


class EventBus:
    LOOKBACK = 256  # ids re-read behind the highest seen (commits out of id order)

    def __init__(self, engine: Engine, sessions: sessionmaker[Session], *, poll_s: float = 0.25,
                 keep_s: float = 3600.0) -> None:
        self.engine = engine
        self.sessions = sessions
        self.poll_s = poll_s
        self.keep_s = keep_s
        self.origin = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self._subs: list[tuple[str, Callable[[Message], None]]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._listener: threading.Thread | None = None
        self._stop_channel = stop_channel_name()
        self._last_id: int | None = None
        self._seen: set[int] = set()  # delivered ids within LOOKBACK of _last_id
        self._start_id = 0
        self._last_prune = 0.0

    @property
    def is_postgres(self) -> bool:
        return self.engine.dialect.name == "postgresql"

    # ---- publish ----------------------------------------------------------------------------
    def publish(self, kind: str, scene_id: int | None = None, **payload) -> Message:
        if kind not in CATALOGUE:
            raise ValueError(f"event {kind!r} is not in app.events.CATALOGUE")
        payload = {**payload, "origin": self.origin}
        with self.sessions() as s:
            ev = Event(kind=kind, scene_id=scene_id, payload=payload, created_at=utcnow())
            s.add(ev)
            s.flush()
            if self.is_postgres:
                s.execute(text("SELECT pg_notify(:c, :p)"), {"c": CHANNEL, "p": str(ev.id)})
            s.commit()
            msg = Message(ev.id, kind, scene_id, payload)
        self._deliver(msg)
        if time.monotonic() - self._last_prune > 60:
            self._prune()
        return msg

    def _prune(self) -> None:
        self._last_prune = time.monotonic()
        try:
            with self.sessions() as s:
                s.execute(delete(Event).where(
                    Event.created_at < utcnow() - timedelta(seconds=self.keep_s)))
                s.commit()
        except Exception:  # noqa: BLE001 - pruning is housekeeping
            log.warning("pruning events failed", exc_info=True)

    # ---- subscribe --------------------------------------------------------------------------
    def subscribe(self, kind: str, fn: Callable[[Message], None]) -> None:
        """Call ``fn(message)`` for every ``kind`` event from now on (any process)."""
        with self._lock:
            self._subs.append((kind, fn))
            if self._thread is None:
                with self.sessions() as s:
                    self._last_id = s.scalar(select(func.max(Event.id))) or 0
                self._start_id = self._last_id  # nothing before subscribing is delivered
                self._thread = threading.Thread(target=self._loop, name="occufly-events",
                                                daemon=True)
                self._thread.start()
                if self.is_postgres:
                    self._listener = threading.Thread(
                        target=listen, name="occufly-events-listen", daemon=True,
                        args=(self.engine, (CHANNEL,)),
                        kwargs=dict(stop=self._stop, on_wake=self._wake.set,
                                    stop_channel=self._stop_channel))
                    self._listener.start()

    def _deliver(self, msg: Message, *, remote_only: bool = False) -> None:
        if remote_only and msg.payload.get("origin") == self.origin:
            return  # already delivered by publish()
        with self._lock:
            subs = [fn for k, fn in self._subs if k == msg.kind]
        for fn in subs:
            try:
                fn(msg)
            except Exception:  # noqa: BLE001 - one subscriber must not starve the others
                log.exception("subscriber of %s failed", msg.kind)

    def poll(self) -> int:
        """Deliver events newer than the last one seen; returns how many."""
        last = self._last_id or 0
        with self.sessions() as s:
            rows = s.execute(select(Event.id, Event.kind, Event.scene_id, Event.payload)
                             .where(Event.id > last - self.LOOKBACK).order_by(Event.id)
                             .limit(1000 + self.LOOKBACK)).all()
        n = 0
        for r in rows:
            if r.id in self._seen or r.id <= self._start_id:
                continue
            self._seen.add(r.id)
            self._last_id = max(self._last_id or 0, r.id)
            n += 1
            self._deliver(Message(r.id, r.kind, r.scene_id, dict(r.payload or {})),
                          remote_only=True)
        floor = (self._last_id or 0) - self.LOOKBACK
        self._seen = {i for i in self._seen if i > floor}
        return n

    def _loop(self) -> None:
        # PostgreSQL: woken by NOTIFY (and the listener's 1 s heartbeat); SQLite: polled
        interval = 5.0 if self.is_postgres else self.poll_s
        while not self._stop.is_set():
            self._wake.wait(interval)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                self.poll()
            except Exception:  # noqa: BLE001 - database briefly away
                log.warning("polling events failed", exc_info=True)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._listener is not None and self._listener.is_alive():
            wake_listener(self.engine, self._stop_channel)
        for t in (self._thread, self._listener):
            if t is not None:
                t.join(timeout=5)
