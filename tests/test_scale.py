"""Scale machinery: streamed strip fusion, banded rendering, full-size frames, the render cull.

Each piece must give exactly what the all-in-memory path gives; the survey preset itself is
measured by bench/bench_survey.py, not here.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from occufly.synthetic import presets as presets_mod
from occufly.synthetic.flight import make_camera, plan_flight
from occufly.synthetic.fuse import FusedCloud, Samples, SampleSpill, fuse
from occufly.synthetic.generate import full_size_frames, generate
from occufly.synthetic.render import Renderer, render_banded
from occufly.synthetic.world import build_world
from occufly.taxonomy import default_taxonomy


def _random_samples(rng: np.random.Generator, n_frames: int, per_frame: int) -> Samples:
    # clustered points so many cells hold samples of several frames, some straddling strips
    centres = rng.uniform(-20, 20, (400, 3)).astype(np.float32)
    parts = {k: [] for k in ("xyz", "rgb", "cls", "normal", "frame")}
    for f in range(n_frames):
        c = centres[rng.integers(0, len(centres), per_frame)]
        parts["xyz"].append((c + rng.normal(0, 0.4, c.shape)).astype(np.float32))
        parts["rgb"].append(rng.integers(0, 256, (per_frame, 3), dtype=np.uint8))
        parts["cls"].append(rng.integers(1, 6, per_frame).astype(np.uint8))
        parts["normal"].append(rng.normal(0, 1, (per_frame, 3)).astype(np.float16))
        parts["frame"].append(np.full(per_frame, f, np.int32))
    return Samples(**{k: np.concatenate(v) for k, v in parts.items()})


def _same_cloud(a: FusedCloud, b: FusedCloud) -> None:
    for k in ("xyz", "rgb", "normal", "label", "n_samples"):
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert np.array_equal(x, y), k  # bit-identical, not merely close


@pytest.mark.parametrize("n_strips", [1, 3, 17, 160])
def test_strip_fusion_is_identical_to_fusing_at_once(tmp_path, n_strips):
    rng = np.random.default_rng(n_strips)
    s = _random_samples(rng, n_frames=9, per_frame=4000)
    prio = default_taxonomy().priority_lut()
    ref, ref_pairs = fuse(s, 0.3, 9, prio, min_views=2)
    # strips narrower than a voxel (160 over 40 m) force seams carried over several strips
    spill = SampleSpill(tmp_path / "spill", np.linspace(-22, 22, n_strips + 1))
    for f in range(9):
        m = s.frame == f
        spill.add(s.xyz[m], s.rgb[m], s.cls[m], s.normal[m], f, np.arange(int(m.sum())))
    assert spill.n_samples == len(s.xyz)
    got, pairs = spill.fuse(0.3, 9, prio, min_views=2)
    spill.close()
    assert not (tmp_path / "spill").exists()
    _same_cloud(ref, got)
    assert np.array_equal(ref_pairs[0], pairs[0]) and np.array_equal(ref_pairs[1], pairs[1])
    assert len(got.xyz) > 1000


def test_spill_rejects_bad_edges_and_empty(tmp_path):
    with pytest.raises(ValueError, match="increasing"):
        SampleSpill(tmp_path / "a", np.array([0.0, 0.0, 1.0]))
    sp = SampleSpill(tmp_path / "b", np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match="no depth samples"):
        sp.fuse(0.1, 1, default_taxonomy().priority_lut())


def test_banded_render_is_identical_to_one_pass():
    P = presets_mod.PRESETS["tiny"]
    world = build_world(P, 0)
    cam = make_camera(P)
    fr = plan_flight(P, world, cam)[5]
    r = Renderer(world, 0)
    rng_a, rng_b = np.random.default_rng([0, 1, 5]), np.random.default_rng([0, 1, 5])
    a = r.render(cam, fr.T_cam_world, rng_a)
    b = render_banded(r, cam, fr.T_cam_world, rng_b, band_pixels=cam.width * 7)  # 23 bands, last short
    for k in ("rgb", "cls", "inst", "depth", "normal"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert np.array_equal(np.isnan(a.xyz), np.isnan(b.xyz))
    assert np.array_equal(np.nan_to_num(a.xyz), np.nan_to_num(b.xyz))
    # the generators are left in the same state (the depth noise drawn next is the same)
    assert rng_a.random() == rng_b.random()
    with pytest.raises(ValueError, match="rows"):
        r.render(cam, fr.T_cam_world, rng_a, rows=(5, 5))


def test_survey_presets_meet_the_benchmark_scale():
    P = presets_mod.PRESETS["survey"]
    assert (P.full_width, P.full_height) == (5472, 3648) and P.full_frames >= 20
    assert P.full_scale == 12 and P.altitudes == (50, 40, 30)
    cam = make_camera(P)
    assert cam.focal[0] == pytest.approx(304.0) and cam.scaled(12).focal[0] == pytest.approx(3648.0)
    assert cam.scaled(12).width == 5472 and cam.scaled(12).height == 3648
    world = build_world(P, 0)
    n = len(plan_flight(P, world, cam))
    assert n >= 2000
    full = full_size_frames(P, n)
    assert len(full) == 20 and min(full) > 0 and max(full) < n - 1
    half = presets_mod.PRESETS["survey-half"]
    assert 0.4 < len(plan_flight(half, build_world(half, 0), make_camera(half))) / n < 0.6
    # old presets keep their meta.json: no full-size keys in their parameters
    assert "full_frames" not in presets_mod.PRESETS["bench"].to_dict()
    with pytest.raises(ValueError, match="integer multiple"):
        replace(P, full_width=5000)


@pytest.fixture(scope="module")
def tinyfull(tmp_path_factory):
    """``tiny`` with 3 frames at 4x the size, fused in 39 strips."""
    presets_mod.PRESETS["tinyfull"] = replace(presets_mod.PRESETS["tiny"], name="tinyfull",
                                              full_frames=3, full_width=960, full_height=640)
    try:
        out = tmp_path_factory.mktemp("scale") / "tinyfull"
        summary = generate(out, preset="tinyfull", seed=0, strip_samples=20_000)
    finally:
        del presets_mod.PRESETS["tinyfull"]
    return out, summary


def test_full_size_frames_are_written_and_readable(tinyfull):
    import pycolmap
    from PIL import Image

    from occufly.io.colmap_dense import read_depth_map

    out, summary = tinyfull
    meta = json.loads((out / "truth" / "meta.json").read_text())
    assert summary["full_size_frames"] == 3 and summary["full_image_size"] == [960, 640]
    names = meta["full_size_frames"]
    assert len(names) == 3
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    sizes = {c.camera_id: (c.width, c.height) for c in rec.cameras.values()}
    assert sizes == {1: (240, 160), 2: (960, 640)}
    by_name = {im.name: im.camera_id for im in rec.images.values()}
    for d in meta["frames_detail"]:
        cid = 2 if d["name"] in names else 1
        assert d["camera_id"] == cid and by_name[d["name"]] == cid
    for n in names:
        assert Image.open(out / "images" / n).size == (960, 640)
        assert Image.open(out / "truth" / "masks" / (Path(n).stem + ".png")).size == (960, 640)
        dm = read_depth_map(out / "dense" / "stereo" / "depth_maps" / f"{n}.geometric.bin")
        assert dm.shape == (640, 960) and (dm > 0).mean() > 0.5
    # the full-size frames are sampled at the reduced frames' density: each of them contributes
    # about as many fused-point observations as a reduced frame, not 16x as many
    from occufly.io.colmap_dense import read_fused_vis

    off, frames = read_fused_vis(out / "dense" / "fused.ply.vis")
    per_frame = np.bincount(frames, minlength=len(meta["frames_detail"]))
    idx = [d["image_id"] - 1 for d in meta["frames_detail"] if d["name"] in names]
    assert per_frame[idx].max() < 3 * np.median(per_frame)


def test_render_cull_is_exact(tinyfull, tmp_path, monkeypatch):
    """render_labels with the frustum cull forced on gives the same image and depth as a pass
    over every point, on reduced and full-size frames."""
    import occufly.render as R
    from occufly.io.importer import import_scene
    from occufly.scene import Scene

    out, _ = tinyfull
    ws = tmp_path / "ws"
    import_scene(out, ws)
    scene = Scene.load(ws)
    labels = np.load(out / "truth" / "point_labels.npy")
    for f in (0, 6, 17, 30):
        monkeypatch.setattr(R, "_CULL_MIN_POINTS", 10**12)
        a, da = R.render_labels(scene, labels, f)
        monkeypatch.setattr(R, "_CULL_MIN_POINTS", 0)
        cand = R.frustum_candidates(scene, scene.frames[f].camera, scene.frames[f].T_cam_world)
        b, db = R.render_labels(scene, labels, f)
        assert cand is not None and 0 < len(cand) < scene.n_points
        assert np.array_equal(a, b) and np.array_equal(da, db)
        assert (a > 0).mean() > 0.3


def test_too_big_for_the_machine_is_a_clear_error_before_writing(tmp_path, monkeypatch):

    from occufly.errors import OccuflyError
    from occufly.synthetic.generate import estimate_resources

    P = presets_mod.PRESETS["survey"]
    est = estimate_resources(P, 2100, workers=2)
    assert 2e9 < est["memory_bytes"] < 16e9 and est["disk_bytes"] > 5e9
    # memory grows with the workers (one frame render each), disk does not
    assert estimate_resources(P, 2100, workers=1)["memory_bytes"] <= est["memory_bytes"]
    assert estimate_resources(P, 2100, workers=64)["memory_bytes"] > est["memory_bytes"]
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: 1 << 30)
    with pytest.raises(OccuflyError, match=r"needs about .* GB of memory .* 1.0 GB are available; try --workers 1"):
        generate(tmp_path / "s", preset="survey", workers=2)
    assert not any(tmp_path.iterdir())  # nothing written, not even a partial folder

    class Usage:
        free = 1 << 20

    monkeypatch.setattr("shutil.disk_usage", lambda _p: Usage)
    with pytest.raises(OccuflyError, match=r"needs about .* GB of disk .* 0.0 GB free"):
        generate(tmp_path / "t", preset="tiny")
    assert not any(tmp_path.iterdir())


def test_large_frames_render_coarse_and_repeat(tinyfull, tmp_path, monkeypatch):
    """Above COARSE_MIN_PIXELS a frame whose splats would be wide is rendered k x coarser and
    each pixel repeated: same result as rendering the coarse camera, fewer holes than full size."""
    import occufly.render as R
    from occufly.io.importer import import_scene
    from occufly.scene import Scene

    out, _ = tinyfull
    ws = tmp_path / "ws"
    import_scene(out, ws)
    scene = Scene.load(ws)
    labels = np.load(out / "truth" / "point_labels.npy")
    f = scene.frame_index(json.loads((out / "truth" / "meta.json").read_text())["full_size_frames"][0])
    cam = scene.frames[f].camera
    fine, _ = R.render_labels(scene, labels, f)  # 0.6 MP: below the threshold, unchanged path
    monkeypatch.setattr(R, "COARSE_MIN_PIXELS", 0)
    spacing = R.scene_point_spacing(scene)
    k = R._coarsening(scene, cam, scene.frames[f].T_cam_world, spacing, R.SPLAT_FACTOR, None)
    assert k >= 2
    got, depth = R.render_labels(scene, labels, f)
    assert got.shape == fine.shape == (cam.height, cam.width) and depth.shape == got.shape
    small, _ = R._render(scene, labels, scene.frames[f], cam.scaled(1.0 / k), spacing, R.SPLAT_FACTOR,
                         3.0, 500_000, None)
    assert np.array_equal(got, R._upsample(small, k, cam.height, cam.width))
    assert (got > 0).mean() > (fine > 0).mean()  # the surfaces close
    agree = (got == fine) & (fine > 0)
    assert agree.sum() / (fine > 0).sum() > 0.85
