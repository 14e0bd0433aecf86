"""Masks in and out of CVAT / COCO / Label Studio / PNG (occufly.io.mask_interchange, issue 26).

Round trips: our masks -> our exporter -> read by the format's own library (Datumaro,
pycocotools, Label Studio's brush codec; not by our reader) -> identical raw class ids; and
back through our importer. Archives written by Datumaro's own CVAT writer and by pycocotools
(polygons and RLE) import; unknown classes and unmatched images are one error, nothing read.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import datumaro  # noqa: F401 -- the `masks` extra: scripts/setup.sh installs it (no skip)
import numpy as np
import pytest

from occufly.camera import Camera
from occufly.errors import MaskError
from occufly.io import mask_interchange as mi
from occufly.scene import Frame
from occufly.taxonomy import default_taxonomy
from tests.mask_archives import datumaro_cvat_archive

W, H = 48, 32
TAX = default_taxonomy()
NAMES = {c.id: c.name for c in TAX.classes}
ROUND_TRIP_FORMATS = ("cvat_images", "cvat_mask", "coco", "coco_panoptic", "labelstudio", "png")


def _frames(n: int = 3) -> list[Frame]:
    cam = Camera("PINHOLE", W, H, np.array([50.0, 50.0, W / 2, H / 2]))
    return [Frame(name=f"DJI_{i:04d}.JPG", camera=cam, T_cam_world=np.eye(4)) for i in range(n)]


def _masks() -> dict[int, np.ndarray]:
    """Non-contiguous ids (1, 6, 16, 33, 36), an ignore region, an unpainted frame."""
    out = {}
    for i in range(3):
        m = np.zeros((H, W), np.uint8)
        m[:10] = 1
        m[10:20, 5 + i:30] = 16
        m[25:, :] = 36
        m[20:25, 40:] = 33
        m[0:5, 40:] = 255 if i == 1 else 6
        out[i] = m
    out[2][:] = 0
    return out


def _unzip(path: Path, dest: Path) -> Path:
    with zipfile.ZipFile(path) as zf:
        zf.extractall(dest)
    return dest


def _third_party_read(fmt: str, root: Path) -> dict[str, np.ndarray]:
    """{image stem: raw ids} read by the format's own library from an extracted archive."""
    name_to_id = {**{n: i for i, n in NAMES.items()}, "ignore": 255}
    out: dict[str, np.ndarray] = {}
    if fmt == "coco":
        from pycocotools.coco import COCO

        coco = COCO(str(root / "annotations" / "instances_default.json"))
        for img in coco.imgs.values():
            m = np.zeros((img["height"], img["width"]), np.uint8)
            for ann in coco.loadAnns(coco.getAnnIds(imgIds=img["id"])):
                m[coco.annToMask(ann).astype(bool)] = name_to_id[coco.cats[ann["category_id"]]["name"]]
            out[Path(img["file_name"]).stem] = m
        return out
    if fmt == "labelstudio":
        from label_studio_converter.brush import decode_rle

        for task in json.loads((root / "tasks.json").read_text()):
            stem = Path(task["data"]["image"]).stem
            m = np.zeros((H, W), np.uint8)
            for ann in task["annotations"]:
                for r in ann["result"]:
                    rgba = np.asarray(decode_rle(r["value"]["rle"]), np.uint8).reshape(
                        r["original_height"], r["original_width"], 4)
                    m[rgba[..., 3] > 0] = name_to_id[r["value"]["brushlabels"][0]]
            out[stem] = m
        return out
    if fmt == "png":
        from PIL import Image

        classes = json.loads((root / "classes.json").read_text())
        for p in sorted(root.glob("*.png")):
            arr = np.asarray(Image.open(p))
            assert set(np.unique(arr).tolist()) <= {int(k) for k in classes}
            out[p.stem] = arr.astype(np.uint8)
        return out
    import datumaro as dm
    from datumaro.components.annotation import AnnotationType

    if fmt == "cvat_images":
        # Datumaro's CVAT reader insists on the images (CVAT's "with images" export has them)
        from PIL import Image

        (root / "images").mkdir(exist_ok=True)
        for i in range(3):
            Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(root / "images" / f"DJI_{i:04d}.JPG",
                                                                format="JPEG")
    if fmt == "coco_panoptic":
        (root / "images").mkdir(exist_ok=True)  # Datumaro's COCO reader wants the folder
    ds = dm.Dataset.import_from(str(root), {"cvat_images": "cvat", "cvat_mask": "voc_segmentation",
                                            "coco_panoptic": "coco_panoptic"}[fmt])
    labels = ds.categories()[AnnotationType.label]
    for item in ds:
        m = np.zeros((H, W), np.uint8)
        for ann in item.annotations:
            if ann.type == AnnotationType.mask:
                name = labels[ann.label].name
                m[np.asarray(ann.image, bool)] = 0 if name == "background" else name_to_id[name]
        out[item.id] = m
    return out


