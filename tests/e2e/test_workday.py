"""Issue 17 defects that break an annotator's / reviewer's / admin's day, each driven in
Chromium against the real app (the session's `live` server, one browser for the module).

Ordered: the first test paints and submits the frames the later ones review.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from app.viewer import scene_builder as sb
from tests.e2e.conftest import grey_png, import_own_scene, png_ids, shot, wait_js
from tests.e2e.test_browser import drag, editor_ids, painted_share, wait_opened

pytestmark = pytest.mark.e2e

STATE: dict = {}


@pytest.fixture(scope="module")
def sid(live):
    """A scene of its own (the same source imported again): a clean queue for this module,
    whatever the other modules leased, submitted or rejected."""
    return import_own_scene(live, "workday_scene")


def watch(page) -> list[str]:
    """Every HTTP answer >= 400 the page receives (console noise such as favicon / mask 404)."""
    bad: list[str] = []
    page.on("response", lambda r: r.status >= 400 and bad.append(f"{r.status} {r.request.method} {r.url}"))
    return bad


def puts(page) -> list[str]:
    sent: list[str] = []
    page.on("request", lambda r: r.method == "PUT" and sent.append(r.url))
    return sent


def versions_of(live, fid: int) -> list[dict]:
    return live.client("admin").get(f"/api/frames/{fid}/mask/versions").json()


def test_submit_makes_the_frame_read_only_with_reopen_and_per_frame_versions(live, sid, new_page):
    """Defects 1, 4, 10: after Submit the frame is read-only (banner, tools off, no PUT, no
    dialog); "Reopen" takes it back; versions are numbered per frame and the list refreshes;
    a fresh frame does not ask for a mask (no 404) and there is a favicon (no 404)."""
    page = new_page("annotator")
    bad = watch(page)
    sent = puts(page)
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    fid = wait_opened(page)
    assert live.client("admin").get(f"/api/frames/{fid}").json()["current_version"] is None
    assert painted_share(page) == 0.0
    page.evaluate("() => window.__occufly.page.editor.setSize(24)")
    drag(page, [(0.2, 0.2), (0.5, 0.3)])
    page.keyboard.press("Control+s")
    page.wait_for_selector("#save-state[data-state='saved']:has-text('Saved (version 1)')")
    page.click("details.versions summary")
    page.wait_for_selector(".version-list li[data-number='1']")
    drag(page, [(0.3, 0.6), (0.7, 0.6)])
    page.click("#submit")
    page.wait_for_selector("#save-state:has-text('Submitted (version 2)')")
    # the version list (open) was refreshed after Submit: both versions, numbered 1 and 2
    page.wait_for_selector(".version-list li[data-number='2']")
    assert page.locator(".version-list li").count() == 2
    vs = versions_of(live, fid)
    assert [v["number"] for v in vs] == [1, 2] and [v["kind"] for v in vs] == ["draft", "submitted"]
    # global ids differ from the per-frame numbers once other frames have versions
    assert page.locator(f".version-list li[data-version='{vs[1]['version']}']").inner_text().startswith("v2 ")
    # read-only now: banner with reopen, painting tools disabled, a drag changes nothing
    banner = page.locator("#readonly-banner")
    assert banner.get_attribute("data-reason") == "submitted" and "read-only" in banner.inner_text()
    assert page.locator("button[data-tool='brush']").is_disabled()
    assert page.locator("#submit").is_disabled() and page.locator("#prefill").is_disabled()
    before = editor_ids(page)
    n_put = len(sent)
    drag(page, [(0.1, 0.8), (0.9, 0.8)])
    page.keyboard.press("Control+s")
    page.wait_for_timeout(3000)  # past the 2.5 s autosave
    assert np.array_equal(editor_ids(page), before)
    assert len(sent) == n_put, "no PUT may be sent for a read-only frame"
    assert page.locator("dialog[open]").count() == 0
    assert [v["kind"] for v in versions_of(live, fid)] == ["draft", "submitted"]  # no conflict version
    shot(page, "17_01_submitted_read_only")
    # reopen (nobody reviewed it yet): editable again, the next save is version 3
    page.click("#reopen")
    wait_js(page, "() => !document.querySelector('#readonly-banner') && window.__occufly.page.stats.openMs !== null")
    assert live.client("admin").get(f"/api/frames/{fid}").json()["state"] == "in_progress"
    page.locator(".layer-overlay").focus()
    page.keyboard.press("b")
    drag(page, [(0.4, 0.4), (0.6, 0.5)])
    page.click("#submit")
    page.wait_for_selector("#save-state:has-text('Submitted (version 3)')")
    assert live.client("admin").get(f"/api/frames/{fid}").json()["state"] == "submitted"
    assert not bad, bad
    STATE.update(frame_1=fid, ids_1=editor_ids(page))


def test_edit_in_a_stale_tab_after_submit_names_the_real_cause(live, sid, new_page):
    """Defect 1: a second tab still editing a frame that was submitted meanwhile gets a dialog
    that says so (not "changed by someone else"); "Reopen and save mine" saves it, once."""
    ann = live.client("annotator")
    f = ann.post(f"/api/scenes/{sid}/next").json()
    fid = f["id"]
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}&frame={fid}")
    wait_opened(page, fid)
    # meanwhile the same annotator submits from elsewhere (e.g. another tab)
    ids = np.zeros((f["height"], f["width"]), np.uint8)
    ids[: f["height"] // 3] = STATE["ids_1"].max() or 1
    r = ann.put(f"/api/frames/{fid}/mask?kind=submitted", content=grey_png(ids),
                headers={"Content-Type": "image/png", "If-Match": "none"})
    assert r.status_code == 200, r.text
    page.evaluate("() => window.__occufly.page.editor.setSize(30)")
    drag(page, [(0.5, 0.5), (0.8, 0.7)])
    mine = editor_ids(page)
    dlg = page.locator("dialog.modal")
    dlg.wait_for(timeout=10_000)  # the idle autosave hits 409 (lease)
    text = dlg.inner_text()
    assert "no longer leased" in text and "already submitted" in text
    assert "changed by someone else" not in text and "another session" not in text
    shot(page, "17_02_lease_lost_dialog")
    dlg.get_by_role("button", name="Reopen and save mine").click()
    page.wait_for_selector("#save-state[data-state='saved']")
    assert page.locator("dialog[open]").count() == 0
    cur = live.client("admin").get(f"/api/frames/{fid}/mask")
    assert np.array_equal(png_ids(cur.content), mine)
    kinds = [v["kind"] for v in versions_of(live, fid)]
    assert kinds == ["submitted", "conflict", "draft"], kinds  # one conflict version, not one per try
    assert live.client("admin").get(f"/api/frames/{fid}").json()["state"] == "in_progress"
    page.click("#submit")
    page.wait_for_selector("#save-state:has-text('Submitted (version 4)')")
    STATE.update(frame_2=fid)


def test_reviewer_sees_who_painted_per_class_names_and_a_pinned_rejection_once(live, sid, new_page):
    """Defects 5, 6, 7."""
    f1, f2 = STATE["frame_1"], STATE["frame_2"]
    page = new_page("reviewer")
    bad = watch(page)
    page.goto(f"{live.base_url}/#/review?scene={sid}")
    row = page.locator(f"#frame-list tr[data-frame='{f2}']")
    row.wait_for()
    cell = row.locator(".annotator-name")
    assert cell.inner_text() == "annotator"  # assignee is null after submit; who painted it shows
    pane = page.locator(".list-pane").bounding_box()
    box = cell.bounding_box()
    assert box["x"] + box["width"] <= pane["x"] + pane["width"] + 0.5, "annotator column is cut off"
    row.locator("a").click()
    page.wait_for_selector("#agreement[data-value]")
    api = live.client("reviewer").get(f"/api/frames/{f2}/agreement").json()
    page.click("#per-class summary")
    rows = page.locator("#per-class tbody tr")
    assert rows.count() == len(api["per_class"]) >= 1
    names = [rows.nth(i).locator("td").first.inner_text().strip() for i in range(rows.count())]
    assert set(names) == set(api["per_class"]) and not any(n.startswith("id ") for n in names)
    # every painted class is listed, the most painted first, with or without independent views
    painted = {int(v["id"]) for v in api["per_class"].values() if v["painted_pixels"] > 0}
    cur = png_ids(live.client("reviewer").get(f"/api/frames/{f2}/mask").content)
    assert painted == set(np.unique(cur).tolist()) - {0, 255}
    top = max(api["per_class"].items(), key=lambda kv: kv[1]["painted_pixels"])
    cells = [c.strip() for c in rows.first.locator("td").all_inner_texts()]
    assert cells[0] == top[0]
    assert cells[1].replace(",", "") == str(top[1]["painted_pixels"])

    def fmt(v):
        return "–" if v is None else f"{100 * v:.1f} %"

    assert cells[3] == fmt(top[1]["recall"]) and cells[5] == fmt(top[1]["iou"])
    if api["status"] == "not_enough_independent_views":
        assert "not enough independent views" in page.locator("#per-class summary").inner_text()
    shot(page, "17_03_reviewer_per_class")
    # pinned rejection: the comment exists once, as the pinned item
    cv = page.locator("canvas[data-layer='image']")
    cv.scroll_into_view_if_needed()
    b = cv.bounding_box()
    page.mouse.click(b["x"] + 0.5 * b["width"], b["y"] + 0.5 * b["height"])
    comment = "Pinned once: the car edge needs a cleaner outline."
    assert page.locator("#pin-text").inner_text().startswith("Pinned pixel")
    page.uncheck("#auto-advance")  # stay on this frame to read its items
    page.fill("#review-comment", comment)
    page.click("#reject")
    page.wait_for_selector(".badge.state-rejected")
    items = [it for it in live.client("reviewer").get(f"/api/scenes/{sid}/review-items").json()
             if it["frame_id"] == f2]
    texts = [c["text"] for it in items for c in it["comments"]]
    assert sum(comment in t for t in texts) == 1, texts
    assert page.locator("#review-items").inner_text().count(comment) == 1
    # accept frame 1 for the read-only test below
    v1 = live.client("reviewer").get(f"/api/frames/{f1}").json()["current_version"]
    r = live.client("reviewer").post(f"/api/frames/{f1}/review",
                                     json={"decision": "accept", "version": v1})
    assert r.status_code == 200
    assert not bad, bad
    ann = new_page("annotator")
    ann.goto(f"{live.base_url}/#/annotate?scene={sid}&frame={f2}")
    wait_opened(ann, f2)
    assert ann.locator("#review-comments").inner_text().count(comment) == 1
    assert ann.locator("#readonly-banner").count() == 0  # a rejected frame is theirs to fix


def test_accepted_frame_opened_by_url_is_read_only(live, sid, new_page):
    """Defect 2: no tool works, nothing is sent, the banner says why, no reopen offered."""
    f1 = STATE["frame_1"]
    page = new_page("annotator")
    sent = puts(page)
    page.goto(f"{live.base_url}/#/annotate?scene={sid}&frame={f1}")
    wait_opened(page, f1)
    banner = page.locator("#readonly-banner")
    assert banner.get_attribute("data-reason") == "accepted" and "accepted" in banner.inner_text()
    assert page.locator("#reopen").count() == 0
    for sel in ("button[data-tool='brush']", "button[data-tool='polygon']", "button[data-tool='flood']",
                "#submit", "#save-draft", "#prefill", ".swatch-btn"):
        assert page.locator(sel).first.is_disabled(), sel
    before = editor_ids(page)
    page.locator(".layer-overlay").focus()
    page.keyboard.press("b")  # even the brush key: painting stays off
    drag(page, [(0.2, 0.5), (0.8, 0.5)])
    page.keyboard.press("Control+z")
    page.keyboard.press("Control+s")
    page.keyboard.press("Control+Enter")
    page.wait_for_timeout(800)
    assert np.array_equal(editor_ids(page), before)
    assert not sent and page.locator("dialog[open]").count() == 0
    shot(page, "17_04_accepted_read_only")


def test_prefill_clicked_while_the_next_frame_loads_is_bound_to_its_frame(live, sid, new_page):
    """Defect 3: no stale dialog and no prefill of the previous frame on the new one."""
    f1 = STATE["frame_1"]
    frames = live.client("admin").get(f"/api/scenes/{sid}/frames").json()
    fresh = next(f["id"] for f in frames if f["current_version"] is None and f["id"] != f1)
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}&frame={f1}")
    wait_opened(page, f1)
    assert painted_share(page) > 0  # a painted frame: a prefill on it would ask first
    held = []
    page.route(f"**/api/frames/{fresh}/image*", lambda route: held.append(route))
    page.evaluate(f"() => {{ window.__occufly.page.openOrExplain({fresh}); }}")
    wait_js(page, "() => true")
    for _ in range(100):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the new frame's image request was not made"
    assert page.locator("#prefill").is_disabled(), "Prefill stays clickable while the next frame loads"
    page.evaluate("() => { window.__occufly.page.prefill(); }")  # a click that slips through
    page.wait_for_timeout(1200)
    assert page.locator("dialog[open]").count() == 0
    held[0].continue_()
    page.unroute(f"**/api/frames/{fresh}/image*")
    wait_opened(page, fresh)
    page.wait_for_timeout(500)
    assert page.locator("dialog[open]").count() == 0
    assert painted_share(page) == 0.0 and not editor_ids(page).any()
    assert not page.locator("#prefill").is_disabled()


def test_admin_histogram_coverage_plot_and_readable_metrics(live, sid, new_page):
    """Defect 9 (+10 on the admin page)."""
    admin = live.client("admin")
    if admin.get(f"/api/scenes/{sid}/metrics").status_code != 200:
        job = admin.post(f"/api/scenes/{sid}/eval").json()
        assert live.wait_job(job)["status"] == "done"
    page = new_page("admin")
    bad = watch(page)
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.wait_for_selector("#coverage-plot")
    page.wait_for_selector("#sec-labels p")
    page.wait_for_selector("#metrics")
    assert "null" not in page.locator("#sec-labels").inner_text()
    sel = admin.get(f"/api/scenes/{sid}/selection").json()
    curve = sel["curve"]
    plot = page.locator("#coverage-plot")
    first = plot.get_attribute("data-first")
    assert first is not None and [round(v, 6) for v in eval(first)] == [round(v, 6) for v in curve[0]]
    assert curve[0][0] > 0  # the curve starts at the stratified set: no invented (0, 0)
    assert float(plot.get_attribute("data-x1")) >= curve[-1][0]  # the last point is inside the axis
    visible = page.locator("#metrics").inner_text()
    assert "job_id" not in visible and "finished_at" not in visible and "frame_id" not in visible
    assert not re.search(r"\d{4}-\d\d-\d\dT\d\d:", visible), "raw ISO timestamp shown"
    assert "Evaluation job #" in visible
    m = admin.get(f"/api/scenes/{sid}/metrics").json()
    if m.get("agreement") is not None:
        assert f"{100 * m['agreement']:.2f} %" in visible
    page.locator("#metrics").scroll_into_view_if_needed()
    shot(page, "17_05_admin_metrics", full_page=True)
    # the one 4xx the page asks for on purpose: a scene's quality report before its first
    # fill is a 404 the page shows as "No lifted labels yet" -- accepted only where the API
    # still says so (run alone, this module's scenes have no labels when the page opens;
    # in the whole suite an earlier module has lifted them)
    expected = []
    for b in bad:
        m = re.fullmatch(r"404 GET .*/api/scenes/(\d+)/quality", b)
        if m:
            r = admin.get(f"/api/scenes/{m.group(1)}/quality")
            if r.status_code == 404 and "no lifted labels yet" in r.text:
                expected.append(b)
    assert not [b for b in bad if b not in expected], bad


def test_annotator_progress_skip_help_zoom_outline_hide_and_kept_brush(live, sid, new_page):
    """Step 2: "frame k of n", per-annotator progress, Skip, '?' help, zoom %, minimap, outline
    mode, per-class hide, brush size and tool kept between frames."""
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    fa = wait_opened(page)
    frames = [f for f in live.client("admin").get(f"/api/scenes/{sid}/frames").json() if f["selected"]]
    # counted among hand-outs (issue 28: the first frame handed out said "frame 8 of 17")
    k = sum(f["state"] in ("submitted", "accepted") for f in frames) + 1
    left = sum(f["state"] in ("unassigned", "in_progress", "rejected") for f in frames)
    page.wait_for_selector(f"#queue-pos:has-text('frame {k} of {len(frames)}')")
    assert f"{left} left" in page.locator("#queue-pos").inner_text()
    page.click("#scene-progress summary")
    page.locator("#progress-table th[data-who='annotator (you)']").wait_for()
    mine = [f for f in frames if (f["assignee"] or f["last_annotator"]) == "annotator"]
    for st in ("submitted", "accepted", "rejected", "in_progress"):
        cell = page.locator(f"#progress-table tr[data-state='{st}'] td[data-who='annotator (you)']")
        assert int(cell.inner_text()) == sum(f["state"] == st for f in mine), st
        assert int(page.locator(f"#progress-table tr[data-state='{st}'] td[data-who='all']").inner_text()) \
            == sum(f["state"] == st for f in frames), st
    # tool and brush size survive the next frame
    page.locator(".layer-overlay").focus()
    page.keyboard.press("e")
    page.evaluate("() => window.__occufly.page.editor.setSize(57)")
    # zoom readout and the minimap follow the view
    z0 = page.locator("#zoom-level").inner_text()
    page.keyboard.press("+")
    wait_js(page, f"() => document.querySelector('#zoom-level').textContent !== '{z0}'")
    assert re.fullmatch(r"\d+ %", page.locator("#zoom-level").inner_text())
    assert page.locator("#minimap").is_visible()
    # '?' shows the key help
    page.keyboard.press("?")
    page.wait_for_selector("dialog[open] #hotkeys")
    assert "outline" in page.locator("#hotkeys").inner_text()
    page.keyboard.press("Escape")
    # Skip: released, and the next frame is another one
    page.click("#skip")
    wait_js(page, f"() => window.__occufly.page.frame && window.__occufly.page.frame.id !== {fa} && window.__occufly.page.stats.openMs !== null")
    fb = wait_opened(page)
    assert fb != fa
    assert live.client("admin").get(f"/api/frames/{fa}").json()["assignee"] is None
    assert page.evaluate("() => [window.__occufly.page.editor.tool.name, window.__occufly.page.editor.state.size]") == ["eraser", 57]
    assert page.get_attribute("button[data-tool='eraser']", "aria-pressed") == "true"
    # outline mode: inside a painted block the colour layer is faint, on its border opaque
    page.keyboard.press("b")
    page.evaluate("""() => { const p = window.__occufly.page, m = p.editor.mask;
        const ids = new Uint8Array(m.ids.length); const c = p.editor.state.classId;
        for (let y = 20; y < 60; y++) for (let x = 20; x < 60; x++) ids[y * m.width + x] = c;
        p.editor.replaceIds('test block', ids); }""")
    alpha = "(x, y) => window.__occufly.page.editor.mask.ctx.getImageData(x, y, 1, 1).data[3]"
    assert page.evaluate(f"() => ({alpha})(40, 40)") == 255
    page.keyboard.press("l")
    assert page.locator("#outline").is_checked()
    assert page.evaluate(f"() => ({alpha})(40, 40)") < 80 and page.evaluate(f"() => ({alpha})(20, 40)") == 255
    page.keyboard.press("l")
    # hide / show one class in the colour layer (ids untouched)
    cls = page.evaluate("() => window.__occufly.page.editor.state.classId")
    page.click(f".eye[data-class='{cls}']")
    assert page.evaluate(f"() => ({alpha})(40, 40)") == 0
    assert page.evaluate("() => window.__occufly.page.editor.mask.ids[40 * window.__occufly.page.editor.mask.width + 40]") == cls
    page.click(f".eye[data-class='{cls}']")
    assert page.evaluate(f"() => ({alpha})(40, 40)") == 255
    shot(page, "17_06_annotator_progress_tools")
    # region fill on superpixels: one click fills exactly the superpixel under it, one undo step
    before = editor_ids(page)
    page.keyboard.press("r")
    assert page.get_attribute("button[data-tool='superpixel']", "aria-pressed") == "true"
    x, y = page.evaluate("() => window.__occufly.page.editor.view.toScreen(150.5, 120.5)")
    ov = page.locator(".layer-overlay").bounding_box()
    page.mouse.click(ov["x"] + x, ov["y"] + y)
    # the fill's own status (not "Region fill: cutting the photo into superpixels...", which
    # shows while the segmentation is still being computed)
    page.wait_for_selector("#status:has-text('pixels in')")
    member = np.array(page.evaluate("""() => { const t = window.__occufly.page.editor.tools.superpixel;
        const m = window.__occufly.page.editor.mask, s = t.seg, want = t.at([150.5, 120.5]);
        const out = new Array(m.width * m.height);
        for (let yy = 0; yy < m.height; yy++) for (let xx = 0; xx < m.width; xx++)
          out[yy * m.width + xx] = s.labels[Math.min(s.h - 1, Math.floor(yy * s.h / m.height)) * s.w
                                            + Math.min(s.w - 1, Math.floor(xx * s.w / m.width))] === want ? 1 : 0;
        return out; }""")).reshape(before.shape).astype(bool)
    after = editor_ids(page)
    assert 20 < member.sum() < member.size // 10  # a superpixel, not the whole photo
    assert (after[member] == cls).all() and np.array_equal(after[~member], before[~member])
    page.keyboard.press("Control+z")
    assert np.array_equal(editor_ids(page), before)
    # GrabCut box (server-side OpenCV): exactly the server's cut-out, inside the box, one undo
    page.keyboard.press("g")
    p0 = page.evaluate("() => window.__occufly.page.editor.view.toScreen(60.5, 70.5)")
    p1 = page.evaluate("() => window.__occufly.page.editor.view.toScreen(150.5, 140.5)")
    page.mouse.move(ov["x"] + p0[0], ov["y"] + p0[1])
    page.mouse.down()
    page.mouse.move(ov["x"] + p1[0], ov["y"] + p1[1], steps=6)
    page.mouse.up()
    page.wait_for_selector("#status:has-text('GrabCut:') >> text=/pixels of the box/", timeout=30_000)
    rect = page.evaluate("() => window.__occufly.page.editor.tools.grabcut.lastRect")
    x0, y0, x1, y1 = rect
    r = live.client("annotator").post(f"/api/frames/{fb}/grabcut", json={"rect": rect})
    assert r.status_code == 200 and r.headers["x-box"] == ",".join(map(str, rect))
    cut = png_ids(r.content) > 0
    assert 0 < cut.sum() < cut.size  # an object, not the whole box
    g = editor_ids(page)
    inside = np.zeros(g.shape, bool)
    inside[y0:y1, x0:x1] = cut
    assert (g[inside] == cls).all() and np.array_equal(g[~inside], before[~inside])
    page.keyboard.press("Control+z")
    assert np.array_equal(editor_ids(page), before)
    assert live.client("annotator").post(f"/api/frames/{fb}/grabcut",
                                         json={"rect": [0, 0, 10 ** 6, 5]}).status_code == 422
    page.keyboard.press("b")
    # a prefill from few masks says so (2 frames of this scene are lifted at this point)
    n_masks = len(live.client("admin").get(f"/api/scenes/{sid}/labels/status").json()["included_versions"])
    page.click("#prefill")
    dlg = page.locator("dialog.modal")
    dlg.wait_for()  # the frame has the test block painted: fill only the unpainted pixels
    dlg.get_by_role("button", name="Fill unpainted only").click()
    if n_masks < 3:
        page.wait_for_selector("#prefill-warning")
        assert f"only {n_masks} submitted mask" in page.locator("#prefill-warning").inner_text()
    else:
        page.wait_for_selector("#prefill-info")
        assert f"from {n_masks} masks" in page.locator("#prefill-info").inner_text()
    # low-confidence prefill pixels are counted and marked (the server's confidence image)
    lab = page.locator("label.low-conf")
    lab.wait_for()
    low = int(lab.get_attribute("data-low"))
    conf = png_ids(live.client("admin").get(f"/api/frames/{fb}/prefill/confidence").content)
    pre = png_ids(live.client("admin").get(f"/api/frames/{fb}/prefill").content)
    assert conf.shape == pre.shape and (conf[pre > 0] > 0).mean() > 0.9  # confidence where labels are
    assert low == int(((conf > 0) & (conf < 1 + round(254 * 0.6)) & (pre > 0)).sum())
    assert page.locator("#show-low-confidence").is_checked()
    page.keyboard.press("Control+z")
    page.keyboard.press("Control+z")


def test_reviewer_legend_linked_zoom_and_hotkeys_with_auto_advance(live, sid, new_page):
    """Step 2 (reviewer): class legend + disagreement key, one zoom for all panels, A accepts
    and moves on to the next frame of the list."""
    ann = live.client("annotator")
    done = []
    for _ in range(2):  # two more submitted frames to review
        f = ann.post(f"/api/scenes/{sid}/next").json()
        ids = np.full((f["height"], f["width"]), int(STATE["ids_1"].max() or 1), np.uint8)
        r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
                    headers={"Content-Type": "image/png",
                             "If-Match": str(f["current_version"] or "none")})
        assert r.status_code == 200, r.text
        done.append(f["id"])
    page = new_page("reviewer")
    page.goto(f"{live.base_url}/#/review?scene={sid}&state=submitted")
    page.locator(f"#frame-list tr[data-frame='{done[0]}'] a").click()
    page.wait_for_selector("#agreement[data-value]")
    legend = page.locator("#legend")
    assert "grey = painted, but no 3D label there" in legend.inner_text()
    assert legend.locator(".legend-item[data-class]").count() >= 1
    c0 = page.locator("canvas[data-layer='image']")
    c0.scroll_into_view_if_needed()
    b = c0.bounding_box()
    page.mouse.move(b["x"] + b["width"] / 2, b["y"] + b["height"] / 2)
    page.mouse.wheel(0, -300)
    wait_js(page, "() => window.__occufly_review && window.__occufly_review.view.z > 1")
    # every panel shows the same zoomed window: the same image pixel sits under each centre
    fits = page.evaluate("""() => { const p = window.__occufly_review;
        return p.canvases.map(({c}) => { const f = p.fitOf(c); return [(c.width / 2 - f.ox) / f.s, (c.height / 2 - f.oy) / f.s]; }); }""")
    assert len(fits) == 4 and all(abs(x - fits[0][0]) < 1e-6 and abs(y - fits[0][1]) < 1e-6 for x, y in fits)
    order = [int(r.get_attribute("data-frame")) for r in page.locator("#frame-list tr[data-frame]").all()]
    cur = order.index(done[0])
    page.keyboard.press("a")
    wait_js(page, f"() => window.__occufly_review.frameId !== {done[0]} && window.__occufly_review.frame && window.__occufly_review.frame.id !== {done[0]}")
    assert live.client("reviewer").get(f"/api/frames/{done[0]}").json()["state"] == "accepted"
    assert page.evaluate("() => window.__occufly_review.frameId") != done[0]
    assert cur < len(order)
    shot(page, "17_07_reviewer_legend_zoom")


def test_open_in_3d_flies_to_the_frame_and_scene_grid_before_voxelize_says_so(live, sid, new_page):
    """Defects 8 and 11, in the viewer page reached through the reviewer's "Open in 3D" link."""
    import time

    svc = live.app.state.viewer
    f1 = STATE["frame_1"]
    frame = live.client("admin").get(f"/api/frames/{f1}").json()
    page = new_page("reviewer")
    page.goto(f"{live.base_url}/#/review?scene={sid}&frame={f1}")
    link = page.locator("#open-3d")
    link.wait_for()
    href = link.get_attribute("href")
    assert href == f"/viewer/?scene={sid}&frame={f1}"
    before = {id(c) for c in svc.client_states()}
    page.goto(f"{live.base_url}{href}")

    def mine():
        return next((c for c in svc.client_states() if id(c) not in before and c.scene_id == str(sid)
                     and c.ready.is_set()), None)

    t_end = time.monotonic() + 60
    while (st := mine()) is None or st.highlighted is None:
        assert time.monotonic() < t_end, "the viewer did not focus the frame"
        time.sleep(0.2)
    assert st.highlighted == frame["index"] == st.frame_index
    h = st.frustum_handles[frame["index"]]
    assert tuple(h.color) == (255, 0, 200)
    # the view is that camera (issue 40, defect 8: pose and vertical fov), looking where it looks
    fr = st.data.scene.frames[frame["index"]]
    T = np.linalg.inv(np.asarray(fr.T_cam_world, np.float64))
    cam = st.client.camera
    # the server-side camera is what the browser last reported: a report the browser sent
    # before it applied the fly-to can still arrive after it, so wait for the echo
    t_end = time.monotonic() + 15
    while np.linalg.norm(T[:3, 3] - np.asarray(cam.position)) >= 1e-3:
        if time.monotonic() > t_end:
            break
        time.sleep(0.2)
    assert np.linalg.norm(T[:3, 3] - np.asarray(cam.position)) < 1e-3
    assert float(sb.quat_to_matrix(cam.wxyz)[:, 2] @ T[:3, 2]) > 0.9999
    assert cam.fov == pytest.approx(2 * np.arctan2(fr.camera.height / 2, fr.camera.focal[1]),
                                    abs=1e-3)
    wait_js(page, f"() => document.body.innerText.includes('{fr.stem}')", timeout=30_000)
    # no grid before voxelize: ticking "Scene grid" explains it and unticks
    assert st.data.grid is None
    page.get_by_text("Voxel grids").click()
    box = page.locator("div.mantine-Flex-root", has=page.get_by_text("Scene grid")).locator("input").last
    box.evaluate("e => e.click()")  # the server unticks it at once, so no .check()
    wait_js(page, "() => document.body.innerText.includes('no voxel grid yet')", timeout=15_000)
    assert st.gui["grid_scene"].value is False and not st.grid_handles
    assert "no voxel grid yet" in st.gui["grid_info"].content  # the note stays under the box
    shot(page, "17_08_viewer_open_in_3d")


