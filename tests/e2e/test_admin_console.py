"""Issue 28, the admin's day in the browser: the import form names the roots and browses
them, uploads a project zip, adds members, and clears its error banner after a successful
import; the users table changes roles, deactivates and resets passwords; a scene and an
export are deleted after a confirmation that says what it frees; the overview across scenes
and annotators; the audit log shows frame and scene names.

Screenshots (looked at): docs/screenshots/admin_folder_browser.png, admin_users.png,
admin_delete_confirm.png, admin_overview.png."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from tests.e2e.conftest import REPO, grey_png, import_own_scene

pytestmark = pytest.mark.e2e

DOCS = REPO / "docs" / "screenshots"


def _doc_shot(locator, name: str, ready: str | None = None) -> None:
    """Screenshot into docs/screenshots once ``ready`` (a selector) shows: the admin page is
    mounted again when its hash changes, and a fresh mount is empty until it has loaded."""
    DOCS.mkdir(parents=True, exist_ok=True)
    page = locator.page
    for attempt in range(3):
        try:
            if ready:
                page.wait_for_timeout(600)
                page.wait_for_selector(ready)
            locator.screenshot(path=str(DOCS / f"{name}.png"))
            return
        except Exception:  # noqa: BLE001 - "not attached to the DOM": take the new one
            if attempt == 2:
                raise
            page.wait_for_timeout(500)


def _source(live):  # noqa: ANN001, ANN202
    root = live.app.state.ctx.settings.import_roots[0]
    return root, next(p for p in sorted(root.iterdir()) if p.is_dir())


def test_import_form_browses_the_roots_adds_members_and_clears_its_error(live, new_page):
    admin = live.client("admin")
    root, src = _source(live)
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin")
    page.wait_for_selector("#imp-members input[type=checkbox]")
    # a path outside the roots: the error names them
    page.fill("#imp-name", "console_outside")
    page.fill("#imp-source", "/etc")
    page.click("form[aria-label='Import a scene'] button[type=submit]")
    page.wait_for_selector("#alert:not(:empty)")
    assert str(root) in page.locator("#alert").inner_text()
    # the folder browser: the roots, then the folders of one, nothing outside
    page.fill("#imp-source", "")
    page.click("button[aria-label='Browse for imp-source']")
    page.wait_for_selector("#folder-browser .fb-dir")
    assert str(root) in page.locator("#fb-list").inner_text()
    page.click(f"#folder-browser .fb-dir[data-path='{root}']")
    page.wait_for_selector(f"#folder-browser .fb-dir[data-path='{src}']")
    paths = page.eval_on_selector_all("#folder-browser [data-path]", "els => els.map(e => e.dataset.path)")
    assert paths and all(p.startswith(str(root)) for p in paths)
    page.click(f"#folder-browser .fb-dir[data-path='{src}']")
    page.wait_for_selector(f"#fb-path:has-text('{src.name}')")
    _doc_shot(page.locator("#folder-browser"), "admin_folder_browser")
    page.click("#fb-choose")
    assert page.input_value("#imp-source") == str(src)
    # members chosen in the form
    users = {u["username"]: u["id"] for u in admin.get("/api/users").json()}
    page.check(f"#imp-member-{users['annotator']}")
    page.fill("#imp-name", "console_members")
    page.click("form[aria-label='Import a scene'] button[type=submit]")
    page.wait_for_selector("#toast:has-text('Import job')")
    assert page.locator("#alert").inner_text().strip() == ""  # the refusal is gone
    job = next(j for j in admin.get("/api/jobs").json() if j["kind"] == "import")
    assert live.wait_job(job)["status"] == "done"
    sid = job["scene_id"]
    assert [m["username"] for m in admin.get(f"/api/scenes/{sid}/members").json()] == ["annotator"]


def test_import_form_uploads_a_project_zip(live, new_page, tmp_path):
    _root, src = _source(live)
    zpath = tmp_path / "site_upload.zip"
    with zipfile.ZipFile(zpath, "w", zipfile.ZIP_DEFLATED) as z:
        for p in sorted(src.rglob("*")):
            if p.is_file():
                z.write(p, (p.relative_to(src.parent)).as_posix())
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin")
    page.wait_for_selector("#imp-zip")
    page.fill("#imp-name", "console_upload")
    page.set_input_files("#imp-zip", str(zpath))
    page.click("#imp-upload")
    page.wait_for_selector("#imp-zip-status:has-text('Uploaded')")
    up = live.app.state.ctx.settings.data_dir / "uploads" / "console_upload" / src.name
    assert page.input_value("#imp-source") == str(up) and up.is_dir()
    assert sorted(p.name for p in up.iterdir()) == sorted(p.name for p in src.iterdir())


def test_users_table_changes_role_deactivates_and_resets(live, new_page):
    admin = live.client("admin")
    r = admin.post("/api/users", json={"username": "dayuser", "password": "dayuser-password", "role": "annotator"})
    assert r.status_code == 201, r.text
    uid = r.json()["id"]
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin")
    row = page.locator("#sec-users tr[data-user='dayuser']")
    row.wait_for()
    row.locator("select.user-role").select_option("reviewer")
    page.wait_for_selector("#toast:has-text('dayuser is now reviewer')")
    assert next(u for u in admin.get("/api/users").json() if u["id"] == uid)["role"] == "reviewer"
    row.locator("button.user-reset").click()
    page.fill("#reset-password", "another-password-9")
    page.click("dialog.modal button.primary")
    page.wait_for_selector("#toast:has-text('Password of dayuser reset')")
    import httpx

    assert httpx.post(f"{live.base_url}/api/auth/login", json={"username": "dayuser", "password": "another-password-9"}).status_code == 200
    row.locator("button.user-active").click()
    page.click("dialog.modal button.primary")
    page.wait_for_selector("#sec-users tr[data-user='dayuser'][data-active='false']")
    assert next(u for u in admin.get("/api/users").json() if u["id"] == uid)["active"] is False
    assert httpx.post(f"{live.base_url}/api/auth/login", json={"username": "dayuser", "password": "another-password-9"}).status_code != 200
    page.locator("#sec-users").scroll_into_view_if_needed()
    _doc_shot(page.locator("#sec-users"), "admin_users", ready="#sec-users tr[data-user='dayuser'][data-active='false']")


def _fake_export(live, sid: int, name: str, nbytes: int) -> int:  # noqa: ANN001
    from app.jobs.models import Job

    out = live.app.state.ctx.settings.exports_dir / name
    (out / "data").mkdir(parents=True)
    (out / "data" / "a.bin").write_bytes(b"\1" * nbytes)
    with live.app.state.ctx.sessions() as s:
        job = Job(kind="export", scene_id=sid, status="done", params={"layout": "occufly"},
                  result={"output": str(out)}, progress=1.0, message="done", log="")
        s.add(job)
        s.commit()
        return job.id


def test_delete_an_export_and_a_scene_after_seeing_what_it_frees(live, new_page):
    admin = live.client("admin")
    sid = import_own_scene(live, "console_delete")
    jid = _fake_export(live, sid, "console_export", 1_500_000)
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.reload()  # one mount: the hash change after the login's landing page mounts it twice
    row = page.locator(f"#export-list tr[data-export='{jid}']")
    row.wait_for()
    row.locator("button.export-delete").click()
    page.wait_for_selector("#delete-export-preview:has-text('1.5 MB')")
    page.click("dialog.modal button.primary")
    page.wait_for_selector(f"#export-list tr[data-export='{jid}']", state="detached")
    assert not (live.app.state.ctx.settings.exports_dir / "console_export").exists()
    # the scene: its storage is listed, the confirmation says what deleting it frees
    srow = page.locator("#sec-scenes tr[data-scene='console_delete']")
    srow.locator(".storage").wait_for()
    preview = admin.get(f"/api/scenes/{sid}/deletion").json()
    srow.locator("button.scene-delete").click()
    page.wait_for_selector("#delete-scene-preview")
    shown = page.locator("#delete-frees").inner_text()
    assert shown and shown[0].isdigit()
    page.fill("#confirm-scene-name", "console_delete")
    _doc_shot(page.locator("dialog.modal"), "admin_delete_confirm")
    page.click("dialog.modal button.primary")
    page.wait_for_selector("#sec-scenes tr[data-scene='console_delete']", state="detached")
    assert sid not in {s["id"] for s in admin.get("/api/scenes").json()}
    assert preview["freed_bytes"] > 0


def test_overview_and_audit_names(live, new_page):
    admin = live.client("admin")
    ann = live.client("annotator")
    sid = import_own_scene(live, "console_overview")
    r = ann.post(f"/api/scenes/{sid}/next")
    assert r.status_code == 200, r.text
    f = r.json()
    ids = np.full((f["height"], f["width"]), 6, np.uint8)
    r = ann.put(f"/api/frames/{f['id']}/mask?kind=draft", content=grey_png(ids), headers={"If-Match": "none"})
    v = r.json()["version"]
    r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids), headers={"If-Match": str(v)})
    assert r.status_code == 200, r.text
    o = admin.get("/api/overview").json()
    row = next(s for s in o["scenes"] if s["scene_id"] == sid)
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.reload()  # one mount: the hash change after the login's landing page mounts it twice
    srow = page.locator("#overview tr[data-scene='console_overview']").first
    srow.wait_for()
    cells = srow.locator("td").all_inner_texts()
    assert cells[0] == "console_overview" and cells[1] == str(row["todo"]) and cells[3] == str(row["submitted"])
    assert page.locator("#overview tr[data-annotator='annotator'][data-scene='console_overview']").count() == 1
    tot = next(a for a in o["annotators"] if a["username"] == "annotator")
    cells = page.locator("#overview tr[data-annotator-total='annotator'] td").all_inner_texts()
    assert cells[2] == str(tot["scenes"]) and cells[4] == str(tot["submitted"])
    _doc_shot(page.locator("#sec-overview"), "admin_overview",
              ready="#overview tr[data-annotator-total='annotator']")
    # the audit log names the frame and the scene
    page.fill("#audit-action", "mask_submit")
    page.click("form[aria-label='Filter audit log'] button[type=submit]")
    page.wait_for_selector(f"#audit td:text-is('{f['name']}')")
    assert page.locator("#audit td:text-is('console_overview')").count() >= 1


def test_folder_browser_marks_a_hard_linked_file_and_does_not_offer_it(live, new_page):
    """Imports refuse a file with a second name (it may be a file from outside the roots):
    the folder browser shows such a file with the reason and gives no button to pick it."""
    import os
    import shutil

    root, _src = _source(live)
    probe = root / "zz_hard_link_probe"  # sorts after the scene sources (_source takes the first)
    probe.mkdir()
    try:
        (probe / "cameras.xml").write_text("<document/>")
        os.link(probe / "cameras.xml", probe / "linked.xml")
        (probe / "plain.xml").write_text("<document/>")
        page = new_page("admin")
        page.goto(f"{live.base_url}/#/admin")
        page.wait_for_selector("#imp-members input[type=checkbox]")
        page.click("button[aria-label='Browse for imp-source']")
        page.wait_for_selector(f"#folder-browser .fb-dir[data-path='{root}']")
        page.click(f"#folder-browser .fb-dir[data-path='{root}']")
        page.click(f"#folder-browser .fb-dir[data-path='{probe}']")
        page.wait_for_selector("#folder-browser li[data-refused]")
        refused = page.locator("#folder-browser li[data-refused]")
        assert refused.count() == 2  # both names of the linked file
        text = refused.first.inner_text()
        assert "hard link" in text and "copy the file in" in text, text
        assert refused.locator("button").count() == 0
        plain = page.locator("#folder-browser li[data-kind='file']:not([data-refused])")
        assert plain.count() == 1 and "plain.xml" in plain.inner_text()
        _doc_shot(page.locator("#folder-browser"), "admin_folder_browser_hard_link")
    finally:
        shutil.rmtree(probe)
