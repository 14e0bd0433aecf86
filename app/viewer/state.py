"""What the viewer keeps per browser tab and per connection: the one-time ticket a connection
arrives with (:class:`Ticket`), the tab's state (:class:`ClientState`), and the callables the
app hands the viewer (scenes, frame states, masks, review items)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from app.viewer import scene_builder as sb

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
    grid_classes: dict[str, int] = field(default_factory=dict)  # grid node name -> class id
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
    # level of detail (app.viewer.point_lod): the plan, the chunks sent by (group, class id)
    # and their handles; point_handles then holds each class's frame, point_nodes the
    # chunks merged by class. lod_gen stops a refinement made stale by a new send.
    lod_plan: Any = None
    chunks: dict[tuple[int, int], sb.PointNode] = field(default_factory=dict)
    chunk_handles: dict[tuple[int, int], Any] = field(default_factory=dict)
    sent_groups: set[int] = field(default_factory=set)
    lod_gen: int = 0
    lod_started: float = 0.0
    lod_done_at: float = 0.0
    first_sent_at: float = 0.0  # perf_counter when the first points of a scene were sent
    lod_done: threading.Event = field(default_factory=threading.Event)
    detail_handles: dict[int, Any] = field(default_factory=dict)  # /points/<class>/detail
    # the resting level of detail this browser draws (scene_view._refine): whether the user
    # set "LOD max points" (then every point of the plan is sent), and (points shown, points
    # planned, seconds a frame) where the refinement stopped because this browser draws
    # slowly, else None
    lod_explicit: bool = False
    lod_stopped: tuple[int, int, float] | None = None
    lod_gui_sync: bool = False  # the viewer writes its choice into the field: not the user's
    moving: bool = False  # the camera moves: the detail frames are hidden
    updating: int = 0  # corrections whose chunks the browser has not drawn yet: hidden too
    last_move: float = 0.0
    motion_hooked: bool = False
    motion_lock: threading.Lock = field(default_factory=threading.Lock)
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


def user_key(user: Any) -> str | None:
    """The name a user is known by in the viewer's prefs and tab states (None: anonymous)."""
    if user is None:
        return None
    name = user.get("username") if isinstance(user, dict) else getattr(user, "username", None)
    return str(name) if name else None
