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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from app.viewer import corrections_panel, session_state
from app.viewer import scene_builder as sb
from app.viewer.md import md_text
from occufly.sampling import FrameGridSpec, sample_frame
from occufly.workspace import Workspace

log = logging.getLogger(__name__)

TICKET_HEADER = "X-Occufly-Viewer-Ticket"
TICKET_TTL_S = 60.0

# scene id -> (display name, workspace folder)
ScenesFn = Callable[[], Mapping[str, tuple[str, Path]]]
# scene id -> {frame index: viewer state}
FrameStatesFn = Callable[[str], Mapping[int, str]]
# (scene id, frame index) -> (h, w) uint8 raw-id mask or None
FrameMaskFn = Callable[[str, int], np.ndarray | None]
ReviewItemFn = Callable[[str, list[int], str, Any], Any]


@dataclass
class Ticket:
    user: Any
    scene_id: str | None
    expires: float
    frame: str | None = None  # ?frame= of the page: fly to that camera on connect
    suspect: str | None = None  # ?suspect= of the page: select that suspect's points
    view: str | None = None  # the page load's view id: a reconnect restores its tab state


@dataclass
class ClientState:
    """Everything one browser tab sees."""

    client: Any
    user: Any = None
    scene_id: str | None = None
    data: sb.ViewerData | None = None
    subsample: np.ndarray | None = None
    mode: str = "semantic"
    point_size: float = 0.05
    point_size_set: bool = False
    max_points: int = sb.DEFAULT_MAX_POINTS
    class_visible: dict[int, bool] = field(default_factory=dict)
    point_handles: dict[int, Any] = field(default_factory=dict)
    point_nodes: dict[int, sb.PointNode] = field(default_factory=dict)
    grid_handles: dict[str, Any] = field(default_factory=dict)
    frustum_handles: dict[int, Any] = field(default_factory=dict)
    selection: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_index: int | None = None
    highlighted: int | None = None  # frame whose frustum is highlighted (Open in 3D)
    camera_filter: str = sb.CAMERA_FILTERS[0]  # "Show cameras"
    highlight_restore: tuple = ((0, 0, 0), 1.0)
    gui: dict[str, Any] = field(default_factory=dict)
    class_boxes: dict[int, Any] = field(default_factory=dict)
    lock: threading.RLock = field(default_factory=threading.RLock)
    sent_points: int = 0
    ready: threading.Event = field(default_factory=threading.Event)
    view: str | None = None  # the tab's view id (app.viewer.session_state)
    last_edit: dict | None = None  # the last correction made here ("File as proposal")
    restoring: dict | None = None  # the tab state being put back (kept if the socket drops)


def default_scenes(data_dir: Path) -> ScenesFn:
    """Scenes found on disk: every ``scene.json`` up to three levels below ``data_dir``;
    the id is the workspace folder name."""

    def scan() -> dict[str, tuple[str, Path]]:
        out: dict[str, tuple[str, Path]] = {}
        root = Path(data_dir)
        for pattern in ("*/scene.json", "*/*/scene.json", "*/*/*/scene.json"):
            for p in sorted(root.glob(pattern)):
                out.setdefault(p.parent.name, (p.parent.name, p.parent))
        return out

    return scan


