"""Issue 40 defect 2 in Chromium: a reviewer fixes a mask in 2D with the annotator's painting
tools (the shared paint/workbench.js) and saves it as the reviewer's correction -- a new
version marked ``reviewer_correction`` that becomes the voting version, is lifted (the 3D labels
follow), and whose annotator is notified; the page then shows that version, so a decision names
it. And "Propose from 3D": an active 3D relabel this frame sees becomes a proposal with one
click, the annotator notified.

Screenshot (looked at): docs/screenshots/reviewer_editor.png (the editor at 1440x900).
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from tests.e2e.conftest import REPO, grey_png, import_own_scene, png_ids, shot, wait_js

pytestmark = pytest.mark.e2e
DOCS = REPO / "docs" / "screenshots"
GRASS, ROAD, TREE = 6, 1, 8
R = "window.__occufly_review"


@pytest.fixture(scope="module")
def setup(live):
    """Two frames of the module's own scene submitted all grass, lifted and filled."""
    sid = import_own_scene(live, "review_editor_e2e")
    ann, rev = live.client("annotator"), live.client("reviewer")
    frames = []
    for _ in range(2):
        f = ann.post(f"/api/scenes/{sid}/next").json()
        m = np.full((f["height"], f["width"]), GRASS, np.uint8)
        r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(m),
                    headers={"If-Match": "none", "Content-Type": "image/png"})
        assert r.status_code == 200, r.text
        frames.append({**f, "version": r.json()["version"]})

    def filled():
        st = rev.get(f"/api/scenes/{sid}/labels/status").json()
        return all(st.get("filled_versions", {}).get(str(f["id"])) == f["version"] for f in frames)

    live.wait_until(filled, 90, "the first fill")
    ann.post("/api/notifications/read", json={})
    return {"sid": sid, "frames": frames}


def _open_review(page, live, sid, fid):
    page.goto(f"{live.base_url}/#/review?scene={sid}&frame={fid}")
    wait_js(page, f"() => {R} && {R}.frame && {R}.frame.id === {fid} && !!document.querySelector('#fix-2d')")


