"""The viewer's "Correct labels" panel: selection tools (rectangle, lasso, click-to-grow, 3D
brush) with filters and add / subtract modes, the highlighted selection counted by class, and
relabel / undo / redo through the app's corrections service (``ViewerService.corrections``:
``relabel(scene_id, point_ids, to_class, comment, user, frame_index) -> dict``,
``undo(scene_id, user)``, ``redo(scene_id, user)``, ``stack(scene_id, user) -> {undo, redo}``,
``propose(scene_id, edit_id, frame_index, user) -> dict``).

"File as proposal" turns the last correction made in this tab into a proposed mask change of
the frame the viewer was opened for (or the frustum clicked since): its annotator sees it as
an overlay and takes it with one key (issue 40, defect 2).

Selections are evaluated on every point of the classes shown (not only the LOD subsample the
browser draws), in chunks, with the vectorised functions of :mod:`app.viewer.selection`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from app.viewer import scene_builder as sb
from app.viewer import selection as sel
from app.viewer.markdown_escape import md_text

log = logging.getLogger(__name__)

HIGHLIGHT = (0, 255, 255)  # cyan: in no default class colour
CHUNK = 4_000_000
ORIGIN_CHOICES = {"any origin": None, "voted (direct)": {1}, "filled": {2}, "denoised": {3},
                  "filled or denoised": {2, 3}, "corrected": {4}}
LEGENDS = {
    "confidence": "**Confidence**: dark red = 0 -> yellow = 1 (a calibrated probability).",
    "origin": ("**Origin**: grey none - blue voted (direct) - orange filled (kNN) - purple "
               "denoised - pink corrected by a reviewer."),
    "disagreement": ("**Disagreement**: green = the lifted label agrees with the votes - red = "
                     "it disagrees - grey = no vote."),
    "semantic": "**Semantic**: the class colours of the taxonomy (see *Classes*).",
    "rgb": "**RGB**: the reconstruction's colours.",
}


def legend(mode: str) -> str:
    return LEGENDS.get(mode, "")


def build(svc: Any, st: Any) -> None:
    """Add the panel to client ``st``'s GUI (called from ``ViewerService._build_gui``)."""
    gui = st.client.gui
    g = st.gui
    g["legend"] = gui.add_markdown(legend(st.mode))
    with gui.add_folder("Correct labels"):
        g["tool"] = gui.add_dropdown("Tool", list(sel.TOOLS), initial_value="lasso")
        g["sel_mode"] = gui.add_dropdown("Mode", list(sel.MODES), initial_value="replace")
        g["f_class"] = gui.add_dropdown("Only class", ["any class"])
        g["f_origin"] = gui.add_dropdown("Only origin", list(ORIGIN_CHOICES))
        g["f_hmin"] = gui.add_number("Min height above ground (m)", initial_value=-1000.0,
                                     step=0.5)
        g["f_hmax"] = gui.add_number("Max height above ground (m)", initial_value=1000.0,
                                     step=0.5)
        g["brush_r"] = gui.add_number("Brush / grow radius (m)", initial_value=1.0, min=0.01,
                                      step=0.1)
        g["arm_btn"] = gui.add_button("Start selecting")
        g["lasso_btn"] = gui.add_button("Close lasso", disabled=True)
        g["clear_btn"] = gui.add_button("Clear selection")
        g["counts"] = gui.add_markdown("No points selected.")
        g["to_class"] = gui.add_dropdown("Relabel to", ["unlabelled"])
        g["relabel_btn"] = gui.add_button("Relabel selection", disabled=True)
        g["undo_btn"] = gui.add_button("Undo my last correction")
        g["redo_btn"] = gui.add_button("Redo")
        g["edit_info"] = gui.add_markdown("")
        g["propose_btn"] = gui.add_button("File as proposal", disabled=True,
                                          hint="The last correction's projection into the "
                                               "frame, as a proposed mask change")
        g["propose_info"] = gui.add_markdown("")
    st.lasso = []  # screen vertices of the lasso being drawn
    st.lasso_cam = None
    st.armed = None

    @g["arm_btn"].on_click
    def _(_e: Any) -> None:
        arm(svc, st)

    @g["lasso_btn"].on_click
    def _(_e: Any) -> None:
        close_lasso(svc, st)

    @g["clear_btn"].on_click
    def _(_e: Any) -> None:
        set_selection(svc, st, np.zeros(0, np.int64))

    @g["relabel_btn"].on_click
    def _(_e: Any) -> None:
        relabel(svc, st, g["to_class"].value, g["comment"].value if "comment" in g else "")

    @g["undo_btn"].on_click
    def _(_e: Any) -> None:
        undo_redo(svc, st, "undo")

    @g["redo_btn"].on_click
    def _(_e: Any) -> None:
        undo_redo(svc, st, "redo")

    @g["propose_btn"].on_click
    def _(_e: Any) -> None:
        file_proposal(svc, st)