def test_export_downloads_as_a_compressed_archive_with_its_size_and_no_bookkeeping(live, sid, new_page):
    """Step 4: zip / tar.gz of an export, its size on the page before the download, no
    .occufly_export/ inside."""
    import io
    import tarfile
    import zipfile

    admin = live.client("admin")
    # an export another module made already (test_browser's) saves a voxelize + export run
    done = [j for j in admin.get("/api/jobs").json() if j["kind"] == "export" and j["status"] == "done"]
    job = done[0] if done else None
    for kind in () if job else ("voxelize", "export"):
        body = {"layout": "occufly"} if kind == "export" else None
        r = admin.post(f"/api/scenes/{sid}/{kind}", json=body) if body else admin.post(f"/api/scenes/{sid}/{kind}")
        assert r.status_code in (200, 202), r.text
        job = live.wait_job(r.json(), timeout=300)
        assert job["status"] == "done", job
    jid = job["id"]
    page_scene = job["scene_id"]
    out = Path(job["result"]["output"])
    want = sorted(p.relative_to(out).as_posix() for p in out.rglob("*")
                  if p.is_file() and not any(part.startswith(".occufly") for part in p.relative_to(out).parts))
    assert want  # (the exporter also writes .occufly_export/ bookkeeping there: left out)
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={page_scene}")
    li = page.locator(f"li.job[data-job='{jid}']")
    li.wait_for()
    li.locator(".archive-content").wait_for()
    assert f"{len(want)} files" in li.locator(".archive-content").inner_text()
    li.locator(".archive-build").click()
    link = li.locator("a.archive-link")
    link.wait_for(timeout=60_000)
    size = int(link.get_attribute("data-bytes"))
    assert " MB" in link.inner_text() or " kB" in link.inner_text() or " GB" in link.inner_text()
    with page.expect_download() as dl:
        link.click()
    data = open(dl.value.path(), "rb").read()
    assert len(data) == size and dl.value.suggested_filename == f"{out.name}.tar.gz"
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as t:
        names = sorted(m.name.split("/", 1)[1] for m in t.getmembers() if m.isfile())
    assert names == want and not any(".occufly" in n for n in names)
    raw = sum((out / n).stat().st_size for n in want)
    # zip too, through the API (same files)
    z = admin.get(f"/api/jobs/{jid}/archive?format=zip")
    assert z.status_code == 200 and int(z.headers["content-length"]) == len(z.content)
    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        assert sorted(n.split("/", 1)[1] for n in zf.namelist()) == want
    li.scroll_into_view_if_needed()
    shot(page, "17_09_admin_export_archive")
    assert size < raw  # compressed
