"""Issue 17, "measure the promise" on the real scene's saved masks: an annotator starts a frame
from "Prefill from 3D", corrects it and submits; the admin page's "Annotation effort" curve
shows, per submission, the share painted from scratch and the share changed versus the prefill
(recorded by the server at submit time)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.e2e.conftest import ARTIFACTS, grey_png, import_own_scene, shot, wait_js
from tests.e2e.test_browser import drag, editor_ids, wait_opened

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def sid(live):
    """A scene of its own (the same source imported again), so the curve holds only this
    module's submissions."""
    return import_own_scene(live, "effort_scene")


def test_admin_effort_curve_of_submissions_started_from_the_prefill(live, sid, new_page):
    ann = live.client("annotator")
    admin = live.client("admin")
    # hand-out order: the selection ranked the frames (most unseen points first)
    sel = admin.get(f"/api/scenes/{sid}/selection").json()
    order = sel.get("handout_order")
    assert order and sorted(order) == sorted(sel["frames"])
    # 1st frame painted from scratch (API), lifted into 3D
    r = ann.post(f"/api/scenes/{sid}/next")
    assert r.status_code == 200, r.text
    f1 = r.json()
    assert f1["index"] == order[0]
    ids = np.full((f1["height"], f1["width"]), 6, np.uint8)  # grass
    ids[: f1["height"] // 3] = 1  # road
    r = ann.put(f"/api/frames/{f1['id']}/mask?kind=submitted", content=grey_png(ids),
                headers={"If-Match": "none"})
    assert r.status_code == 200, r.text

    def filled():
        st = admin.get(f"/api/scenes/{sid}/labels/status").json()
        return str(f1["id"]) in (st.get("filled_versions") or {}) and not st["pending_fill"]

    live.wait_until(filled, timeout=60, what="the first mask lifted and filled")

    # 2nd frame in the browser: Prefill from 3D, one correcting stroke, Submit
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    f2 = wait_opened(page)
    assert admin.get(f"/api/frames/{f2}").json()["index"] == order[1]
    page.click("#prefill")
    page.wait_for_selector("#prefill-warning, #prefill-info")
    pre = editor_ids(page).copy()
    assert (pre > 0).any()
    page.evaluate("() => window.__occufly.page.editor.setSize(16)")
    drag(page, [(0.2, 0.7), (0.6, 0.75)])
    submitted = editor_ids(page).copy()
    page.click("#submit")
    page.wait_for_selector("#save-state:has-text('Submitted')")

    e = admin.get(f"/api/scenes/{sid}/effort").json()
    a, b = e["submissions"]
    assert (a["frame_id"], a["prefilled"]) == (f1["id"], False)
    assert a["changed_px"] == a["painted_px"] == ids.size
    assert (b["frame_id"], b["prefilled"]) == (f2, True)
    # the server compared the submitted mask with the prefill it handed out: what the stroke
    # and the unfilled pixels changed, as the editor held them
    assert b["painted_px"] == int((submitted > 0).sum())
    assert b["changed_px"] == int((submitted != pre).sum())
    assert 0 < b["changed_px"] < b["painted_px"]

    # the admin page draws both curves and sums them up
    adm = new_page("admin")
    adm.goto(f"{live.base_url}/#/admin?scene={sid}")
    adm.wait_for_selector("#effort-plot")
    try:  # the page may draw a first, older answer before the refresh that holds both masks
        wait_js(adm, "document.querySelector('#effort-summary')?.innerText"
                              ".includes('2 submitted mask(s)')", timeout=15_000)
    except Exception:  # noqa: BLE001 - the assertion below reports what the page shows
        pass
    summary = adm.locator("#effort-summary").inner_text()
    assert "2 submitted mask(s), 1 started from the 3D prefill" in summary
    t = e["totals"]
    assert f"{t['reduction_x']:.2f}\u00d7 less" in summary
    label = adm.get_attribute("#effort-plot", "aria-label")
    assert "changed vs prefill" in label and "painted from scratch" in label
    pct_b = round(100 * b["changed_share"])
    assert f"to {pct_b}% at 2" in label, label
    adm.locator("#sec-effort details summary").click()
    rows = adm.locator("#effort tbody tr")
    assert rows.count() == 2 and "no prefill" in rows.nth(1).inner_text()
    adm.locator("#sec-effort").scroll_into_view_if_needed()
    shot(adm, "17_effort_curve")
    adm.locator("#sec-effort").screenshot(path=str(ARTIFACTS / "17_effort_curve_section.png"))


def test_a_prefill_undone_in_the_editor_does_not_count(live, sid, new_page):
    """Issue 28 item 5: Prefill from 3D, Undo, paint by hand, Submit: the editor no longer
    names the prefill, so the submission is not counted as started from it."""
    admin = live.client("admin")
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    fid = wait_opened(page)
    page.click("#prefill")
    page.wait_for_selector("#prefill-warning, #prefill-info")
    assert (editor_ids(page) > 0).any()
    page.click("#undo")
    assert not (editor_ids(page) > 0).any()
    page.evaluate("() => window.__occufly.page.editor.setSize(16)")
    drag(page, [(0.2, 0.5), (0.7, 0.5)])
    submitted = editor_ids(page).copy()
    page.click("#submit")
    page.wait_for_selector("#save-state:has-text('Submitted')")
    row = next(r for r in admin.get(f"/api/scenes/{sid}/effort").json()["submissions"]
               if r["frame_id"] == fid)
    assert not row["prefilled"]
    assert row["changed_px"] == row["painted_px"] == int((submitted > 0).sum())
