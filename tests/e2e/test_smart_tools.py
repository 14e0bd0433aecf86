"""The annotator's server-side smart tools in Chromium, on a scene of their own whose photos
have known edges (two bright blocks on a dark, noisy background): GrabCut refined with
scribbles, and the intelligent-scissors polygon. Both are one command on the undo stack."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from sqlalchemy import update

from tests.e2e.conftest import grant_members, shot, wait_js
from tests.e2e.test_browser import editor_ids, wait_opened

pytestmark = pytest.mark.e2e

W, H = 64, 48  # tests.app.conftest's tiny scene
A = (8, 10, 26, 38)  # x0, y0, x1, y1 (exclusive) of the left block
B = (36, 10, 56, 38)  # the right block


def block(r) -> np.ndarray:  # noqa: ANN001
    m = np.zeros((H, W), bool)
    m[r[1]:r[3], r[0]:r[2]] = True
    return m


def photo() -> np.ndarray:
    rng = np.random.default_rng(0)
    img = rng.integers(20, 50, (H, W, 3)).astype(np.uint8)
    for x0, y0, x1, y1 in (A, B):
        img[y0:y1, x0:x1] = rng.integers(200, 230, (y1 - y0, x1 - x0, 3)).astype(np.uint8)
    return img


@pytest.fixture(scope="module")
def sid(live):
    from app.scenes.models import Frame
    from tests.app.conftest import write_tiny_workspace

    root = live.app.state.ctx.settings.import_roots[0]
    # named to sort after the session's own source: test_workday imports "the first folder"
    src = write_tiny_workspace(root / "zz_smart_tools_src")
    for p in (src / "images").iterdir():
        Image.fromarray(photo()).save(p)
    admin = live.client("admin")
    r = admin.post("/api/scenes/import", json={"name": "smart_tools", "source": str(src)})
    assert r.status_code in (200, 202), r.text
    job = live.wait_job(r.json())
    assert job["status"] == "done", job
    grant_members(live, job["scene_id"])
    with live.app.state.ctx.sessions() as s:
        s.execute(update(Frame).where(Frame.scene_id == job["scene_id"]).values(selected=True))
        s.commit()
    return job["scene_id"]


def open_frame(live, sid: int, new_page):  # noqa: ANN001
    page = new_page("annotator")
    page.goto(f"{live.base_url}/#/annotate?scene={sid}")
    page.click("#next-frame")
    wait_opened(page)
    assert page.evaluate("() => [window.__occufly.page.editor.mask.width, window.__occufly.page.editor.mask.height]") == [W, H]
    return page


def at(page, x: float, y: float) -> tuple[float, float]:
    """Screen position of image point (x, y)."""
    ov = page.locator(".layer-overlay").bounding_box()
    sx, sy = page.evaluate(f"() => window.__occufly.page.editor.view.toScreen({x}, {y})")
    return ov["x"] + sx, ov["y"] + sy


def n_undo(page) -> int:
    return page.evaluate("() => window.__occufly.page.editor.history.undos.length")


def test_grabcut_scribbles_refine_the_cut_as_one_command(live, sid, new_page):
    page = open_frame(live, sid, new_page)
    cls = page.evaluate("() => window.__occufly.page.editor.state.classId")
    before = editor_ids(page)
    assert not before.any()
    steps0 = n_undo(page)
    page.keyboard.press("g")
    # the box around both blocks: the first cut takes both
    page.mouse.move(*at(page, 4, 5))
    page.mouse.down()
    page.mouse.move(*at(page, 60, 43), steps=6)
    page.mouse.up()
    page.wait_for_selector("#status:has-text('pixels of the box given the class')")
    first = editor_ids(page) == cls
    assert first[block(A)].mean() > 0.9 and first[block(B)].mean() > 0.9
    assert n_undo(page) == steps0 + 1
    # a background scribble (right drag) across the right block: cut again without it
    page.mouse.move(*at(page, 40.5, 14.5))
    page.mouse.down(button="right")
    page.mouse.move(*at(page, 52.5, 33.5), steps=10)
    page.mouse.move(*at(page, 40.5, 33.5), steps=10)
    page.mouse.up(button="right")
    page.wait_for_selector("#status:has-text('(1 scribble)')")
    refined = editor_ids(page)
    shot(page, "smart_grabcut_scribble")
    assert (refined[block(A)] == cls).mean() > 0.9
    assert (refined[block(B)] == cls).mean() < 0.1
    assert n_undo(page) == steps0 + 1  # the new cut replaced the old one in the same command
    # X switches what the left button marks (and back)
    page.keyboard.press("x")
    assert page.evaluate("() => window.__occufly.page.editor.tools.grabcut.mark") == "bg"
    page.keyboard.press("x")
    # a foreground scribble (left drag) across it, over the background one: the later wins
    page.mouse.move(*at(page, 38.5, 20.5))
    page.mouse.down()
    page.mouse.move(*at(page, 53.5, 20.5), steps=10)
    page.mouse.up()
    page.wait_for_selector("#status:has-text('(2 scribbles)')")
    again = editor_ids(page)
    assert (again[20, 38:54] == cls).all()
    assert not np.array_equal(again, refined) and n_undo(page) == steps0 + 1
    page.keyboard.press("Enter")  # accept
    page.wait_for_selector("#status:has-text('GrabCut accepted')")
    # undo: the mask from before the GrabCut; redo: exactly the refined cut
    page.keyboard.press("Control+z")
    assert np.array_equal(editor_ids(page), before)
    page.keyboard.press("Control+Shift+z")
    assert np.array_equal(editor_ids(page), again)
    # a second box, cancelled with Escape: the mask as before it, nothing new on the stack
    steps1 = n_undo(page)
    page.mouse.move(*at(page, 2, 2))
    page.mouse.down()
    page.mouse.move(*at(page, 30, 44), steps=6)
    page.mouse.up()
    page.wait_for_selector("#status:has-text('pixels of the box given the class')")
    page.keyboard.press("Escape")
    page.wait_for_selector("#status:has-text('GrabCut cancelled')")
    assert np.array_equal(editor_ids(page), again) and n_undo(page) == steps1
    # the key is in the ? help
    page.keyboard.press("?")
    help_text = page.locator("#hotkeys").inner_text()
    assert "GrabCut" in help_text and "scribble" in help_text and "scissors" in help_text
    page.keyboard.press("Escape")


def test_scissors_polygon_snaps_to_the_edges_and_fills_the_block(live, sid, new_page):
    page = open_frame(live, sid, new_page)
    cls = page.evaluate("() => window.__occufly.page.editor.state.classId")
    before = editor_ids(page)
    steps0 = n_undo(page)
    sent = []
    page.on("request", lambda r: "/scissors" in r.url and sent.append(r.url))
    page.keyboard.press("i")
    assert page.get_attribute("button[data-tool='scissors']", "aria-pressed") == "true"
    # anchors in the middle of the left block's sides: a straight polygon would be a diamond
    mids = [(8, 24), (17, 10), (25, 24), (17, 37)]
    page.mouse.click(*at(page, mids[0][0] + 0.5, mids[0][1] + 0.5))
    # live preview to the cursor, snapped (it goes round the top-left corner)
    page.mouse.move(*at(page, mids[1][0] + 0.5, mids[1][1] + 0.5), steps=4)
    wait_js(page, f"""() => {{ const p = window.__occufly.page.editor.tools.scissors.preview;
        return p && p.to[0] === {mids[1][0]} && p.to[1] === {mids[1][1]}; }}""")
    pv = np.array(page.evaluate("() => window.__occufly.page.editor.tools.scissors.preview.path"))
    assert np.hypot(pv[:, 0] - 8, pv[:, 1] - 10).min() <= 1.5
    page.mouse.click(*at(page, mids[1][0] + 0.5, mids[1][1] + 0.5))
    # a wrong anchor, then Backspace removes it
    page.mouse.click(*at(page, 50.5, 40.5))
    assert page.evaluate("() => window.__occufly.page.editor.tools.scissors.anchors.length") == 3
    page.keyboard.press("Backspace")
    assert page.evaluate("() => window.__occufly.page.editor.tools.scissors.anchors.length") == 2
    for x, y in mids[2:]:
        page.mouse.click(*at(page, x + 0.5, y + 0.5))
    assert np.array_equal(editor_ids(page), before)  # nothing painted before closing
    page.mouse.click(*at(page, mids[0][0] + 0.5, mids[0][1] + 0.5))  # the first anchor closes it
    page.wait_for_selector("#status:has-text('Scissors: the outline')")
    got = editor_ids(page)
    shot(page, "smart_scissors_filled")
    filled = got == cls
    a = block(A)
    # the block, to within a pixel of its edge (a step edge lies between two pixel rings, and
    # the live-wire may run on either)
    grown = block((A[0] - 1, A[1] - 1, A[2] + 1, A[3] + 1))
    assert (filled & a).sum() / a.sum() > 0.97 and not (filled & ~grown).any()
    assert np.array_equal(got[~filled], before[~filled])
    # the straight polygon through the same anchors covers about half of the block
    yy, xx = np.mgrid[0:H, 0:W]
    diamond = (np.abs(xx + 0.5 - 17) / 9 + np.abs(yy + 0.5 - 24) / 14) <= 1
    assert (diamond & a).sum() / a.sum() < 0.7
    assert n_undo(page) == steps0 + 1 and len(sent) >= 4
    page.keyboard.press("Control+z")
    assert np.array_equal(editor_ids(page), before)
    page.keyboard.press("Control+Shift+z")
    assert np.array_equal(editor_ids(page), got)
    # Escape cancels an outline in progress: nothing painted
    page.mouse.click(*at(page, 40.5, 24.5))
    page.mouse.click(*at(page, 46.5, 10.5))
    page.keyboard.press("Escape")
    assert page.evaluate("() => window.__occufly.page.editor.tools.scissors.anchors.length") == 0
    assert np.array_equal(editor_ids(page), got) and n_undo(page) == steps0 + 1


def test_low_confidence_marks_hide_when_the_prefill_is_undone(live, sid, new_page):
    from tests.e2e.conftest import grey_png

    # one submitted mask on this scene, so the next frame has lifted labels to prefill from
    ann = live.client("annotator")
    f = ann.post(f"/api/scenes/{sid}/next").json()
    ids = np.zeros((H, W), np.uint8)
    ids[:, : W // 2], ids[:, W // 2:] = 6, 1
    ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
            headers={"Content-Type": "image/png",
                     "If-Match": str(f["current_version"] or "none")}).raise_for_status()

    def lifted():
        st = live.labels_status(sid)
        return not st["pending_fill"] and st["included_versions"]
    live.wait_until(lifted, timeout=90, what="the lifted labels of the smart-tools scene")
    page = open_frame(live, sid, new_page)
    assert page.evaluate("() => window.__occufly.page.frame.id") != f["id"]
    page.click("#prefill")
    page.locator("label.low-conf").wait_for()
    assert int(page.get_attribute("label.low-conf", "data-low")) > 0
    # a marked pixel, and what the overlay shows there before / after undoing the prefill
    probe = """async () => { const p = window.__occufly.page, lc = p.lowConf, v = p.editor.view;
        const d = lc.canvas.getContext('2d').getImageData(0, 0, lc.canvas.width, lc.canvas.height).data;
        let i = 0; while (i < d.length / 4 && d[4 * i + 3] < 200) i++;
        const x = i % lc.canvas.width, y = Math.floor(i / lc.canvas.width);
        await new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
        const [sx, sy] = v.toScreen(x + 0.5, y + 0.5), k = v.dpr || 1;
        return v.overlay.getContext('2d').getImageData(Math.floor(sx * k), Math.floor(sy * k), 1, 1).data[3]; }"""
    assert page.evaluate(probe) > 100
    page.keyboard.press("Control+z")
    assert page.evaluate("() => Number(document.querySelector('#painted').dataset.share)") == 0
    assert page.evaluate(probe) == 0
    page.keyboard.press("Control+Shift+z")  # redo: the prefill and its marks are back
    assert page.evaluate(probe) > 100
