"""Issue 36 (finding 2, 5, 8 and "tests that measure what they claim"): what one upload costs
the SERVER, measured on the server process itself.

The app runs as a child process (tests.harness.ProcessServer, uvicorn, SQLite). Before each
request its high-water mark is reset (``/proc/<pid>/clear_refs`` = 5 sets VmHWM to the
current RSS); after the answer, VmHWM minus that RSS is the request's own peak, whatever the
rest of the test run allocated (``ru_maxrss`` of pytest, which the old tests read, is the
peak of the whole run). CPU is the server's utime + stime over the request. One test per
attack, so a failure names what broke. Target: <= +200 MB per request, whatever the upload
declares."""

from __future__ import annotations

import io
import json
import os
import struct
import threading
import zipfile
import zlib
from pathlib import Path

import httpx
import numpy as np
import pytest

from occufly.io.masks import png_chunk
from tests.app.conftest import PASSWORD, H, W, make_tiny_scene, seed_served_data
from tests.harness import ProcessServer

REPO = Path(__file__).resolve().parents[2]
LIMIT_MB = 200
pytestmark = pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(),
                                reason="needs Linux /proc/<pid>/clear_refs")


def _status_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Server:
    def __init__(self, proc: ProcessServer, token: str, sid: int, frames: list) -> None:
        self.proc, self.sid, self.frames = proc, sid, frames
        self.hdr = {"Authorization": f"Bearer {token}"}
        self.http = httpx.Client(base_url=proc.url, timeout=120)

    def measure(self, send):  # noqa: ANN001, ANN201
        """(response, peak MB over the RSS before, CPU seconds) of ``send(http)``."""
        pid = self.proc.pid
        Path(f"/proc/{pid}/clear_refs").write_text("5")
        base, cpu = _status_kb(pid, "VmRSS"), _cpu_s(pid)
        r = send(self.http)
        return r, (_status_kb(pid, "VmHWM") - base) / 1024, _cpu_s(pid) - cpu

    def import_masks(self, data: bytes, fmt: str, **extra):  # noqa: ANN201
        files = {"archive": ("a.zip", data), **extra.pop("files", {})}
        return self.measure(lambda c: c.post(f"/api/scenes/{self.sid}/masks/import",
                                              headers=self.hdr, data={"format": fmt, **extra},
                                              files=files))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from occufly.io import mask_interchange

    tmp = tmp_path_factory.mktemp("import_memory")
    (tmp / "tmp").mkdir()
    env, sid = seed_served_data(tmp, {"TMPDIR": str(tmp / "tmp")})
    proc = ProcessServer(env, tmp / "server.log", start_timeout=90).start()
    try:
        c = httpx.Client(base_url=proc.url, timeout=30)
        tok = c.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
        assert tok.status_code == 200, tok.text
        srv = Server(proc, tok.json()["token"], sid, make_tiny_scene().frames)
        srv.tmp = tmp
        # warm up: one valid import per format, so the readers' libraries (Datumaro,
        # pycocotools, Label Studio's brush codec) are loaded before anything is measured
        sc = make_tiny_scene()
        mask = np.zeros((H, W), np.uint8)
        mask[: H // 2, : W // 2] = 8
        for k, fmt in enumerate(("cvat_images", "cvat_mask", "coco", "labelstudio", "png")):
            out = tmp / f"warm_{fmt}.zip"
            mask_interchange.write_masks(out, fmt, {k % 4: mask}, sc.frames, sc.taxonomy)
            r, _mb, _cpu = srv.import_masks(out.read_bytes(), fmt)
            assert r.status_code == 200, (fmt, r.text[:500])
        yield srv
    finally:
        proc.stop()


def _zip(files: dict) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for k, v in files.items():
            zf.writestr(k, v)
    return buf.getvalue()


def _held(r, mb: float, cpu: float, *, status=(413, 422), words: str = "", cpu_max: float = 2.0):  # noqa: ANN001
    print(f"MEASURED {os.environ.get('PYTEST_CURRENT_TEST', '').split(' ')[0]}: HTTP "
          f"{r.status_code}, server peak +{mb:.0f} MB, {cpu:.2f} s CPU")
    assert r.status_code in status, (r.status_code, r.text[:400])
    if words:
        assert words in r.text, r.text[:400]
    assert len(r.content) < 20_000
    assert mb <= LIMIT_MB, f"the server's peak grew {mb:.0f} MB"
    assert cpu <= cpu_max, f"{cpu:.1f} s of server CPU"


# ---- finding 2: sizes the upload declares ------------------------------------------------------
def test_coco_rle_declaring_30000_squared(server):
    f = server.frames[0]
    coco = {"images": [{"id": 1, "file_name": f.name, "width": W, "height": H}],
            "categories": [{"id": 1, "name": "tree"}],
            "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "iscrowd": 1,
                             "bbox": [0, 0, 1, 1], "area": 1,
                             "segmentation": {"size": [30000, 30000], "counts": "0QQ1"}}]}
    data = _zip({"annotations/instances_default.json": json.dumps(coco)})
    assert len(data) < 1000
    _held(*server.import_masks(data, "coco"), words="30000x30000")


