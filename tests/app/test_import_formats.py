"""The import endpoint takes the project kind (format), the image folder and the CRS."""

from __future__ import annotations

import shutil

from tests.harness import SHARED_DATA, shared_data

DATA = SHARED_DATA


def test_import_validates_format_and_crs(env):
    adm = env.bearer("admin")
    (env.import_root / "proj").mkdir()
    r = env.client.post("/api/scenes/import", json={"name": "p", "source": "proj",
                                                    "format": "agisoft"}, headers=adm)
    assert r.status_code == 422
    r = env.client.post("/api/scenes/import", json={"name": "p", "source": "proj",
                                                    "crs": "EPSG:not-a-code"}, headers=adm)
    assert r.status_code == 422 and "crs" in r.text


def test_import_metashape_xml_reaches_the_reader(env):
    """A real Metashape export with format=metashape: the job runs the Metashape reader and
    fails naming the missing photos (the fixture ships none), not a generic error."""
    adm = env.bearer("admin")
    shutil.copy(shared_data("metashape-bitbyt3r-local", "cameras.xml"), env.import_root / "cams.xml")
    (env.import_root / "photos").mkdir()
    r = env.client.post("/api/scenes/import", json={
        "name": "ms", "source": "cams.xml", "format": "metashape", "images": "photos"},
        headers=adm)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"])
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()
    assert j["status"] == "failed"
    assert "94 of 94 images are missing: 001, 002" in j["message"]


def test_import_of_a_model_in_unknown_units_is_refused_unless_scaled(env):
    """COLMAP's cup model (SfM units, no GPS, no CRS) fails naming the cause and the fix;
    with scale=1 (metric already) it imports; a non-positive scale is a 422."""
    adm = env.bearer("admin")
    shutil.copytree(shared_data("colmap-dense-cup"), env.import_root / "cup")
    r = env.client.post("/api/scenes/import", json={"name": "cup", "source": "cup"}, headers=adm)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"])
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()
    assert j["status"] == "failed"
    assert "units are unknown" in j["message"] and "--scale" in j["message"]
    r = env.client.post("/api/scenes/import", json={"name": "cup2", "source": "cup", "scale": 0},
                        headers=adm)
    assert r.status_code == 422 and "scale" in r.text
    r = env.client.post("/api/scenes/import", json={"name": "cup2", "source": "cup", "scale": 1},
                        headers=adm)
    assert r.status_code == 202, r.text
    env.app.state.ctx.jobs.wait(r.json()["id"])
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()
    assert j["status"] == "done", j
