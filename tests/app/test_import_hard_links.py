"""Issue 36 (part B, item 2): a hard link inside an import root to a file outside it looks
like any file there (symlinks were already refused). Imports refuse every regular file with
more than one name, naming it; the folder browser marks it; a frame image hard-linked after
its import is not served. SQLite and PostgreSQL."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
from PIL import Image

from tests.app.conftest import H, W, write_tiny_workspace


def _import(env, adm, name, src, **kw):  # noqa: ANN001, ANN202
    r = env.client.post("/api/scenes/import", json={"name": name, "source": str(src), **kw},
                        headers=adm)
    if r.status_code != 202:
        return r.status_code, r.json()["detail"]
    env.app.state.ctx.jobs.wait(r.json()["id"], timeout=60)
    j = env.client.get(f"/api/jobs/{r.json()['id']}", headers=adm).json()
    return j["status"], j["message"]


def test_workspace_file_hard_linked_from_outside_is_refused(env, tmp_path):
    adm = env.bearer("admin")
    secret = tmp_path / "secret.json"  # outside the import root, same disk
    secret.write_text('{"password": "hunter2"}')
    src = env.import_root / "ws_tax"
    write_tiny_workspace(src)
    (src / "taxonomy.json").unlink()
    os.link(secret, src / "taxonomy.json")
    status, msg = _import(env, adm, "tax", src)
    assert status in (403, 422, "failed"), (status, msg)
    assert "taxonomy.json is a hard link (2 names for one file)" in msg, msg
    assert "hunter2" not in msg


def test_frame_image_hard_linked_from_outside_is_refused(env, tmp_path):
    adm = env.bearer("admin")
    outside = tmp_path / "private.png"
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(outside)
    src = env.import_root / "ws_img"
    write_tiny_workspace(src)
    img = sorted((src / "images").iterdir())[0]
    img.unlink()
    os.link(outside, img)
    status, msg = _import(env, adm, "img", src)
    assert status == 403, (status, msg)
    assert f"{img.name} is a hard link" in msg and "copy the file in" in msg, msg


def test_colmap_project_file_hard_linked_is_refused(env, tmp_path):
    from tests.recon_builder import make_reconstruction

    adm = env.bearer("admin")
    src = env.import_root / "recon"
    make_reconstruction(src)
    cams = next(src.rglob("cameras.txt"))
    shutil.move(cams, tmp_path / "cameras.txt")
    os.link(tmp_path / "cameras.txt", cams)
    status, msg = _import(env, adm, "recon", src)
    assert status in (403, 422, "failed"), (status, msg)
    assert "cameras.txt is a hard link" in msg, msg


def test_browser_marks_hard_links_and_a_copy_imports(env, tmp_path):
    adm = env.bearer("admin")
    src = env.import_root / "ws_ok"
    write_tiny_workspace(src)
    (tmp_path / "x.bin").write_bytes(b"x" * 10)
    os.link(tmp_path / "x.bin", src / "linked.bin")
    r = env.client.get("/api/imports/browse", params={"path": str(src)}, headers=adm)
    assert r.status_code == 200
    rows = {e["name"]: e for e in r.json()["entries"]}
    assert rows["linked.bin"].get("hard_link") is True and "refused" in rows["linked.bin"]
    assert "hard_link" not in rows["scene.json"]
    status, msg = _import(env, adm, "ok_linked", src)
    assert status in (403, "failed") and "linked.bin is a hard link" in msg, (status, msg)
    # the same file copied (one name) imports
    (src / "linked.bin").unlink()
    shutil.copy(tmp_path / "x.bin", src / "linked.bin")
    status, msg = _import(env, adm, "ok", src)
    assert status == "done", msg


def test_frame_image_hard_linked_after_the_import_is_not_served(world, tmp_path):
    env, hdr, scene, frames = world
    ws = env.settings.workspaces_dir / "tiny"
    img = json.loads((ws / "scene.json").read_text())["frames"][0]["image_path"]
    r = env.client.get(f"/api/frames/{frames[0]['id']}/image", headers=hdr["annotator"])
    assert r.status_code == 200
    outside = tmp_path / "other.png"
    Image.fromarray(np.full((H, W, 3), 7, np.uint8)).save(outside)
    os.unlink(img)
    os.link(outside, img)
    r = env.client.get(f"/api/frames/{frames[0]['id']}/image", headers=hdr["annotator"])
    assert r.status_code == 404 and "hard link" in r.json()["detail"], r.text