def on_scene_opened(svc: Any, st: Any) -> None:
    """Fill the class choices of a freshly opened scene; clear any lasso."""
    d = st.data
    if d is None or "f_class" not in st.gui:
        return
    names = [f"{c.name} ({c.id})" for c in d.taxonomy.classes]
    st.gui["f_class"].options = ["any class"] + names
    st.gui["to_class"].options = ["unlabelled"] + names
    st.lasso = []
    highlight(st)
    update_stack(svc, st)


def _class_of(choice: str) -> int | None:
    if choice in ("any class", ""):
        return None
    if choice == "unlabelled":
        return 0
    return int(choice.rsplit("(", 1)[1].rstrip(")"))


def filters_of(st: Any) -> sel.Filters:
    g = st.gui
    c = _class_of(g["f_class"].value)
    hmin, hmax = float(g["f_hmin"].value), float(g["f_hmax"].value)
    return sel.Filters(classes=None if c is None else {c},
                       origins=ORIGIN_CHOICES.get(g["f_origin"].value),
                       min_height=hmin if hmin > -1000 else None,
                       max_height=hmax if hmax < 1000 else None)


def candidates(st: Any) -> np.ndarray:
    """(M,) int64 ids of the points a tool may select: classes shown, filters passed."""
    d = st.data
    n = d.scene.n_points
    ids = np.arange(n, dtype=np.int64)
    lab = None if d.labels is None else np.asarray(d.labels)
    if lab is not None:
        hidden = [c for c, vis in st.class_visible.items() if not vis]
        if hidden:
            ids = ids[~np.isin(lab, hidden)]
    f = filters_of(st)
    if f.classes is None and f.origins is None and f.min_height is None and f.max_height is None:
        return ids
    xyz = np.asarray(d.scene.xyz)
    h = None
    if f.min_height is not None or f.max_height is not None:
        h = sel.height_above_ground(xyz)[ids]
    ok = f.mask(xyz[ids], None if lab is None else lab[ids],
                None if d.origin is None else np.asarray(d.origin)[ids], h)
    return ids[ok]


def _chunked(ids: np.ndarray, xyz: np.ndarray, fn) -> np.ndarray:  # noqa: ANN001
    """The ``ids`` whose points ``fn`` (float32 (n, 3) -> (n,) bool) keeps, ``CHUNK`` at a
    time. When every point is a candidate the cloud is read in slices (no gather)."""
    out = []
    if len(ids) == len(xyz):  # sorted unique ids of every point: 0..N-1
        for a in range(0, len(ids), CHUNK):
            keep = fn(np.asarray(xyz[a:a + CHUNK], np.float32))
            out.append(a + np.flatnonzero(keep))
    else:
        for a in range(0, len(ids), CHUNK):
            part = ids[a:a + CHUNK]
            out.append(part[fn(np.asarray(xyz[part], np.float32))])
    return np.concatenate(out).astype(np.int64, copy=False) if out else np.zeros(0, np.int64)


