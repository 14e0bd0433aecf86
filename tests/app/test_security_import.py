"""Issue 24, finding 1 at import time (and finding 2's name refusal): every path read from a
file -- a workspace's scene.json ``image_path``, an image that is a symlink, a Metashape
``.psx``'s absolute photo paths, a cloud or depth map that is a symlink -- resolves inside
the import roots, or the import is refused naming the file and the path."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from occufly.errors import InputFormatError, UnsafePathError
from tests.app.conftest import write_tiny_workspace

ROOT = Path(__file__).resolve().parents[1]


def _import(env, adm, src: Path, name: str):  # noqa: ANN001, ANN202
    return env.client.post("/api/scenes/import", json={"name": name, "source": str(src)},
                           headers=adm)


def _set_image_path(src: Path, value: str, frame: int = 0, name: str | None = None) -> None:
    hdr = json.loads((src / "scene.json").read_text())
    hdr["frames"][frame]["image_path"] = value
    if name is not None:
        hdr["frames"][frame]["name"] = name
    (src / "scene.json").write_text(json.dumps(hdr))


def test_workspace_image_paths_outside_the_roots_are_refused(env, tmp_path):
    """/etc/passwd, ../../occufly.db, the app's SQLite file, a PNG in the data dir (another
    scene's stored mask), a database file inside the import roots (refused for not being an
    image), a symlink out of the roots: 403 naming scene.json and the path; no scene row, no
    job. A clean workspace still imports."""
    adm = env.bearer("admin")
    outside = tmp_path / "outside.png"
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(outside)
    db_file = env.settings.data_dir / "occufly.db"
    if not db_file.exists():  # PostgreSQL run: a stand-in SQLite file in the data dir
        db_file.write_bytes(b"SQLite format 3\x00" + bytes(4096))
    in_data = env.settings.data_dir / "masks" / "ab" / "cd" / ("ab" * 32 + ".png")
    in_data.parent.mkdir(parents=True)
    shutil.copy(outside, in_data)
    db_in_root = env.import_root / "copy.db"
    db_in_root.write_bytes(b"SQLite format 3\x00" + bytes(4096))
    vectors = {"etc_passwd": "/etc/passwd", "dotdot_db": "../../occufly.db",
               "app_db": str(db_file), "dotdot_out": "../../outside.png",
               "data_mask": str(in_data), "db_in_root": str(db_in_root)}
    tried = 0
    for name, value in vectors.items():
        src = env.import_root / f"{name}_src"
        write_tiny_workspace(src)
        _set_image_path(src, value)
        r = _import(env, adm, src, name)
        tried += 1
        assert r.status_code == 403, (name, r.status_code, r.text)
        assert "scene.json" in r.text and value in r.text, r.text
    # an image symlinked out of the roots
    src = env.import_root / "symlink_src"
    write_tiny_workspace(src)
    img = src / "images" / "img_000.png"
    img.unlink()
    os.symlink(outside, img)
    r = _import(env, adm, src, "symlinked")
    tried += 1
    assert r.status_code == 403 and "outside the import roots" in r.text, r.text
    scenes = env.client.get("/api/scenes", headers=adm).json()
    assert scenes == [], scenes  # nothing was created for any refused import
    assert tried == 7
    env.import_tiny(adm, name="clean")


def test_workspace_frame_name_with_markup_is_refused(env):
    adm = env.bearer("admin")
    for i, bad in enumerate(['<iframe srcdoc="x">.png', "a\x1b[31m.png", "\u202egnp.exe"]):
        src = env.import_root / f"bad{i}_src"
        write_tiny_workspace(src)
        _set_image_path(src, "images/img_000.png", name=bad)
        r = _import(env, adm, src, f"bad{i}")
        assert r.status_code == 422, (bad, r.status_code, r.text)
        assert "not allowed in names" in r.text


def test_workspace_custom_taxonomy_with_markup_is_refused(env):
    adm = env.bearer("admin")
    src = env.import_root / "tax_src"
    write_tiny_workspace(src)
    tax = json.loads((src / "taxonomy.json").read_text())
    tax["classes"][0]["name"] = "<img src=x onerror=alert(1)>"
    (src / "taxonomy.json").write_text(json.dumps(tax))
    r = _import(env, adm, src, "tax")
    assert r.status_code == 422 and "not allowed in names" in r.text, r.text


# ---- reconstructions (the library's confinement, what the import job runs) -----------------
def test_colmap_image_symlinked_out_is_refused(tmp_path):
    from occufly.io.importer import import_scene
    from tests.recon_builder import make_reconstruction

    roots = [tmp_path / "imports"]
    src = roots[0] / "recon"
    make_reconstruction(src, depth_maps=False)
    secret = tmp_path / "secret.png"
    shutil.copy(src / "images" / "img_001.png", secret)
    (src / "images" / "img_001.png").unlink()
    os.symlink(secret, src / "images" / "img_001.png")
    with pytest.raises(UnsafePathError, match=r"img_001.png is a symbolic link to .*secret.png"):
        import_scene(src, tmp_path / "ws", roots=roots)
    assert not (tmp_path / "ws").exists()
    # a cloud symlinked out is refused the same way
    (src / "images" / "img_001.png").unlink()
    shutil.copy(secret, src / "images" / "img_001.png")
    shutil.move(src / "dense" / "fused.ply", tmp_path / "fused.ply")
    os.symlink(tmp_path / "fused.ply", src / "dense" / "fused.ply")
    with pytest.raises(UnsafePathError, match=r"fused.ply is a symbolic link to .*fused.ply"):
        import_scene(src, tmp_path / "ws", roots=roots)
    # without roots (the command line) the same project imports
    import_scene(src, tmp_path / "ws", roots=None)


def test_colmap_image_name_with_markup_is_refused(tmp_path):
    from occufly.io.importer import import_scene
    from tests.recon_builder import make_reconstruction

    src = tmp_path / "recon"
    make_reconstruction(src, depth_maps=False)
    bad = '<iframe srcdoc="x">.png'
    (src / "images" / "img_000.png").rename(src / "images" / bad)
    t = (src / "sparse" / "images.txt").read_text().replace("img_000.png", bad)
    (src / "sparse" / "images.txt").write_text(t)
    with pytest.raises(InputFormatError, match="not allowed in names"):
        import_scene(src, tmp_path / "ws")


def test_metashape_psx_absolute_photo_paths_are_refused(tmp_path):
    """A .psx whose frame.zip gives absolute photo paths outside the roots (the photos
    exist there): refused naming the project, before any photo is opened."""
    import zipfile

    from occufly.io.importer import import_scene
    from tests.harness import shared_data
    from tests.test_io_photogrammetry import _make_psx

    shared_data("metashape-easyidp-wheat-tanashi", "chunk_doc.xml")

    roots = [tmp_path / "imports"]
    photos = tmp_path / "elsewhere" / "photos"
    photos.mkdir(parents=True)
    psx = _make_psx(roots[0] / "proj", photos)
    fz = psx.with_name("wheat.files") / "0" / "0" / "frame.zip"
    with zipfile.ZipFile(fz) as z:
        doc = z.read("doc.xml").decode()
    rel = os.path.relpath(photos, fz.parent)
    doc = doc.replace(f'path="{rel}/', f'path="{photos}/')
    assert f'path="{photos}/' in doc
    with zipfile.ZipFile(fz, "w") as z:
        z.writestr("doc.xml", doc)
    for i in range(138):
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(photos / f"DJI_{i + 1:04d}.JPG", "JPEG")
    with pytest.raises(UnsafePathError, match=r"wheat.psx: image folder .*elsewhere/photos"):
        import_scene(psx, tmp_path / "ws", roots=roots)


def test_project_file_symlinked_out_is_refused(tmp_path):
    """A COLMAP cameras.txt that is a link to a file elsewhere is refused before any reader
    opens it (an error message would otherwise quote its first line)."""
    from occufly.io.importer import import_scene
    from tests.recon_builder import make_reconstruction

    roots = [tmp_path / "imports"]
    src = roots[0] / "recon"
    make_reconstruction(src, depth_maps=False)
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$secret-hash:19000:0:99999:7:::\n")
    (src / "sparse" / "cameras.txt").unlink()
    os.symlink(secret, src / "sparse" / "cameras.txt")
    with pytest.raises(UnsafePathError, match=r"cameras.txt is a symbolic link to .*shadow") as e:
        import_scene(src, tmp_path / "ws", roots=roots)
    assert "secret-hash" not in str(e.value)


def test_workspace_array_symlinked_out_is_refused(env, tmp_path):
    adm = env.bearer("admin")
    src = env.import_root / "arr_src"
    write_tiny_workspace(src)
    rgb = src / "points" / "rgb.npy"
    shutil.move(rgb, tmp_path / "other_rgb.npy")
    os.symlink(tmp_path / "other_rgb.npy", rgb)
    r = _import(env, adm, src, "arr")
    assert r.status_code == 403 and "rgb.npy is a symbolic link" in r.text, r.text


def test_workspace_image_path_with_a_nul_is_403_not_500(env):
    adm = env.bearer("admin")
    src = env.import_root / "nul_src"
    write_tiny_workspace(src)
    _set_image_path(src, "images/img_000.png\x00/etc/passwd")
    r = _import(env, adm, src, "nul")
    assert r.status_code == 403 and "NUL byte" in r.text, (r.status_code, r.text)


def test_served_image_in_the_mask_store_is_404(world):
    """An image path into the data dir outside the workspaces (another scene's stored mask, a
    PNG) is not served: the data dir is no longer a root for frame images."""
    env, hdr, scene, frames = world
    from app.scenes.models import Scene

    blob = env.settings.mask_store_dir / "ab" / "cd" / ("ab" * 32 + ".png")
    blob.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.zeros((48, 64), np.uint8)).save(blob)
    with env.app.state.ctx.sessions() as s:
        ws = Path(s.get(Scene, scene["id"]).workspace)
    img = env.app.state.ctx.load_scene(str(ws)).frames[0].image_path
    p = Path(img) if Path(img).is_absolute() else ws / img
    p.unlink()
    os.symlink(blob, p)
    r = env.client.get(f"/api/frames/{frames[0]['id']}/image", headers=hdr["annotator"])
    assert r.status_code == 404 and "outside the import roots" in r.text, r.text
