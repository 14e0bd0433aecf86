"""The review's after-fill refresh, run in a child process at a low priority.

After each fill the lifting worker recomputes the stored agreement of up to
``AGREEMENT_REFRESH_FRAMES`` submitted frames and the suspects list
(:func:`app.review.service.refresh_after_fill`). On the survey preset that is about 13 minutes
of CPU after a 3-minute fill. Run in the fill thread, it kept ``labels/status`` at "filling"
for those 13 minutes (the next fill waited for it), and it took the interpreter's lock from the
thread that applies the annotators' votes (votes lag p95 2.75 s against 2 s). A thread of its
own did not help: thread priorities do not order the interpreter's lock (docs/bench/history.md).

So the refresh runs in a spawned child process, niced (``nice``, default 10): it shares no
interpreter lock with the votes, and on a busy host the kernel gives the votes and the API's
requests the CPU first. What it computes reaches the API processes as before: the figures in
the database, the reviews and the suspects in the shared disk cache (:mod:`app.review.disk_cache`).

Requests are coalesced per scene: one child at a time; a fill that ends while a scene's refresh
runs queues one more refresh of that scene (the labels changed again), never more than one.
:meth:`ReviewRefresher.busy` tells :meth:`app.lifting.client.LiftingClient.wait_idle` that a
scene's refresh is pending or running; :meth:`close` stops the child (SIGTERM: it stops between
two frames; killed after ``term_wait_s``) and the supervising thread. A child whose parent
died exits on its own within a second.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger("occufly.review")

# entry(settings, scene_id, stop): the refresh of one scene, in the child process
# (app.bootstrap.run_review_refresh: it builds the child's own context)
Entry = Callable[[Any, int, threading.Event], None]


def _child_main(entry: Entry, settings: Any, scene_id: int, nice: int, parent: int) -> None:
    """The child process: lower its priority, stop between frames on SIGTERM, exit when the
    parent is gone, run ``entry``."""
    if nice > 0:
        try:
            os.nice(nice)
        except OSError:  # not permitted: run at the parent's priority
            pass
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def watch_parent() -> None:
        while not stop.wait(1.0):
            if os.getppid() != parent:  # the parent died (re-parented): nobody needs this
                os._exit(3)

    threading.Thread(target=watch_parent, name="occufly-refresh-parent", daemon=True).start()
    entry(settings, scene_id, stop)


class ReviewRefresher:
    """A ``labels_updated`` subscriber of the lifting service (:data:`app.lifting.service.
    OwnedSubscriber`) that runs ``entry(settings, scene_id, stop)`` in a spawned child process
    per refresh, one at a time, coalesced per scene (see the module's docstring)."""

    def __init__(self, settings: Any, entry: Entry, *, nice: int = 10,
                 term_wait_s: float = 10.0) -> None:
        self.settings = settings
        self.entry = entry
        self.nice = nice
        self.term_wait_s = term_wait_s
        self._mp = multiprocessing.get_context("spawn")  # a forked child would copy the threads' locks
        self._cv = threading.Condition()
        self._pending: list[int] = []  # scene ids, first come first served, each at most once
        self._running: int | None = None
        self._proc: Any = None
        self._thread: threading.Thread | None = None
        self._closed = False
        self.runs = 0  # children run to completion (exit 0)
        self.failures = 0  # children that exited otherwise

    def __call__(self, msg: Any, stop: threading.Event) -> None:  # noqa: ARG002 - close() stops it
        """Queue a refresh of the event's scene and return at once (the fill thread goes on)."""
        self.request(int(msg.scene_id))

    def request(self, scene_id: int) -> None:
        with self._cv:
            if self._closed:
                return
            if scene_id not in self._pending:
                self._pending.append(scene_id)
            if self._thread is None:
                self._thread = threading.Thread(target=self._loop, name="occufly-review-refresh",
                                                 daemon=True)
                self._thread.start()
            self._cv.notify_all()

    def busy(self, scene_id: int) -> bool:
        """Whether a refresh of the scene is queued or running."""
        with self._cv:
            return self._running == scene_id or scene_id in self._pending

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Until nothing is queued or running (tests, benchmarks); False at ``timeout``."""
        end = time.monotonic() + timeout
        with self._cv:
            while self._pending or self._running is not None:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(left)
        return True

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._pending.clear()
            proc = self._proc
            self._cv.notify_all()
        if proc is not None and proc.is_alive():
            proc.terminate()  # SIGTERM: the child stops between two frames
        t = self._thread
        if t is not None:
            t.join(timeout=self.term_wait_s + 5)

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                sid = self._pending.pop(0)
                self._running = sid
                proc = self._mp.Process(target=_child_main, name=f"occufly-review-refresh-{sid}",
                                        args=(self.entry, self.settings, sid, self.nice, os.getpid()),
                                        daemon=True)
                self._proc = proc
            try:
                t0 = time.monotonic()
                proc.start()
                while proc.is_alive():
                    proc.join(0.2)
                    if self._closed:
                        proc.terminate()
                        proc.join(self.term_wait_s)
                        if proc.is_alive():
                            proc.kill()
                            proc.join()
                        break
                ok = proc.exitcode == 0
                if ok:
                    self.runs += 1
                    log.info("review refresh of scene %s: %.1f s in pid %s", sid,
                             time.monotonic() - t0, proc.pid)
                elif not self._closed:
                    self.failures += 1
                    log.warning("review refresh of scene %s: the child process exited with %s",
                                sid, proc.exitcode)
            except Exception:  # noqa: BLE001 - a refresh is best effort; the next fill retries
                self.failures += 1
                log.warning("review refresh of scene %s failed to start", sid, exc_info=True)
            finally:
                with self._cv:
                    self._running = None
                    self._proc = None
                    self._cv.notify_all()
