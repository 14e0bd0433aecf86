"""Issue 24, finding 8: ``occufly backup`` carries the frame images that live outside the data
dir (workspaces point at the import folder), so a restore without that folder serves every
image (before: 404s, and its export failed). ``--no-images`` records and checks them and says
the backup is not complete. SQLite and PostgreSQL."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from tests.app.conftest import PASSWORD, mask_png
from tests.app.test_backup import fresh_target  # noqa: F401 - fixture


def _scene_with_a_mask(env) -> tuple[dict, list[dict], dict]:  # noqa: ANN001
    adm = env.bearer("admin")
    scene = env.import_tiny(adm)
    env.select_all(scene["id"])
    ann = env.bearer("annotator")
    fid = env.client.post(f"/api/scenes/{scene['id']}/next", headers=ann).json()["id"]
    r = env.client.put(f"/api/frames/{fid}/mask", content=mask_png(),
                       headers={**ann, "If-Match": "none"})
    assert r.status_code == 200, r.text
    frames = env.client.get(f"/api/scenes/{scene['id']}/frames", headers=adm).json()
    images = {f["id"]: env.client.get(f"/api/frames/{f['id']}/image", headers=adm).content
              for f in frames}
    assert all(len(b) > 100 for b in images.values())
    return scene, frames, images


def test_restore_without_the_import_folder_serves_every_image(env, fresh_target, tmp_path):  # noqa: F811
    from app.backup import backup, restore
    from app.main import close, create_app

    scene, frames, images = _scene_with_a_mask(env)
    out = backup(env.settings, tmp_path / "bk")
    assert out["complete"] is True
    assert out["external_images"] == {"frames": len(frames), "files": len(frames),
                                      "copied": True}, out["external_images"]
    assert len(list((tmp_path / "bk" / "images").rglob("*.png"))) == len(frames)
    # the import folder is gone (another machine, or deleted after the import)
    shutil.move(str(env.import_root), str(tmp_path / "moved_away"))
    restore(fresh_target, tmp_path / "bk")
    app = create_app(fresh_target)
    try:
        c = TestClient(app)
        tok = c.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
        hdr = {"Authorization": f"Bearer {tok.json()['token']}"}
        for fid, data in images.items():
            r = c.get(f"/api/frames/{fid}/image", headers=hdr)
            assert r.status_code == 200, (fid, r.status_code, r.text[:200])
            assert r.content == data, fid
        assert c.get(f"/api/frames/{frames[0]['id']}/image?size=thumb",
                     headers=hdr).status_code == 200
        ws = fresh_target.workspaces_dir / scene["name"]
        header = json.loads((ws / "scene.json").read_text())
        assert all(f["image_path"].startswith("images_restored/") for f in header["frames"])
    finally:
        close(app)


def test_missing_image_fails_the_backup_and_leaves_nothing(env, tmp_path):
    from app.backup import BackupError, backup

    _scene_with_a_mask(env)
    victim = next((env.import_root / "tiny_src" / "images").glob("*.png"))
    victim.unlink()
    with pytest.raises(BackupError, match=r"1 frame image\(s\).*missing.*img_000"):
        backup(env.settings, tmp_path / "bk")
    assert not (tmp_path / "bk").exists()


def test_no_images_backup_is_incomplete_and_restore_checks_the_folder(env, fresh_target,  # noqa: F811
                                                                      tmp_path):
    from app.backup import BackupError, backup, restore

    _scene_with_a_mask(env)
    out = backup(env.settings, tmp_path / "bk", images=False)
    assert out["complete"] is False and "not copied" in out["incomplete_because"]
    assert not (tmp_path / "bk" / "images").exists()
    manifest = json.loads((tmp_path / "bk" / "manifest.json").read_text())
    assert manifest["complete"] is False
    # one recorded image changed since: the restore refuses before writing anything
    changed = next((env.import_root / "tiny_src" / "images").glob("*.png"))
    changed.write_bytes(changed.read_bytes() + b"\0")
    with pytest.raises(BackupError, match="missing or changed since the backup"):
        restore(fresh_target, tmp_path / "bk")
    assert not fresh_target.workspaces_dir.exists() or not any(
        fresh_target.workspaces_dir.iterdir())


def test_an_image_outside_the_roots_is_not_carried(env, tmp_path):
    """A legacy scene.json naming a file outside the import roots and the data dir (the app
    never serves it): the backup does not copy it, and the manifest lists it."""
    from app.backup import backup
    from app.scenes.models import Scene

    scene, _frames, _images = _scene_with_a_mask(env)
    secret = tmp_path / "elsewhere" / "secret.png"
    secret.parent.mkdir()
    secret.write_bytes(b"\x89PNG\r\n\x1a\n" + b"not for backups" * 10)
    with env.app.state.ctx.sessions() as s:
        ws = Path(s.get(Scene, scene["id"]).workspace)
    header = json.loads((ws / "scene.json").read_text())
    header["frames"][1]["image_path"] = str(secret)
    (ws / "scene.json").write_text(json.dumps(header))
    out = backup(env.settings, tmp_path / "bk")
    sc = next(x for x in out["scenes"] if x["name"] == scene["name"])
    assert sc["images_outside_roots"] == [{"frame": 1, "path": str(secret)}]
    assert all(e["frame"] != 1 for e in sc["external_images"])
    blob = secret.read_bytes()
    assert not any(p.read_bytes() == blob for p in (tmp_path / "bk").rglob("*") if p.is_file())
