"""Limits that hold across API processes (issue 36, carried over from round two).

A quota that counts rows and then adds one is a race: two requests both count ``quota - 1``
and both add theirs. A lock in the API process closes that race for that process only, so N
replicas gave N x the quota. :func:`serialise` takes a lock *in the database*, inside the
transaction that counts and then inserts, so the count a request sees already holds every
row a concurrent request (in any process) added under the same key:

- PostgreSQL: ``pg_advisory_xact_lock(scope, key)`` -- one lock per (quota, user), released
  by the commit or rollback; other users' requests do not wait.
- SQLite: the database write lock (a write statement that matches no row opens the write
  transaction; another writer, in any process, waits for the commit). One host, possibly
  several processes; every writer waits, which is what SQLite does anyway.

Viewer sockets are not rows of any other table: :class:`ViewerSocket` keeps one row per open
``/viewer/`` socket, with the API process that holds it and a lease (``expires_at``) the
process renews while it runs (:class:`SocketLeases`), so the per-user cap counts every
process's sockets and the sockets of a killed process stop counting when their lease runs out.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import uuid
import zlib
from collections.abc import Callable
from datetime import datetime, timedelta

from sqlalchemy import DateTime, Integer, String, delete, func, select, text, update
from sqlalchemy.orm import Mapped, Session, mapped_column

from app.db import Base, utcnow

log = logging.getLogger(__name__)

# advisory-lock scopes (the first int of the two-int form; app.lifting.service uses 0x4F43/44)
JOB_QUOTA = 0x4F51  # key: user id -- active jobs per user (app.jobs.service)
REVIEW_QUOTA = 0x4F52  # key: user id -- open review items, comments per hour (app.review)
ITEM_COMMENTS = 0x4F53  # key: review item id -- comments per item
VIEWER_SOCKETS = 0x4F54  # key: crc of the user name -- open viewer sockets per user


def serialise(session: Session, scope: int, key: int) -> None:
    """Serialise, until ``session``'s transaction ends, every caller that passes the same
    (scope, key): on PostgreSQL an advisory transaction lock, on SQLite the write lock. Call
    it first in the transaction that counts and then adds (see the module doc)."""
    if session.get_bind().dialect.name == "postgresql":
        session.execute(text("SELECT pg_advisory_xact_lock(:scope, :key)"),
                        {"scope": int(scope), "key": int(key)})
    else:
        # the statement opens the write transaction (pysqlite begins before a write) and takes
        # the write lock even though it changes nothing; busy_timeout makes others wait
        session.execute(update(ViewerSocket).where(ViewerSocket.id == -1)
                        .values(expires_at=ViewerSocket.expires_at))


def name_key(name: str) -> int:
    """A stable int32 advisory-lock key for a name (collisions only make two users wait)."""
    return zlib.crc32(name.encode()) - (1 << 31)


# ---- viewer sockets --------------------------------------------------------------------------
class ViewerSocket(Base):
    """One open ``/viewer/`` socket: its user, the API process holding it, and the lease that
    process renews (a row whose lease ran out belongs to a process that is gone)."""

    __tablename__ = "viewer_sockets"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    username: Mapped[str] = mapped_column(String(64), index=True)
    process: Mapped[str] = mapped_column(String(64), index=True)
    opened_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(DateTime, index=True)


class SocketCapReached(Exception):
    """The user already holds the cap of open viewer sockets (in all API processes)."""

    def __init__(self, open_now: int, cap: int) -> None:
        super().__init__(f"{open_now} viewer sockets open, at most {cap}")
        self.open_now = open_now
        self.cap = cap


class SocketLeases:
    """The viewer-socket rows of one API process: :meth:`claim` counts the user's live rows
    (every process) and adds one under the cap, :meth:`release` deletes it, and a thread
    renews this process's leases every ``lease_s / 3`` while any is held. ``sessions``: the
    app's session factory."""

    def __init__(self, sessions: Callable[[], Session], *, lease_s: float = 30.0) -> None:
        self.sessions = sessions
        self.lease_s = float(lease_s)
        self.process = f"{socket.gethostname()[:30]}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.held: set[int] = set()
        self._mu = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def claim(self, username: str, cap: int) -> int:
        """The id of a new row for ``username``; :class:`SocketCapReached` when the user
        already holds ``cap`` live sockets. Expired rows (a killed process's) are removed."""
        now = utcnow()
        with self.sessions() as s:
            serialise(s, VIEWER_SOCKETS, name_key(username))
            s.execute(delete(ViewerSocket).where(ViewerSocket.username == username,
                                                 ViewerSocket.expires_at <= now))
            n = int(s.scalar(select(func.count()).select_from(ViewerSocket).where(
                ViewerSocket.username == username)) or 0)
            if n >= cap:
                s.commit()  # the expired rows' removal
                raise SocketCapReached(n, cap)
            row = ViewerSocket(username=username, process=self.process, opened_at=now,
                               expires_at=now + timedelta(seconds=self.lease_s))
            s.add(row)
            s.commit()
            rid = int(row.id)
        with self._mu:
            self.held.add(rid)
            if self._thread is None or not self._thread.is_alive():
                self._stop.clear()
                self._thread = threading.Thread(target=self._renew_loop, daemon=True,
                                                name="viewer-socket-leases")
                self._thread.start()
        return rid

    def release(self, rid: int) -> None:
        with self._mu:
            self.held.discard(rid)
        with self.sessions() as s:
            s.execute(delete(ViewerSocket).where(ViewerSocket.id == rid,
                                                 ViewerSocket.process == self.process))
            s.commit()

    def renew(self) -> int:
        """Push this process's leases ``lease_s`` ahead; the number of rows renewed. A row
        another process removed as expired (this one stalled past its lease) is not brought
        back: that socket no longer counts until it closes."""
        with self._mu:
            ids = sorted(self.held)
        if not ids:
            return 0
        with self.sessions() as s:
            # by id *and* process: a row removed as expired frees its id, which SQLite (no
            # AUTOINCREMENT) or a truncated table gives to the next row, another process's
            n = s.execute(update(ViewerSocket).where(
                ViewerSocket.id.in_(ids), ViewerSocket.process == self.process).values(
                expires_at=utcnow() + timedelta(seconds=self.lease_s))).rowcount
            s.commit()
        return int(n or 0)

    def close(self) -> None:
        """Stop renewing and delete this process's rows (a clean shutdown)."""
        self._stop.set()
        with self._mu:
            self.held.clear()
        try:
            with self.sessions() as s:
                s.execute(delete(ViewerSocket).where(ViewerSocket.process == self.process))
                s.commit()
        except Exception:  # noqa: BLE001 - shutting down: the leases expire by themselves
            log.warning("viewer sockets: could not remove this process's rows", exc_info=True)

    def _renew_loop(self) -> None:
        while not self._stop.wait(self.lease_s / 3):
            try:
                self.renew()
            except Exception:  # noqa: BLE001 - a database hiccup: the next round retries
                log.warning("viewer sockets: renewing the leases failed", exc_info=True)
