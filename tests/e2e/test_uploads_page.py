"""Issue 36 finding 5: the admin console lists uploaded project folders and deletes one."""

from __future__ import annotations

import io
import zipfile

from tests.e2e.conftest import shot, wait_js


def test_admin_lists_and_deletes_an_upload(live, new_page):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("proj/readme.txt", "x" * 5000)
    c = live.client("admin")
    r = c.post("/api/imports/upload", params={"name": "e2e_spare"}, content=buf.getvalue(),
               headers={"Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin")
    row = page.locator("#uploads tr[data-upload='e2e_spare']")
    row.wait_for()
    assert "5 kB" in row.inner_text() and "1" in row.inner_text()
    page.locator("#uploads").scroll_into_view_if_needed()
    shot(page, "admin_uploads")
    btn = row.locator("button", has_text="Delete")
    btn.dblclick()  # a hurried double click: one dialog, one deletion
    page.locator("dialog.modal button.primary").click()
    wait_js(page, "() => !document.querySelector(\"#uploads tr[data-upload='e2e_spare']\")")
    assert "e2e_spare" not in [u["name"] for u in c.get("/api/imports/uploads").json()]
