"""Browser checks of issue 7, in the order a real session would happen:
annotator paints/undoes/redoes/submits/reloads; prefill from 3D on a neighbouring frame;
conflict dialog keeps both versions; reviewer rejects with a pinned comment and the annotator
gets the frame back; admin runs an export job to completion. Screenshots go to test-artifacts/.
"""

from __future__ import annotations

import base64
import re

import numpy as np
import pytest

from tests.e2e.conftest import grey_png, png_ids, shot, wait_js

pytestmark = pytest.mark.e2e

STATE: dict = {}  # shared between the ordered tests of this module


def editor_ids(page) -> np.ndarray:
    """The editor's raw id buffer (H, W) read out of the page."""
    b64, w, h = page.evaluate(
        """() => { const m = window.__occufly.page.editor.mask;
                   let s = ''; const a = m.ids;
                   for (let i = 0; i < a.length; i += 0x8000)
                     s += String.fromCharCode.apply(null, a.subarray(i, i + 0x8000));
                   return [btoa(s), m.width, m.height]; }"""
    )
    return np.frombuffer(base64.b64decode(b64), np.uint8).reshape(h, w)


def painted_share(page) -> float:
    return float(page.get_attribute("#painted", "data-share"))


def wait_opened(page, fid: int | None = None) -> int:
    wait_js(page, "() => window.__occufly && window.__occufly.page.stats.openMs !== null")
    got = page.evaluate("() => window.__occufly.page.frame.id")
    if fid is not None:
        assert got == fid
    return got


def drag(page, pts):
    box = page.locator(".layer-overlay").bounding_box()
    x0, y0 = box["x"], box["y"]
    page.mouse.move(x0 + pts[0][0] * box["width"], y0 + pts[0][1] * box["height"])
    page.mouse.down()
    for fx, fy in pts[1:]:
        page.mouse.move(x0 + fx * box["width"], y0 + fy * box["height"], steps=8)
    page.mouse.up()


def test_annotator_paint_undo_redo_submit_reload(live, new_page):
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate")
    shot(page, "01_annotator_empty")
    page.click("#next-frame")
    fid = wait_opened(page)
    assert painted_share(page) == 0.0
    scene = live.client("annotator").get(f"/api/scenes/{live.scene_id}").json()
    classes = [c["id"] for c in scene["taxonomy"]["classes"]]
    cls = 16 if 16 in classes else classes[0]
    page.locator(".layer-overlay").focus()
    page.keyboard.press("3")  # number keys pick palette entries
    assert page.get_attribute(f".swatch-btn[data-class='{classes[2]}']", "aria-checked") == "true"
    # , and . step through the palette, wrapping around: every class has a key, the 21st too
    page.keyboard.press("Shift+Digit0")  # the 20th class
    assert page.get_attribute(f".swatch-btn[data-class='{classes[19]}']", "aria-checked") == "true"
    page.keyboard.press(".")
    assert page.get_attribute(f".swatch-btn[data-class='{classes[20]}']", "aria-checked") == "true"
    page.keyboard.press(".")
    assert page.get_attribute(f".swatch-btn[data-class='{classes[0]}']", "aria-checked") == "true"
    page.keyboard.press(",")
    assert page.get_attribute(f".swatch-btn[data-class='{classes[-1]}']", "aria-checked") == "true"
    page.click(f".swatch-btn[data-class='{cls}']")
    assert page.get_attribute(f".swatch-btn[data-class='{cls}']", "aria-checked") == "true"
    page.evaluate("() => window.__occufly.page.editor.setSize(30)")
    drag(page, [(0.3, 0.3), (0.7, 0.35), (0.6, 0.7), (0.35, 0.6)])
    s1 = painted_share(page)
    assert s1 > 0.01
    ids1 = editor_ids(page)
    assert set(np.unique(ids1)) == {0, cls}
    assert (ids1 == cls).mean() == pytest.approx(s1)
    # one drag = one stroke = one undo step
    page.keyboard.press("Control+z")
    assert painted_share(page) == 0.0 and not editor_ids(page).any()
    page.click("#redo")
    assert painted_share(page) == pytest.approx(s1)
    assert np.array_equal(editor_ids(page), ids1)
    page.click("#submit")
    page.wait_for_selector("#save-state:has-text('Submitted')")
    shot(page, "02_annotator_submitted")
    # the server holds exactly the painted ids, as a single-channel PNG
    rev = live.client("reviewer")
    r = rev.get(f"/api/frames/{fid}/mask")
    assert r.status_code == 200
    version = int(r.headers["etag"].strip('"'))
    assert np.array_equal(png_ids(r.content), ids1)
    frame = rev.get(f"/api/frames/{fid}").json()
    assert frame["state"] == "submitted"
    # reload: the same frame comes back with the submitted mask
    page.reload()
    wait_opened(page, fid)
    assert painted_share(page) == pytest.approx(s1)
    assert np.array_equal(editor_ids(page), ids1)
    assert page.locator("#save-state").inner_text().startswith("Saved")
    # the lifted labels include this version and now carry the painted class
    def lifted():
        st = live.labels_status(live.scene_id, "reviewer")  # a 500 fails here, at once
        inc = {str(k): v for k, v in st["included_versions"].items()}
        hist = {str(k): v for k, v in st["class_histogram"].items()}
        return st if inc.get(str(fid)) == version and hist.get(str(cls), 0) > 0 else None
    live.wait_until(lifted, timeout=60, what="lifted labels to include the submitted mask")
    STATE.update(frame_a=fid, cls=cls, ids_a=ids1)


