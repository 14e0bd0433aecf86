"""Issue 37, the admin's lifting panel: the annotator model of the live lifting is chosen per
scene; a hurried double click applies it once, the scene is filled again with it and the
panel says how (how many painters were told apart); a panel answer for a scene the admin has
left is not shown on the next one."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from tests.e2e.conftest import REPO, grey_png, import_own_scene, shot

pytestmark = pytest.mark.e2e

GRASS, VEGETATION = 6, 7  # the default taxonomy's ids


@pytest.fixture(scope="module")
def sids(live):
    return import_own_scene(live, "lifting_model_a"), import_own_scene(live, "lifting_model_b")


def _paint_truth(live, sid: int, who: str, as_vegetation=None) -> tuple:  # noqa: ANN001
    """``who`` submits the next frame of scene ``sid`` painted as the synthetic scene's truth
    mask (``as_vegetation(ids)``: a mask of its pixels painted vegetation instead); returns
    (frame, mask, version)."""
    root = live.app.state.ctx.settings.import_roots[0]
    src = next(p for p in sorted(root.iterdir()) if p.is_dir())
    c = live.client(who)
    f = c.post(f"/api/scenes/{sid}/next").json()
    ids = np.array(Image.open(src / "truth" / "masks" / f"{f['name'].rsplit('.', 1)[0]}.png"))
    if as_vegetation is not None:
        ids[as_vegetation(ids)] = VEGETATION
    r = c.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
              headers={"If-Match": "none"})
    assert r.status_code == 200, r.text
    return f, ids, r.json()["version"]


def _wait_filled(live, sid: int, n: int) -> None:  # noqa: ANN001
    """Until the scene's ``n`` masks are lifted and filled."""
    admin = live.client("admin")

    def filled() -> bool:
        st = admin.get(f"/api/scenes/{sid}/labels/status").json()
        return len(st.get("filled_versions") or {}) == n and not st["pending_fill"]

    live.wait_until(filled, timeout=120, what=f"{n} masks lifted and filled")