@pytest.mark.parametrize("fmt", ROUND_TRIP_FORMATS)
def test_round_trip_through_the_formats_own_reader(fmt, tmp_path):
    frames, masks = _frames(), _masks()
    archive = tmp_path / f"out_{fmt}.zip"
    summary = mi.write_masks(archive, fmt, masks, frames, TAX)
    assert summary["frames"] == 3 and summary["annotated_frames"] == 2
    theirs = _third_party_read(fmt, _unzip(archive, tmp_path / "x"))
    for fi in (0, 1):
        np.testing.assert_array_equal(theirs[frames[fi].stem], masks[fi], err_msg=fmt)
    assert not theirs.get("DJI_0002", np.zeros(1)).any()  # the unpainted frame stays unpainted
    back = mi.read_masks(archive, "cvat" if fmt.startswith("cvat") else fmt, frames, TAX)
    assert sorted(back.masks) == [0, 1]
    for fi in (0, 1):
        np.testing.assert_array_equal(back.masks[fi], masks[fi], err_msg=fmt)
    assert back.classes["ignore"] == 255 and back.classes["truck"] == 36


def test_downscaled_masks_are_written_at_the_image_size(tmp_path):
    frames = _frames()
    small = {0: _masks()[0][::2, ::2]}
    mi.write_masks(tmp_path / "a.zip", "coco", small, frames, TAX)
    back = mi.read_masks(tmp_path / "a.zip", "coco", frames, TAX)
    np.testing.assert_array_equal(back.masks[0], np.repeat(np.repeat(small[0], 2, 0), 2, 1))


def _datumaro_cvat_archive(tmp_path: Path, labels: list[str], image_names: list[str]) -> Path:
    return datumaro_cvat_archive(tmp_path / "datumaro_cvat.zip", labels, image_names, (H, W))


def test_archive_written_by_datumaros_cvat_writer_imports(tmp_path):
    frames = _frames()
    archive = _datumaro_cvat_archive(tmp_path, ["Road", "Vehicle"], ["DJI_0000.JPG", "DJI_0002.JPG"])
    res = mi.read_masks(archive, "cvat", frames, TAX)
    assert res.fmt == "cvat_images" and res.tool == "CVAT" and sorted(res.masks) == [0, 2]
    expect = np.zeros((H, W), np.uint8)
    from pycocotools import mask as mask_utils

    poly = mask_utils.decode(mask_utils.merge(mask_utils.frPyObjects(
        [[0, 0, 24, 0, 24, 16, 0, 16]], H, W))).astype(bool)
    expect[poly] = 1  # "Road" -> road (case does not matter)
    expect[4:12, 20:40] = 13  # the mask is on top (z_order 1): "Vehicle" -> vehicle
    np.testing.assert_array_equal(res.masks[0], expect)
    assert res.classes == {"Road": 1, "Vehicle": 13}


