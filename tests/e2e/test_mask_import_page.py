"""Issue 26: masks painted in CVAT come in through the admin page. The archive is written by a
real CVAT-format writer (Datumaro's, the format framework CVAT uses): a polygon and an RLE mask
per image. The admin uploads it with a class mapping and an external author; the page lists the
imported versions, which wait for review. A second archive with an unknown class and images of
another scene is refused with every problem listed and nothing stored.

Screenshot (looked at): docs/screenshots/admin_mask_import.png."""

from __future__ import annotations

import json
import zipfile

import datumaro  # noqa: F401 -- the `masks` extra: scripts/setup.sh installs it (no skip)
import pytest

from tests.e2e.conftest import ARTIFACTS, REPO, import_own_scene, shot
from tests.mask_archives import datumaro_cvat_archive

pytestmark = pytest.mark.e2e

DOCS = REPO / "docs" / "screenshots"


@pytest.fixture(scope="module")
def sid(live):
    return import_own_scene(live, "mask_import_scene")


def _wait_mounted(page, sid) -> None:  # noqa: ANN001
    """The admin page showing scene ``sid`` (the page after the login shows the first scene;
    the hash change mounts it again for ``?scene=``)."""
    from playwright.sync_api import expect

    expect(page.locator("#admin-scene")).to_have_value(str(sid))
    page.wait_for_load_state("networkidle")
    page.wait_for_selector("#sec-masks form")


def _frames(live, sid):  # noqa: ANN001, ANN202
    return live.client("admin").get(f"/api/scenes/{sid}/frames").json()


def test_admin_imports_a_datumaro_written_cvat_archive(live, sid, new_page, tmp_path):
    admin = live.client("admin")
    frames = _frames(live, sid)[:3]
    size = (frames[0]["height"], frames[0]["width"])
    archive = datumaro_cvat_archive(tmp_path / "cvat_task_7_annotations.zip", ["Road", "car"],
                                    [f["name"] for f in frames], size)
    mapping = tmp_path / "cvat_classes.json"
    mapping.write_text(json.dumps({"car": "vehicle"}))
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    _wait_mounted(page, sid)
    page.set_input_files("#mi-archive", str(archive))
    page.select_option("#mi-format", "cvat")
    page.set_input_files("#mi-mapping", str(mapping))
    page.fill("#mi-author", "J. Doe (field team)")
    page.click("#sec-masks button[type=submit]")
    page.wait_for_selector("#mask-import-result table, #mask-import-result [role=alert]",
                           timeout=60_000)
    text = page.locator("#mask-import-result").inner_text()
    assert "3 frame(s) imported" in text, text
    assert "imported from CVAT by J. Doe (field team)" in text and "car → 13" in text
    rows = page.locator("#mask-import-result tbody tr")
    assert rows.count() == 3 and "imported" in rows.nth(0).inner_text()
    # issue 40: the frame's version number ("v1": their first), not the global version id
    got = {rows.nth(i).locator("td").first.inner_text(): rows.nth(i).locator(".mi-version")
           for i in range(3)}
    for f in frames:
        vs = admin.get(f"/api/frames/{f['id']}/mask/versions").json()
        cell = got[f["name"]]
        assert cell.inner_text() == f"v{vs[-1]['number']}" == "v1", cell.inner_text()
        assert cell.get_attribute("data-version") == str(vs[-1]["version"])
    for f in frames:
        vs = admin.get(f"/api/frames/{f['id']}/mask/versions").json()
        assert vs[-1]["kind"] == "imported"
        assert vs[-1]["source"] == "imported from CVAT by J. Doe (field team)"
        assert admin.get(f"/api/frames/{f['id']}").json()["state"] == "submitted"
    # and back out for the tool: the masks that count, as COCO
    page.select_option("#mx-what", "masks")
    page.select_option("#mx-format", "coco")
    with page.expect_download() as dl:
        page.click("#sec-masks form[aria-label='Download masks for another tool'] button")
    with zipfile.ZipFile(dl.value.path()) as zf:
        doc = json.loads(zf.read("annotations/instances_default.json"))
    assert sorted(i["file_name"] for i in doc["images"]) == sorted(f["name"] for f in frames)
    assert {c["name"] for c in doc["categories"]} >= {"road", "vehicle"}
    page.locator("#sec-masks").scroll_into_view_if_needed()
    DOCS.mkdir(parents=True, exist_ok=True)
    page.locator("#sec-masks").screenshot(path=str(DOCS / "admin_mask_import.png"))
    shot(page, "26_admin_mask_import")


def test_a_refused_archive_lists_every_problem_and_stores_nothing(live, sid, new_page, tmp_path):
    admin = live.client("admin")
    frames = _frames(live, sid)
    f = frames[-1]
    before = admin.get(f"/api/frames/{f['id']}/mask/versions").json()
    archive = datumaro_cvat_archive(tmp_path / "other.zip", ["Road", "hedge"],
                                    [f["name"], "DJI_9999.JPG"], (f["height"], f["width"]))
    page = new_page("admin")
    page.goto(f"{live.base_url}/#/admin?scene={sid}")
    _wait_mounted(page, sid)
    page.set_input_files("#mi-archive", str(archive))
    page.click("#sec-masks button[type=submit]")
    page.wait_for_selector("#mask-import-result [role=alert]")
    items = page.locator("#mask-import-result li")
    assert items.count() == 2
    text = page.locator("#mask-import-result").inner_text()
    assert "Nothing imported from other.zip" in text and "'hedge'" in text and "'DJI_9999'" in text
    assert admin.get(f"/api/frames/{f['id']}/mask/versions").json() == before
    page.locator("#sec-masks").screenshot(path=str(ARTIFACTS / "26_admin_mask_import_refused.png"))
