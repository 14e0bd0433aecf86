"""How uvicorn serves the app: header-read and idle timeouts, header size cap, proxy headers.

uvicorn (0.55) has a keep-alive timeout that starts only *after* a response; a connection that
sends an incomplete request head (a "slowloris" client dribbling one header byte at a time, or
one that connects and sends nothing) has no timer at all and stays open for ever. 50 such
connections stayed open 60 s (issue 24). :class:`TimedH11Protocol` adds the missing timer: from
the moment a connection opens, and again after each response, a complete request head must
arrive within ``OCCUFLY_HEADER_TIMEOUT_S`` (default 10 s) or the connection is closed. Once
the head is in, the request's own handling is not timed here; a websocket upgrade cancels the
timer (the viewer socket lives for hours and has its own ping/pong).

A request *body* must keep moving: once the head is in, a body that sends nothing for
``OCCUFLY_BODY_IDLE_TIMEOUT_S`` (default 30 s) closes the connection (not while the app itself
has paused reading, i.e. is slower than the client).

A body must also keep *up* a minimum average rate (issue 36): one that dribbles a byte every
few seconds re-arms the idle timer with each byte and was held open for as long as the body
caps allowed. From the first body bytes on, after ``OCCUFLY_BODY_RATE_GRACE_S`` (default
10 s) the bytes received must average at least ``OCCUFLY_BODY_MIN_RATE_BPS`` (default 500
bytes/s, Apache's ``mod_reqtimeout`` default; 0 turns it off), or the connection is closed.
While the app has paused reading the measurement stops and starts afresh (with its grace)
when bytes flow again: a client is never cut for the app's slowness.

A websocket is not a request body. h11 reports the upgrade request's sender in ``SEND_BODY``
(uvicorn hands the connection to its websocket protocol on the ``Request`` event, before h11
sees the end of the message), so the body timer used to be armed by the upgrade's own bytes --
and, the transport now belonging to the websocket protocol, never re-armed nor cancelled: every
``/viewer/`` socket was closed (1006 in the browser) exactly ``OCCUFLY_BODY_IDLE_TIMEOUT_S``
after it opened, pings or not (issue 40, defect 4). The upgrade now cancels both timers and
marks the connection, and neither timer is armed on it again; the websocket's liveness is
uvicorn's ping/pong (``ws_ping_interval`` / ``ws_ping_timeout``).

The head is parsed by h11, whose incomplete-event cap (``h11_max_incomplete_event_size``,
64 KiB here) bounds what one connection can make the server buffer before the head is
complete: a longer head gets 400 at once.

``--proxy-headers`` (``occufly serve``): uvicorn believes ``X-Forwarded-Proto`` and
``X-Forwarded-For`` from ``OCCUFLY_TRUSTED_PROXIES`` only, so behind a TLS-terminating proxy
the request scheme is ``https`` and the session cookie is sent ``Secure``.

Each serving process keeps up to ``OCCUFLY_MALLOC_KEEP_MB`` (512) MB of freed heap for its
next requests (:func:`tune_allocator`, glibc only): a review's temporaries are not faulted in
afresh on every request.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from occufly.errors import InputFormatError

log = logging.getLogger("occufly.serving")

HEADER_TIMEOUT_S = 10.0
BODY_IDLE_TIMEOUT_S = 30.0
BODY_MIN_RATE_BPS = 500.0
BODY_RATE_GRACE_S = 10.0
RATE_RECHECK_S = 0.25  # the rate timer wakes at most this often
KEEP_ALIVE_S = 5
MAX_HEAD_BYTES = 64 * 1024


def _seconds(name: str, default: float) -> float:
    raw = os.environ.get(name, "")
    try:
        value = float(raw) if raw else default
    except ValueError:
        raise InputFormatError(f"{name} must be a number of seconds, got {raw!r}") from None
    if not value > 0:
        raise InputFormatError(f"{name} must be > 0, got {raw!r}")
    return value


def header_timeout_s() -> float:
    return _seconds("OCCUFLY_HEADER_TIMEOUT_S", HEADER_TIMEOUT_S)


def body_idle_timeout_s() -> float:
    return _seconds("OCCUFLY_BODY_IDLE_TIMEOUT_S", BODY_IDLE_TIMEOUT_S)


def body_rate_grace_s() -> float:
    return _seconds("OCCUFLY_BODY_RATE_GRACE_S", BODY_RATE_GRACE_S)


def body_min_rate_bps() -> float:
    """The minimum average body rate in bytes/s (``OCCUFLY_BODY_MIN_RATE_BPS``; 0: off)."""
    name, raw = "OCCUFLY_BODY_MIN_RATE_BPS", os.environ.get("OCCUFLY_BODY_MIN_RATE_BPS", "")
    try:
        value = float(raw) if raw else BODY_MIN_RATE_BPS
    except ValueError:
        raise InputFormatError(f"{name} must be a number of bytes per second, got {raw!r}") \
            from None
    if not value >= 0 or value == float("inf"):
        raise InputFormatError(f"{name} must be >= 0 (0: no minimum rate), got {raw!r}")
    return value


# glibc's malloc (M_TRIM_THRESHOLD): free heap memory kept for the process's next requests
MALLOC_KEEP_MB = 512
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (malloc.h)
_MMAP_THRESHOLD = 32 << 20  # glibc's largest dynamic mmap threshold, fixed here


def malloc_keep_mb() -> int:
    """``OCCUFLY_MALLOC_KEEP_MB``: MB of freed heap memory an API process keeps instead of
    returning it to the system (default 512; 0: glibc's own defaults)."""
    name, raw = "OCCUFLY_MALLOC_KEEP_MB", os.environ.get("OCCUFLY_MALLOC_KEEP_MB", "")
    try:
        value = int(raw) if raw else MALLOC_KEEP_MB
    except ValueError:
        raise InputFormatError(f"{name} must be a whole number of MB, got {raw!r}") from None
    if not 0 <= value <= 4096:
        raise InputFormatError(f"{name} must be 0..4096 (MB; 0: the C library's defaults), "
                               f"got {raw!r}")
    return value


def tune_allocator() -> bool:
    """Let a serving process keep up to :func:`malloc_keep_mb` MB of freed heap (glibc
    ``mallopt``: trim threshold that size, blocks up to 32 MB from the heap). A review of a
    20 MP frame allocates and frees a few hundred MB of temporaries; with glibc's defaults
    most of it went back to the system after each request and the next one faulted it in
    again (40-55 k page faults, 0.15-0.45 s of system time per review of a survey frame:
    wall 0.88-1.30 s; kept: 12-13 k faults, 0.79-0.82 s, the process ~350 MB larger).
    A no-op (False) off glibc, with ``OCCUFLY_MALLOC_KEEP_MB=0``, or where the environment
    already tunes malloc (``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_MMAP_THRESHOLD_``,
    ``GLIBC_TUNABLES``: the operator's choice wins)."""
    keep = malloc_keep_mb()
    if keep == 0 or platform.libc_ver()[0] != "glibc":
        return False
    if any(os.environ.get(v) for v in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_",
                                       "GLIBC_TUNABLES")):
        return False
    try:
        libc = ctypes.CDLL(None)
        ok = (libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD) == 1
              and libc.mallopt(_M_TRIM_THRESHOLD, keep << 20) == 1)
    except (OSError, AttributeError):
        return False
    return bool(ok)


class TimedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline for each request head (see the module doc)."""

    closed_for_slow_head = 0  # per process; the tests and the log read it
    closed_for_idle_body = 0
    closed_for_slow_body = 0

    def connection_made(self, transport: Any) -> None:  # noqa: ANN401
        super().connection_made(transport)
        self._head_timer = None
        self._body_timer = None
        self._rate_timer = None
        self._rate_t0: float | None = None  # loop time the body's measurement started
        self._rate_bytes = 0  # bytes received since then
        self._upgraded = False  # handed to the websocket protocol: no timer of ours applies
        self._arm_head_timer()

    def data_received(self, data: bytes) -> None:
        if self._head_too_large(data):
            return
        super().data_received(data)
        self._arm_body_timer()
        self._count_body(len(data))

    # ---- the head's size, however it arrives (issue 36) --------------------------------------
    _head_bytes = 0
    _head_tail = b""

    def _head_too_large(self, data: bytes) -> bool:
        """h11's cap (``h11_max_incomplete_event_size``) holds only while a head is still
        incomplete: a 100 KiB head arriving in one read was answered. Count the bytes of
        the head under way (up to its blank line) and answer 400 past MAX_HEAD_BYTES (as h11
        does for an incomplete one)."""
        if self._upgraded or self.conn.their_state is not h11.IDLE:
            self._head_bytes, self._head_tail = 0, b""
            return False
        buf = self._head_tail + data
        end = buf.find(b"\r\n\r\n")
        size = self._head_bytes + (len(data) if end < 0 else end + 4 - len(self._head_tail))
        if size > MAX_HEAD_BYTES:
            msg = f"request head over {MAX_HEAD_BYTES} bytes\r\n".encode()
            self.transport.write(b"HTTP/1.1 400 Bad Request\r\n"
                                 b"content-type: text/plain; charset=utf-8\r\nconnection: "
                                 b"close\r\ncontent-length: %d\r\n\r\n%s" % (len(msg), msg))
            self.transport.close()
            return True
        if end < 0:
            self._head_bytes, self._head_tail = size, buf[-3:]
        else:
            self._head_bytes, self._head_tail = 0, b""
        return False

    # ---- minimum body rate -----------------------------------------------------------------
    def _rate_reset(self) -> None:
        timer = getattr(self, "_rate_timer", None)
        if timer is not None:
            timer.cancel()
        self._rate_timer = None
        self._rate_t0 = None
        self._rate_bytes = 0

    def _rate_applies(self) -> bool:
        return (not self._upgraded and not self.transport.is_closing()
                and self.conn.their_state is h11.SEND_BODY
                and not (self.flow is not None and self.flow.read_paused))

    def _count_body(self, n: int) -> None:
        if not self._rate_applies():  # no body under way, a websocket, or the app paused
            self._rate_reset()        # reading: measure afresh when bytes flow again
            return
        if self._rate_t0 is None:  # the body starts (the head's own packet is not counted)
            rate = body_min_rate_bps()
            if rate > 0:
                self._rate_t0 = self.loop.time()
                self._rate_bytes = 0
                self._rate_timer = self.loop.call_later(body_rate_grace_s(), self._rate_deadline)
            return
        self._rate_bytes += n

    def _rate_deadline(self) -> None:
        self._rate_timer = None
        if self._rate_t0 is None:
            return
        if not self._rate_applies():
            self._rate_reset()
            return
        rate = body_min_rate_bps()
        now = self.loop.time()
        if rate <= 0:
            self._rate_reset()
            return
        if self._rate_bytes >= rate * (now - self._rate_t0):
            # when the average would fall under the minimum if nothing more arrived
            due = self._rate_t0 + self._rate_bytes / rate
            self._rate_timer = self.loop.call_later(max(RATE_RECHECK_S, due - now),
                                                    self._rate_deadline)
            return
        TimedH11Protocol.closed_for_slow_body += 1
        log.info("closing connection from %s: request body at %.0f bytes/s (%d bytes in "
                 "%.1f s), under the minimum of %.0f", self.client,
                 self._rate_bytes / max(now - self._rate_t0, 1e-9), self._rate_bytes,
                 now - self._rate_t0, rate)
        self._rate_reset()
        self.transport.close()

    def _cancel_body_timer(self) -> None:
        timer = getattr(self, "_body_timer", None)
        if timer is not None:
            timer.cancel()
            self._body_timer = None

    def _arm_body_timer(self) -> None:
        self._cancel_body_timer()
        if self._upgraded:  # a websocket, not a body (see the module doc)
            return
        if self.conn.their_state is h11.SEND_BODY and not self.transport.is_closing():
            self._body_timer = self.loop.call_later(body_idle_timeout_s(), self._body_deadline)

    def _body_deadline(self) -> None:
        self._body_timer = None
        if (self._upgraded or self.transport.is_closing()
                or self.conn.their_state is not h11.SEND_BODY):
            return
        if self.flow is not None and self.flow.read_paused:  # the app is the slow one
            self._arm_body_timer()
            return
        TimedH11Protocol.closed_for_idle_body += 1
        log.info("closing connection from %s: request body idle for %.1f s", self.client,
                 body_idle_timeout_s())
        self.transport.close()

    def _arm_head_timer(self) -> None:
        self._cancel_head_timer()
        self._head_timer = self.loop.call_later(header_timeout_s(), self._head_deadline)

    def _cancel_head_timer(self) -> None:
        timer = getattr(self, "_head_timer", None)
        if timer is not None:
            timer.cancel()
            self._head_timer = None

    def _head_deadline(self) -> None:
        self._head_timer = None
        if self._upgraded or self.transport.is_closing():
            return
        if self.cycle is not None and not self.cycle.response_complete:
            return  # a complete head arrived; the request is being handled
        TimedH11Protocol.closed_for_slow_head += 1
        log.info("closing connection from %s: no complete request head within %.1f s",
                 self.client, header_timeout_s())
        self.transport.close()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_head_timer()  # the next request head of a kept-alive connection

    def handle_websocket_upgrade(self, event: Any) -> None:  # noqa: ANN401
        # from here on the transport belongs to the websocket protocol: this object sees no
        # more data_received / connection_lost, so a timer left armed would fire on a live
        # socket (data_received arms the body timer *after* this returns: the flag stops it)
        self._upgraded = True
        self._cancel_head_timer()
        self._cancel_body_timer()
        self._rate_reset()
        super().handle_websocket_upgrade(event)

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        self._cancel_body_timer()
        self._rate_reset()
        super().connection_lost(exc)


def uvicorn_options(settings: Any, *, proxy_headers: bool = False) -> dict:  # noqa: ANN401
    """Keyword arguments for ``uvicorn.run`` / ``uvicorn.Config`` (every way the app is
    served uses them)."""
    header_timeout_s()  # a bad OCCUFLY_HEADER_TIMEOUT_S fails here, before serving
    body_idle_timeout_s()
    body_rate_grace_s()
    body_min_rate_bps()
    opts: dict = dict(
        http=TimedH11Protocol, timeout_keep_alive=KEEP_ALIVE_S,
        h11_max_incomplete_event_size=MAX_HEAD_BYTES,
        # no permessage-deflate: the /viewer/ socket carries ~15 B/point of float data,
        # which barely compresses and costs ~5 s per 2 M points (bench/bench_viewer.py)
        ws_per_message_deflate=False,
        # off by default: uvicorn would otherwise believe X-Forwarded-For from loopback; the
        # app honours it only from OCCUFLY_TRUSTED_PROXIES (app.security.client_ip)
        proxy_headers=False,
    )
    if proxy_headers:
        proxies = list(getattr(settings, "trusted_proxies", []) or [])
        if not proxies:
            raise InputFormatError(
                "--proxy-headers needs OCCUFLY_TRUSTED_PROXIES (the reverse proxy's address): "
                "X-Forwarded-Proto/-For are believed from those addresses only")
        opts.update(proxy_headers=True, forwarded_allow_ips=",".join(proxies))
    return opts
