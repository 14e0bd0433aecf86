"""Issue 40 defect 8, the admin page: the overview follows a finished job without a reload,
and a deleted export offers no download (its job card says it was deleted; the archive
endpoints answer 404 naming the deletion)."""

from __future__ import annotations

import pytest

from tests.e2e.conftest import REPO, import_own_scene, shot, wait_js

pytestmark = pytest.mark.e2e
DOCS = REPO / "docs" / "screenshots"


@pytest.fixture(scope="module")
def sid(live):
    return import_own_scene(live, "admin_after_jobs")


def _open(page, live, sid) -> None:  # noqa: ANN001
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    page.reload()  # one mount: the hash change after the login's landing page mounts it twice
    page.locator("#overview tr[data-scene='admin_after_jobs']").first.wait_for()
    page.wait_for_load_state("networkidle")  # a loaded host: the page's last re-render is done


def test_overview_follows_a_finished_selection_job(live, sid, new_page):
    admin = live.client("admin")
    before = next(s for s in admin.get("/api/overview").json()["scenes"] if s["scene_id"] == sid)
    page = new_page("admin")
    _open(page, live, sid)
    todo = page.locator("#overview tr[data-scene='admin_after_jobs'] td").nth(1)
    assert todo.inner_text() == str(before["todo"])
    # a coarser grid selects fewer frames: "to do" changes when the job finishes
    page.fill("#sel-cell", "40")
    assert page.input_value("#sel-cell") == "40"  # not reset by a late re-render
    page.click("#sec-selection button[type=submit]")
    page.wait_for_selector("#toast:has-text('selection) done')", timeout=60_000)
    after = next(s for s in admin.get("/api/overview").json()["scenes"] if s["scene_id"] == sid)
    assert after["todo"] != before["todo"], (before, after)
    wait_js(page, "([sel, want]) => document.querySelectorAll(sel)[1]?.textContent === want",
            arg=["#overview tr[data-scene='admin_after_jobs'] td", str(after["todo"])])
    sc = next(s for s in admin.get("/api/scenes").json() if s["id"] == sid)
    wait_js(page, "([sel, want]) => document.querySelector(sel)?.textContent === want",
            arg=["#sec-scenes tr[data-scene='admin_after_jobs'] td:nth-child(5)",
                 str(sc["n_selected"])])


def _fake_export(live, sid: int, name: str) -> int:  # noqa: ANN001
    from app.jobs.models import Job

    out = live.app.state.ctx.settings.exports_dir / name
    (out / "data").mkdir(parents=True)
    (out / "data" / "a.bin").write_bytes(b"\1" * 5000)
    with live.app.state.ctx.sessions() as s:
        job = Job(kind="export", scene_id=sid, status="done", params={"layout": "occufly"},
                  result={"output": str(out)}, progress=1.0, message="done", log="")
        s.add(job)
        s.commit()
        return job.id


def test_a_deleted_export_is_no_longer_offered_for_download(live, sid, new_page):
    admin = live.client("admin")
    jid = _fake_export(live, sid, "after_jobs_export")
    page = new_page("admin")
    _open(page, live, sid)
    card = page.locator(f"#jobs li[data-job='{jid}']")
    card.locator("button.archive-build").click()  # compress, then the Save link is offered
    link = card.locator("a.archive-link")
    link.wait_for()
    assert admin.get(link.get_attribute("href")).status_code == 200
    card.screenshot(path=str(DOCS / "admin_export_archive.png"))  # docs/guide/admin.md
    page.locator(f"#export-list tr[data-export='{jid}'] button.export-delete").click()
    page.click("dialog.modal button.primary")
    page.wait_for_selector(f"#export-list tr[data-export='{jid}']", state="detached")
    # the job card drops the link and says why; nothing on the page still offers it
    card.locator(".export-deleted").wait_for()
    assert card.locator("a.archive-link, button.archive-build").count() == 0
    assert page.locator(f"a[href^='/api/jobs/{jid}/archive']").count() == 0
    card.screenshot(path=str(DOCS / "admin_export_deleted.png"))
    r = admin.get(f"/api/jobs/{jid}/archive/info")
    assert r.status_code == 404 and "was deleted at" in r.json()["detail"], r.text
    # a fresh page shows the same
    page.reload()
    page.locator(f"#jobs li[data-job='{jid}'] .export-deleted").wait_for()
    assert page.locator(f"#jobs li[data-job='{jid}'] a.archive-link").count() == 0
    shot(page, "40_admin_deleted_export")