def test_reviewer_fixes_a_mask_in_2d_and_it_votes(live, setup, new_page):
    sid, f = setup["sid"], setup["frames"][0]
    fid, W, H = f["id"], f["width"], f["height"]
    page = new_page("reviewer", viewport=(1440, 900))
    _open_review(page, live, sid, fid)
    assert page.evaluate(f"() => {R}.frame.current_version") == f["version"]
    page.click("#fix-2d")
    page.evaluate(f"() => {{ {R}.fixer.open(); }}")  # a second click while it opens
    page.keyboard.press("a")  # a key while it opens decides nothing
    wait_js(page, f"() => {R}.fixer.state === 'open'")
    assert page.locator("#review-editor .canvas-host").count() == 1
    # the frame list is hidden; the annotator's tools and palette are there, with their keys
    assert not page.locator("#frame-list").is_visible()
    assert page.locator("#fix-base").get_attribute("data-version") == str(f["version"])
    tools = page.eval_on_selector_all("#review-editor button.tool", "bs => bs.map(b => b.dataset.tool)")
    assert {"brush", "eraser", "polygon", "flood", "pan"} <= set(tools), tools
    # A / R / N do nothing while the editor is open (R is the region-fill tool here)
    page.keyboard.press("a")
    page.keyboard.press("n")
    assert page.evaluate(f"() => {R}.frame.state") == "submitted"
    page.keyboard.press("b")
    page.click(f"#review-editor .swatch-btn[data-class='{ROAD}']")
    page.evaluate(f"() => {R}.fixer.ed.setSize({max(4, W // 8)})")
    ov = page.locator("#review-editor .layer-overlay").bounding_box()

    def at(x, y):
        sx, sy = page.evaluate(f"() => {R}.fixer.ed.view.toScreen({x}, {y})")
        return ov["x"] + sx, ov["y"] + sy

    y = H / 2
    page.mouse.move(*at(W * 0.25, y))
    page.mouse.down()
    page.mouse.move(*at(W * 0.75, y), steps=12)
    page.mouse.up()
    wait_js(page, "() => document.querySelector('#fix-state').dataset.state === 'unsaved'")
    DOCS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(DOCS / "reviewer_editor.png"))
    # Cancel with unsaved painting asks first; "Keep editing" keeps it
    page.click("#fix-cancel")
    page.click("dialog[open] .dlg-buttons button:has-text('Keep editing')")
    assert page.evaluate(f"() => {R}.fixer.state") == "open"
    assert page.evaluate(f"() => {R}.fixer.ed.history.undos.length") >= 1

    page.keyboard.press("Control+s")
    wait_js(page, f"() => {R}.fixer.state === null && {R}.frame && {R}.frame.current_version !== {f['version']}", timeout=30_000)
    rev, ann = live.client("reviewer"), live.client("annotator")
    versions = rev.get(f"/api/frames/{fid}/mask/versions").json()
    new = max(versions, key=lambda v: v["version"])
    assert new["source"] == "reviewer_correction" and new["author"] == "reviewer"
    assert new["kind"] == "submitted" and new["base_version"] == f["version"]
    # the page shows the new version: a decision now names it
    assert page.evaluate(f"() => {R}.frame.current_version") == new["version"]
    assert page.locator("#fix-note").get_attribute("data-version") == str(new["version"])
    from app.scenes.models import Frame

    with live.app.state.ctx.sessions() as s:
        assert s.get(Frame, fid).voting_version_id == new["version"]  # it votes
    # what was painted: road along the stroke, grass elsewhere
    ids = png_ids(rev.get(f"/api/frames/{fid}/mask").content)
    assert ids.shape == (H, W)
    assert ids[int(y), W // 2] == ROAD and ids[0, 0] == GRASS and ids[-1, -1] == GRASS
    assert set(np.unique(ids)) == {ROAD, GRASS}
    road = ids == ROAD
    assert 0.03 < road.mean() < 0.5, road.mean()
    # the annotator is told
    n = ann.get("/api/notifications?unread=true").json()
    assert any(x["kind"] == "corrected" and x["frame_id"] == fid for x in n["items"]), n
    # the lifting includes it (filled), and the page says so once the 3D labels follow
    live.wait_until(lambda: rev.get(f"/api/scenes/{sid}/labels/status").json()
                    .get("filled_versions", {}).get(str(fid)) == new["version"], 90, "the correction lifted")
    wait_js(page, "() => { const n = document.querySelector('#fix-note'); return n && n.dataset.lifted === 'true'; }", timeout=30_000)
    # the lifted labels follow the correction: points seen on the road stroke are road now
    from app.scenes.models import Scene
    from occufly.lifting import load_labels

    with live.app.state.ctx.sessions() as s:
        ws = s.get(Scene, sid).workspace
    scene = live.app.state.ctx.load_scene(ws)
    frame = rev.get(f"/api/frames/{fid}").json()
    pids, uv, _d = scene.visibility.frame(frame["index"])
    uv = np.asarray(uv, np.float64)
    cam = scene.frames[frame["index"]].camera
    col = np.clip((uv[:, 0] * W / cam.width).astype(int), 0, W - 1)
    row = np.clip((uv[:, 1] * H / cam.height).astype(int), 0, H - 1)
    on_road = road[row, col]
    assert on_road.sum() > 20
    labels = np.asarray(load_labels(ws).labels)
    assert (labels[np.asarray(pids)[on_road]] == ROAD).mean() > 0.8
    # a decision now lands on the correction: A accepts the version on screen
    assert page.evaluate(f"() => {R}.frame.current_version") == new["version"]
    page.evaluate("() => document.activeElement && document.activeElement.blur()")
    page.keyboard.press("a")
    live.wait_until(lambda: rev.get(f"/api/frames/{fid}").json()["state"] == "accepted", 30,
                    "the accept")
    kinds = {v["version"]: v["kind"] for v in rev.get(f"/api/frames/{fid}/mask/versions").json()}
    assert kinds[new["version"]] == "accepted", kinds


def test_propose_from_3d_files_a_proposal_for_the_annotator(live, setup, new_page):
    sid, f = setup["sid"], setup["frames"][1]
    fid = f["id"]
    rev, ann = live.client("reviewer"), live.client("annotator")
    frame = rev.get(f"/api/frames/{fid}").json()
    from app.scenes.models import Scene

    with live.app.state.ctx.sessions() as s:
        ws = s.get(Scene, sid).workspace
    seen = np.sort(np.asarray(live.app.state.ctx.load_scene(ws).visibility.frame(frame["index"])[0],
                              np.int64))
    e = rev.post(f"/api/scenes/{sid}/corrections",
                 json={"point_ids": seen[: max(50, len(seen) // 10)].tolist(), "to_class": TREE,
                       "comment": "these are trees", "frame_id": fid})
    assert e.status_code == 201, e.text
    e = e.json()
    ann.post("/api/notifications/read", json={})
    page = new_page("reviewer", viewport=(1440, 900))
    _open_review(page, live, sid, fid)
    page.click("#propose-3d")
    btn = page.locator(f"#propose-list tr[data-edit='{e['id']}'] .propose-btn")
    btn.wait_for()
    assert btn.is_enabled()
    assert "these are trees" in page.locator(f"#propose-list tr[data-edit='{e['id']}']").inner_text()
    btn.click()
    page.wait_for_selector("#proposal-list li[data-status='open']")
    shot(page, "review_propose_3d")  # test-artifacts/: the dialog after proposing
    assert "null" not in page.locator("#propose-list").inner_text()
    assert page.locator(f"#propose-list tr[data-edit='{e['id']}'] .propose-btn").is_disabled()
    props = rev.get(f"/api/frames/{fid}/proposals?status=open").json()
    assert [p["edit_id"] for p in props] == [e["id"]] and props[0]["author"] == "reviewer"
    assert props[0]["changed_px"] > 0
    n = ann.get("/api/notifications?unread=true").json()
    assert any(x["kind"] == "proposal" and x["frame_id"] == fid for x in n["items"]), n
    # the proposal's change is tree where the frame's mask was grass
    ov = np.asarray(Image.open(io.BytesIO(
        ann.get(f"/api/frames/{fid}/proposals/{props[0]['id']}/overlay").content)))
    assert (ov[..., 3] > 0).sum() == props[0]["changed_px"]
    page.click("dialog[open] .dlg-buttons button")  # Close
    page.wait_for_selector("dialog[open]", state="detached")
