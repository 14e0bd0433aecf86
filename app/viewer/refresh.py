"""Live refresh: open tabs re-sent the classes that changed when a scene's labels or grid
change (event driven; a viewer without an event source watches the workspace stamp) (a mixin
of :class:`app.viewer.server.ViewerService`)."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

import numpy as np

from app.viewer import point_lod
from app.viewer import scene_builder as sb
from occufly.workspace import Workspace

log = logging.getLogger("app.viewer.server")


class RefreshMixin:
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
        """Synchronous refresh; returns the class ids re-sent.

        When only the correction layer changed since the scene's data was loaded (a relabel,
        undo or redo, by anyone), the data is brought up to date as a delta
        (:meth:`ViewerData.with_corrections`) and each tab re-sends only the chunks holding
        changed points (:func:`point_lod.delta_chunks`); otherwise the workspace is read
        again and old and new are compared."""
        with self._refresh_lock:  # one refresh at a time: each delta applies to its data
            with self._lock:
                old = self._data.get(scene_id)
            if old is None:
                return set()  # nobody has it open
            new, delta = self._reload(scene_id, old)
            if classes is not None:
                affected = set(classes)
            elif delta is not None:
                affected = {int(c) for c in np.union1d(delta.old, delta.new)}
            else:
                affected = changed_classes(old, new)
            for st in self.clients_of(scene_id):
                self._refresh_client(st, old, new, delta, classes, affected)
        return set() if affected is None else affected

    def _refresh_client(self, st: Any, old: sb.ViewerData, new: sb.ViewerData,
                        delta: sb.LabelDelta | None, classes: set[int] | None,
                        affected: set[int] | None) -> None:
        with st.lock:
            prev, st.data = st.data if st.data is not None else old, new
            if new.labels is not None and old.labels is None:
                st.subsample = None
                st.lod_plan = None
                affected = None  # first labels: everything changes
            if affected is None or affected:
                self._rebuild_class_boxes(st)
            if (classes is None and affected is not None and st.lod_plan is not None
                    and self.lod_scheme != "legacy"):
                # only the (class, tile) chunks holding changed points
                if delta is not None and prev is old:
                    keys = point_lod.delta_chunks(st.lod_plan, delta, st.mode)
                else:  # this tab showed other data: compare what it showed
                    keys = point_lod.affected_chunks(st.lod_plan, prev, new, st.mode)
                if keys is None:
                    self.send_points(st)
                elif keys:
                    self.update_shown(st, keys)
            elif affected is None or affected:
                self.send_points(st, None if affected is None else affected)

    def _reload(self, scene_id: str, old: sb.ViewerData) -> tuple[sb.ViewerData,
                                                                  sb.LabelDelta | None]:
        """The scene's data now and, when only its correction layer changed since ``old``
        was loaded, what changed (else None: the workspace was read again)."""
        ws = old.workspace
        if self.lod_scheme != "legacy" and ws is not None and old.base is not None:
            full, base = workspace_stamps(ws)  # before the layer is read
            if base == self._base_stamps.get(scene_id):
                new, delta = old.with_corrections()
                if delta is not None:
                    with self._lock:
                        if self._data.get(scene_id) is old:
                            self._data[scene_id] = new
                            self._stamps[scene_id] = full
                    return new, delta
        return self.scene_data(scene_id, reload=True), None

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
                    if sid in table and workspace_stamp(Path(table[sid][1])) != stamps.get(sid):
                        pending[sid] = None
                except Exception:  # noqa: BLE001
                    log.exception("viewer: watching scene %s failed", sid)
            for sid, classes in pending.items():
                try:
                    self.refresh_now(sid, classes)
                except Exception:  # noqa: BLE001 - keep the refresh thread alive
                    log.exception("viewer: refresh of scene %s failed", sid)


def workspace_stamp(ws: Path) -> str:
    return Workspace(ws).stamp()


def workspace_stamps(ws: Path) -> tuple[str, str]:
    """(``Workspace.stamp()``, the same stamp without the correction layer) from one look at
    the files: the second is unchanged when only corrections were made."""
    w = Workspace(ws)
    full, base = hashlib.sha1(), hashlib.sha1()
    for p in w.stamp_paths():
        try:
            st = p.stat()
            part = f"{p.name}:{st.st_mtime_ns}:{st.st_size};".encode()
        except FileNotFoundError:
            part = f"{p.name}:-;".encode()
        full.update(part)
        if p != w.overrides_path:
            base.update(part)
    return full.hexdigest()[:16], base.hexdigest()[:16]


def changed_classes(old: sb.ViewerData, new: sb.ViewerData) -> set[int] | None:
    """Classes whose points changed label, confidence or origin; None = everything."""
    if (old.labels is None) != (new.labels is None) or old.scene.n_points != new.scene.n_points:
        return None
    if new.labels is None:
        return set()
    ol, nl = np.asarray(old.labels), np.asarray(new.labels)
    changed = ol != nl
    for a, b in ((old.confidence, new.confidence), (old.origin, new.origin),
                 (old.direct_array(), new.direct_array())):
        if (a is None) != (b is None):
            return None
        if a is not None:
            changed |= np.asarray(a) != np.asarray(b)
    return {int(c) for c in np.union1d(np.unique(ol[changed]), np.unique(nl[changed]))}