class ViewerService:
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
                 max_sockets_per_user: int | None = None) -> None:
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
        # at most this many open viewer sockets per user and process (the proxy refuses more,
        # 1008); None: no cap. open_sockets: the proxy's count per user name
        self.max_sockets_per_user = max_sockets_per_user
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
        self._stamps: dict[str, str] = {}
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
            import viser

            server = viser.ViserServer(host=self.host, port=0, verbose=False)
            server.gui.configure_theme(control_layout="floating", show_share_button=False,
                                       dark_mode=False, brand_color=(40, 120, 255))
            server.scene.set_up_direction("+z")
            server.on_client_connect(self._on_connect)
            server.on_client_disconnect(self._on_disconnect)
            self.server = server
            self._stop.clear()
            self._worker = threading.Thread(target=self._refresh_loop, name="viewer-refresh",
                                            daemon=True)
            self._worker.start()
            if self.can_open is not None and self.access_check_s > 0:
                self._access_worker = threading.Thread(target=self._access_loop,
                                                       name="viewer-access", daemon=True)
                self._access_worker.start()

    def stop(self) -> None:
        with self._start_lock:
            if self.server is None:
                return
            self._stop.set()
            self._wake.set()
            if self._worker is not None:
                self._worker.join(timeout=5)
            if self._access_worker is not None:
                self._access_worker.join(timeout=5)
            self.server.stop()
            self.server = None
            self._clients.clear()

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
        data = sb.ViewerData.load(ws)
        with self._lock:
            self._data[scene_id] = data
            self._stamps[scene_id] = _stamp(ws)
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
        return (_user_key(st.user), st.scene_id, st.view)

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

    # ---- GUI -------------------------------------------------------------------------------
    def _build_gui(self, st: ClientState, scenes: Mapping[str, tuple[str, Path]],
                   scene_id: str | None) -> None:
        gui = st.client.gui
        g = st.gui
        ids = list(scenes)
        labels = [f"{scenes[s][0]} ({s})" for s in ids]
        g["status"] = gui.add_markdown("Loading...")
        g["scene"] = gui.add_dropdown("Scene", labels or ["(none)"],
                                      initial_value=labels[ids.index(scene_id)] if scene_id in ids else None)
        g["mode"] = gui.add_dropdown("Colour", list(sb.COLOUR_MODES), initial_value=st.mode)
        g["size"] = gui.add_slider("Point size", min=0.005, max=3.0, step=0.005,
                                   initial_value=st.point_size)
        g["lod"] = gui.add_number("LOD max points", initial_value=st.max_points, min=1000,
                                  max=50_000_000, step=1000)
        g["classes"] = gui.add_folder("Classes")
        with gui.add_folder("Voxel grids", expand_by_default=False):
            g["grid_scene"] = gui.add_checkbox("Scene grid", initial_value=False)
            g["grid_info"] = gui.add_markdown("")
            g["grid_frame"] = gui.add_dropdown("Camera grid of frame", ["(none)"])
            g["grid_surface"] = gui.add_checkbox("Surface voxels only", initial_value=False)
        with gui.add_folder("Review"):
            g["sel_info"] = gui.add_markdown("No points selected.")
            g["sel_btn"] = gui.add_button("Select points (drag a rectangle)")
            g["comment"] = gui.add_text("Comment", initial_value="")
            g["file_btn"] = gui.add_button("File review item", disabled=True)
        with gui.add_folder("Camera"):
            g["frusta"] = gui.add_dropdown("Show cameras", list(sb.CAMERA_FILTERS),
                                           initial_value=sb.CAMERA_FILTERS[0])
            g["frusta_info"] = gui.add_markdown("")
            g["cam_info"] = gui.add_markdown("Click a camera frustum.")
            g["goto"] = gui.add_button("Move view to camera", disabled=True)
        corrections_panel.build(self, st)  # selection tools, relabel, undo/redo, legend
        g["image"] = None
        g["mask"] = None

        @g["scene"].on_update
        def _(_e: Any) -> None:
            if g["scene"].value in labels:
                self.open_scene(st, ids[labels.index(g["scene"].value)])

        @g["mode"].on_update
        def _(_e: Any) -> None:
            st.mode = g["mode"].value
            if "legend" in g:
                g["legend"].content = corrections_panel.legend(st.mode)
            self.send_points(st)

        @g["frusta"].on_update
        def _(_e: Any) -> None:
            if st.data is not None and g["frusta"].value != st.camera_filter:
                st.camera_filter = g["frusta"].value
                self.remember(st.user, camera_filter=st.camera_filter)
                self.send_frusta(st)

        @g["size"].on_update
        def _(_e: Any) -> None:
            if abs(float(g["size"].value) - st.point_size) < 1e-9:
                return  # our own default being applied
            st.point_size_set = True
            st.point_size = float(g["size"].value)
            with st.lock:
                for h in st.point_handles.values():
                    h.point_size = st.point_size

        @g["lod"].on_update
        def _(_e: Any) -> None:
            st.max_points = max(1000, int(g["lod"].value))
            st.subsample = None
            self.send_points(st)

        @g["grid_scene"].on_update
        def _(_e: Any) -> None:
            if g["grid_scene"].value and st.data is not None and st.data.grid is None:
                # before voxelize there is no grid: say so instead of silently doing nothing
                msg = ("This scene has no voxel grid yet: run **Voxelize scene** on the admin "
                       "page first, then tick *Scene grid* again.")
                g["grid_info"].content = msg
                st.client.add_notification("No scene grid yet", msg.replace("**", "")
                                           .replace("*", ""), color="yellow",
                                           auto_close_seconds=8.0)
                g["grid_scene"].value = False
                return
            if g["grid_scene"].value:  # (unticking above re-enters here: keep the note)
                g["grid_info"].content = ""
            self.send_grids(st)

        @g["grid_frame"].on_update
        def _(_e: Any) -> None:
            self.send_grids(st)

        @g["grid_surface"].on_update
        def _(_e: Any) -> None:
            self.send_grids(st)

        @g["sel_btn"].on_click
        def _(_e: Any) -> None:
            self._arm_rect_select(st)

        @g["file_btn"].on_click
        def _(_e: Any) -> None:
            self.file_review_item(st, g["comment"].value)

        @g["goto"].on_click
        def _(_e: Any) -> None:
            if st.frame_index is not None:
                self.move_to_camera(st, st.frame_index)

    def _arm_rect_select(self, st: ClientState) -> None:
        scene = st.client.scene
        st.gui["sel_info"].content = "Drag a rectangle on the view..."

        def on_rect(event: Any) -> None:
            scene.remove_rect_select_callback(on_rect)
            cam = event.client.camera
            ids = self.select_rect(st, np.asarray(cam.position), np.asarray(cam.wxyz),
                                   float(cam.fov), float(cam.aspect), event.screen_min,
                                   event.screen_max)
            st.gui["sel_info"].content = f"**{len(ids)}** points selected."
            st.gui["file_btn"].disabled = len(ids) == 0
            corrections_panel.after_selection(self, st)  # highlight + counts by class

        scene.on_rect_select()(on_rect)

    def _rebuild_class_boxes(self, st: ClientState) -> None:
        """One checkbox per class present; existing boxes are kept (only their counts are
        relabelled) so a reviewer's click is never lost to a live refresh."""
        data = st.data
        if data is None:
            return
        lab = data.labels
        if lab is not None:
            counts = np.bincount(np.asarray(lab), minlength=256)
        else:
            counts = np.zeros(256, np.int64)
            counts[0] = data.scene.n_points
        present = set(np.flatnonzero(counts).tolist())
        for cid in [c for c in st.class_boxes if c not in present]:
            st.class_boxes.pop(cid).remove()
        for cid in sorted(present):
            name = sb.class_name(data.taxonomy, cid)
            label = f"{name} ({int(counts[cid]):,})"
            box = st.class_boxes.get(cid)
            if box is not None:
                if box.label != label:
                    box.label = label
                continue
            with st.gui["classes"]:
                box = st.client.gui.add_checkbox(label, initial_value=st.class_visible.get(cid, True))

            def toggle(_e: Any, cid: int = cid, box: Any = box) -> None:
                self.set_class_visible(st, cid, bool(box.value))

            box.on_update(toggle)
            st.class_boxes[cid] = box

    # ---- scene content ---------------------------------------------------------------------
    def open_scene(self, st: ClientState, scene_id: str, *, done: bool = True) -> None:
        """Load and send ``scene_id`` to client ``st``; ``done`` False leaves ``st.ready``
        to the caller (a connect sets it once the tab's state or frame is in place)."""
        st.ready.clear()
        if scene_id not in self.scenes_for(st.user):  # the dropdown lists only these; a
            st.gui["status"].content = f"You cannot open scene {md_text(scene_id)}."  # stale list
            st.ready.set()
            return
        with st.lock:
            st.scene_id = scene_id
            st.gui["status"].content = f"Loading scene **{md_text(scene_id)}**..."
            try:
                st.data = self.scene_data(scene_id)
            except Exception as e:  # noqa: BLE001 - show the reason to the reviewer
                log.exception("viewer: cannot open scene %s", scene_id)
                st.gui["status"].content = f"Cannot open scene {md_text(scene_id)}: {md_text(e)}"
                st.ready.set()
                return
            st.client.scene.reset()
            st.client.scene.set_up_direction("+z")
            st.point_handles.clear()
            st.point_nodes.clear()
            st.grid_handles.clear()
            st.frustum_handles.clear()
            st.subsample = None
            st.selection = np.zeros(0, np.int64)
            st.class_visible = {}
            for b in st.class_boxes.values():
                b.remove()
            st.class_boxes.clear()
            self._rebuild_class_boxes(st)
            if not st.point_size_set:
                shown = min(st.max_points, st.data.scene.n_points)
                st.point_size = round(sb.default_point_size(st.data, shown), 3)
                st.gui["size"].value = st.point_size
            frames = ["(none)"] + [f.stem for f in st.data.scene.frames]
            st.gui["grid_frame"].options = frames
            st.camera_filter = self.pref(st.user, "camera_filter",
                                         sb.default_camera_filter(len(st.data.scene.frames)))
            if st.camera_filter not in sb.CAMERA_FILTERS:
                st.camera_filter = sb.default_camera_filter(len(st.data.scene.frames))
            st.gui["frusta"].value = st.camera_filter
            self._place_camera(st)
            d = st.data
            n_show = min(st.max_points, d.scene.n_points)
            if self.preview_points and n_show > 4 * self.preview_points:
                full = sb.stratified_subsample(d.labels, d.scene.n_points, st.max_points)
                st.subsample = sb.stratified_subsample(d.labels, d.scene.n_points,
                                                       self.preview_points)
                self.send_points(st)  # quick first picture
                self.send_frusta(st)
                st.subsample = full
            self.send_points(st)
            if not st.frustum_handles:
                self.send_frusta(st)
            self.send_grids(st)
            corrections_panel.on_scene_opened(self, st)
            d = st.data
            lifted = "lifted labels" if d.labels is not None else "no lifted labels yet (RGB only)"
            st.gui["status"].content = (
                f"**{md_text(scene_id)}**: {d.scene.n_points:,} points, {len(d.scene.frames)} cameras, "
                f"{lifted}; showing {st.sent_points:,} points."
            )
        if done:
            st.ready.set()

    def _place_camera(self, st: ClientState) -> None:
        xyz = np.asarray(st.data.scene.xyz[:: max(1, st.data.scene.n_points // 50_000)], np.float64)
        if len(xyz) == 0:
            return
        c = xyz.mean(axis=0)
        ext = sb.scene_extent(st.data)
        cam = st.client.camera
        cam.up_direction = (0.0, 0.0, 1.0)
        cam.position = tuple(c + np.array([0.0, -0.9 * ext, 0.8 * ext]))
        cam.look_at = tuple(c)

    def send_points(self, st: ClientState, classes: set[int] | None = None) -> list[sb.PointNode]:
        """(Re)send point nodes of ``classes`` (all when None) to this client."""
        with st.lock:
            d = st.data
            if d is None:
                return []
            if st.subsample is None:
                st.subsample = sb.stratified_subsample(d.labels, d.scene.n_points, st.max_points)
            nodes = sb.build_point_nodes(d, mode=st.mode, classes=classes, subsample=st.subsample)
            present = {nd.class_id for nd in nodes}
            stale = [cid for cid in st.point_handles if (classes is None or cid in classes)
                     and cid not in present]
            for cid in stale:
                st.point_handles.pop(cid).remove()
                st.point_nodes.pop(cid, None)
            with st.client.atomic():
                st.point_handles.update(sb.send_point_nodes(
                    st.client.scene, nodes, point_size=st.point_size, visible=st.class_visible))
            st.point_nodes.update({nd.class_id: nd for nd in nodes})
            st.client.flush()
            st.sent_points = int(sum(len(nd.point_ids) for nd in st.point_nodes.values()))
            return nodes

    def send_frusta(self, st: ClientState) -> None:
        """(Re)send the camera frusta the "Show cameras" choice keeps (the focused frame of
        "Open in 3D" always); a survey of thousands of frames starts with only the selected
        and annotated ones."""
        with st.lock:
            d = st.data
            states = dict(self.frame_states(st.scene_id)) if self.frame_states else {}
            every = sb.frustum_nodes(d.scene, states)
            keep = {st.highlighted} if st.highlighted is not None else set()
            nodes = sb.filter_frustum_nodes(every, st.camera_filter, keep)
            for h in st.frustum_handles.values():
                h.remove()
            scale = 0.04 * sb.scene_extent(d)
            st.frustum_handles = sb.send_frustum_nodes(st.client.scene, nodes, scale=scale)
            if st.gui.get("frusta_info") is not None:
                st.gui["frusta_info"].content = f"{len(nodes):,} of {len(every):,} cameras shown."
            for idx, h in st.frustum_handles.items():
                def clicked(_e: Any, idx: int = idx) -> None:
                    self.show_frame(st, idx)

                h.on_click(clicked)
            if st.highlighted is not None:  # new handles: highlight the focused frame again
                idx, st.highlighted = st.highlighted, None
                self.highlight_frustum(st, idx)

    def send_grids(self, st: ClientState) -> None:
        with st.lock:
            for h in st.grid_handles.values():
                h.remove()
            st.grid_handles.clear()
            d = st.data
            if d is None:
                return
            surface_only = bool(st.gui["grid_surface"].value)
            nodes: list[sb.VoxelNode] = []
            if st.gui["grid_scene"].value and d.grid is not None:
                from app.viewer.grid_lod import scene_grid_nodes_lod  # no per-voxel freeze

                nodes += scene_grid_nodes_lod(d.grid, d.scene.origin, d.taxonomy)
            frame = st.gui["grid_frame"].value
            if frame and frame != "(none)":
                cg = load_camera_grid(d, d.scene.frame_index(frame))
                if cg is not None:
                    nodes += sb.camera_grid_nodes(*cg, taxonomy=d.taxonomy,
                                                  surface_only=surface_only)
            st.grid_handles = sb.send_voxel_nodes(st.client.scene, nodes, st.class_visible)

    def set_class_visible(self, st: ClientState, class_id: int, visible: bool) -> None:
        """Show/hide a class's points and voxels. Takes no lock on purpose: a toggle must
        not wait for a refresh that is re-sending other classes (dict reads are atomic)."""
        st.class_visible[class_id] = visible
        h = st.point_handles.get(class_id)
        if h is not None:
            h.visible = visible
        name = sb.class_name(st.data.taxonomy, class_id) if st.data else None
        for n, gh in list(st.grid_handles.items()):
            if n.rsplit("/", 1)[-1] == name:
                gh.visible = visible

    # ---- cameras ---------------------------------------------------------------------------
    def show_frame(self, st: ClientState, frame_index: int) -> None:
        d = st.data
        fr = d.scene.frames[frame_index]
        st.frame_index = frame_index
        states = dict(self.frame_states(st.scene_id)) if self.frame_states else {}
        state = states.get(frame_index, "not_selected")
        st.gui["cam_info"].content = f"**{md_text(fr.stem)}** - {md_text(state.replace('_', ' '))}"
        st.gui["goto"].disabled = False
        img = _frame_image(d, frame_index)
        mask = self.frame_mask(st.scene_id, frame_index) if self.frame_mask else None
        gui = st.client.gui
        for key in ("image", "mask"):
            if st.gui.get(key) is not None:
                st.gui[key].remove()
                st.gui[key] = None
        if img is not None:
            st.gui["image"] = gui.add_image(img, label="image", format="jpeg")
        if mask is not None:
            rgb = d.taxonomy.colour_lut()[np.asarray(mask, np.uint8)]
            st.gui["mask"] = gui.add_image(_thumb(rgb), label="mask", format="png")

    def resolve_frame(self, scene_id: str, frame: str, data: sb.ViewerData) -> int | None:
        """The frame index named by a page's ``?frame=`` (app frame id via the hook, else a
        frame index or stem); None when it is not a frame of the scene."""
        n = len(data.scene.frames)
        if self.frame_index is not None:
            try:
                idx = self.frame_index(scene_id, frame)
            except Exception:  # noqa: BLE001 - a bad id is just not found
                log.exception("viewer: frame_index(%s, %s)", scene_id, frame)
                idx = None
            return int(idx) if idx is not None and 0 <= int(idx) < n else None
        if frame.isdigit() and int(frame) < n:
            return int(frame)
        stems = [f.stem for f in data.scene.frames]
        return stems.index(frame) if frame in stems else None

    def open_at_frame(self, st: ClientState, frame_index: int) -> None:
        """The page was opened for a frame ("3D" on the reviewer / annotator page or a
        suspect): look through that frame's camera (pose and vertical field of view), its
        frustum highlighted and the other cameras hidden for this tab ("Show cameras" brings
        them back; the reviewer's saved choice is not changed)."""
        st.camera_filter = sb.CAMERA_FILTERS[-1]  # "none": only the kept (highlighted) one
        st.gui["frusta"].value = st.camera_filter  # equal to st's: the callback does nothing
        st.highlighted = frame_index
        self.send_frusta(st)  # highlights it
        self.show_frame(st, frame_index)
        self.move_to_camera(st, frame_index)
        n = len(st.data.scene.frames)
        st.gui["frusta_info"].content = (
            f"Opened at **{md_text(st.data.scene.frames[frame_index].stem)}** (highlighted); "
            f"the other {n - 1:,} cameras are hidden: choose *all* above to show them.")

    def focus_frame(self, st: ClientState, frame_index: int) -> None:
        """Open in 3D: show the frame's panel, fly just behind its camera (its frustum and
        what it sees in front) and highlight its frustum."""
        self.show_frame(st, frame_index)
        fr = st.data.scene.frames[frame_index]
        T = np.linalg.inv(np.asarray(fr.T_cam_world, np.float64))
        c, fwd, up = T[:3, 3], T[:3, 2], -T[:3, 1]
        back = 0.12 * sb.scene_extent(st.data)
        cam = st.client.camera
        with st.client.atomic():
            cam.position = tuple(c - back * fwd + 0.3 * back * up)
            cam.look_at = tuple(c + 20.0 * fwd)
        self.highlight_frustum(st, frame_index)

    def select_suspect(self, st: ClientState, key: str) -> np.ndarray:
        """Select the points of the scene's suspect ``key`` (highlighted, counted by class,
        ready to relabel or file as a review item); a key the current ranking no longer
        has (the labels changed) says so and selects nothing."""
        ids = None
        if self.suspect_points is not None and st.scene_id is not None:
            try:
                ids = self.suspect_points(st.scene_id, key)
            except Exception:  # noqa: BLE001 - a lookup failure is a note, not a dead viewer
                log.exception("viewer: suspect_points(%s, %s)", st.scene_id, key)
        n = st.data.scene.n_points if st.data is not None else 0
        if ids is None:
            st.gui["sel_info"].content = (f"Suspect {md_text(key)} is not in the current list "
                                          "(the labels changed): reopen it from the Suspects tab.")
            return np.zeros(0, np.int64)
        ids = np.asarray(ids, np.int64).reshape(-1)
        ids = np.unique(ids[(ids >= 0) & (ids < n)])
        with st.lock:
            st.selection = ids
        st.gui["sel_info"].content = f"Suspect {md_text(key)}: **{len(ids):,}** points selected."
        corrections_panel.after_selection(self, st)  # highlight + counts by class, relabel
        if len(ids) and st.frame_index is None:  # no frame: the region in the middle of the
            # view, seen from above (opened at a frame, the view stays at that frame's camera,
            # the one that sees the suspect best)
            xyz = np.asarray(st.data.scene.xyz[ids], np.float64)
            c = xyz.mean(axis=0)
            size = float(np.linalg.norm(xyz.max(axis=0) - xyz.min(axis=0)))
            d = max(4.0 * size, 0.15 * sb.scene_extent(st.data))
            if st.frame_index is not None:
                T = np.linalg.inv(np.asarray(st.data.scene.frames[st.frame_index].T_cam_world,
                                             np.float64))
                fwd = T[:3, 2]
            else:
                fwd = np.array([0.0, 0.0, -1.0])
            with st.client.atomic():
                st.client.camera.position = tuple(float(v) for v in c - d * fwd)
                st.client.camera.look_at = tuple(float(v) for v in c)
        return ids

    def highlight_frustum(self, st: ClientState, frame_index: int | None) -> None:
        if (frame_index is not None and frame_index not in st.frustum_handles
                and st.data is not None and 0 <= frame_index < len(st.data.scene.frames)):
            # hidden by "Show cameras": send the frusta again with this one kept (fresh
            # handles, so nothing to restore); send_frusta highlights it
            st.highlighted = frame_index
            self.send_frusta(st)
            return
        prev = st.highlighted
        if prev is not None and prev in st.frustum_handles and prev != frame_index:
            h = st.frustum_handles[prev]
            h.color, h.scale = st.highlight_restore
        st.highlighted = frame_index
        h = st.frustum_handles.get(frame_index) if frame_index is not None else None
        if h is not None:
            if prev != frame_index:
                st.highlight_restore = (h.color, h.scale)
            h.color = sb.HIGHLIGHT_COLOUR
            h.scale = 2.0 * st.highlight_restore[1]

    def move_to_camera(self, st: ClientState, frame_index: int) -> None:
        fr = st.data.scene.frames[frame_index]
        T = np.linalg.inv(np.asarray(fr.T_cam_world, np.float64))
        cam = st.client.camera
        fov = 2.0 * float(np.arctan2(fr.camera.height / 2.0, fr.camera.focal[1]))
        with st.client.atomic():
            cam.fov = fov  # the view then matches the frame's image (vertical fov)
            cam.wxyz = sb.matrix_to_quat(T[:3, :3])
            cam.position = tuple(T[:3, 3])
            cam.look_at = tuple(T[:3, 3] + 20.0 * T[:3, 2])

    # ---- review ----------------------------------------------------------------------------
    def select_rect(self, st: ClientState, position: np.ndarray, wxyz: np.ndarray, fov: float,
                    aspect: float, screen_min: tuple[float, float],
                    screen_max: tuple[float, float]) -> np.ndarray:
        """Point ids (into the full cloud) of visible, sent points inside the rectangle."""
        with st.lock:
            parts = []
            for cid, nd in st.point_nodes.items():
                if not st.class_visible.get(cid, True):
                    continue
                inside = sb.points_in_screen_rect(nd.xyz, position, wxyz, fov, aspect,
                                                  screen_min, screen_max)
                parts.append(nd.point_ids[inside])
            st.selection = np.sort(np.concatenate(parts)) if parts else np.zeros(0, np.int64)
            return st.selection

    def file_review_item(self, st: ClientState, comment: str) -> dict | None:
        ids = [int(i) for i in st.selection]
        if not ids or st.scene_id is None:
            return None
        item = {"scene_id": st.scene_id, "point_ids": ids, "comment": comment, "user": st.user}
        result = None
        if self.on_review_item is not None:
            try:
                import inspect

                kw = ({"frame_index": st.frame_index} if "frame_index" in
                      inspect.signature(self.on_review_item).parameters else {})
                result = self.on_review_item(st.scene_id, ids, comment, st.user, **kw)
            except Exception as e:  # noqa: BLE001 - tell the reviewer instead of dying
                log.exception("viewer: filing a review item failed")
                st.client.add_notification("Review item not filed", str(e), color="red")
                return None
        self.filed_items.append(item)
        st.client.add_notification("Review item filed",
                                   f"{len(ids)} points in scene {st.scene_id}", color="green")
        st.gui["sel_info"].content = "No points selected."
        st.gui["file_btn"].disabled = True
        st.selection = np.zeros(0, np.int64)
        corrections_panel.after_selection(self, st)
        return {"item": item, "result": result}

    # ---- per-user preferences --------------------------------------------------------------
    def pref(self, user: Any, key: str, default: Any = None) -> Any:
        return self.prefs.get(_user_key(user), {}).get(key, default)

    def remember(self, user: Any, **values: Any) -> None:
        """Keep a viewer preference of ``user`` (e.g. the camera filter) for their next visit."""
        k = _user_key(user)
        if k is None:
            return
        with self._lock:
            self.prefs.setdefault(k, {}).update(values)
            if self.prefs_path is not None:
                import json

                from occufly.fsutil import atomic_write_text

                try:
                    self.prefs_path.parent.mkdir(parents=True, exist_ok=True)
                    atomic_write_text(self.prefs_path, json.dumps(self.prefs))
                except OSError:
                    log.warning("viewer: cannot keep preferences in %s", self.prefs_path)

    # ---- live ------------------------------------------------------------------------------
    def refresh(self, scene_id: str, classes: set[int] | list[int] | None = None) -> None:
        """Queue a re-send of the affected class nodes of ``scene_id`` to its open viewers.

        ``classes`` None means: work out which classes changed by comparing old and new
        labels/confidence/origin. Returns at once; the work runs in the refresh thread and
        several calls for one scene within a cycle are merged.
        """
        with self._lock:
            prev = self._pending.get(scene_id, set())
            if classes is None or prev is None:
                self._pending[scene_id] = None
            else:
                self._pending[scene_id] = set(prev) | {int(c) for c in classes}
        self._wake.set()

    def on_labels_updated(self, scene_id: str, stamp: str | None = None) -> bool:
        """Event handler: queue a refresh of ``scene_id`` unless nobody has it open or what is
        loaded already carries ``stamp``. Returns whether a refresh was queued."""
        with self._lock:
            if scene_id not in self._data:
                return False
            if stamp is not None and self._stamps.get(scene_id) == stamp:
                return False
        self.refresh(scene_id)
        return True

    def refresh_now(self, scene_id: str, classes: set[int] | None = None) -> set[int]:
        """Synchronous refresh; returns the class ids re-sent."""
        with self._lock:
            old = self._data.get(scene_id)
        if old is None:
            return set()  # nobody has it open
        new = self.scene_data(scene_id, reload=True)
        affected = set(classes) if classes is not None else changed_classes(old, new)
        for st in self.clients_of(scene_id):
            with st.lock:
                st.data = new
                if new.labels is not None and old.labels is None:
                    st.subsample = None
                    affected = None  # first labels: everything changes
                if affected is None or affected:
                    self._rebuild_class_boxes(st)
                    self.send_points(st, None if affected is None else affected)
        return set() if affected is None else affected

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
            self.revoked.append((_user_key(st.user), st.scene_id))
            log.info("viewer: access of %s to scene %s withdrawn; socket closed",
                     _user_key(st.user), st.scene_id)
            self._close_client(cid, "access to this scene was withdrawn")
            closed.append(cid)
        return closed

    def _access_loop(self) -> None:
        while not self._stop.wait(self.access_check_s):
            try:
                self.check_access()
            except Exception:  # noqa: BLE001 - keep the thread alive
                log.exception("viewer: access check failed")

    def _refresh_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(timeout=self.watch_interval_s)  # None: until an event
            self._wake.clear()
            if self._stop.is_set():
                return
            with self._lock:
                pending, self._pending = self._pending, {}
                open_scenes = {c.scene_id for c in self._clients.values() if c.scene_id}
                stamps = dict(self._stamps)
                table = None
            watched = open_scenes if self.watch_interval_s else set()
            for sid in watched - set(pending):
                try:
                    table = table if table is not None else self.scenes()
                    if sid in table and _stamp(Path(table[sid][1])) != stamps.get(sid):
                        pending[sid] = None
                except Exception:  # noqa: BLE001
                    log.exception("viewer: watching scene %s failed", sid)
            for sid, classes in pending.items():
                try:
                    self.refresh_now(sid, classes)
                except Exception:  # noqa: BLE001 - keep the refresh thread alive
                    log.exception("viewer: refresh of scene %s failed", sid)


# ---- helpers ---------------------------------------------------------------------------------
def _user_key(user: Any) -> str | None:
    if user is None:
        return None
    name = user.get("username") if isinstance(user, dict) else getattr(user, "username", None)
    return str(name) if name else None


def _read_prefs(path: Path | None) -> dict:
    if path is None or not path.is_file():
        return {}

    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def _stamp(ws: Path) -> str:
    return Workspace(ws).stamp()


def changed_classes(old: sb.ViewerData, new: sb.ViewerData) -> set[int] | None:
    """Classes whose points changed label, confidence or origin; None = everything."""
    if (old.labels is None) != (new.labels is None) or old.scene.n_points != new.scene.n_points:
        return None
    if new.labels is None:
        return set()
    ol, nl = np.asarray(old.labels), np.asarray(new.labels)
    changed = ol != nl
    for a, b in ((old.confidence, new.confidence), (old.origin, new.origin),
                 (old.direct, new.direct)):
        if (a is None) != (b is None):
            return None
        if a is not None:
            changed |= np.asarray(a) != np.asarray(b)
    return {int(c) for c in np.union1d(np.unique(ol[changed]), np.unique(nl[changed]))}


def _thumb(img: np.ndarray, max_side: int = 320) -> np.ndarray:
    h, w = img.shape[:2]
    step = max(1, int(np.ceil(max(h, w) / max_side)))
    return np.ascontiguousarray(img[::step, ::step])


def _frame_image(d: sb.ViewerData, frame_index: int) -> np.ndarray | None:
    fr = d.scene.frames[frame_index]
    if not fr.image_path:
        return None
    p = Path(fr.image_path)
    if not p.is_absolute() and d.workspace is not None:
        p = d.workspace / p
    if not p.is_file():
        return None

    with Image.open(p) as im:
        im.draft("RGB", (640, 640))
        im = im.convert("RGB")
        im.thumbnail((320, 320))
        return np.asarray(im)


def load_camera_grid(d: sb.ViewerData, frame_index: int, spec: Any = None) -> tuple | None:
    """(labels, invalid, occluded, surface, T_cam_world, voxel_size) of a frame sampled from
    the scene grid with ``occufly.sampling.sample_frame`` (default FrameGridSpec), or None."""
    if d.grid is None:
        return None

    spec = spec or FrameGridSpec()
    fr = d.scene.frames[frame_index]
    gt = sample_frame(d.grid, fr.camera, fr.T_cam_world, d.scene.origin, spec)
    return gt.labels, gt.invalid, gt.occluded, gt.surface, fr.T_cam_world, spec.voxel_size