def test_admin_sets_the_annotator_model_and_sees_what_the_fill_used(live, sids, new_page):
    sid, other = sids
    admin = live.client("admin")
    # two painters: the annotator paints three frames as the truth, the admin one with its
    # grass as vegetation (the synthetic scene's truth masks)
    for who in ("annotator", "admin", "annotator", "annotator"):
        _paint_truth(live, sid, who, (lambda ids: ids == GRASS) if who == "admin" else None)
    _wait_filled(live, sid, 4)
    page = new_page("admin", viewport=(1366, 900))
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.reload()
    panel = page.locator(f"#lifting [data-scene='{sid}']")
    panel.wait_for(timeout=30_000)
    assert page.locator("#lift-model-pooled").is_checked()
    assert page.locator("#lift-model-apply").is_disabled()  # nothing to apply yet
    assert "one model for all painters" in page.locator("#lift-last").inner_text()
    page.check("#lift-model-per_author")
    assert page.locator("#lift-model-apply").is_enabled()
    with page.expect_response(lambda r: r.url.endswith(f"/scenes/{sid}/lifting")
                              and r.request.method == "PUT"):
        page.dblclick("#lift-model-apply")  # a hurried double click applies once
    page.wait_for_function(
        "() => (document.querySelector('#lift-last')?.textContent || '').includes('2 painters')",
        timeout=120_000)
    text = page.locator("#lift-last").inner_text()
    assert "one model per painter" in text and "2 painters told apart" in text, text
    assert "4 painted frames" in text, text
    assert page.locator("#lift-model-per_author").is_checked()
    learned = admin.get(f"/api/scenes/{sid}/lifting").json()["last_fill"].get("learned") or []
    assert learned and learned[0]["painter"] == "admin", learned  # the grass painted vegetation
    top = learned[0]["confusions"][0]
    assert (top["true"], top["painted"]) == ("grass", "vegetation"), learned
    assert page.locator("#lift-learned li").count() == len(learned)
    for x in learned:  # what the model learned, as the API says it
        assert x["painter"] in page.locator("#lift-learned").inner_text()
    audit = admin.get("/api/audit?action=lifting_model").json()
    rows = audit["events"] if isinstance(audit, dict) else audit
    assert [(e["detail"]["from"], e["detail"]["to"]) for e in rows if e["scene_id"] == sid] == [
        ("pooled", "per_author")]
    sec = page.locator("#sec-lifting")
    sec.scroll_into_view_if_needed()
    page.wait_for_timeout(300)  # the toast's fade-in is not part of the picture
    sec.screenshot(path=str(REPO / "docs" / "screenshots" / "admin_lifting_model.png"))
    shot(page, "admin_lifting_model")

    # the answer for scene A arrives after the admin switched to scene B: B's panel stays
    held = []

    def of_a(url: str) -> bool:
        return url.endswith(f"/api/scenes/{sid}/lifting")

    def hold(route) -> None:  # noqa: ANN001
        held.append(route)

    page.route(of_a, hold)
    page.select_option("#admin-scene", str(other))
    page.locator(f"#lifting [data-scene='{other}']").wait_for(timeout=30_000)
    page.select_option("#admin-scene", str(sid))
    for _ in range(100):
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the panel did not ask for scene A's model"
    page.select_option("#admin-scene", str(other))
    page.locator(f"#lifting [data-scene='{other}']").wait_for(timeout=30_000)
    page.unroute(of_a)  # the held answers go on now (unrouting lets them through)
    for route in held:
        try:
            route.continue_()
        except Exception:  # noqa: BLE001 - already let through by unroute
            pass
    page.wait_for_timeout(1000)
    assert page.locator(f"#lifting [data-scene='{sid}']").count() == 0
    assert page.locator(f"#lifting [data-scene='{other}']").count() == 1
    assert page.locator("#lift-model-pooled").is_checked()  # scene B never changed


def test_a_small_correction_keeps_the_model_and_the_panel_says_so(live, new_page):
    """Issue 37, eighth round: after a brush stroke the fill keeps the robust decision's
    fitted model and decides again only around it; the panel says so, with how many points."""
    sid = import_own_scene(live, "lifting_model_held")
    ctx = live.app.state.ctx
    done = [_paint_truth(live, sid, "annotator") for _ in range(3)]
    admin = live.client("admin")
    _wait_filled(live, sid, 3)
    # the test scene is small: a stroke is more of its voted points than on a survey
    held = ctx.lifting.service._scenes[sid].incremental.held
    held.max_share_save = held.max_share = 0.5
    f, ids, version = done[-1]
    ids = ids.copy()
    h, w = ids.shape
    ids[h // 2 - 8:h // 2 + 8, w // 2 - 8:w // 2 + 8] = VEGETATION  # a reviewer's stroke
    r = admin.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
                  headers={"If-Match": str(version)})
    assert r.status_code == 200, r.text

    def kept() -> bool:
        last = admin.get(f"/api/scenes/{sid}/lifting").json()["last_fill"]
        return bool(last.get("robust_warm"))

    live.wait_until(kept, timeout=120, what="a fill that kept the model")
    page = new_page("admin", viewport=(1366, 900))
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.locator(f"#lifting [data-scene='{sid}']").wait_for(timeout=30_000)
    text = page.locator("#lift-last").inner_text()
    decided = admin.get(f"/api/scenes/{sid}/lifting").json()["last_fill"]["robust_warm_decided"]
    assert "kept the model of the last full decision" in text, text
    assert f"only the {decided:,} points around the change" in text, text
    sec = page.locator("#sec-lifting")
    sec.scroll_into_view_if_needed()
    page.wait_for_timeout(300)
    sec.screenshot(path=str(REPO / "docs" / "screenshots" / "admin_lifting_held.png"))
