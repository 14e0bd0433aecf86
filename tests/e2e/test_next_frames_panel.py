"""Issue 37, the admin's selection panel: 'Propose more frames to paint' runs the
next_frames job once per click and lists the frames with why."""

from __future__ import annotations

import numpy as np
import pytest

from tests.e2e.conftest import grey_png, import_own_scene, shot

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def sid(live):
    return import_own_scene(live, "next_frames_panel")


def test_admin_proposes_frames_with_why(live, sid, new_page):
    ann, admin = live.client("annotator"), live.client("admin")
    # two frames, one painted grass and one road: what both see is contested
    for cls in (6, 1):
        f = ann.post(f"/api/scenes/{sid}/next").json()
        ids = np.full((f["height"], f["width"]), cls, np.uint8)
        r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
                    headers={"If-Match": "none"})
        assert r.status_code == 200, r.text

    def filled():
        st = admin.get(f"/api/scenes/{sid}/labels/status").json()
        return len(st.get("filled_versions") or {}) == 2 and not st["pending_fill"]

    live.wait_until(filled, timeout=120, what="both masks lifted and filled")
    page = new_page("admin", viewport=(1366, 900))
    # the page's job list is answered by the server at once but delivered only after the click
    # has started the job: a list that left before the job existed must not drop it (its card
    # and the next-frames table were lost that way)
    held, released = [], []

    def hold(route):  # noqa: ANN001, ANN202
        if released:
            route.continue_()
        else:
            held.append((route, route.fetch()))  # the list as it is now, delivered later

    page.route(lambda url: "/api/jobs?scene_id=" in url, hold)
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.reload()  # a fresh page on this scene (the one new_page opened shows the first scene)
    for _ in range(300):  # the page has asked for the scene's job list: click now
        if any(f"scene_id={sid}" in r.request.url for r, _ in held):
            break
        page.wait_for_timeout(100)
    assert any(f"scene_id={sid}" in r.request.url for r, _ in held), "the job list was not held"
    page.fill("#next-k", "3")
    with page.expect_response(lambda r: r.url.endswith("/next-frames")):
        page.dblclick("#next-run")  # a hurried double click starts one job
    released.append(True)
    for route, answer in held:
        try:
            route.fulfill(response=answer)
        except Exception:  # noqa: BLE001 - a request of the page before the reload: gone
            pass
    page.locator("#next-summary").wait_for(timeout=180_000)  # a remote job: a loaded CI host is slow
    jobs = [j for j in admin.get(f"/api/jobs?scene_id={sid}").json() if j["kind"] == "next_frames"]
    assert len(jobs) == 1, jobs
    res = jobs[0]["result"]
    assert res["frames"] and res["contested_points"] > 0
    rows = page.locator("#next-frames tbody tr")
    assert rows.count() == len(res["frames"])
    assert rows.first.locator("td[data-col='frame_name']").inner_text() == res["reasons"][0]["frame_name"]
    assert int(rows.first.locator("td[data-col='contested_points']").inner_text()) == \
        res["reasons"][0]["contested_points"]
    page.locator("#sec-selection").scroll_into_view_if_needed()
    shot(page, "admin_next_frames")