def neighbour_of(live, fid: int) -> int:
    """The frame whose camera centre is closest to frame `fid`'s."""
    c = live.client("admin")
    frames = c.get(f"/api/scenes/{live.scene_id}/frames").json()
    centers = {f["id"]: np.array(c.get(f"/api/frames/{f['id']}").json()["center"]) for f in frames}
    others = [f for f in centers if f != fid]
    return min(others, key=lambda f: float(np.linalg.norm(centers[f] - centers[fid])))


def test_prefill_from_3d_on_neighbouring_frame(live, new_page):
    fa = STATE["frame_a"]
    fb = neighbour_of(live, fa)
    admin = live.client("admin")
    def filled():
        return not live.labels_status(live.scene_id)["pending_fill"]
    live.wait_until(filled, timeout=60, what="kNN fill of the lifted labels")
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/annotate?scene={live.scene_id}&frame={fb}")
    wait_opened(page, fb)
    assert painted_share(page) == 0.0
    page.click("#prefill")
    wait_js(page, "() => Number(document.querySelector('#painted').dataset.share) > 0")
    ids = editor_ids(page)
    # exactly the server's rendering of the lifted labels, and it carries the painted class
    server = png_ids(admin.get(f"/api/frames/{fb}/prefill").content)
    assert server.shape == ids.shape
    assert np.array_equal(ids, server)
    assert (ids == STATE["cls"]).sum() > 0
    shot(page, "03_annotator_prefill_from_3d")
    # prefill is one undoable command
    page.click("#undo")
    assert painted_share(page) == 0.0
    page.click("#redo")
    assert np.array_equal(editor_ids(page), server)
    # idle autosave stores it as a draft (If-Match none -> first version)
    page.wait_for_selector("#save-state[data-state='saved']:has-text('version')", timeout=15_000)
    r = admin.get(f"/api/frames/{fb}/mask")
    assert np.array_equal(png_ids(r.content), server)
    STATE.update(frame_b=fb, version_b=int(r.headers["etag"].strip('"')))


