"""Issue 29: the editor tells the annotator how far the 3D labels trail the submitted masks
("3D labels N s behind", from GET /api/scenes/{sid}/labels/status ``lag_s``), and the notice
goes away once the lifting worker has caught up."""

from __future__ import annotations

import re

import numpy as np
import pytest

from tests.e2e.conftest import grey_png, import_own_scene, shot
from tests.e2e.test_browser import wait_opened

pytestmark = pytest.mark.e2e


def test_editor_shows_how_far_the_3d_labels_are_behind(live, new_page):
    sid = import_own_scene(live, "lag_scene")
    ann = live.client("annotator")
    admin = live.client("admin")
    lifting = live.app.state.ctx.lifting
    lifting.stop()  # the lifting worker is down: the submit waits in the queue
    try:
        r = ann.post(f"/api/scenes/{sid}/next")
        assert r.status_code == 200, r.text
        f1 = r.json()
        ids = np.full((f1["height"], f1["width"]), 6, np.uint8)
        r = ann.put(f"/api/frames/{f1['id']}/mask?kind=submitted", content=grey_png(ids),
                    headers={"If-Match": "none"})
        assert r.status_code == 200, r.text
        live.wait_until(lambda: admin.get(f"/api/scenes/{sid}/labels/status").json()["lag_s"]
                        >= 3, timeout=20, what="a lag of 3 s")

        page = new_page("annotator")
        page.goto(f"{live.base_url}/#/annotate?scene={sid}")
        page.click("#next-frame")
        wait_opened(page)
        lag = page.locator("#lift-lag")
        lag.wait_for(state="visible", timeout=15_000)
        text = lag.inner_text()
        m = re.fullmatch(r"3D labels (\d+) s behind", text)
        assert m and int(m.group(1)) >= 3, text
        assert int(lag.get_attribute("data-pending")) == 1
        shot(page, "annotator_lift_lag")
    finally:
        lifting.start()  # the worker comes back and drains the queue
    assert lifting.wait_idle(sid, timeout=60)
    lag.wait_for(state="hidden", timeout=20_000)  # the next poll sees no lag
    assert admin.get(f"/api/scenes/{sid}/labels/status").json()["lag_s"] == 0.0
