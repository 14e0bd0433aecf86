"""A viewer tab's state across reconnects: selection, panel choices, camera, focused frame.

viser's browser client reopens its websocket by itself whenever it drops (a network blip, an
app restart, a proxy in between); the server sees a *new* client and used to build a fresh
panel: the selection was gone, the "Tool" / "Relabel to" choices were back to their defaults
and the view flew back to the page's frame (issue 40, defect 4). Now:

- The page load (``GET /viewer/``) gives the tab a *view id* (cookie ``occufly_viewer_view``,
  new on every load, see :mod:`app.viewer.proxy`); the socket's ticket carries it.
- When a client disconnects, :func:`snapshot` records what its tab showed under
  ``(user, scene, view)`` in :class:`SessionStore` (kept ``ttl_s``, 30 min by default; with a
  folder also on disk, so an app restart keeps it).
- The next connect with the same user, scene and view id -- a reconnect, not a new page
  load -- takes the snapshot and :func:`restore` puts it back: selection (highlighted and
  counted), every choice of the "Correct labels" panel, the colour mode, classes shown,
  point size, "Show cameras", the frame's panel and highlight, the last correction (for
  "File as proposal") and the camera.

A reload of the page (or a new "3D" link) has a new view id and opens fresh, at its frame.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from app.viewer import corrections_panel
from occufly.fsutil import atomic_write_bytes

log = logging.getLogger(__name__)

#: the panel inputs kept across a reconnect (ClientState.gui keys)
PANEL_KEYS = ("tool", "sel_mode", "f_class", "f_origin", "f_hmin", "f_hmax", "brush_r",
              "to_class", "comment")
TTL_S = 30 * 60.0


def snapshot(st: Any) -> dict:  # noqa: ANN401
    """What client ``st``'s tab shows, as plain values (JSON-able but the selection)."""
    g = st.gui
    cam = st.client.camera
    snap: dict = {
        "panel": {k: g[k].value for k in PANEL_KEYS if k in g},
        "mode": st.mode, "point_size": float(st.point_size),
        "point_size_set": bool(st.point_size_set), "max_points": int(st.max_points),
        "class_visible": {str(k): bool(v) for k, v in st.class_visible.items()},
        "camera_filter": st.camera_filter, "frame_index": st.frame_index,
        "highlighted": st.highlighted, "last_edit": getattr(st, "last_edit", None),
        "edit_info": g["edit_info"].content if "edit_info" in g else "",
    }
    try:
        snap["camera"] = {"position": [float(v) for v in cam.position],
                          "look_at": [float(v) for v in cam.look_at],
                          "up": [float(v) for v in cam.up_direction], "fov": float(cam.fov)}
    except (AssertionError, AttributeError):  # the client never reported a camera
        snap["camera"] = None
    snap["selection"] = np.asarray(st.selection, np.int64).copy()
    return snap


def restore(svc: Any, st: Any, snap: dict) -> None:  # noqa: ANN401
    """Put ``snap`` back on client ``st`` (its scene already open)."""

    g = st.gui
    d = st.data
    n = d.scene.n_points if d is not None else 0
    if snap.get("mode") in getattr(g.get("mode"), "options", ()) and snap["mode"] != st.mode:
        g["mode"].value = snap["mode"]  # its callback re-sends the points in that colouring
    if snap.get("point_size_set"):
        st.point_size_set = True
        g["size"].value = float(snap["point_size"])
    for cid, vis in (snap.get("class_visible") or {}).items():
        box = st.class_boxes.get(int(cid))
        if box is not None and bool(box.value) != vis:
            box.value = vis  # its callback shows / hides the class
        elif box is None:
            st.class_visible[int(cid)] = vis
    for k, v in (snap.get("panel") or {}).items():
        h = g.get(k)
        if h is None:
            continue
        options = getattr(h, "options", None)
        if options is not None and v not in options:
            continue  # the taxonomy changed meanwhile: keep the default
        h.value = v
    fi = snap.get("frame_index")
    if d is not None and fi is not None and 0 <= fi < len(d.scene.frames):
        svc.show_frame(st, fi)
    if snap.get("camera_filter") and snap["camera_filter"] != st.camera_filter:
        st.camera_filter = snap["camera_filter"]
        g["frusta"].value = st.camera_filter
        hi = snap.get("highlighted")
        st.highlighted = hi if d is not None and hi is not None and hi < len(d.scene.frames) \
            else None
        svc.send_frusta(st)  # highlights st.highlighted again
    elif snap.get("highlighted") is not None and d is not None \
            and snap["highlighted"] < len(d.scene.frames):
        svc.highlight_frustum(st, snap["highlighted"])
    st.last_edit = snap.get("last_edit")
    if snap.get("edit_info") and "edit_info" in g:
        g["edit_info"].content = snap["edit_info"]
    ids = np.asarray(snap.get("selection", np.zeros(0, np.int64)), np.int64)
    corrections_panel.set_selection(svc, st, ids[(ids >= 0) & (ids < n)])
    cam = snap.get("camera")
    if cam:
        with st.client.atomic():
            st.client.camera.fov = cam["fov"]
            st.client.camera.up_direction = tuple(cam["up"])
            st.client.camera.position = tuple(cam["position"])
            st.client.camera.look_at = tuple(cam["look_at"])
    corrections_panel.update_proposal_button(svc, st)