def test_conflict_dialog_keeps_both_versions(live, new_page):
    fb, base = STATE["frame_b"], STATE["version_b"]
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/annotate?scene={live.scene_id}&frame={fb}")
    wait_opened(page, fb)
    # someone else saves a different mask meanwhile (another admin session's correction:
    # reviewers no longer write masks since the hardening of issue 14)
    theirs = editor_ids(page).copy()
    theirs[: theirs.shape[0] // 4] = STATE["cls"]
    rev = live.client("reviewer")
    r = live.client("admin").put(f"/api/frames/{fb}/mask?kind=draft", content=grey_png(theirs),
                headers={"Content-Type": "image/png", "If-Match": str(base)})
    assert r.status_code == 200, r.text
    theirs_version = r.json()["version"]
    # we paint and save on top of the stale version -> 409 -> dialog
    page.keyboard.press("e")  # eraser
    drag(page, [(0.2, 0.5), (0.8, 0.5)])
    mine = editor_ids(page)
    assert not np.array_equal(mine, theirs)
    page.keyboard.press("Control+s")
    dlg = page.locator("dialog.modal")
    dlg.wait_for()
    assert "changed by someone else" in dlg.inner_text()
    shot(page, "04_conflict_dialog")
    with page.expect_download() as dl:
        dlg.get_by_role("button", name="Download mine").click()
    path = dl.value.path()
    assert np.array_equal(png_ids(open(path, "rb").read()), mine)
    dlg = page.locator("dialog.modal")
    dlg.wait_for()
    dlg.get_by_role("button", name="Keep mine as new version").click()
    page.wait_for_selector("#save-state[data-state='saved']")
    cur = rev.get(f"/api/frames/{fb}/mask")
    assert np.array_equal(png_ids(cur.content), mine)
    assert int(cur.headers["etag"].strip('"')) > theirs_version
    # theirs is still there, and our stale upload was kept as a conflict version too
    old = rev.get(f"/api/frames/{fb}/mask/versions/{theirs_version}")
    assert np.array_equal(png_ids(old.content), theirs)
    kinds = [v["kind"] for v in rev.get(f"/api/frames/{fb}/mask/versions").json()]
    assert "conflict" in kinds
    # the version history restores theirs as the newest version (and the editor shows it)
    page.click("details.versions summary")
    page.click(f".version-list li[data-version='{theirs_version}'] button:has-text('restore')")
    wait_js(page, f"() => window.__occufly.page.version !== '{cur.headers['etag'].strip(chr(34))}' && window.__occufly.page.stats.openMs !== null")
    assert np.array_equal(editor_ids(page), theirs)
    assert np.array_equal(png_ids(rev.get(f"/api/frames/{fb}/mask").content), theirs)


def test_reviewer_rejects_with_pinned_comment_annotator_gets_it_back(live, new_page):
    fa = STATE["frame_a"]
    page = new_page("reviewer")
    page.goto(f"{live.base_url}/#/review?scene={live.scene_id}")
    row = page.locator(f"#frame-list tr[data-frame='{fa}'] a")
    row.click()
    page.wait_for_selector("#agreement[data-value]")
    res = live.client("reviewer").get(f"/api/frames/{fa}/agreement").json()
    text = page.locator("#agreement").inner_text()
    if res["agreement"] is None:  # leave-one-out: no other submitted frame sees enough of it
        assert res["status"] == "not_enough_independent_views"
        assert "not enough independent views" in text
    else:
        assert f"{100 * res['agreement']:.1f} %" in text
    assert page.get_attribute("#open-3d", "href") == f"/viewer/?scene={live.scene_id}&frame={fa}"
    viewer = live.client("reviewer").get(f"/viewer/?scene={live.scene_id}&frame={fa}", follow_redirects=True)
    assert viewer.status_code == 200 and "html" in viewer.headers.get("content-type", "")
    page.wait_for_selector("canvas[data-layer='image']")
    page.wait_for_timeout(300)
    shot(page, "05_reviewer_side_by_side")
    # pin a comment to the pixel at 25 %/40 % of the image panel
    cv = page.locator("canvas[data-layer='image']")
    box = cv.bounding_box()
    page.mouse.click(box["x"] + 0.25 * box["width"], box["y"] + 0.40 * box["height"])
    pin = page.locator("#pin-text").inner_text()
    x, y = map(int, re.search(r"\((\d+), (\d+)\)", pin).groups())
    W, H = STATE["ids_a"].shape[1], STATE["ids_a"].shape[0]
    assert abs(x - 0.25 * W) <= 1 + W / box["width"] and abs(y - 0.40 * H) <= 1 + H / box["height"]
    comment = "Roof edge is off by a few pixels here; please fix."
    page.fill("#review-comment", comment)
    page.click("#reject")
    page.wait_for_selector(".badge.state-rejected")
    page.click("button:has-text('Blended')")
    page.wait_for_timeout(300)
    shot(page, "06_reviewer_rejected_blended")
    rev = live.client("reviewer")
    assert rev.get(f"/api/frames/{fa}").json()["state"] == "rejected"
    items = [it for it in rev.get(f"/api/scenes/{live.scene_id}/review-items").json()
             if it["frame_id"] == fa]
    assert any(it["pixel"] == [x, y] and any(c["text"] == comment for c in it["comments"])
               for it in items), items
    # the annotator asks for the next frame and gets the rejected one back, with the comment
    ann = new_page("annotator")
    ann.goto(f"{live.base_url}/#/annotate?scene={live.scene_id}")
    ann.click("#next-frame")
    wait_opened(ann, fa)
    assert comment in ann.locator("#review-comments").inner_text()
    assert np.array_equal(editor_ids(ann), STATE["ids_a"])
    shot(ann, "07_annotator_got_rejected_frame_back")


def test_admin_export_job_completes(live, new_page):
    # a rejected mask no longer votes (issue 23): its annotator submits the frame again, so
    # the scene has labels to voxelize and export
    fa = STATE["frame_a"]
    ann = live.client("annotator")
    cur = ann.get(f"/api/frames/{fa}/mask")
    assert cur.status_code == 200, cur.text
    r = ann.put(f"/api/frames/{fa}/mask?kind=submitted", content=grey_png(STATE["ids_a"]),
                headers={"If-Match": cur.headers["etag"]})
    assert r.status_code == 200, r.text
    resubmitted = r.json()["version"]

    def refilled():
        st = live.labels_status(live.scene_id)
        return (st["filled_versions"].get(str(fa)) == resubmitted and not st["pending_fill"]
                and st["class_histogram"])
    live.wait_until(refilled, timeout=90, what="the resubmitted mask lifted and filled")
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={live.scene_id}")
    page.wait_for_selector("#coverage-plot")
    page.wait_for_selector("#camera-map")
    assert "frames selected" in page.locator("#selection-summary").inner_text()
    assert "occupied grid cells" in page.locator("#sec-selection figcaption").nth(1).inner_text()
    shot(page, "08_admin", full_page=True)
    # users: create one through the form, it is listed and can log in
    page.fill("#new-username", "annotator2")
    page.fill("#new-password", "annotator2-password")
    page.select_option("#new-role", "annotator")
    page.click("form[aria-label='Create user'] button[type=submit]")
    page.wait_for_selector("#sec-users td:has-text('annotator2')")
    import httpx
    r = httpx.post(f"{live.base_url}/api/auth/login",
                   json={"username": "annotator2", "password": "annotator2-password"})
    assert r.status_code == 200 and r.json()["user"]["role"] == "annotator"
    # import from outside the allowed roots: refused with a readable message, nothing created
    n_scenes = len(live.client("admin").get("/api/scenes").json())
    page.fill("#imp-name", "outside")
    page.fill("#imp-source", "/etc")
    page.click("form[aria-label='Import a scene'] button[type=submit]")
    page.wait_for_selector("#alert:not(:empty)")
    assert "/etc" in page.locator("#alert").inner_text() or "allowed" in page.locator("#alert").inner_text()
    assert len(live.client("admin").get("/api/scenes").json()) == n_scenes
    admin = live.client("admin")

    def run_job(button: str, kind: str, confirm: bool = False) -> int:
        before = {j["id"] for j in admin.get("/api/jobs").json()}
        page.click(button)
        if confirm:  # issue 23: the page asks before an export that takes unreviewed masks in
            page.locator("dialog.modal:has(#export-confirm) button:has-text('Export')").click()
        new = live.wait_until(lambda: [j for j in admin.get("/api/jobs").json()
                                       if j["id"] not in before and j["kind"] == kind],
                              timeout=20, what=f"a new {kind} job")
        jid = new[0]["id"]
        # the page's job list follows the job live until it ends
        page.wait_for_selector(f"li.job[data-job='{jid}'][data-status='done'], "
                               f"li.job[data-job='{jid}'][data-status='failed']", timeout=180_000)
        j = admin.get(f"/api/jobs/{jid}").json()
        assert j["status"] == "done", f"{kind} failed: {j['message']} {j['log_tail'][-5:]}"
        return jid

    run_job("#start-voxelize", "voxelize")
    page.select_option("#export-layout", "occufly")
    # its frames are submitted, not accepted: the export takes them in by choice (issue 23)
    page.check("#export-include-unreviewed")
    jid = run_job("#start-export", "export", confirm=True)
    for attempt in range(10):  # the job list is redrawn when a poll lands: the card is replaced
        try:
            page.locator(f"li.job[data-job='{jid}']").scroll_into_view_if_needed(timeout=5000)
            break
        except Exception:  # noqa: BLE001 - "not attached to the DOM": take the new card
            if attempt == 9:
                raise
            page.wait_for_timeout(300)
    shot(page, "09_admin_export_finished", full_page=True)
    assert page.locator(f"li.job[data-job='{jid}'] progress").get_attribute("value") == "1"
    # issue 28 item 7: the only download is the compressed archive (the legacy tar is gone)
    row = page.locator(f"li.job[data-job='{jid}']")
    assert row.locator(f"a[href='/api/jobs/{jid}/download']").count() == 0
    row.locator("button.archive-build").click()
    link = row.locator("a.archive-link")
    link.wait_for(timeout=120_000)
    assert link.get_attribute("href") == f"/api/jobs/{jid}/archive?format=tar.gz"
    r = live.client("admin").get(f"/api/jobs/{jid}/archive?format=tar.gz")
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content) > 1000
    assert live.client("admin").get(f"/api/jobs/{jid}/download").status_code == 404
    # evaluation job -> metric tables on the page
    run_job("#start-eval", "eval")
    metrics = page.locator("#metrics")
    metrics.wait_for()
    assert metrics.locator("table").count() >= 1
    m = admin.get(f"/api/scenes/{live.scene_id}/metrics").json()
    scalars = {k: v for k, v in m.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    for k in list(scalars)[:3]:  # the page shows the API's numbers
        assert metrics.locator(f"td:text-is('{k}')").count() >= 1
    metrics.scroll_into_view_if_needed()
    shot(page, "11_admin_metrics", full_page=True)
    # frame selection with the best cell of 23-28 m (greedy): the form sends "auto", the page
    # shows the edge the server chose; the previous selection is restored afterwards
    before = admin.get(f"/api/scenes/{live.scene_id}/selection").json()
    page.check("#sel-auto")
    assert page.locator("#sel-cell").is_disabled() and page.locator("#sel-mode").input_value() == "greedy"
    run_job("form[aria-label='Selection parameters'] button[type=submit]", "selection")
    def auto_selection():
        s = admin.get(f"/api/scenes/{live.scene_id}/selection").json()
        return s if s.get("params", {}).get("cell") == "auto" else None

    sel = live.wait_until(auto_selection, timeout=20, what="auto selection")
    assert 23.0 <= sel["cell"] <= 28.0 and len(sel["auto_cells"]) == 11
    wait_js(page, f"document.querySelector('#sel-cell').value == '{sel['cell']:g}'", timeout=20_000)
    assert page.locator("#sel-auto").is_checked()
    page.locator("#sec-selection").scroll_into_view_if_needed()
    shot(page, "12_admin_selection_best_cell")
    prm = before.get("params", {})
    r = admin.post(f"/api/scenes/{live.scene_id}/selection",
                   json={k: prm[k] for k in ("cell", "mode", "target_coverage", "altitude") if prm.get(k) is not None})
    assert r.status_code == 202
    live.wait_until(lambda: admin.get(f"/api/jobs/{r.json()['id']}").json()["status"] == "done", timeout=60,
                    what="selection restored")


def test_errors_are_readable_never_a_blank_page(live, new_page):
    page = new_page(None)
    page.goto(f"{live.base_url}/#/login")
    page.fill("#username", "annotator")
    page.fill("#password", "wrong-password")
    page.click("button[type=submit]")
    alert = page.locator("#alert")
    alert.wait_for()
    msg = alert.inner_text()
    assert msg.strip() and "{" not in msg  # a sentence from the API's detail, not JSON
    shot(page, "00_login_error")
    page.fill("#password", "annotator-password-1")
    page.click("button[type=submit]")
    page.wait_for_selector("#whoami:has-text('annotator')")
    # a page the role may not use
    page.goto(f"{live.base_url}/#/admin")
    page.wait_for_selector("main h1:has-text('Not available')")
    # a frame that does not exist: the API's 404 message is shown, the page stays usable
    page.goto(f"{live.base_url}/#/annotate?scene={live.scene_id}&frame=987654")
    page.wait_for_selector("#alert:not(:empty)")
    assert "987654" in page.locator("#alert").inner_text() or "not found" in page.locator("#alert").inner_text().lower()
    assert page.locator("#next-frame").is_visible()


def test_polygon_and_flood_fill_tools_in_the_page(live, new_page):
    used = {STATE["frame_a"], STATE["frame_b"]}
    frames = live.client("admin").get(f"/api/scenes/{live.scene_id}/frames").json()
    fc = next(f["id"] for f in frames if f["id"] not in used and f["current_version"] is None)
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/annotate?scene={live.scene_id}&frame={fc}")
    wait_opened(page, fc)
    ov = page.locator(".layer-overlay")
    ov.focus()
    page.keyboard.press("p")
    assert page.get_attribute("button[data-tool='polygon']", "aria-pressed") == "true"
    box = ov.bounding_box()
    # a rectangle: corners at image pixels (40, 30) .. (120, 90), clicked through the view
    corners = page.evaluate("""() => { const v = window.__occufly.page.editor.view;
        return [[40, 30], [120, 30], [120, 90], [40, 90]].map(([x, y]) => v.toScreen(x, y)); }""")
    for x, y in corners:
        page.mouse.click(box["x"] + x, box["y"] + y)
    page.keyboard.press("Enter")
    ids = editor_ids(page)
    cls = page.evaluate("() => window.__occufly.page.editor.state.classId")
    assert (ids == cls).sum() == 80 * 60  # exactly the rectangle's pixels
    assert (ids[30:90, 40:120] == cls).all()
    # flood fill from a photo pixel outside the rectangle adds a connected similar region
    page.keyboard.press("f")
    page.keyboard.press("2")  # another class (switches back to the brush) ...
    page.keyboard.press("f")  # ... so pick the flood tool again
    cls2 = page.evaluate("() => window.__occufly.page.editor.state.classId")
    x, y = page.evaluate("() => window.__occufly.page.editor.view.toScreen(200.5, 140.5)")
    page.mouse.click(box["x"] + x, box["y"] + y)
    wait_js(page, f"() => window.__occufly.page.editor.mask.ids.some((v) => v === {cls2})")
    ids2 = editor_ids(page)
    assert ids2[140, 200] == cls2 and (ids2 == cls).sum() <= 80 * 60
    # two undo steps: flood fill, then the polygon
    page.keyboard.press("Control+z")
    assert np.array_equal(editor_ids(page), ids)
    page.keyboard.press("Control+z")
    assert not editor_ids(page).any()
    shot(page, "10_annotator_tools")


def test_chromium_decodes_the_review_pngs_to_their_pixels(browser):
    """The review's PNGs come from our own encoder (Up filter, ISA-L deflate; the overlay
    indexed with PLTE + tRNS): Chromium, the reviewer's reader, decodes the grey /render
    image to its label ids and the overlay to ``palette[indices]`` (alpha exact; colour exact
    where opaque, within canvas premultiplication rounding where translucent)."""
    from app.pipeline import encode_png, encode_png_palette
    from occufly.render import disagreement_indices, disagreement_palette
    from occufly.taxonomy import default_taxonomy

    tax = default_taxonomy()
    rng = np.random.default_rng(4)
    ids = np.concatenate([[0, 255], np.asarray(tax.ids)]).astype(np.uint8)
    h, w = 120, 1500
    mask = rng.choice(ids, (h, w)).astype(np.uint8)
    mask[:, :400] = ids[3]  # runs, as real masks have
    rend = np.where(rng.random((h, w)) < 0.5, mask, rng.choice(ids, (h, w))).astype(np.uint8)
    pal = disagreement_palette(tax)
    idx = disagreement_indices(mask, rend, tax)
    want = pal[idx]
    assert len(np.unique(want[..., 3])) >= 3  # opaque, translucent and clear pixels

    ctx = browser.new_context()
    page = ctx.new_page()
    try:
        def decoded(png: bytes) -> np.ndarray:
            b64 = page.evaluate("""async (src) => {
                const img = new Image(); img.src = src; await img.decode();
                const c = document.createElement('canvas'); c.width = img.width; c.height = img.height;
                const g = c.getContext('2d', {colorSpace: 'srgb'}); g.drawImage(img, 0, 0);
                const a = g.getImageData(0, 0, c.width, c.height).data; let s = '';
                for (let i = 0; i < a.length; i += 0x8000) s += String.fromCharCode.apply(null, a.subarray(i, i + 0x8000));
                return btoa(s); }""", "data:image/png;base64," + base64.b64encode(png).decode())
            return np.frombuffer(base64.b64decode(b64), np.uint8).reshape(h, w, 4)

        grey = decoded(encode_png(rend))
        assert (grey[..., 3] == 255).all()
        for ch in range(3):
            assert np.array_equal(grey[..., ch], rend)
        over = decoded(encode_png_palette(idx, pal))
        assert np.array_equal(over[..., 3], want[..., 3])
        opaque = want[..., 3] == 255
        assert np.array_equal(over[opaque], want[opaque])
        part = (want[..., 3] > 0) & ~opaque
        assert part.any()
        assert np.abs(over[part][:, :3].astype(int) - want[part][:, :3]).max() <= 3
    finally:
        ctx.close()
