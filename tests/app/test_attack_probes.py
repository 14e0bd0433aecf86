"""The attack round after issue 24's fixes -- paths from files, sizes a client controls and
values leaving as HTML that the issue did not list -- one test per probe, so a failure names
the probe (issue 36). Each probe asserts what it claims: a path probe that the import is
refused (or, where the path stays inside the source, that nothing outside is read); a size
probe a 4xx (a bomb counts as held only when it is refused, never on a 200) and, where it is
about memory, the server process's own peak for that request (the app in a child process,
its high-water mark reset before the request: tests/app/test_import_memory.py); an HTML probe
the headers it names. Paths and HTML on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import os
import shutil
import struct
import zlib

import pytest
from fastapi.testclient import TestClient

from occufly.io.masks import png_chunk as chunk
from tests.app.conftest import H, W, write_tiny_workspace
from tests.app.test_import_memory import server  # noqa: F401 - the child-process server


# ---- paths from files -----------------------------------------------------------------------
class Importer:
    def __init__(self, env) -> None:  # noqa: ANN001
        self.env = env
        self.adm = env.bearer("admin")
        self.c = TestClient(env.app, raise_server_exceptions=False)

    def workspace(self, name: str):  # noqa: ANN201
        src = self.env.import_root / name
        write_tiny_workspace(src)
        return src

    def run(self, src, **kw) -> tuple:  # noqa: ANN001
        """(HTTP status, detail) when refused at once, else (job status, job message)."""
        r = self.c.post("/api/scenes/import", json={"name": src.name, "source": str(src), **kw},
                        headers=self.adm)
        if r.status_code != 202:
            return r.status_code, r.text
        self.env.app.state.ctx.jobs.wait(r.json()["id"], timeout=60)
        j = self.c.get(f"/api/jobs/{r.json()['id']}", headers=self.adm).json()
        return j["status"], j["message"]

    def with_image_path(self, name: str, image_path: str) -> tuple:
        src = self.workspace(name)
        doc = json.loads((src / "scene.json").read_text())
        doc["frames"][0]["image_path"] = image_path
        (src / "scene.json").write_text(json.dumps(doc))
        return self.run(src)


@pytest.fixture
def imp(env) -> Importer:
    return Importer(env)


REFUSED = (403, 422, "failed")


def test_path_taxonomy_json_symlinked_to_etc_passwd(imp):
    src = imp.workspace("tax")
    (src / "taxonomy.json").unlink()
    os.symlink("/etc/passwd", src / "taxonomy.json")
    st = imp.run(src)
    assert st[0] in REFUSED and "root:" not in st[1], st


def test_path_scene_json_symlinked_out(imp, tmp_path):
    src = imp.workspace("hdr")
    shutil.move(src / "scene.json", tmp_path / "scene.json")
    os.symlink(tmp_path / "scene.json", src / "scene.json")
    st = imp.run(src)
    assert st[0] in REFUSED, st


def test_path_images_folder_symlinked_out(imp, tmp_path):
    src = imp.workspace("imgdir")
    shutil.move(src / "images", tmp_path / "images")
    os.symlink(tmp_path / "images", src / "images")
    st = imp.run(src)
    assert st[0] in REFUSED, st


@pytest.mark.parametrize("path", ["/dev/zero", "/proc/self/environ", "/etc/passwd"])
def test_path_image_path_to_a_system_file(imp, path):
    st = imp.with_image_path("sys" + str(abs(hash(path)) % 1000), path)
    assert st[0] in (403, 422) and path in st[1], st


def test_path_image_path_file_url_stays_inside_the_source(imp):
    """``file:///etc/passwd`` is a relative name under the source folder (no such file): the
    import must not read /etc/passwd -- refused, or imported with the frame's image missing."""
    st = imp.with_image_path("fileurl", "file:///etc/passwd")
    if st[0] == "done":
        c, hdr = imp.c, imp.adm
        sid = c.get("/api/scenes", headers=hdr).json()[-1]["id"]
        fid = c.get(f"/api/scenes/{sid}/frames", headers=hdr).json()[0]["id"]
        r = c.get(f"/api/frames/{fid}/image", headers=hdr)
        assert r.status_code == 404 and b"root:" not in r.content, r.text[:200]
    else:
        assert st[0] in (403, 422), st


def test_path_image_path_with_nul(imp):
    st = imp.with_image_path("nul", "images/img_000.png\x00/etc/passwd")
    assert st[0] in (403, 422) and "NUL" in st[1], st


def test_path_source_folder_symlinked_out(imp, tmp_path):
    tgt = tmp_path / "ws_out"
    write_tiny_workspace(tgt)
    os.symlink(tgt, imp.env.import_root / "link_ws")
    st = imp.run(imp.env.import_root / "link_ws")
    assert st[0] in (403, 422), st


def test_path_colmap_depth_map_symlinked_out(imp, tmp_path):
    from tests.recon_builder import make_reconstruction

    src = imp.env.import_root / "recon_d"
    make_reconstruction(src, depth_maps=True)
    dm = sorted((src / "dense" / "stereo" / "depth_maps").iterdir())[0]
    shutil.move(dm, tmp_path / dm.name)
    os.symlink(tmp_path / dm.name, dm)
    st = imp.run(src)
    assert st[0] == "failed" and "symbolic link" in st[1], st


