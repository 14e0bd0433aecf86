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

from tests.e2e.conftest import grey_png, png_ids, shot

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
    page.wait_for_function("() => window.__occufly && window.__occufly.page.stats.openMs !== null")
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
        st = rev.get(f"/api/scenes/{live.scene_id}/labels/status").json()
        inc = {str(k): v for k, v in st["included_versions"].items()}
        hist = {str(k): v for k, v in st["class_histogram"].items()}
        return st if inc.get(str(fid)) == version and hist.get(str(cls), 0) > 0 else None
    live.wait_until(lifted, timeout=60, what="lifted labels to include the submitted mask")
    STATE.update(frame_a=fid, cls=cls, ids_a=ids1)