class SessionStore:
    """Snapshots by ``(user, scene, view)``, each taken at most once, dropped after ``ttl_s``;
    with ``folder`` they are also kept on disk (one ``.json`` + ``.npy`` pair each)."""

    def __init__(self, folder: Path | None = None, ttl_s: float = TTL_S) -> None:
        self.folder = Path(folder) if folder else None
        self.ttl_s = float(ttl_s)
        self._mem: dict[tuple, tuple[float, dict]] = {}
        self._lock = threading.Lock()

    @staticmethod
    def _name(key: tuple) -> str:
        return hashlib.sha256(json.dumps([str(k) for k in key]).encode()).hexdigest()[:32]

    def put(self, key: tuple, snap: dict) -> None:
        now = time.time()
        with self._lock:
            for k in [k for k, (t, _) in self._mem.items() if now - t > self.ttl_s]:
                del self._mem[k]
            self._mem[key] = (now, snap)
        if self.folder is None:
            return
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            base = self.folder / self._name(key)
            sel = np.asarray(snap["selection"], np.int64)
            if len(sel) == 0 or int(sel.max()) < 2**32:
                sel = sel.astype(np.uint32)  # half the bytes: point ids fit
            buf = _npy_bytes(sel)
            atomic_write_bytes(base.with_suffix(".npy"), buf)
            meta = {k: v for k, v in snap.items() if k != "selection"}
            atomic_write_bytes(base.with_suffix(".json"),
                               json.dumps({"t": now, "snap": meta}).encode())
            self._sweep(now)
        except (OSError, TypeError, ValueError):
            log.warning("viewer: cannot keep the tab state in %s", self.folder, exc_info=True)

    def take(self, key: tuple) -> dict | None:
        now = time.time()
        with self._lock:
            hit = self._mem.pop(key, None)
        got = hit[1] if hit is not None and now - hit[0] <= self.ttl_s else None
        if self.folder is None:
            return got
        base = self.folder / self._name(key)
        js, npy = base.with_suffix(".json"), base.with_suffix(".npy")
        if got is None and js.is_file():
            try:
                rec = json.loads(js.read_text())
                if now - float(rec["t"]) <= self.ttl_s:
                    got = dict(rec["snap"], selection=np.load(npy, allow_pickle=False)
                               .astype(np.int64))
            except (OSError, ValueError, KeyError, TypeError):
                log.warning("viewer: unreadable tab state %s", js, exc_info=True)
        for p in (js, npy):
            p.unlink(missing_ok=True)
        return got

    def _sweep(self, now: float) -> None:
        for p in self.folder.glob("*.json"):
            try:
                if now - p.stat().st_mtime > self.ttl_s:
                    p.unlink(missing_ok=True)
                    p.with_suffix(".npy").unlink(missing_ok=True)
            except OSError:
                pass


def _npy_bytes(arr: np.ndarray) -> bytes:

    b = io.BytesIO()
    np.save(b, arr, allow_pickle=False)
    return b.getvalue()