def _cvat_xml(image_w: int, image_h: int, mask_w: int, mask_h: int) -> str:
    f = make_tiny_scene().frames[0]
    return (f'<?xml version="1.0" encoding="utf-8"?><annotations><version>1.1</version><meta>'
            f'<task><labels><label><name>tree</name><type>any</type><attributes/></label>'
            f'</labels></task></meta><image id="0" name="{f.name}" width="{image_w}" '
            f'height="{image_h}"><mask label="tree" source="manual" occluded="0" '
            f'rle="0, {mask_w * mask_h}" left="0" top="0" width="{mask_w}" '
            f'height="{mask_h}" z_order="0"></mask></image></annotations>')


def test_cvat_mask_declaring_20000_squared_in_a_frame_sized_image(server):
    data = _zip({"annotations.xml": _cvat_xml(W, H, 20000, 20000)})
    _held(*server.import_masks(data, "cvat_images"), words="outside its 64x48 image")


def test_cvat_image_declaring_20000_squared(server):
    data = _zip({"annotations.xml": _cvat_xml(20000, 20000, 20000, 20000)})
    _held(*server.import_masks(data, "cvat_images"), words="20000x20000")


def test_label_studio_brush_of_200_megapixels(server):
    f = server.frames[0]
    n = 14000 * 14000 * 4
    task = [{"data": {"image": f.name}, "annotations": [{"result": [
        {"type": "brushlabels", "original_width": 14000, "original_height": 14000,
         "value": {"format": "rle", "rle": list(n.to_bytes(4, "big")) + [0] * 64,
                   "brushlabels": ["tree"]}}]}]}]
    _held(*server.import_masks(_zip({"tasks.json": json.dumps(task)}), "labelstudio"),
          words="14000")


def _bomb(w: int, h: int) -> bytes:
    from tests.app.test_hardening import bomb

    return bomb(w, h)


def test_png_bomb_with_a_class_map_naming_no_frame(server):
    data = _zip({"nosuchframe.png": _bomb(16000, 12000), "classes.json": '{"1": "tree"}'})
    _held(*server.import_masks(data, "png"))


def test_png_header_of_200_megapixels_in_a_cvat_segmentation_export(server):
    stem = server.frames[0].stem
    data = _zip({"labelmap.txt": "# label:color_rgb:parts:actions\nbackground:0,0,0::\n"
                                 "tree:0,128,0::\n",
                 "ImageSets/Segmentation/default.txt": f"{stem}\n",
                 f"SegmentationClass/{stem}.png": _bomb(16000, 12000)})
    _held(*server.import_masks(data, "cvat_mask"), words="larger than any frame")


