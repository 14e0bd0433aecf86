"""Empty work is not success: lift / agreement / preview with nothing to do say so (exit 2)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from occufly.cli import main
from tests.lift_scene import make_scene, truth_mask


@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    scene, _ = make_scene()
    path = tmp_path_factory.mktemp("empty-work") / "ws"
    scene.save(path)
    return path, scene


def _err(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_lift_with_no_matching_mask(ws, tmp_path, capsys):
    path, scene = ws
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "notes.txt").write_text("no PNG here")
    assert main(["lift", str(path), "--masks", str(masks)]) == 2
    msg = _err(capsys)
    assert str(masks) in msg and "no mask to lift" in msg and f"{scene.frames[0].stem}.png" in msg
    assert not (path / "lifting").exists() or not any((path / "lifting").glob("*labels*"))


def test_lift_with_only_empty_masks(ws, tmp_path, capsys):
    path, scene = ws
    masks = tmp_path / "masks"
    masks.mkdir()
    for f in scene.frames[:2]:
        Image.fromarray(np.zeros((f.camera.height, f.camera.width), np.uint8)).save(masks / f"{f.stem}.png")
    assert main(["lift", str(path), "--masks", str(masks)]) == 2
    msg = _err(capsys)
    assert str(masks) in msg and "all 2 masks are empty" in msg


def test_agreement_with_nothing_to_compare(ws, tmp_path, capsys):
    path, scene = ws
    masks = tmp_path / "masks"
    masks.mkdir()
    f = scene.frames[0]
    Image.fromarray(truth_mask(f)).save(masks / f"{f.stem}.png")
    assert main(["lift", str(path), "--masks", str(masks), "--json"]) == 0
    capsys.readouterr()
    # every mask is of an annotated frame: --held-out leaves nothing
    assert main(["agreement", str(path), "--masks", str(masks), "--held-out"]) == 2
    assert "nothing to compare" in _err(capsys)
    empty = tmp_path / "none"
    empty.mkdir()
    assert main(["agreement", str(path), "--masks", str(empty)]) == 2
    msg = _err(capsys)
    assert str(empty) in msg and "nothing to compare" in msg
    # a mask with no painted pixel: no pixel to compare either, instead of 'null'
    blank = tmp_path / "blank"
    blank.mkdir()
    g = scene.frames[1]
    Image.fromarray(np.zeros((g.camera.height, g.camera.width), np.uint8)).save(blank / f"{g.stem}.png")
    assert main(["agreement", str(path), "--masks", str(blank)]) == 2
    assert "no pixel" in _err(capsys)


def test_preview_default_output_path(tmp_path, capsys):
    import json

    from occufly.export import export_dataset
    from tests.export_fixtures import SPEC, make_workspace

    ws = make_workspace(tmp_path / "exp", n_frames=2)
    out = tmp_path / "dataset"
    export_dataset(ws, out, spec=SPEC, workers=1, frames=[1])
    assert main(["preview", str(out), "--frame", "1", "--height", "64", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    alt = next((out / "OccuFly_Dataset" / "scene_01").glob("*/ground_truth/000001")).parents[1].name
    png = out / "previews" / f"scene_01_{alt}_000001.png"
    assert res["out"] == str(png) and Image.open(png).height > 64
    assert png.stat().st_mode & 0o777 != 0o600  # an ordinary file, not mkstemp's 0600