def arm(svc: Any, st: Any) -> None:
    """Start the chosen tool: rectangle -> one drag; lasso -> clicks add vertices until
    "Close lasso"; grow / brush -> one click on the cloud."""
    scene = st.client.scene
    tool = st.gui["tool"].value
    _disarm(st)
    if tool == "rectangle":
        def on_rect(event: Any) -> None:
            scene.remove_rect_select_callback(on_rect)
            st.armed = None
            cam = event.client.camera
            pos, wxyz, fov, asp = (np.asarray(cam.position), np.asarray(cam.wxyz),
                                   float(cam.fov), float(cam.aspect))
            xyz = st.data.scene.xyz
            picked = _chunked(candidates(st), xyz, lambda p: sel.rectangle(
                p, pos, wxyz, fov, asp, event.screen_min, event.screen_max))
            apply_pick(svc, st, picked)

        st.armed = ("rect", on_rect)
        scene.on_rect_select()(on_rect)
        st.gui["counts"].content = "Drag a rectangle on the view..."
        return

    def on_click(event: Any) -> None:
        cam = event.client.camera
        if tool == "lasso":
            st.lasso.append(tuple(float(x) for x in event.screen_pos))
            st.lasso_cam = (np.asarray(cam.position), np.asarray(cam.wxyz), float(cam.fov),
                            float(cam.aspect))
            st.gui["lasso_btn"].disabled = len(st.lasso) < 3
            st.gui["counts"].content = (f"Lasso: **{len(st.lasso)}** vertices; click more, "
                                        "then *Close lasso*.")
            return
        scene.remove_click_callback(on_click)
        st.armed = None
        d = st.data
        r = float(st.gui["brush_r"].value)
        cand = candidates(st)
        xyz = np.asarray(d.scene.xyz)
        hit = sel.ray_hit(xyz[cand], event.ray_origin, event.ray_direction, r)
        if hit is None:
            st.gui["counts"].content = "The click hit no point; try again (a larger radius?)."
            return
        if tool == "brush":
            centre = xyz[cand[hit]].astype(np.float64)
            picked = _chunked(cand, xyz, lambda p: np.einsum(
                "ij,ij->i", p - centre, p - centre) <= r * r)
        else:  # grow: the connected region of the clicked point's label
            lab = np.asarray(d.labels) if d.labels is not None else np.zeros(len(xyz), np.uint8)
            region = sel.grow(xyz[cand], lab[cand], int(hit), voxel=r)
            picked = cand[region]
        apply_pick(svc, st, picked)

    st.armed = ("click", on_click)
    scene.on_click()(on_click)
    st.lasso = []
    st.gui["counts"].content = {"lasso": "Click the lasso's vertices on the view...",
                                "grow": "Click a point: its connected region of one class.",
                                "brush": "Click the surface: points within the radius."}[tool]


def _disarm(st: Any) -> None:
    if st.armed is None:
        return
    kind, fn = st.armed
    try:
        if kind == "rect":
            st.client.scene.remove_rect_select_callback(fn)
        else:
            st.client.scene.remove_click_callback(fn)
    except Exception:  # noqa: BLE001 - already gone
        pass
    st.armed = None


def close_lasso(svc: Any, st: Any) -> np.ndarray:
    if len(st.lasso) < 3 or st.lasso_cam is None:
        return st.selection
    poly = np.asarray(st.lasso, np.float64)
    pos, wxyz, fov, asp = st.lasso_cam
    st.last_lasso, st.last_lasso_cam = poly, st.lasso_cam  # what was selected with
    _disarm(st)
    st.lasso = []
    st.gui["lasso_btn"].disabled = True
    picked = _chunked(candidates(st), st.data.scene.xyz,
                      lambda p: sel.lasso(p, pos, wxyz, fov, asp, poly))
    return apply_pick(svc, st, picked)


