"""Issue 28 item 6: the annotator's defects, each driven in Chromium against the real app.

"Next frame" on an unsubmitted frame keeps it and its undo history; at 768 px (a tablet) the
page fits and Submit is on screen; undo/redo are disabled on an empty history; frame names are
not cut; the position counts frames handed out, not list order; the prefill warning goes with
an undone prefill; dark mode follows the system; the reviewer's Accept/Reject are above the
fold at 1440 x 900.
"""

from __future__ import annotations

import pytest

from tests.e2e.conftest import import_own_scene, shot
from tests.e2e.test_browser import drag, wait_opened

pytestmark = pytest.mark.e2e

SUBMITTED: list[int] = []  # frames submitted by an earlier test (the reviewer's test opens one)


@pytest.fixture(scope="module")
def sid(live):
    return import_own_scene(live, "annotator_day_scene")


def _open(page, live, sid):
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    return wait_opened(page)


def test_next_frame_on_an_unsubmitted_frame_keeps_it_and_its_history(live, sid, new_page):
    page = new_page("annotator")
    fid = _open(page, live, sid)
    # an empty history: undo and redo are disabled, not merely inert
    assert page.is_disabled("#undo") and page.is_disabled("#redo")
    page.evaluate("() => window.__occufly.page.editor.setSize(24)")
    drag(page, [(0.2, 0.2), (0.5, 0.3)])
    assert not page.is_disabled("#undo") and page.is_disabled("#redo")
    undos = page.evaluate("() => window.__occufly.page.editor.history.undos.length")
    page.click("#next-frame")
    # the same frame stays open with its history, and the page says why
    page.wait_for_selector("#next-notice", timeout=10_000)
    assert "not submitted" in page.inner_text("#next-notice")
    assert page.evaluate("() => window.__occufly.page.frame.id") == fid
    assert page.evaluate("() => window.__occufly.page.editor.history.undos.length") == undos
    page.click("#undo")
    assert page.is_disabled("#undo") and not page.is_disabled("#redo")


def test_tablet_width_fits_and_submit_is_on_screen(live, sid, new_page):
    page = new_page("annotator", viewport=(768, 1024))
    _open(page, live, sid)
    width = page.evaluate("() => document.documentElement.scrollWidth")
    assert width <= 768, f"page is {width} px wide at a 768 px viewport"
    box = page.locator("#submit").bounding_box()
    assert box and box["x"] >= 0 and box["x"] + box["width"] <= 768 and box["y"] + box["height"] <= 1024
    shot(page, "annotator_768")


def test_frame_name_in_full_and_position_counts_hand_outs(live, sid, new_page):
    page = new_page("annotator")
    fid = _open(page, live, sid)
    name = live.client("admin").get(f"/api/frames/{fid}").json()["name"]
    info = page.locator("#frame-info")
    assert name in (info.get_attribute("title") or "")
    # the visible text is not cut: its box is as wide as its content
    assert page.evaluate("() => { const e = document.querySelector('#frame-info .frame-name');"
                         " return e && e.scrollWidth <= e.clientWidth + 1; }")
    q = page.inner_text(".queue-pos")
    # the first frame this annotator gets is not "frame 8 of 17": it is counted among hand-outs
    frames = [f for f in live.client("admin").get(f"/api/scenes/{sid}/frames").json() if f["selected"]]
    done = sum(f["state"] in ("submitted", "accepted") for f in frames)
    assert q.startswith(f"frame {done + 1} of {len(frames)}"), q


def test_dark_mode_follows_the_system(live, sid, browser):
    ctx = browser.new_context(color_scheme="dark", viewport={"width": 1366, "height": 800})
    page = ctx.new_page()
    from tests.e2e.conftest import login

    login(page, live, "annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.wait_for_selector("#next-frame")
    bg = page.evaluate("() => getComputedStyle(document.documentElement).backgroundColor")
    card = page.evaluate("() => getComputedStyle(document.querySelector('#skip')).backgroundColor")
    fg = page.evaluate("() => getComputedStyle(document.documentElement).color")
    def lum(c):
        r, g, b = [int(v) for v in c[c.index("(") + 1:c.index(")")].split(",")[:3]]
        return 0.2126 * r + 0.7152 * g + 0.0722 * b
    assert lum(bg) < 60 and lum(card) < 90 and lum(fg) > 160, (bg, card, fg)
    shot(page, "annotator_dark")
    ctx.close()


def test_prefill_warning_goes_with_an_undone_prefill(live, sid, new_page):
    import numpy as np

    from tests.e2e.conftest import grey_png

    ann = live.client("annotator")
    admin = live.client("admin")
    # one mask submitted through the API and lifted: the next frame's prefill comes from
    # fewer than 3 masks, so the page warns
    r = ann.post(f"/api/scenes/{sid}/next")
    assert r.status_code == 200, r.text
    f1 = r.json()
    ids = np.full((f1["height"], f1["width"]), 6, np.uint8)
    ids[: f1["height"] // 3] = 1
    cur = admin.get(f"/api/frames/{f1['id']}").json()["current_version"]  # earlier tests' draft
    r = ann.put(f"/api/frames/{f1['id']}/mask?kind=submitted", content=grey_png(ids),
                headers={"If-Match": str(cur) if cur else "none"})
    assert r.status_code == 200, r.text

    def filled():
        st = admin.get(f"/api/scenes/{sid}/labels/status").json()
        return str(f1["id"]) in (st.get("filled_versions") or {}) and not st["pending_fill"]

    live.wait_until(filled, timeout=60, what="the first mask lifted and filled")
    SUBMITTED.append(f1["id"])
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    assert wait_opened(page) != f1["id"]
    page.click("#prefill")
    page.wait_for_selector("#prefill-warning")
    page.click("#undo")
    page.wait_for_selector("#prefill-warning", state="detached", timeout=5_000)
    page.click("#redo")
    page.wait_for_selector("#prefill-warning", timeout=5_000)


def test_reviewer_accept_and_reject_are_above_the_fold_at_1440x900(live, sid, new_page):
    assert SUBMITTED, "needs the frame the prefill test submitted"
    page = new_page("reviewer", viewport=(1440, 900))
    page.goto(f"{live.base_url}/#/review?scene={sid}&frame={SUBMITTED[0]}")
    page.wait_for_selector("#accept")
    page.wait_for_selector("#panels canvas")
    for sel in ("#accept", "#reject", "#review-comment"):
        box = page.locator(sel).bounding_box()
        assert box and box["y"] >= 0 and box["y"] + box["height"] <= 900, (sel, box)
    shot(page, "reviewer_1440x900")
