"""The viser server behind ``/viewer/``: per-client state, GUI, review from 3D, live refresh.

The server binds 127.0.0.1 on a free port and never requests a share link. A browser reaches
it only through the app's proxy (:mod:`app.viewer.proxy`), which authenticates the user and
hands the upstream connection a one-time *ticket* (header ``X-Occufly-Viewer-Ticket``) naming
the user and the scene. A connection without a valid ticket (e.g. another local process
talking to the loopback port directly) gets nothing but a notice and is closed.

Each client has its own scene (``client.scene``) so reviewers can pick colour modes, classes
and LOD independently. Heavy work (loading, subsampling, colouring) runs in viser's thread
pool; live refreshes run in one background thread and are coalesced per scene.

Live refresh is event driven: the app subscribes :meth:`ViewerService.on_labels_updated` to
the lifting service's ``labels_updated(scene, stamp)`` events (and ``grid_updated`` from the
voxelize job), so an open viewer re-sends the changed classes as soon as new labels are
written, in whichever process wrote them. Only a viewer mounted without an event source (a
bare data directory, no backend) falls back to watching ``Workspace.stamp()`` every
``watch_interval_s``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from app.shared_limits import SocketLeases
from app.viewer import scene_builder as sb
from app.viewer import session_state
from app.viewer.markdown_escape import md_text
from app.viewer.panels import PanelsMixin
from app.viewer.refresh import RefreshMixin, workspace_stamps
from app.viewer.scene_view import SceneViewMixin
from app.viewer.state import (
    TICKET_HEADER,
    TICKET_TTL_S,
    ClientState,
    FrameMaskFn,
    FrameStatesFn,
    ReviewItemFn,
    ScenesFn,
    Ticket,
    user_key,
)
from occufly import subsample

log = logging.getLogger(__name__)


class ViewerService(SceneViewMixin, PanelsMixin, RefreshMixin):
    """Owns the viser server and the per-client state."""

    def __init__(self, *, scenes: ScenesFn, frame_states: FrameStatesFn | None = None,
                 frame_mask: FrameMaskFn | None = None,
                 on_review_item: ReviewItemFn | None = None,
                 max_points: int = sb.DEFAULT_MAX_POINTS, preview_points: int = 150_000,
                 host: str = "127.0.0.1",
                 watch_interval_s: float | None = None, require_ticket: bool = True,
                 can_open: Callable[[Any, str], bool] | None = None,
                 corrections: dict[str, Callable[..., Any]] | None = None,
                 prefs_path: Path | None = None, access_check_s: float = 0.25,
                 max_sockets_per_user: int | None = None,
                 socket_leases: SocketLeases | None = None) -> None:
        if host not in ("127.0.0.1", "localhost", "::1"):
            raise ValueError(f"the viewer binds loopback only, got host {host!r}")
        self.scenes = scenes
        # can_open(user, scene_id) -> bool: which of the scenes a ticket's user may open (the
        # app: admins every scene, reviewers their member scenes); None: every scene
        self.can_open = can_open
        # every access_check_s the open clients are checked against can_open(user, scene)
        # again: a reviewer removed from the scene, demoted or deactivated is disconnected
        # (1008) within that time, on whichever replica the socket is (issue 24, finding 7)
        self.access_check_s = float(access_check_s)
        # at most this many open viewer sockets per user (the proxy refuses more, 1008); None:
        # no cap. Counted in the database across every API process when socket_leases is
        # given (the app: app.shared_limits.SocketLeases, issue 36), else per process.
        # open_sockets: this process's count per user name
        self.max_sockets_per_user = max_sockets_per_user
        self.socket_leases = socket_leases
        self.open_sockets: dict[str, int] = {}
        self.revoked: list[tuple[str | None, str | None]] = []  # (user, scene) closed for access
        self.frame_states = frame_states
        self.frame_mask = frame_mask
        # frame_index(scene_id, frame) -> frame index or None: resolves the page's ?frame=
        # (the app's frame id); without it ?frame= is a frame index or a frame's stem
        self.frame_index: Callable[[str, str], int | None] | None = None
        # suspect_points(scene_id, key) -> point ids or None: the page's ?suspect= (a key of
        # GET /api/scenes/{sid}/suspects) is selected on connect, ready to relabel
        self.suspect_points: Callable[[str, str], Any] | None = None
        self.on_review_item = on_review_item
        # relabel / undo / redo / stack hooks of the app's corrections service (issue 25)
        self.corrections = corrections
        # per-user viewer preferences (the camera filter), kept in prefs_path if given
        self.prefs_path = Path(prefs_path) if prefs_path else None
        self.prefs: dict[str, dict] = _read_prefs(self.prefs_path)
        # each tab's state by (user, scene, view id), kept when its socket drops and put back
        # when the same tab reconnects (beside the prefs on disk, so a restart keeps it too)
        self.tabs = session_state.SessionStore(
            self.prefs_path.parent / "viewer_tabs" if self.prefs_path else None)
        self.max_points = int(max_points)
        # a scene showing more than 4x this many points first gets a stratified preview of
        # this size (a quick first picture, ~7 % extra bytes), then the full LOD
        self.preview_points = int(preview_points)
        self.host = host
        self.watch_interval_s = watch_interval_s
        self.require_ticket = require_ticket
        self.server: Any = None
        self.filed_items: list[dict] = []
        # per proxied websocket: bytes/frames sent to the browser, perf_counter of the last
        self.proxy_stats: deque[dict] = deque(maxlen=64)
        self._tickets: dict[str, Ticket] = {}
        self._clients: dict[int, ClientState] = {}
        self._data: dict[str, sb.ViewerData] = {}
        self._plans: dict[tuple, tuple] = {}  # level of detail plans (scene_view._plan)
        self._stamps: dict[str, str] = {}
        self._base_stamps: dict[str, str] = {}  # the stamps without the correction layer
        self._refresh_lock = threading.RLock()
        self._lock = threading.RLock()
        self._start_lock = threading.Lock()
        self._pending: dict[str, set[int] | None] = {}
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._access_worker: threading.Thread | None = None

    # ---- lifecycle -------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.server is not None

    @property
    def port(self) -> int:
        self.start()
        return int(self.server.get_port())

    def start(self) -> None:
        """Start viser on a free loopback port (idempotent, thread safe)."""
        with self._start_lock:
            if self.server is not None:
                return
            import viser  # the viewer's one dependency, imported where it is used (the app runs without it)

            server = viser.ViserServer(host=self.host, port=0, verbose=False)
            server.gui.configure_theme(control_layout="floating", show_share_button=False,
                                       dark_mode=False, brand_color=(40, 120, 255))
            server.scene.set_up_direction("+z")
            server.on_client_connect(self._on_connect)
            server.on_client_disconnect(self._on_disconnect)
            self.server = server
            self._stop.clear()
            # the level of detail's compiled kernels loaded now, not in a first picture
            threading.Thread(target=subsample.warm, name="viewer-warm", daemon=True).start()
            self._worker = threading.Thread(target=self._refresh_loop, name="viewer-refresh",
                                            daemon=True)
            self._worker.start()
            if self.can_open is not None and self.access_check_s > 0:
                self._access_worker = threading.Thread(target=self._access_loop,
                                                       name="viewer-access", daemon=True)
                self._access_worker.start()

    def stop(self) -> None:
        with self._start_lock:
            if self.server is not None:
                self._stop.set()
                self._wake.set()
                if self._worker is not None:
                    self._worker.join(timeout=5)
                if self._access_worker is not None:
                    self._access_worker.join(timeout=5)
                self.server.stop()
                self.server = None
                self._clients.clear()
            # this process's socket rows go now, and their renewal stops -- also where the 3D
            # server never started (a socket refused upstream still claimed a lease): else
            # the renewal outlives the app and its database
            if self.socket_leases is not None:
                self.socket_leases.close()

    # ---- tickets ---------------------------------------------------------------------------
    def issue_ticket(self, user: Any, scene_id: str | None, frame: str | None = None, *,
                     suspect: str | None = None, view: str | None = None) -> str:
        """A one-time token the proxy sends upstream; valid for :data:`TICKET_TTL_S`."""
        tok = secrets.token_urlsafe(24)
        now = time.monotonic()
        with self._lock:
            for k in [k for k, t in self._tickets.items() if t.expires < now]:
                del self._tickets[k]
            self._tickets[tok] = Ticket(user, scene_id, now + TICKET_TTL_S, frame, suspect, view)
        return tok

    def _take_ticket(self, client_id: int) -> Ticket | None:
        try:  # viser keeps the raw websocket per client; its handshake carries our header
            conn = self.server._websock_server._live_connections[client_id]
            tok = conn.request.headers.get(TICKET_HEADER)
        except (AttributeError, KeyError):
            return None
        return self.redeem_ticket(tok) if tok else None

    def redeem_ticket(self, tok: str) -> Ticket | None:
        """The ticket's user and scene, once; None for unknown, used or expired tickets."""
        with self._lock:
            t = self._tickets.pop(tok, None)
        if t is None or t.expires < time.monotonic():
            return None
        return t

    def _close_client(self, client_id: int, reason: str) -> None:
        try:
            ws = self.server._websock_server
            conn = ws._live_connections[client_id]
            asyncio.run_coroutine_threadsafe(conn.close(1008, reason), ws._background_event_loop)
        except (AttributeError, KeyError):
            pass

    # ---- data ------------------------------------------------------------------------------
    def scene_data(self, scene_id: str, *, reload: bool = False) -> sb.ViewerData:
        with self._lock:
            if not reload and scene_id in self._data:
                return self._data[scene_id]
        table = self.scenes()
        if scene_id not in table:
            raise KeyError(scene_id)
        ws = Path(table[scene_id][1])
        full, base = workspace_stamps(ws)  # before the files are read: a change meanwhile
        data = sb.ViewerData.load(ws)      # is seen by the next event or look
        with self._lock:
            self._data[scene_id] = data
            self._stamps[scene_id] = full
            self._base_stamps[scene_id] = base
        return data

    def scenes_for(self, user: Any) -> dict:
        """The scenes ``user`` may open (the dropdown lists only these)."""
        table = self.scenes()
        if self.can_open is None or user is None:
            return dict(table)
        return {sid: v for sid, v in table.items() if self.can_open(user, sid)}

    def clients_of(self, scene_id: str) -> list[ClientState]:
        with self._lock:
            return [c for c in self._clients.values() if c.scene_id == scene_id]

    def client_states(self) -> list[ClientState]:
        with self._lock:
            return list(self._clients.values())

    # ---- connection ------------------------------------------------------------------------
    def _on_connect(self, client: Any) -> None:
        ticket = self._take_ticket(client.client_id)
        if ticket is None and self.require_ticket:
            client.add_notification("Not authorised", "Open the viewer through OccuFly Studio.",
                                    color="red", auto_close_seconds=False)
            self._close_client(client.client_id, "viewer requires a ticket from the app")
            return
        st = ClientState(client=client, max_points=self.max_points)
        st.user = ticket.user if ticket else None
        st.view = ticket.view if ticket else None
        with self._lock:
            self._clients[client.client_id] = st
        scenes = self.scenes_for(st.user)
        scene_id = ticket.scene_id if ticket and ticket.scene_id in scenes else None
        if scene_id is None and scenes:
            scene_id = next(iter(scenes))
        self._build_gui(st, scenes, scene_id)
        if scene_id is not None:
            self.open_scene(st, scene_id, done=False)
            try:
                self._resume_or_focus(st, ticket)
            finally:
                st.ready.set()  # after the tab's state or the page's frame is in place
        else:
            st.gui["status"].content = "No scene has been imported yet."
            st.ready.set()

    def _resume_or_focus(self, st: ClientState, ticket: Ticket | None) -> None:
        """A reconnecting tab gets its state back; a page load opens at its ?frame= and
        selects its ?suspect=."""
        scene_id = st.scene_id
        if st.data is not None:
            snap = self.tabs.take(self._tab_key(st)) if st.view and st.data is not None \
                else None
            if snap is not None:  # the same tab reconnecting: put its state back
                st.restoring = snap
                try:
                    session_state.restore(self, st, snap)
                    st.restoring = None
                    st.client.add_notification(
                        "Reconnected", "Your selection and panel were kept.", color="blue",
                        auto_close_seconds=3.0)
                except Exception:  # noqa: BLE001 - a stale snapshot must not kill the tab
                    log.exception("viewer: restoring the tab state failed")
                return
        if ticket is not None and ticket.frame and st.data is not None:
            idx = self.resolve_frame(scene_id, ticket.frame, st.data)
            if idx is None:
                st.gui["cam_info"].content = f"Frame {md_text(ticket.frame)} is not in this scene."
            else:
                self.open_at_frame(st, idx)
        if ticket is not None and ticket.suspect and st.data is not None:
            self.select_suspect(st, ticket.suspect)

    def _tab_key(self, st: ClientState) -> tuple:
        return (user_key(st.user), st.scene_id, st.view)

    def _on_disconnect(self, client: Any) -> None:
        with self._lock:
            st = self._clients.pop(client.client_id, None)
        if st is not None and st.view and st.scene_id is not None and st.data is not None \
                and (st.ready.is_set() or st.restoring is not None):
            try:  # the tab may reconnect (network, restart): keep what it showed (or the
                # state a reconnect was still putting back when it dropped again)
                self.tabs.put(self._tab_key(st), st.restoring if st.restoring is not None
                              else session_state.snapshot(st))
            except Exception:  # noqa: BLE001
                log.exception("viewer: keeping the tab state failed")
        with self._lock:
            if st is not None and st.scene_id is not None and not any(
                    c.scene_id == st.scene_id for c in self._clients.values()):
                self._data.pop(st.scene_id, None)  # nobody looks at it any more
                self._stamps.pop(st.scene_id, None)
                self._base_stamps.pop(st.scene_id, None)


    def check_access(self) -> list[int]:
        """Disconnect every client whose user may no longer see its scene (``can_open``
        re-reads the user); returns the client ids closed. The client leaves ``_clients``
        at once, so no label update reaches it while its close is under way."""
        if self.can_open is None:
            return []
        closed = []
        for st in self.client_states():
            if st.user is None:
                continue
            try:
                ok = self.can_open(st.user, st.scene_id)
            except Exception:  # noqa: BLE001 - a database hiccup is retried next round
                log.warning("viewer: access check failed", exc_info=True)
                continue
            if ok:
                continue
            cid = st.client.client_id
            with self._lock:
                self._clients.pop(cid, None)
                if st.scene_id is not None and not any(
                        c.scene_id == st.scene_id for c in self._clients.values()):
                    self._data.pop(st.scene_id, None)
                    self._stamps.pop(st.scene_id, None)
                    self._base_stamps.pop(st.scene_id, None)
            self.revoked.append((user_key(st.user), st.scene_id))
            log.info("viewer: access of %s to scene %s withdrawn; socket closed",
                     user_key(st.user), st.scene_id)
            self._close_client(cid, "access to this scene was withdrawn")
            closed.append(cid)
        return closed

    def _access_loop(self) -> None:
        while not self._stop.wait(self.access_check_s):
            try:
                self.check_access()
            except Exception:  # noqa: BLE001 - keep the thread alive
                log.exception("viewer: access check failed")


# ---- helpers ---------------------------------------------------------------------------------
def _read_prefs(path: Path | None) -> dict:
    if path is None or not path.is_file():
        return {}

    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


