"""An admin uploads masks painted in another tool (issue 26): POST /api/scenes/{sid}/masks/import
stores ``imported`` versions (source "imported from CVAT", the admin as author, an external
author recorded) that vote and go through review; a bad archive is one 422 listing every
unknown class and unmatched image, with nothing stored. On SQLite and PostgreSQL."""

from __future__ import annotations

import io
import json

import datumaro  # noqa: F401 -- the `masks` extra: scripts/setup.sh installs it (no skip)
import numpy as np
from PIL import Image
from sqlalchemy import func, select

from tests.app.conftest import H, W
from tests.mask_archives import datumaro_cvat_archive


def _post(env, sid, path, hdr, fmt="cvat", mapping=None, author=None):  # noqa: ANN001, ANN202
    files = {"archive": (path.name, path.read_bytes(), "application/zip")}
    if mapping is not None:
        files["mapping"] = ("map.json", json.dumps(mapping).encode(), "application/json")
    data = {"format": fmt, **({"author": author} if author else {})}
    return env.client.post(f"/api/scenes/{sid}/masks/import", files=files, data=data,
                           headers=hdr)


def test_admin_imports_a_datumaro_cvat_archive_which_then_is_reviewed(world, tmp_path):
    from app.annotations.models import MaskVersion
    from app.audit.models import AuditEvent

    env, hdr, scene, frames = world
    sid = scene["id"]
    archive = datumaro_cvat_archive(tmp_path / "task.zip", ["Road", "car"],
                                    [frames[0]["name"], frames[2]["name"]], (H, W))
    assert _post(env, sid, archive, hdr["annotator"]).status_code == 403
    r = _post(env, sid, archive, hdr["admin"], mapping={"car": "vehicle"}, author="Jane Doe")
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["format"] == "cvat_images" and out["frames_imported"] == 2
    assert out["source"] == "imported from CVAT by Jane Doe"
    assert out["classes"] == {"Road": 1, "car": 13}
    assert [f["frame_id"] for f in out["frames"]] == [frames[0]["id"], frames[2]["id"]]
    # issue 40: each frame's own version number beside the global id (the page shows "v1")
    assert [f["number"] for f in out["frames"]] == [1, 1]
    again = _post(env, sid, archive, hdr["admin"], mapping={"car": "vehicle"}, author="Jane Doe")
    assert again.status_code == 200 and again.json()["frames_imported"] == 0
    assert again.json()["unchanged"] == [frames[0]["name"], frames[2]["name"]]
    ctx = env.app.state.ctx
    with ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(MaskVersion)) == 2
        v = s.get(MaskVersion, out["frames"][0]["version"])
        assert v.kind == "imported" and v.source == "imported from CVAT by Jane Doe"
        admin_id = s.scalar(select(AuditEvent.actor_id).where(AuditEvent.action == "mask_import"))
        assert v.author_id == admin_id
    got = env.client.get(f"/api/frames/{frames[0]['id']}/mask", headers=hdr["admin"])
    m = np.asarray(Image.open(io.BytesIO(got.content)))
    assert m[1, 1] == 1 and m[H // 4, W * 2 // 3] == 13 and m[H - 1, W - 1] == 0
    # the imported versions vote and wait for review like submitted ones
    assert ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=hdr["admin"]).json()
    assert set(st["included_versions"]) == {str(frames[0]["id"]), str(frames[2]["id"])}
    f0 = env.client.get(f"/api/frames/{frames[0]['id']}", headers=hdr["admin"]).json()
    assert f0["state"] == "submitted"
    r = env.client.post(f"/api/frames/{frames[0]['id']}/review",
                        json={"decision": "reject", "version": out["frames"][0]["version"]},
                        headers=hdr["reviewer"])
    assert r.status_code == 200 and r.json()["state"] == "rejected"
    assert ctx.lifting.wait_idle(sid, timeout=30)
    st = env.client.get(f"/api/scenes/{sid}/labels/status", headers=hdr["admin"]).json()
    assert set(st["included_versions"]) == {str(frames[2]["id"])}