def _deflated_member(name: str, chunk: bytes, size: int) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf, \
            zf.open(name, "w", force_zip64=True) as fh:
        for _ in range(size // len(chunk)):
            fh.write(chunk)
    return buf.getvalue()


@pytest.fixture(scope="module")
def whitespace_json():
    data = _deflated_member("tasks.json", b"[" + b" " * ((1 << 20) - 1), 300 << 20)
    assert len(data) < 1 << 20  # 300 MB of whitespace in under 1 MB
    return data


def test_zip_of_whitespace_json(server, whitespace_json):
    _held(*server.import_masks(whitespace_json, "labelstudio"), words="times its size")


def test_json_member_over_its_cap(server):
    """24 MB of whitespace JSON: within the archive's inflation floor, over the 16 MB an
    annotation file may be; refused while it is unpacked, before it is parsed."""
    data = _deflated_member("tasks.json", b"[" + b" " * ((1 << 20) - 1), 24 << 20)
    _held(*server.import_masks(data, "labelstudio"), words="tasks.json")


def test_json_of_a_million_values(server):
    data = _zip({"tasks.json": "[" + "{}," * 1_200_000 + "{}]"})
    _held(*server.import_masks(data, "labelstudio"), words="values")


def test_densest_json_the_caps_let_through(server):
    """Just under the 3 M values cap, all floats: what parsing it costs."""
    body = "[" + "1.5," * 2_990_000 + "1.5]"
    _held(*server.import_masks(_zip({"tasks.json": body}), "labelstudio"),
          words="list of tasks", cpu_max=5.0)


def test_xml_of_the_most_tags_the_caps_let_through(server):
    f = server.frames[0]
    body = (f'<?xml version="1.0"?><annotations><version>1.1</version><meta><task><labels>'
            f'<label><name>tree</name><attributes/></label></labels></task></meta>'
            f'<image id="0" name="{f.name}" width="{W}" height="{H}">'
            + '<a/>' * 990_000 + "</image></annotations>")
    r, mb, cpu = server.import_masks(_zip({"annotations.xml": body}), "cvat_images")
    _held(r, mb, cpu, status=(422,), cpu_max=30.0)


# ---- finding 5: archives unpacked whole --------------------------------------------------------
def test_zip_bomb_of_pngs_is_not_unpacked(server):
    """2 GB of zeros in a 2 MB zip, named like masks: refused on the declared sizes, with no
    byte written (the server's CPU shows no inflation)."""
    data = _deflated_member(f"{server.frames[0].stem}.png", b"\0" * (1 << 20), 2 << 30)
    assert len(data) < 3 << 20
    r, mb, cpu = server.import_masks(data, "png")
    _held(r, mb, cpu, words="times its size", cpu_max=1.0)
    assert not any((server.tmp / "tmp").iterdir())  # nothing left in the server's temp folder


def test_member_lying_about_its_size_is_cut(server):
    """A member whose header declares 100 bytes but inflates to 300 MB is stopped at its
    declared size, not after unpacking it."""
    buf = bytearray(_deflated_member("tasks.json", b" " * (1 << 20), 300 << 20))
    # patch the declared uncompressed size in the local header and the central directory
    for sig, off in ((b"PK\x03\x04", 22), (b"PK\x01\x02", 24)):
        i = buf.find(sig)
        while i >= 0:
            if buf[i + off:i + off + 4] == b"\xff\xff\xff\xff":  # zip64: size in the extra field
                break
            buf[i + off:i + off + 4] = struct.pack("<I", 100)
            i = buf.find(sig, i + 4)
    r, mb, cpu = server.import_masks(bytes(buf), "labelstudio")
    _held(r, mb, cpu, cpu_max=1.0)


def test_zip_of_sixty_thousand_empty_members(server):
    """Refused from the zip's end record, before its directory is parsed or a file is
    written (199,000 members took +218 MB and 28 s of CPU when 200,000 were accepted)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for i in range(60_000):
            zf.writestr(f"{i:x}.json", b"")
    _held(*server.import_masks(buf.getvalue(), "labelstudio"), words="60000 files", cpu_max=1.0)


# ---- finding 8: shapes and CPU -----------------------------------------------------------------
def test_twenty_thousand_small_polygons(server):
    f = server.frames[0]
    shapes = "".join(f'<polygon label="tree" source="manual" occluded="0" z_order="0" '
                     f'points="{x % W},{x % H};{x % W + 1},{x % H};{x % W},{x % H + 1}"/>'
                     for x in range(20_000))
    body = (f'<?xml version="1.0"?><annotations><version>1.1</version><meta><task><labels>'
            f'<label><name>tree</name><attributes/></label></labels></task></meta>'
            f'<image id="0" name="{f.name}" width="{W}" height="{H}">{shapes}</image>'
            f'</annotations>')
    data = _zip({"annotations.xml": body})
    assert len(data) < 100_000
    _held(*server.import_masks(data, "cvat_images"), words="shapes", cpu_max=5.0)


def test_nine_thousand_small_polygons_are_painted_fast(server):
    """Under the shape cap: rasterised within their bounding boxes, not over the frame."""
    f = server.frames[1]
    shapes = "".join(f'<polygon label="tree" source="manual" occluded="0" z_order="0" '
                     f'points="{x % W},{x % H};{x % W + 2},{x % H};{x % W},{x % H + 2}"/>'
                     for x in range(9_000))
    body = (f'<?xml version="1.0"?><annotations><version>1.1</version><meta><task><labels>'
            f'<label><name>tree</name><attributes/></label></labels></task></meta>'
            f'<image id="0" name="{f.name}" width="{W}" height="{H}">{shapes}</image>'
            f'</annotations>')
    r, mb, cpu = server.import_masks(_zip({"annotations.xml": body}), "cvat_images")
    _held(r, mb, cpu, status=(200,), cpu_max=10.0)
    assert r.json()["frames_imported"] == 1


# ---- a mask PUT: a zlib bomb at the frame's size -----------------------------------------------
def test_zlib_bomb_mask_put(server):
    """A frame-sized PNG whose IDAT inflates to 60 MB: the 200 answer stores the frame-sized
    mask (the trailing data never inflated into memory), or it is refused; either way the
    server's own peak stays small."""
    raw = b"".join(b"\0" + b"\x06" * W for _ in range(H)) + b"\0" * (60 << 20)
    zb = (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0))
          + png_chunk(b"IDAT", zlib.compress(raw, 9)) + png_chunk(b"IEND", b""))
    row = server.http.get(f"/api/scenes/{server.sid}/frames", headers=server.hdr).json()[2]
    fid, current = row["id"], row["current_version"]
    r, mb, cpu = server.measure(lambda c: c.put(f"/api/frames/{fid}/mask", content=zb, headers={
        **server.hdr, "If-Match": str(current) if current else "none"}))
    print(f"MEASURED zlib bomb PUT: HTTP {r.status_code}, server peak +{mb:.0f} MB, "
          f"{cpu:.2f} s CPU")
    assert r.status_code in (200, 409, 413, 422), r.text[:300]
    assert mb <= 100, f"the server's peak grew {mb:.0f} MB for a {len(zb)}-byte mask"
    if r.status_code == 200:
        got = server.http.get(f"/api/frames/{fid}/mask", headers=server.hdr)
        from PIL import Image

        assert np.asarray(Image.open(io.BytesIO(got.content))).shape == (H, W)


