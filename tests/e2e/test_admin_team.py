"""Admin page: scene membership and the audit log (issue 14: "admins assign", "audit log ...
shown on the admin page")."""

from __future__ import annotations

import pytest

from tests.e2e.conftest import PASSWORDS, shot, wait_js

pytestmark = pytest.mark.e2e


def test_admin_assigns_members_and_reads_the_audit_log(live, new_page):
    admin = live.client("admin")
    sid = live.scene_id
    # a fresh annotator that is not a member of the scene yet
    r = admin.post("/api/users", json={"username": "teamnew", "password": "teamnew-password",
                                       "role": "annotator"})
    assert r.status_code in (200, 201), r.text
    uid = r.json()["id"]
    members = {m["user_id"] for m in admin.get(f"/api/scenes/{sid}/members").json()}
    assert uid not in members

    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.wait_for_selector("#members table, #members p")
    page.select_option("#member-add", str(uid))
    page.click("form[aria-label='Add scene member'] button[type=submit]")
    page.wait_for_selector("#members td:has-text('teamnew')")
    assert uid in {m["user_id"] for m in admin.get(f"/api/scenes/{sid}/members").json()}
    # the new member can now see the scene
    import httpx

    tok = httpx.post(f"{live.base_url}/api/auth/login",
                     json={"username": "teamnew", "password": "teamnew-password"}).json()["token"]
    seen = httpx.get(f"{live.base_url}/api/scenes", headers={"Authorization": f"Bearer {tok}"}).json()
    assert sid in {s["id"] for s in seen}

    # the audit log lists that membership change and the logins, newest first
    page.fill("#audit-action", "membership")
    page.click("form[aria-label='Filter audit log'] button[type=submit]")
    page.wait_for_selector("#audit td:has-text('membership')")
    rows = page.locator("#audit tbody tr")
    assert rows.count() >= 1
    assert "admin" in rows.first.inner_text()
    page.fill("#audit-action", "login")
    page.click("form[aria-label='Filter audit log'] button[type=submit]")
    page.wait_for_selector("#audit td:has-text('teamnew')")
    shot(page, "14_admin_members_audit", full_page=True)

    # removing the member takes the scene away again
    page.click("#members button[aria-label='Remove teamnew']")
    wait_js(page, "() => ![...document.querySelectorAll('#members td')].some((td) => td.innerText.includes('teamnew'))")
    assert "teamnew" in page.locator("#member-add").inner_text()  # offered again
    assert uid not in {m["user_id"] for m in admin.get(f"/api/scenes/{sid}/members").json()}
    assert PASSWORDS  # the fixture's accounts are untouched
