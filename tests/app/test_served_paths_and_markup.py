"""Security round two (issue 24): regression tests, each failing before its fix."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image


def _served_path(env, scene: dict, index: int = 0) -> Path:  # noqa: ANN001
    """The image file the workspace names for frame ``index`` (as the server would open it)."""
    from app.scenes.models import Scene

    with env.app.state.ctx.sessions() as s:
        ws = s.get(Scene, scene["id"]).workspace
    f = env.app.state.ctx.load_scene(ws).frames[index]
    p = Path(f.image_path)
    return p if p.is_absolute() else Path(ws) / p


def test_image_symlinked_out_of_the_roots_is_not_served(world, tmp_path):
    """Finding 1: an image that resolves (symlink) outside the import roots and the data dir
    is refused when served; the database file is never served either."""
    env, hdr, scene, frames = world
    secret = tmp_path / "outside" / "secret.png"
    secret.parent.mkdir()
    Image.fromarray(np.full((8, 8, 3), 7, np.uint8)).save(secret)
    p = _served_path(env, scene)
    p.unlink()
    os.symlink(secret, p)
    r = env.client.get(f"/api/frames/{frames[0]['id']}/image", headers=hdr["annotator"])
    assert r.status_code == 404, r.status_code
    assert "outside the import roots" in r.text
    assert r.content != secret.read_bytes()
    db = tmp_path / "occufly.db"
    if db.exists():  # SQLite: the app's own database through a symlink
        p.unlink()
        os.symlink(db, p)
        r = env.client.get(f"/api/frames/{frames[0]['id']}/image", headers=hdr["annotator"])
        assert r.status_code == 404 and b"SQLite format" not in r.content


def test_image_content_type_from_content_with_nosniff(world):
    """Finding 3: the content type comes from the bytes (PNG -> image/png) with nosniff; an
    HTML file where an image should be is not served at all (was text/html)."""
    env, hdr, scene, frames = world
    fid = frames[1]["id"]
    r = env.client.get(f"/api/frames/{fid}/image", headers=hdr["annotator"])
    assert r.status_code == 200
    assert r.headers["content-type"] == "image/png"
    assert r.headers["x-content-type-options"] == "nosniff"
    p = _served_path(env, scene, 1)
    p.write_bytes(b"<html><script>alert(1)</script></html>")
    for size in ("full", "thumb"):
        r = env.client.get(f"/api/frames/{fid}/image?size={size}", headers=hdr["annotator"])
        assert r.status_code == 404, (size, r.status_code)
        assert "text/html" not in r.headers.get("content-type", "")


def test_confined_follows_symlinks(tmp_path):
    from occufly.fsutil import PathNotConfined, confined

    root = tmp_path / "root"
    (root / "a").mkdir(parents=True)
    (tmp_path / "out.txt").write_text("x")
    os.symlink(tmp_path / "out.txt", root / "a" / "link.png")
    assert confined(root / "a", [root]) == (root / "a").resolve()
    for bad in (root / "a" / "link.png", root / ".." / "out.txt", Path("/etc/passwd")):
        try:
            confined(bad, [root])
        except PathNotConfined:
            continue
        raise AssertionError(f"{bad} was not refused")


def test_viewer_markdown_escapes_markup():
    """Finding 2: a frame stem / class name with markup reaches viser's markdown as text."""
    from app.viewer.markdown_escape import md_text

    hostile = '<iframe srcdoc="<script>alert(1)</script>">**x**[a](javascript:1)\n# h'
    out = md_text(hostile)
    for bad in ("<", ">", '"', "**", "](", "\n"):
        assert bad not in out, bad
    assert "&lt;iframe" in out and "alert" in out