def apply_pick(svc: Any, st: Any, picked: np.ndarray) -> np.ndarray:
    return set_selection(svc, st, sel.combine(st.selection, picked, st.gui["sel_mode"].value))


def set_selection(svc: Any, st: Any, ids: np.ndarray) -> np.ndarray:
    st.selection = np.asarray(ids, np.int64)
    after_selection(svc, st)
    return st.selection


def after_selection(svc: Any, st: Any) -> None:
    """Highlight the selection and count it by class (also after the old rectangle tool)."""
    if "counts" not in st.gui:
        return
    highlight(st)
    d = st.data
    n = len(st.selection)
    if n == 0:
        st.gui["counts"].content = "No points selected."
    else:
        counts = sel.class_counts(d.labels if d is not None else None, st.selection)
        rows = ", ".join(f"{md_text(sb.class_name(d.taxonomy, c))} {k:,}" for c, k in
                         list(counts.items())[:8])
        st.gui["counts"].content = f"**{n:,}** points selected: {rows}"
    st.gui["relabel_btn"].disabled = n == 0 or svc.corrections is None
    if "file_btn" in st.gui:
        st.gui["file_btn"].disabled = n == 0


def highlight(st: Any, max_points: int = 500_000) -> None:
    """Draw the selected points on top in cyan, a little larger than the cloud."""
    h = st.gui.pop("_sel_handle", None)
    if h is not None:
        h.remove()
    if st.data is None or len(st.selection) == 0:
        return
    ids = st.selection
    stopped = getattr(st, "lod_stopped", None)
    if stopped is not None:  # a browser that draws slowly (scene_view._refine): a highlight
        max_points = min(max_points, max(20_000, stopped[0] // 2))  # of half what it shows
    if len(ids) > max_points:
        ids = ids[:: int(np.ceil(len(ids) / max_points))]
    xyz = np.asarray(st.data.scene.xyz[ids], np.float32)
    st.gui["_sel_handle"] = st.client.scene.add_point_cloud(
        "/selection", points=xyz, colors=np.broadcast_to(np.asarray(HIGHLIGHT, np.uint8),
                                                         xyz.shape).copy(),
        point_size=float(st.point_size) * 1.6, precision="float32", point_shape="square",
        point_shading="flat")


def relabel(svc: Any, st: Any, choice: str, comment: str) -> dict | None:
    if svc.corrections is None or len(st.selection) == 0 or st.scene_id is None:
        return None
    to_class = _class_of(choice)
    if to_class is None:
        return None
    with svc.tiles_held(st):  # from the click until the change is drawn
        try:
            edit = svc.corrections["relabel"](st.scene_id, st.selection, to_class, comment,
                                              st.user, st.frame_index)
        except Exception as e:  # noqa: BLE001 - tell the reviewer (403, bad class, ...)
            log.warning("viewer: relabel failed: %s", e)
            st.client.add_notification("Correction not saved", str(getattr(e, "detail", e)),
                                       color="red")
            return None
        name = "unlabelled" if to_class == 0 else sb.class_name(st.data.taxonomy, to_class)
        with show_change(svc, st):
            st.gui["edit_info"].content = (f"Correction **{edit['id']}**: {edit['n_points']:,} "
                                           f"points -> {md_text(name)}.")
            st.last_edit = {"id": int(edit["id"]), "n_points": int(edit["n_points"]),
                            "to": name}
            update_proposal_button(svc, st)
            st.client.add_notification("Correction saved",
                                       f"{edit['n_points']:,} points -> {name}",
                                       color="green", auto_close_seconds=4.0)
            set_selection(svc, st, np.zeros(0, np.int64))
    update_stack(svc, st)
    return edit


@contextmanager
def show_change(svc: Any, st: Any) -> Iterator[None]:
    """The panel's messages of a correction this tab made, and the points it changed, in
    one message window: the browser applies them together and draws the change once
    (under software WebGL every window that touches the scene costs a frame of all the
    points shown). The refresh runs here, in the tab's callback, not queued: only the
    correction layer changed, so it is a delta (:meth:`ViewerService.refresh_now`); the
    labels_updated event that follows finds the data current. The old path
    (``lod_scheme = "legacy"``, the benchmark's baseline) queues it as before."""
    if svc.lod_scheme == "legacy":
        try:
            yield
        finally:
            svc.refresh(st.scene_id)
        return
    with st.client.atomic():
        try:
            yield
        finally:  # the correction is saved: show it whatever the panel's messages did
            try:
                svc.refresh_now(st.scene_id)
            except Exception:  # noqa: BLE001 - the refresh thread tries again
                log.exception("viewer: refresh after a correction failed")
                svc.refresh(st.scene_id)


def undo_redo(svc: Any, st: Any, which: str) -> dict | None:
    if svc.corrections is None or st.scene_id is None:
        return None
    with svc.tiles_held(st):  # from the click until the change is drawn
        try:
            edit = svc.corrections[which](st.scene_id, st.user)
        except Exception as e:  # noqa: BLE001 - nothing to undo, not allowed...
            st.gui["edit_info"].content = md_text(getattr(e, "detail", e))
            return None
        with show_change(svc, st):
            st.gui["edit_info"].content = (f"Correction **{edit['id']}** "
                                           f"{'undone' if which == 'undo' else 'redone'}.")
    update_stack(svc, st)
    return edit


def update_proposal_button(svc: Any, st: Any) -> None:
    """"File as proposal" is enabled once this tab made a correction (the hook present)."""
    if "propose_btn" not in st.gui:
        return
    can = svc.corrections is not None and "propose" in svc.corrections
    st.gui["propose_btn"].disabled = not (can and getattr(st, "last_edit", None))


def file_proposal(svc: Any, st: Any) -> dict | None:
    """File the last correction of this tab as a proposal on the viewer's frame; the panel
    says what happened (no frame, refused and why, or the proposal's size)."""
    info = st.gui["propose_info"]
    edit = getattr(st, "last_edit", None)
    if svc.corrections is None or "propose" not in svc.corrections or st.scene_id is None:
        info.content = "Proposals cannot be filed from this viewer."
        return None
    if not edit:
        info.content = "Relabel a selection first: a proposal is a correction's projection."
        return None
    if st.frame_index is None:
        info.content = ("No frame: open the viewer with **3D** from a frame (or click a "
                        "camera) to propose correction "
                        f"**{edit['id']}** as a change of that frame's mask.")
        return None
    stem = st.data.scene.frames[st.frame_index].stem if st.data is not None else "?"
    try:
        p = svc.corrections["propose"](st.scene_id, edit["id"], st.frame_index, st.user)
    except Exception as e:  # noqa: BLE001 - 409 no submitted mask / already agrees, 403...
        msg = str(getattr(e, "detail", e))
        info.content = f"Proposal refused for {md_text(stem)}: {md_text(msg)}"
        st.client.add_notification("Proposal not filed", msg, color="red")
        return None
    info.content = (f"Proposal **{p['id']}** filed on {md_text(stem)}: {p['changed_px']:,} px "
                    f"-> {md_text(edit['to'])}; the annotator is notified.")
    st.client.add_notification("Proposal filed", f"{p['changed_px']:,} px on {stem}",
                               color="green", auto_close_seconds=4.0)
    return p


def update_stack(svc: Any, st: Any) -> None:
    if svc.corrections is None or st.scene_id is None or "undo_btn" not in st.gui:
        for k in ("undo_btn", "redo_btn"):
            if k in st.gui:
                st.gui[k].disabled = True
        return
    try:
        s = svc.corrections["stack"](st.scene_id, st.user)
    except Exception:  # noqa: BLE001
        s = {"undo": None, "redo": None}
    st.gui["undo_btn"].disabled = s.get("undo") is None
    st.gui["redo_btn"].disabled = s.get("redo") is None