# ---- concurrent bombs (was tests/app/test_hardening.py, measured with pytest's ru_maxrss) -----
def test_concurrent_png_bombs(server):
    stem = server.frames[0].stem
    data = _zip({f"{stem}.png": _bomb(16000, 12000), "classes.json": '{"1": "tree"}'})
    answers: list = []

    def send(c):  # noqa: ANN001, ANN202
        def one():
            answers.append(c.post(f"/api/scenes/{server.sid}/masks/import", headers=server.hdr,
                                  data={"format": "png"}, files={"archive": ("a.zip", data)}))
        threads = [threading.Thread(target=one) for _ in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        return answers

    _r, mb, cpu = server.measure(send)
    print(f"MEASURED 6 concurrent bombs: {sorted(a.status_code for a in answers)}, server peak "
          f"+{mb:.0f} MB, {cpu:.2f} s CPU")
    assert sorted({a.status_code for a in answers}) in ([422], [422, 429], [429]), \
        [a.text[:200] for a in answers]
    assert any(a.status_code == 422 and "16000x12000" in a.text for a in answers)
    assert mb <= LIMIT_MB and cpu <= 3.0, (mb, cpu)


def test_concurrent_mask_put_bombs(server):
    """Six PNG bombs (30000x30000 grey, 9000x9000 RGB; a few hundred KB each) put at once on
    one frame: all refused from their header, the server's peak stays small."""
    from tests.app.test_hardening import bomb

    fid = server.http.get(f"/api/scenes/{server.sid}/frames", headers=server.hdr).json()[3]["id"]
    bombs = [bomb(30000, 30000, 0), bomb(9000, 9000, 2)] * 3
    answers: list = []

    def send(c):  # noqa: ANN001, ANN202
        def one(data: bytes) -> None:
            answers.append(c.put(f"/api/frames/{fid}/mask", content=data,
                                 headers={**server.hdr, "If-Match": "none",
                                          "Content-Type": "image/png"}))
        threads = [threading.Thread(target=one, args=(d,)) for d in bombs]
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    _r, mb, cpu = server.measure(send)
    print(f"MEASURED 6 concurrent mask PUT bombs: {sorted(a.status_code for a in answers)}, "
          f"server peak +{mb:.0f} MB, {cpu:.2f} s CPU")
    assert len(answers) == 6 and all(a.status_code in (413, 422) for a in answers), \
        [a.text[:200] for a in answers]
    assert mb <= 50 and cpu <= 2.0, (mb, cpu)  # decoding one 30000x30000 bomb needs 900 MB


def test_segmentation_mask_import_on_a_real_server(server):
    """A CVAT Segmentation mask 1.1 import read by a server's worker thread (Datumaro's image
    codec ContextVar was unset there: every such import was a 422 'IMAGE_BACKEND')."""
    from occufly.io import mask_interchange

    sc = make_tiny_scene()
    mask = np.zeros((H, W), np.uint8)
    mask[H // 2:, W // 2:] = 8
    out = server.tmp / "seg.zip"
    mask_interchange.write_masks(out, "cvat_mask", {3: mask}, sc.frames, sc.taxonomy)
    r, _mb, _cpu = server.import_masks(out.read_bytes(), "cvat")
    assert r.status_code == 200 and r.json()["format"] == "cvat_mask", r.text[:400]