def test_unknown_classes_and_unmatched_images_store_nothing(world, tmp_path):
    from app.annotations.models import MaskVersion

    env, hdr, scene, frames = world
    sid = scene["id"]
    archive = datumaro_cvat_archive(tmp_path / "bad.zip", ["Road", "hedge"],
                                    [frames[0]["name"], "IMG_9999.JPG", "IMG_9998.JPG"], (H, W))
    r = _post(env, sid, archive, hdr["admin"])
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert "nothing imported" in detail and "'hedge'" in detail
    assert "'IMG_9998'" in detail and "'IMG_9999'" in detail
    assert len(r.json()["problems"]) == 2  # one line per kind of problem, for the page
    with env.app.state.ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(MaskVersion)) == 0
    # a wrong format and a bad author name are refused before anything is read
    assert _post(env, sid, archive, hdr["admin"], fmt="nosuch").status_code == 422
    r = _post(env, sid, archive, hdr["admin"], mapping={"hedge": "vegetation"}, author="a<b")
    assert r.status_code == 422 and "author" in r.json()["detail"]
    with env.app.state.ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(MaskVersion)) == 0


def test_masks_and_prefill_go_out_for_another_tool(world, tmp_path):
    import zipfile

    from pycocotools.coco import COCO

    env, hdr, scene, frames = world
    sid = scene["id"]
    assert env.client.get(f"/api/scenes/{sid}/masks/export?format=coco",
                          headers=hdr["admin"]).status_code == 404  # no mask counts yet
    archive = datumaro_cvat_archive(tmp_path / "task.zip", ["road", "vehicle"],
                                    [frames[1]["name"]], (H, W))
    assert _post(env, sid, archive, hdr["admin"]).status_code == 200
    assert env.client.get(f"/api/scenes/{sid}/masks/export?format=coco",
                          headers=hdr["reviewer"]).status_code == 403
    r = env.client.get(f"/api/scenes/{sid}/masks/export?format=coco", headers=hdr["admin"])
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    (tmp_path / "out.zip").write_bytes(r.content)
    with zipfile.ZipFile(tmp_path / "out.zip") as zf:
        zf.extractall(tmp_path / "out")
    coco = COCO(str(tmp_path / "out" / "annotations" / "instances_default.json"))
    names = {c["id"]: c["name"] for c in coco.cats.values()}
    ids = {"road": 1, "vehicle": 13}
    img = next(i for i in coco.imgs.values() if i["file_name"] == frames[1]["name"])
    got = np.zeros((H, W), np.uint8)
    for ann in coco.loadAnns(coco.getAnnIds(imgIds=img["id"])):
        got[coco.annToMask(ann).astype(bool)] = ids[names[ann["category_id"]]]
    stored = np.asarray(Image.open(io.BytesIO(env.client.get(
        f"/api/frames/{frames[1]['id']}/mask", headers=hdr["admin"]).content)))
    np.testing.assert_array_equal(got, stored)
    # the prefill of the selected frames, as Label Studio predictions
    ctx = env.app.state.ctx
    assert ctx.lifting.wait_idle(sid, timeout=30, include_fill=True)
    r = env.client.get(f"/api/scenes/{sid}/masks/export?format=labelstudio&what=prefill",
                       headers=hdr["admin"])
    assert r.status_code == 200, r.text
    (tmp_path / "pre.zip").write_bytes(r.content)
    with zipfile.ZipFile(tmp_path / "pre.zip") as zf:
        tasks = json.loads(zf.read("tasks.json"))
    assert len(tasks) == len(frames)
    assert all("predictions" in t and "annotations" not in t for t in tasks)
    assert any(t["predictions"] and t["predictions"][0]["result"] for t in tasks)


def test_hostile_upload_names_are_only_names(world, tmp_path):
    from app.annotations.models import MaskVersion

    env, hdr, scene, frames = world
    sid = scene["id"]
    archive = datumaro_cvat_archive(tmp_path / "bad.zip", ["Road", "hedge"], [frames[0]["name"]],
                                    (H, W))
    for bad in ("..", ".", "a\x00b.zip", "../../etc/passwd"):
        files = {"archive": (bad, archive.read_bytes(), "application/zip"),
                 "mapping": (bad, b"{}", "application/json")}
        r = env.client.post(f"/api/scenes/{sid}/masks/import", files=files,
                            data={"format": "cvat"}, headers=hdr["admin"])
        assert r.status_code == 422, (bad, r.status_code, r.text)
    with env.app.state.ctx.sessions() as s:
        assert s.scalar(select(func.count()).select_from(MaskVersion)) == 0