def test_coco_written_by_pycocotools_with_polygons_and_rle(tmp_path):
    from pycocotools import mask as mask_utils

    frames = _frames()
    m = np.zeros((H, W), np.uint8, order="F")
    m[10:30, 30:46] = 1
    rle = mask_utils.encode(np.asfortranarray(m))
    rle["counts"] = rle["counts"].decode()
    doc = {"images": [{"id": 7, "file_name": "subdir/DJI_0001.JPG", "width": W, "height": H}],
           "categories": [{"id": 3, "name": "car"}, {"id": 9, "name": "grass"}],
           "annotations": [
               {"id": 1, "image_id": 7, "category_id": 9, "iscrowd": 0, "area": 100,
                "bbox": [0, 0, 20, 20], "segmentation": [[0, 0, 20, 0, 20, 20, 0, 20]]},
               {"id": 2, "image_id": 7, "category_id": 3, "iscrowd": 1, "area": 320,
                "bbox": [30, 10, 16, 20], "segmentation": rle}]}
    (tmp_path / "c" / "annotations").mkdir(parents=True)
    (tmp_path / "c" / "annotations" / "instances_default.json").write_text(json.dumps(doc))
    mapping = tmp_path / "map.yaml"
    mapping.write_text("car: vehicle\n")
    res = mi.read_masks(tmp_path / "c", "coco", frames, TAX, class_map=mi.load_class_map(mapping))
    got = res.masks[1]
    assert (got[10:30, 30:46] == 13).all()  # RLE, mapped car -> vehicle
    assert (got[1:19, 1:19] == 6).all() and got[25, 5] == 0  # the polygon, rasterised


def test_unknown_classes_and_unmatched_images_are_one_error(tmp_path):
    frames = _frames()
    archive = _datumaro_cvat_archive(tmp_path, ["lamp post", "Vehicle"],
                                     ["DJI_0000.JPG", "nosuch_1.JPG", "nosuch_2.JPG"])
    with pytest.raises(mi.MaskImportError) as e:
        mi.read_masks(archive, "cvat", frames, TAX)
    msg = str(e.value)
    assert "nothing imported" in msg and "'lamp post'" in msg
    assert "'nosuch_1'" in msg and "'nosuch_2'" in msg and "2 image(s) name no frame" in msg
    assert len(e.value.problems) == 2
    # a mapping names the missing class; a bad target is reported too
    with pytest.raises(mi.MaskImportError, match="'pole' names no class"):
        mi.read_masks(archive, "cvat", frames, TAX, class_map={"lamp post": "pole"})


def test_labelstudio_brush_and_polygon_export_imports(tmp_path):
    from label_studio_converter.brush import mask2rle

    frames = _frames()
    brush = np.zeros((H, W), np.uint8)
    brush[0:8, 0:8] = 255
    task = {"id": 5, "data": {"image": "/data/upload/3/0a1b2c3d-DJI_0002.JPG"}, "annotations": [
        {"id": 1, "was_cancelled": True, "result": []},
        {"id": 2, "updated_at": "2026-12-01T10:00:00Z", "result": [
            {"type": "polygonlabels", "original_width": W, "original_height": H,
             "value": {"points": [[50, 50], [100, 50], [100, 100], [50, 100]],
                       "polygonlabels": ["Water"]}},
            {"type": "brushlabels", "original_width": W, "original_height": H,
             "value": {"format": "rle", "rle": [int(v) for v in mask2rle(brush)],
                       "brushlabels": ["tree"]}}]}]}
    path = tmp_path / "export.json"
    path.write_text(json.dumps([task]))
    res = mi.read_masks(path, "labelstudio", frames, TAX)
    m = res.masks[2]  # the upload prefix 0a1b2c3d- is Label Studio's, not the frame's
    assert (m[0:8, 0:8] == 8).all() and (m[17:31, 25:47] == 14).all() and m[12, 12] == 0


