"""``occufly masks import`` / ``occufly masks export`` on a workspace (issue 26): masks out to
a tool's format and back in with the same ids, the lifted labels out as a prefill (Label Studio
pre-annotations), and a refused archive writing nothing."""

from __future__ import annotations

import json
import zipfile

import datumaro  # noqa: F401 -- the `masks` extra: scripts/setup.sh installs it (no skip)
import numpy as np
import pytest

from occufly.cli import main
from occufly.io.masks import read_mask, write_mask
from tests.app.conftest import H, W, make_tiny_scene


@pytest.fixture()
def ws(tmp_path):
    scene = make_tiny_scene(4)
    scene.save(tmp_path / "ws")
    masks = tmp_path / "painted"
    masks.mkdir()
    for i, f in enumerate(scene.frames[:3]):
        m = np.zeros((H, W), np.uint8)
        m[:, : W // 2] = 6  # grass
        m[:, W // 2:] = 1 if i != 1 else 33  # road / parking lot
        m[:4, :4] = 255
        write_mask(masks / f"{f.stem}.png", m)
    return tmp_path / "ws", masks, scene


def _run(capsys, *argv) -> tuple[int, dict | str]:
    rc = main([*argv, "--json"])
    out, err = capsys.readouterr()
    return rc, (json.loads(out) if rc == 0 else err)


@pytest.mark.parametrize("fmt", ["cvat", "cvat_mask", "coco", "coco_panoptic", "labelstudio", "png"])
def test_masks_out_and_back_in(ws, tmp_path, capsys, fmt):
    root, painted, scene = ws
    rc, res = _run(capsys, "masks", "export", str(root), str(tmp_path / "x.zip"), "--format", fmt,
                   "--masks", str(painted))
    assert rc == 0, res
    assert res["frames"] == 3 and res["kind"] == "masks"
    rc, res = _run(capsys, "masks", "import", str(root), str(tmp_path / "x.zip"), "--format", fmt,
                   "--out", str(tmp_path / "back"))
    assert rc == 0, res
    assert res["frames_imported"] == 3
    for f in scene.frames[:3]:
        ours = read_mask(painted / f"{f.stem}.png", f, scene.taxonomy)
        back = read_mask(tmp_path / "back" / f"{f.stem}.png", f, scene.taxonomy)
        np.testing.assert_array_equal(back, ours)


def test_prefill_goes_out_as_labelstudio_predictions(ws, tmp_path, capsys):
    from label_studio_converter.brush import decode_rle

    from occufly.lifting import load_labels
    from occufly.render import render_prefill

    root, painted, scene = ws
    rc, res = _run(capsys, "masks", "export", str(root), str(tmp_path / "p.zip"),
                   "--format", "labelstudio", "--prefill")
    assert rc == 2 and "no lifted labels yet" in res  # nothing lifted: nothing to prefill
    assert not (tmp_path / "p.zip").exists()
    assert main(["lift", str(root), "--masks", str(painted)]) == 0
    capsys.readouterr()
    rc, res = _run(capsys, "masks", "export", str(root), str(tmp_path / "p.zip"),
                   "--format", "labelstudio", "--prefill")
    assert rc == 0, res
    assert res["kind"] == "prefill" and res["frames"] == 4
    with zipfile.ZipFile(tmp_path / "p.zip") as zf:
        tasks = json.loads(zf.read("tasks.json"))
        assert b"<BrushLabels" in zf.read("labeling_config.xml")
    labels = load_labels(root).labels
    ids = {c.name: c.id for c in scene.taxonomy.classes}
    for task in tasks:
        fi = scene.frame_index(task["data"]["image"])
        expect, _d, _f = render_prefill(scene, np.asarray(labels), fi)
        assert expect.any()
        got = np.zeros((H, W), np.uint8)
        assert "annotations" not in task and task["predictions"][0]["model_version"]
        for r in task["predictions"][0]["result"]:
            a = np.asarray(decode_rle(r["value"]["rle"]), np.uint8).reshape(H, W, 4)[..., 3]
            got[a > 0] = ids[r["value"]["brushlabels"][0]]
        np.testing.assert_array_equal(got, expect)


def test_refused_archive_writes_nothing(ws, tmp_path, capsys):
    root, painted, scene = ws
    coco = tmp_path / "c" / "annotations"
    coco.mkdir(parents=True)
    doc = {"images": [{"id": 1, "file_name": f"{scene.frames[0].stem}.png", "width": W, "height": H},
                      {"id": 2, "file_name": "elsewhere.png", "width": W, "height": H}],
           "categories": [{"id": 1, "name": "grass"}, {"id": 2, "name": "hedge"}],
           "annotations": [{"id": i + 1, "image_id": img, "category_id": cat, "iscrowd": 0,
                            "bbox": [0, 0, 9, 9], "area": 81,
                            "segmentation": [[0, 0, 9, 0, 9, 9, 0, 9]]}
                           for i, (img, cat) in enumerate([(1, 1), (1, 2), (2, 1)])]}
    (coco / "instances_default.json").write_text(json.dumps(doc))
    rc, err = _run(capsys, "masks", "import", str(root), str(tmp_path / "c"), "--format", "coco",
                   "--out", str(tmp_path / "back"))
    assert rc == 2
    assert "'hedge'" in err and "'elsewhere'" in err and "nothing imported" in err
    assert not (tmp_path / "back").exists()  # checked before anything is written
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"hedge": "vegetation"}))
    rc, err = _run(capsys, "masks", "import", str(root), str(tmp_path / "c"), "--format", "coco",
                   "--map", str(mapping), "--out", str(tmp_path / "back"))
    assert rc == 2 and "'elsewhere'" in err and "hedge" not in err
