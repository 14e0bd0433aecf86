"""The GUI panels of one tab (scene, colour mode, classes, tools, review item filing) and
the per-user preferences behind them (a mixin of :class:`app.viewer.server.ViewerService`)."""

from __future__ import annotations

import inspect
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from app.viewer import corrections_panel
from app.viewer import scene_builder as sb
from app.viewer.state import ClientState, user_key
from occufly.fsutil import atomic_write_text

log = logging.getLogger("app.viewer.server")


class PanelsMixin:
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
            self.set_point_size(st, float(g["size"].value))

        @g["lod"].on_update
        def _(_e: Any) -> None:
            self.lod_field_changed(st, g["lod"].value)

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
        counts = data.label_counts()  # kept up to date by a relabel's delta
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

    def file_review_item(self, st: ClientState, comment: str) -> dict | None:
        ids = [int(i) for i in st.selection]
        if not ids or st.scene_id is None:
            return None
        item = {"scene_id": st.scene_id, "point_ids": ids, "comment": comment, "user": st.user}
        result = None
        if self.on_review_item is not None:
            try:
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
        return self.prefs.get(user_key(user), {}).get(key, default)

    def remember(self, user: Any, **values: Any) -> None:
        """Keep a viewer preference of ``user`` (e.g. the camera filter) for their next visit."""
        k = user_key(user)
        if k is None:
            return
        with self._lock:
            self.prefs.setdefault(k, {}).update(values)
            if self.prefs_path is not None:
                try:
                    self.prefs_path.parent.mkdir(parents=True, exist_ok=True)
                    atomic_write_text(self.prefs_path, json.dumps(self.prefs))
                except OSError:
                    log.warning("viewer: cannot keep preferences in %s", self.prefs_path)