def test_path_metashape_photo_path_leading_out_of_the_roots(imp, tmp_path):
    from tests.harness import shared_data
    from tests.test_io_photogrammetry import _make_psx

    shared_data("metashape-easyidp-wheat-tanashi", "chunk_doc.xml")  # fails (never skips) without it
    photos = tmp_path / "far" / "photos"
    photos.mkdir(parents=True)
    psx = _make_psx(imp.env.import_root / "proj", photos)  # a relative path leading out
    st = imp.run(psx, format="metashape")
    assert st[0] == "failed" and "outside the import roots" in st[1], st


# ---- sizes ------------------------------------------------------------------------------------
def test_size_review_item_body_of_70_mb(world):
    env, hdr, scene, _frames = world
    r = env.client.post(f"/api/scenes/{scene['id']}/review-items",
                        content=b"{" + b" " * (70 << 20) + b"}",
                        headers={**hdr["reviewer"], "content-type": "application/json"})
    assert r.status_code == 413, r.text[:200]


def test_size_body_of_5_mb_on_a_get(world):
    env, hdr, _scene, _frames = world
    r = env.client.request("GET", "/api/scenes", content=b"x" * (5 << 20), headers=hdr["admin"])
    assert r.status_code == 413, r.text[:200]


def test_size_corrections_body_over_12_bytes_a_point(world):
    env, hdr, scene, _frames = world
    r = env.client.post(f"/api/scenes/{scene['id']}/corrections",
                        content=b"{" + b" " * (400 * 12 + 70000) + b"}",
                        headers={**hdr["reviewer"], "content-type": "application/json"})
    assert r.status_code == 413, r.text[:200]


def _frame_and_version(server):  # noqa: ANN001, ANN202, F811
    row = server.http.get(f"/api/scenes/{server.sid}/frames", headers=server.hdr).json()[1]
    return row["id"], (str(row["current_version"]) if row["current_version"] else "none")


def _put(server, data: bytes):  # noqa: ANN001, ANN202, F811
    fid, ver = _frame_and_version(server)
    r, mb, cpu = server.measure(lambda c: c.put(f"/api/frames/{fid}/mask", content=data,
                                                 headers={**server.hdr, "If-Match": ver}))
    print(f"MEASURED {len(data)} B mask PUT: HTTP {r.status_code}, server peak +{mb:.0f} MB, "
          f"{cpu:.2f} s CPU")
    return r, mb


def test_size_mask_png_declaring_60000_squared(server):  # noqa: F811
    bomb = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 100000)) + chunk(b"IEND", b""))
    r, mb = _put(server, bomb)
    assert r.status_code in (413, 422), r.text[:200]
    assert mb <= 20, f"the server's peak grew {mb:.0f} MB"


def test_size_zlib_bomb_at_the_frame_size_is_refused(server):  # noqa: F811
    """A frame-sized PNG whose IDAT inflates to 60 MB (the image, then 60 MB more): refused
    (4xx) -- a 200 would not count as held -- without inflating it."""
    raw = b"".join(b"\0" + b"\x06" * W for _ in range(H)) + b"\0" * (60 << 20)
    zb = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0))
          + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))
    r, mb = _put(server, zb)
    assert 400 <= r.status_code < 500, r.text[:200]
    assert mb <= 20, f"the server's peak grew {mb:.0f} MB"


def test_size_mask_with_2000_text_chunks_is_stored_without_them(server):  # noqa: F811
    """Not a bomb: a valid mask with 2,000 tEXt chunks (31 KB) is stored canonically, without
    the chunks (or refused)."""
    z = zlib.compress(b"".join(b"\0" + b"\x06" * W for _ in range(H)))
    many = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0))
            + b"".join(chunk(b"tEXt", b"k\0" + b"v" * 10) for _ in range(2000))
            + chunk(b"IDAT", z) + chunk(b"IEND", b""))
    r, mb = _put(server, many)
    assert r.status_code in (409, 413, 422) or (
        r.status_code == 200 and r.json()["size_bytes"] < 1000), r.text[:200]
    assert mb <= 20


# ---- values leaving as HTML ----------------------------------------------------------------------
def test_html_preview_download_headers(world):
    env, hdr, _scene, frames = world
    r = env.client.get(f"/api/frames/{frames[0]['id']}/image?download=1&size=preview",
                       headers=hdr["annotator"])
    assert r.status_code == 200
    assert "sandbox" in r.headers.get("content-security-policy", "")
    assert r.headers.get("content-disposition", "").startswith("attachment")


def test_html_422_echo_of_a_script_tag_in_the_path(world):
    env, hdr, _scene, _frames = world
    r = env.client.get("/api/frames/%3Cscript%3E/image", headers=hdr["annotator"])
    assert r.status_code == 422
    assert r.headers["content-type"].startswith("application/json")
    assert r.headers.get("x-content-type-options") == "nosniff"


def test_html_413_answer_is_json(world):
    env, _hdr, _scene, _frames = world
    r = env.client.post("/api/auth/login", content=b"{" + b" " * (2 << 20) + b"}",
                        headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert r.headers["content-type"].startswith("application/json")
    assert r.headers.get("x-content-type-options") == "nosniff"