def test_labelstudio_brush_decoders_agree_and_a_lying_header_is_refused(tmp_path):
    from label_studio_converter.brush import decode_rle, mask2rle

    frames = _frames()
    m = _masks()[0]
    rle = [int(v) for v in mask2rle(((m == 16) * 255).astype(np.uint8))]
    ours = mi._brush_decoder()(rle)  # the Rust port when installed
    np.testing.assert_array_equal(ours, np.asarray(decode_rle(rle), np.uint8))
    big = W * 1000
    lying = list((big * H * 4).to_bytes(4, "big")) + rle[4:]  # claims a 48000 x 32 stroke
    task = {"data": {"image": "DJI_0000.JPG"}, "annotations": [{"result": [
        {"type": "brushlabels", "original_width": W, "original_height": H,
         "value": {"format": "rle", "rle": lying, "brushlabels": ["road"]}}]}]}
    (tmp_path / "t.json").write_text(json.dumps([task]))
    with pytest.raises(mi.MaskImportError, match="brush RLE declares"):
        mi.read_masks(tmp_path / "t.json", "labelstudio", frames, TAX)
    task["annotations"][0]["result"][0].update(original_width=W * 3, original_height=H * 2)
    (tmp_path / "t.json").write_text(json.dumps([task]))
    with pytest.raises(mi.MaskImportError, match="expected 48x32"):
        mi.read_masks(tmp_path / "t.json", "labelstudio", frames, TAX)


def test_png_with_a_colour_class_map(tmp_path):
    from PIL import Image

    frames = _frames()
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, :10] = (10, 20, 30)
    rgb[:, 10:20] = (200, 0, 0)
    d = tmp_path / "p"
    d.mkdir()
    Image.fromarray(rgb).save(d / "DJI_0001.png")
    (d / "labelmap.txt").write_text("# label:color_rgb:parts:actions\nbackground:0,0,0::\n"
                                    "asphalt:10,20,30::\nhouse:200,0,0::\n")
    with pytest.raises(mi.MaskImportError, match="'asphalt', 'house'"):
        mi.read_masks(d, "png", frames, TAX)
    res = mi.read_masks(d, "png", frames, TAX, class_map={"asphalt": "road", "house": 16})
    assert (res.masks[1][:, :10] == 1).all() and (res.masks[1][:, 10:20] == 16).all()
    assert (res.masks[1][:, 20:] == 0).all()


def test_damaged_and_unsafe_archives_are_refused(tmp_path):
    frames = _frames()
    bad = tmp_path / "slip.zip"
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr("../evil.json", "[]")
    with pytest.raises(MaskError, match="outside the archive"):
        mi.read_masks(bad, "labelstudio", frames, TAX)
    with pytest.raises(MaskError, match="not a COCO instances export"):
        mi.read_masks(_empty_dir(tmp_path), "coco", frames, TAX)
    plain = tmp_path / "plain.zip"
    with zipfile.ZipFile(plain, "w") as zf:
        zf.writestr("readme.txt", "no annotations here")
    with pytest.raises(MaskError) as e:
        mi.read_masks(plain, "cvat", frames, TAX)
    assert str(e.value).startswith("plain.zip: neither a CVAT")  # not the unpacked temp folder
    with pytest.raises(MaskError, match="already exists"):
        mi.write_masks(bad, "coco", _masks(), frames, TAX)


def test_a_damaged_mask_inside_an_archive_is_a_user_error(tmp_path):
    frames = _frames()
    good = tmp_path / "seg.zip"
    mi.write_masks(good, "cvat_mask", _masks(), frames, TAX)
    bad = tmp_path / "seg_bad.zip"
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(bad, "w") as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "SegmentationClass/DJI_0001.png":
                data = data[:40]  # cut off inside the image data
            dst.writestr(info, data)
    with pytest.raises(MaskError, match="DJI_0001"):
        mi.read_masks(bad, "cvat", frames, TAX)


def _empty_dir(tmp_path: Path) -> Path:
    d = tmp_path / "empty"
    d.mkdir()
    return d
