"""Issue 25 end to end in Chromium: a reviewer lassoes points in the 3D viewer, relabels them,
undoes and redoes; the labels, the prefill of another frame and a fresh export reflect it; the
correction's projection becomes a proposed mask change that the annotator sees as an overlay
(with the 3D review item's outline) and takes with one key; annotators cannot edit in 3D.

Screenshots (looked at): docs/screenshots/viewer_selection.png (highlighted selection) and
docs/screenshots/annotator_projected_item.png (proposal overlay + projected 3D item).
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from app.viewer import scene_builder as sb
from app.viewer import selection as sel
from app.viewer.corrections_panel import HIGHLIGHT
from occufly.lifting import load_labels
from tests.e2e.conftest import REPO, grey_png, import_own_scene, png_ids

pytestmark = pytest.mark.e2e
DOCS = REPO / "docs" / "screenshots"
TREE = 8


def _wait(pred, timeout=30.0, what="condition"):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        v = pred()
        if v:
            return v
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def setup(live):
    sid = import_own_scene(live, "corrections_e2e")
    ann, rev = live.client("annotator"), live.client("reviewer")
    f = ann.post(f"/api/scenes/{sid}/next").json()
    m = np.full((f["height"], f["width"]), 6, np.uint8)  # all grass
    r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(m),
                headers={"If-Match": "none", "Content-Type": "image/png"})
    assert r.status_code == 200, r.text
    _wait(lambda: rev.get(f"/api/scenes/{sid}/labels/status").json().get("labels_source")
          == "filled" and str(f["id"]) in rev.get(f"/api/scenes/{sid}/labels/status").json()
          .get("filled_versions", {}), 90, "the first fill")
    return {"sid": sid, "frame": f}


def _ws(live, sid: int) -> Path:
    from app.scenes.models import Scene

    with live.app.state.ctx.sessions() as s:
        return Path(s.get(Scene, sid).workspace)


def _click(page, canvas, u, v):
    box = canvas.bounding_box()
    page.mouse.click(box["x"] + u * box["width"], box["y"] + v * box["height"])


def test_lasso_relabel_undo_redo_and_what_follows(live, setup, new_page):
    sid, f = setup["sid"], setup["frame"]
    ws = _ws(live, sid)
    rev, admin = live.client("reviewer"), live.client("admin")
    svc = live.app.state.viewer
    before = {id(c) for c in svc.client_states()}
    page = new_page("reviewer", viewport=(1200, 800))
    page.goto(f"{live.base_url}/viewer/?scene={sid}&frame={f['id']}")
    st = _wait(lambda: next((c for c in svc.client_states() if id(c) not in before
                             and c.scene_id == str(sid) and c.ready.is_set()
                             and c.highlighted is not None), None), 60, "the viewer")
    fr = st.data.scene.frames[st.highlighted]
    cam = st.client.camera
    svc.move_to_camera(st, st.highlighted)  # look through the frame's camera
    _wait(lambda: np.allclose(cam.position, fr.center, atol=1e-3), 20, "the camera move")
    time.sleep(1.0)  # a camera report the browser sent before the move must not land after
    canvas = page.locator("canvas").first
    page.get_by_role("button", name="Start selecting").click()  # tool: lasso (default)
    _wait(lambda: st.armed is not None, 10, "lasso armed")
    time.sleep(0.7)  # the click filter reaches the browser
    poly = [(0.30, 0.30), (0.62, 0.28), (0.66, 0.62), (0.45, 0.50), (0.32, 0.66)]  # concave
    for u, v in poly:
        _click(page, canvas, u, v)
        time.sleep(0.25)
    _wait(lambda: len(st.lasso) == len(poly), 10, "lasso vertices")
    page.get_by_role("button", name="Close lasso").click()
    _wait(lambda: len(st.selection) > 0, 15, "a selection")
    chosen = st.selection.copy()
    # the vertices the server received are where the page clicked (canvas 0..1)
    got_poly = np.asarray(st.last_lasso)
    assert np.abs(got_poly - np.asarray(poly)).max() < 0.01, got_poly
    # independent check: a pinhole camera from the browser camera's pose, fov and aspect
    from occufly.camera import Camera, make_pose, project_world

    pos, wxyz, fov, aspect = st.last_lasso_cam
    W = 1000
    H = int(round(W / aspect))
    fy = (H / 2) / np.tan(fov / 2)
    pin = Camera("PINHOLE", W, H, np.array([fy, fy, W / 2, H / 2]))
    R = sb.quat_to_matrix(wxyz)
    uv, _, vis = project_world(pin, make_pose(R.T, -R.T @ np.asarray(pos)),
                               np.asarray(st.data.scene.xyz, np.float64))
    expected = np.flatnonzero(vis & sel.points_in_polygon(uv[:, 0] / W, uv[:, 1] / H, got_poly))
    jac = len(np.intersect1d(chosen, expected)) / len(np.union1d(chosen, expected))
    assert len(expected) > 50 and jac > 0.9, (len(chosen), len(expected), jac)
    # the panel's count is written just after the selection is stored: wait for it
    _wait(lambda: "points selected" in st.gui["counts"].content, 10, "the selection's count")
    time.sleep(1.5)  # let the highlight draw
    DOCS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(DOCS / "viewer_selection.png"))
    img = np.asarray(Image.open(DOCS / "viewer_selection.png").convert("RGB")).astype(int)
    cyan = (np.abs(img - np.array(HIGHLIGHT)).sum(axis=2) < 60).mean()
    assert cyan > 0.005, f"the highlighted selection covers only {cyan:.2%} of the page"

    # relabel to tree through the panel
    page.get_by_label("Relabel to").click()
    page.get_by_role("option", name=f"tree ({TREE})", exact=True).click()
    _wait(lambda: st.gui["to_class"].value == f"tree ({TREE})", 10, "the class choice")
    page.get_by_role("button", name="Relabel selection").click()
    edits = _wait(lambda: rev.get(f"/api/scenes/{sid}/corrections").json(), 20, "the edit")
    e = edits[-1]
    _wait(lambda: e["id"] in rev.get(f"/api/scenes/{sid}/corrections/layer").json()["applied"],
          20, "the layer")
    assert len(edits) == 1
    assert e["state"] == "active" and e["n_points"] == len(chosen) and e["to_class"] == TREE
    assert e["author"] == "reviewer" and e["frame_id"] == f["id"]
    assert (np.asarray(load_labels(ws).labels)[chosen] == TREE).all()
    # the viewer follows (labels_updated): tree points are drawn
    _wait(lambda: TREE in st.point_nodes, 20, "the viewer's refresh")

    page.get_by_role("button", name="Undo my last correction").click()
    # (the row commits first, the layer follows: wait for the layer, what readers apply)
    _wait(lambda: rev.get(f"/api/scenes/{sid}/corrections").json()[-1]["state"] == "undone"
          and e["id"] not in rev.get(f"/api/scenes/{sid}/corrections/layer").json()["applied"],
          20, "undo")
    assert not (np.asarray(load_labels(ws).labels)[chosen] == TREE).any(), (
        rev.get(f"/api/scenes/{sid}/corrections").json(),
        rev.get(f"/api/scenes/{sid}/corrections/layer").json())
    page.get_by_role("button", name="Redo", exact=True).click()
    _wait(lambda: rev.get(f"/api/scenes/{sid}/corrections").json()[-1]["state"] == "active"
          and e["id"] in rev.get(f"/api/scenes/{sid}/corrections/layer").json()["applied"],
          20, "redo")
    assert (np.asarray(load_labels(ws).labels)[chosen] == TREE).all()

    # the prefill of another frame that sees the points shows them as tree
    scene = st.data.scene
    idx_to_id = {fr_["index"]: fr_["id"] for fr_ in rev.get(f"/api/scenes/{sid}/frames").json()}
    counts = [(int(np.isin(scene.visibility.frame_ids(i), chosen).sum()), i)
              for i in range(len(scene.frames)) if i != st.highlighted]
    n_seen, other = max(counts)
    assert n_seen > 20
    r = rev.get(f"/api/frames/{idx_to_id[other]}/prefill")
    assert r.status_code == 200
    assert (png_ids(r.content) == TREE).sum() > 20

    # a fresh voxelize + export carries the tree voxels
    j = live.wait_job(admin.post(f"/api/scenes/{sid}/voxelize", json={"voxel_size": 0.5}).json(),
                      timeout=300)
    assert j["status"] == "done", j
    from occufly.workspace import Workspace

    assert (np.asarray(Workspace(ws).grid().labels) == TREE).sum() > 0
    j = live.wait_job(admin.post(f"/api/scenes/{sid}/export",
                                 json={"layout": "occufly", "frames": [other],
                                       # its masks are submitted, not accepted (issue 23)
                                       "include": ["accepted", "submitted", "imported"]}).json(),
                      timeout=300)
    assert j["status"] == "done", j
    out = Path(j["result"]["output"])
    labels = list(out.rglob("*.label"))
    assert labels and any((np.fromfile(p, np.uint8) == TREE).any() for p in labels)
    setup["edit"] = e
    setup["chosen"] = chosen


def test_proposal_reaches_the_annotator_with_the_3d_item_and_is_taken_with_one_key(
        live, setup, new_page):
    sid, f = setup["sid"], setup["frame"]
    e = setup.get("edit")
    if e is None:
        pytest.fail("the viewer test did not leave an edit")
    ann, rev = live.client("annotator"), live.client("reviewer")
    rows = rev.get(f"/api/scenes/{sid}/corrections/{e['id']}/frames").json()
    mine = [r for r in rows if r["frame_id"] == f["id"]]
    assert mine and mine[0]["disagreeing_px"] > 0, rows
    p = rev.post(f"/api/scenes/{sid}/corrections/{e['id']}/proposals",
                 json={"frame_id": f["id"], "dilate": 1})
    assert p.status_code == 201, p.text
    p = p.json()
    r = rev.post(f"/api/scenes/{sid}/review-items",
                 json={"point_ids": setup["chosen"][:2000].tolist(),
                       "comment": "trees, not grass"})
    assert r.status_code == 201
    assert ann.post(f"/api/frames/{f['id']}/reopen").status_code == 200
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}&frame={f['id']}")
    page.wait_for_selector("#proposal-take")
    assert "proposes to change" in page.inner_text("#proposal-bar")
    assert page.get_attribute("#projected-items", "data-count") == "1"
    time.sleep(0.8)
    DOCS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(DOCS / "annotator_projected_item.png"))
    # the overlay is drawn: tree-coloured pixels on the canvas where the mask is grass
    n_notif = page.inner_text("#notif-count")
    assert n_notif.strip() and int(n_notif) >= 1  # the proposal notified the annotator
    page.keyboard.press("t")  # take it
    _wait(lambda: ann.get(f"/api/frames/{f['id']}/proposals").json()[0]["status"] == "taken",
          20, "the proposal taken")
    taken = ann.get(f"/api/frames/{f['id']}/proposals").json()[0]
    vers = ann.get(f"/api/frames/{f['id']}/mask/versions").json()
    newest = max(vers, key=lambda x: x["version"])
    assert newest["version"] == taken["taken_version"] and newest["kind"] == "draft"
    m = png_ids(ann.get(f"/api/frames/{f['id']}/mask").content)
    assert (m == TREE).sum() == p["changed_px"]
    # the page reopened the frame on the new draft: no proposal left, the 3D item still shown
    page.wait_for_selector("#proposal-take", state="detached")
    page.wait_for_selector("#projected-items")

    # the reviewer page of the frame draws the 3D item's outline too
    rp = new_page("reviewer")
    rp.goto(f"{live.base_url}/#/review?scene={sid}&frame={f['id']}")
    rp.wait_for_selector("canvas.panel-canvas")

    def outlined():
        img = np.asarray(Image.open(io.BytesIO(rp.screenshot())).convert("RGB")).astype(int)
        return ((np.abs(img - np.array([0, 229, 255])).sum(axis=2) < 40).sum() > 50)

    _wait(outlined, 20, "the 3D item's outline on the reviewer page")


def test_annotators_cannot_edit_in_3d(live, setup):
    sid = setup["sid"]
    ann = live.client("annotator")
    r = ann.get(f"/viewer/?scene={sid}")
    assert r.status_code == 403
    r = ann.post(f"/api/scenes/{sid}/corrections", json={"point_ids": [1, 2], "to_class": 8})
    assert r.status_code == 403
    assert ann.post(f"/api/scenes/{sid}/corrections/undo").status_code == 403

