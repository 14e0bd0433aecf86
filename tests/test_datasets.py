"""Datasets researchers train on: the OccuFly layout read with the official loading rules, the
SSCBench layout read by a minimal KITTI-360-style loader, the LMSCNet downsampling rule, the
occufly.datasets reader round trip and eval-ssc on predictions in either layout."""

from __future__ import annotations

import glob
import json
import math
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from occufly.camera import Camera
from occufly.datasets import open_dataset
from occufly.export import export_dataset
from occufly.export.common import lmscnet_pool
from occufly.sampling import FrameGridSpec, sample_frame
from occufly.scene import Scene
from occufly.taxonomy import default_taxonomy
from tests.export_fixtures import SPEC, make_grid, make_workspace

TAX = default_taxonomy()


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Path:
    return make_workspace(tmp_path_factory.mktemp("dsws"), n_frames=4)


@pytest.fixture(scope="module")
def ssc(ws, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dsssc") / "ssc"
    export_dataset(ws, out, spec=SPEC, workers=1, layout="sscbench", velodyne=True,
                   downsample_rule="lmscnet")
    return out


@pytest.fixture(scope="module")
def occ(ws, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dsocc") / "occ"
    export_dataset(ws, out, spec=SPEC, workers=1)
    return out


# ---- the official OccuFly loading rules (visualize_gt.py, as FORMATS.md section 3 documents) ---
def official_load_label(path: str, shape=(192, 128, 128)) -> np.ndarray:
    return np.fromfile(path, dtype=np.uint8).reshape(shape)


def official_load_mask(path: str, shape=(192, 128, 128)) -> np.ndarray:
    n = int(np.prod(shape))
    return np.unpackbits(np.fromfile(path, dtype=np.uint8))[:n].reshape(shape)


def official_reshape_depth(d: np.ndarray) -> np.ndarray:
    if d.ndim == 2:
        return d
    for h, w in ((912, 1368), (576, 864)):
        if d.size == h * w:
            return d.reshape(h, w)
    h = int(math.sqrt(d.size * 3 / 4))
    return d.reshape(h, d.size // h)  # fails unless the map is 4:3


def official_voxels(label: np.ndarray, r: float) -> np.ndarray:
    """Occupied voxel centres as the visualizer draws them: label > 0, indices shifted by
    (96, 64, 0)."""
    idx = np.argwhere(label > 0)
    return (idx - np.array([96, 64, 0]) + 0.5) * r


def test_occufly_layout_with_the_official_loading_rules(ws, tmp_path):
    out = tmp_path / "official"
    spec = FrameGridSpec(voxel_size=1.0, near=1.0)  # the official 192 x 128 x 128 grid
    export_dataset(ws, out, spec=spec, workers=1, frames=[0, 1])
    scene = Scene.load(ws)
    sd = out / "OccuFly_Dataset" / "scene_01"
    assert not list(sd.glob("*/calibration.txt"))  # scene level only
    cal_lines = (sd / "calibration.txt").read_text().splitlines()
    cal = np.loadtxt(sd / "calibration.txt")
    assert cal.shape == (6,) and tuple(cal) == (40.0, 40.0, 32.0, 24.0, 64, 48)
    assert "# depth_maps: 12 16" in [ln.split("  (")[0] for ln in cal_lines]
    manifest = json.loads((sd / "manifest.json").read_text())
    assert manifest["depth_map_shape"] == [12, 16] and manifest["split"] == "train"
    for i in (0, 1):
        fr = scene.frames[i]
        fid = f"{i:06d}"
        base = sd / str(fr.nominal_altitude)
        gtd = base / "ground_truth" / fid
        label = official_load_label(str(gtd / f"{fid}.label"))
        expect = sample_frame(make_grid(), fr.camera, fr.T_cam_world, scene.origin, spec)
        assert np.array_equal(label, expect.label_with_invalid())
        for m in ("invalid", "occluded", "surface"):
            assert np.array_equal(official_load_mask(str(gtd / f"{fid}.{m}")).astype(bool), getattr(expect, m))
        # the visualizer's camera-centred voxel centres are our frame-grid convention
        pts = official_voxels(np.where(label == 255, 0, label), 1.0)
        assert len(pts) > 1000 and pts[:, 2].min() > 0
        uv, z = fr.camera.project(pts)
        assert np.mean(fr.camera.in_image(uv) & (z > 0)) > 0.99
        depth = official_reshape_depth(np.load(base / "depth_maps" / f"{fid}.npy"))
        assert depth.shape == (12, 16) == tuple(manifest["frames"][fid]["depth_shape"])
        assert np.count_nonzero(depth) > 100
        with open(base / "preprocess" / f"{fid}.pkl", "rb") as fh:
            pkl = pickle.load(fh)
        assert pkl["1_8"].shape == (24, 16, 16) and pkl["1_16"].shape == (12, 8, 8)
    assert (out / "OccuFly_Dataset" / "splits" / "train.txt").read_text() == "scene_01\n"
    assert (out / "OccuFly_Dataset" / "splits" / "test.txt").read_text() == ""


def test_non_4_3_depth_needs_the_recorded_shape(tmp_path):
    # 16:9 images: the visualizer's 4:3 fallback cannot reshape these
    wide = Camera("PINHOLE", 64, 36, [40.0, 40.0, 32.0, 18.0])
    ws = workspace_with_cameras(tmp_path / "w169", 2, {0: wide, 1: wide})
    out = tmp_path / "o169"
    export_dataset(ws, out, spec=SPEC, workers=1, scene_id="scene_08")
    d = np.load(out / "OccuFly_Dataset/scene_08/50/depth_maps/000000.npy")
    assert d.ndim == 1 and d.size == 16 * 9
    with pytest.raises(ValueError):
        official_reshape_depth(d)
    from occufly.export.occufly import read_calibration

    cal = read_calibration(out / "OccuFly_Dataset/scene_08/calibration.txt")
    assert cal["depth_shape"] == (9, 16) and (cal["width"], cal["height"]) == (64, 36)
    assert d.reshape(cal["depth_shape"]).shape == (9, 16)
    assert (out / "OccuFly_Dataset/splits/test.txt").read_text() == "scene_08\n"  # release rule


def workspace_with_cameras(root: Path, n_frames: int, cameras: dict[int, Camera]) -> Path:
    """The export fixture's workspace with some frames' cameras replaced."""
    ws = make_workspace(root, n_frames=n_frames)
    sc = Scene.load(ws)
    for i, cam in cameras.items():
        sc.frames[i].camera = cam
    sc.save(ws, overwrite=True)
    make_grid().save(ws / "grid" / "scene_grid.npz")
    return ws


CAM_B = Camera("PINHOLE", 64, 48, [44.0, 44.0, 32.0, 24.0])


def test_two_cameras_become_two_scenes(tmp_path):
    ws = workspace_with_cameras(tmp_path / "w2", 4, {1: CAM_B})
    out = tmp_path / "o2"
    res = export_dataset(ws, out, spec=SPEC, workers=1)
    assert [s["scene_id"] for s in res["scenes"]] == ["scene_01", "scene_01_cam2"]
    assert res["written"] == 4 and res["complete"]
    ds = out / "OccuFly_Dataset"
    assert tuple(np.loadtxt(ds / "scene_01" / "calibration.txt"))[:2] == (40.0, 40.0)
    assert tuple(np.loadtxt(ds / "scene_01_cam2" / "calibration.txt"))[:2] == (44.0, 44.0)
    assert (ds / "scene_01_cam2" / "30" / "ground_truth" / "000001" / "000001.label").is_file()
    assert not (ds / "scene_01" / "30" / "ground_truth" / "000001").exists()
    assert (ds / "splits" / "train.txt").read_text() == "scene_01\nscene_01_cam2\n"


# ---- LMSCNet / MonoScene downsampling ------------------------------------------------------------
def lmscnet_reference(label: np.ndarray, ds: int) -> np.ndarray:
    """Their _downsample_label, written from its documented rule with Python loops."""
    X, Y, Z = label.shape
    out = np.zeros((X // ds, Y // ds, Z // ds), np.uint8)
    for x in range(X // ds):
        for y in range(Y // ds):
            for z in range(Z // ds):
                b = label[x * ds:(x + 1) * ds, y * ds:(y + 1) * ds, z * ds:(z + 1) * ds].ravel()
                n0, n255 = int((b == 0).sum()), int((b == 255).sum())
                if n0 + n255 > 0.95 * ds ** 3:
                    out[x, y, z] = 0 if n0 > n255 else 255
                else:
                    out[x, y, z] = int(np.argmax(np.bincount(b[(b > 0) & (b < 255)])))
    return out


def test_lmscnet_rule_matches_reference():
    rng = np.random.default_rng(5)
    lab = np.zeros((32, 16, 24), np.uint8)
    lab[rng.random(lab.shape) < 0.3] = 255
    occ = rng.random(lab.shape) < 0.15
    lab[occ] = rng.choice([3, 5, 9, 14], int(occ.sum()))
    lab[:8, :8, :8] = 0
    lab[0, 0, 0] = 3  # 1 of 512: still empty (> 95 % empty)
    lab[8:16, :8, :8] = 255
    lab[8:12, :8, :8] = 0  # half empty, half invalid: 255 (not more empty than invalid)
    lab[16:24, :8, :8] = 0
    lab[16:24, :2, :4] = 5  # 64 of 512 -> class 5
    lab[16:24, 2:4, :4] = 3  # tie 3 vs 5 -> the smaller id
    for f in (2, 4, 8):
        assert np.array_equal(lmscnet_pool(lab, f), lmscnet_reference(lab, f)), f
    p = lmscnet_pool(lab, 8)
    assert p[0, 0, 0] == 0 and p[1, 0, 0] == 255 and p[2, 0, 0] == 3


# ---- SSCBench layout through a minimal KITTI-360-style loader ------------------------------------
def kitti_read_calib(path: str) -> dict:
    """pykitti-style, as MonoScene's read_calib: 'KEY: values' lines until a blank line."""
    calib_all = {}
    with open(path) as f:
        for line in f.readlines():
            if line == "\n":
                break
            key, value = line.split(":", 1)
            calib_all[key] = np.array([float(x) for x in value.split()])
    tr = np.identity(4)
    tr[:3, :4] = calib_all["Tr"].reshape(3, 4)
    return {"P2": calib_all["P2"].reshape(3, 4), "Tr": tr}


def vox2pix(cam_E, cam_k, vox_origin, voxel_size, img_W, img_H, scene_size):
    """MonoScene's vox2pix conventions: voxel centres, rigid transform, rounded projection,
    FOV mask 0 <= u < W, 0 <= v < H, z > 0."""
    vol_dim = np.ceil(np.asarray(scene_size) / voxel_size).astype(int)
    xv, yv, zv = np.meshgrid(range(vol_dim[0]), range(vol_dim[1]), range(vol_dim[2]), indexing="ij")
    coords = np.stack([xv.ravel(), yv.ravel(), zv.ravel()], axis=1)
    pts = np.asarray(vox_origin) + voxel_size * (coords + 0.5)
    cam = (cam_E @ np.column_stack([pts, np.ones(len(pts))]).T).T[:, :3]
    pix = np.round(cam[:, :2] / cam[:, 2:3] * [cam_k[0, 0], cam_k[1, 1]] + [cam_k[0, 2], cam_k[1, 2]])
    pix = pix.astype(np.int64)
    fov = (pix[:, 0] >= 0) & (pix[:, 0] < img_W) & (pix[:, 1] >= 0) & (pix[:, 1] < img_H) & (cam[:, 2] > 0)
    return pix, fov, cam[:, 2]


def test_sscbench_read_by_a_kitti360_style_loader(ssc, ws):
    cfg = yaml.safe_load((ssc / "occufly.yaml").read_text())
    g = cfg["geometry"]
    assert g["voxel_origin"] == [-32.0, -24.0, 0.0] and g["voxel_size"] == 1.0
    assert g["scene_size"] == [64.0, 48.0, 64.0] and g["grid_shape"] == [64, 48, 64]
    assert (g["image_width"], g["image_height"]) == (64, 48) and g["n_classes"] == len(TAX) + 1
    assert cfg["learning_map_inv"][255] == 255 and cfg["learning_map"][255] == 255
    assert cfg["learning_ignore"][0] is False and cfg["learning_ignore"][255] is True
    assert not any(v for k, v in cfg["learning_ignore"].items() if k != 255)
    splits = {s: (ssc / "splits" / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    assert splits == {"train": ["scene_01_30", "scene_01_50"], "val": [], "test": []}
    scene = Scene.load(ws)
    counts = np.zeros(g["n_classes"], np.int64)
    checked = 0
    for seq in splits["train"]:
        calib_a = kitti_read_calib(str(ssc / "dataset" / "sequences" / seq / "calib.txt"))
        calib_b = kitti_read_calib(str(ssc / "data_2d_raw" / seq / "calib.txt"))
        assert np.array_equal(calib_a["P2"], calib_b["P2"]) and np.array_equal(calib_a["Tr"], np.eye(4))
        P, T = calib_a["P2"], calib_a["Tr"]
        assert np.allclose(P, [[40, 0, 31.5, 0], [0, 40, 23.5, 0], [0, 0, 1, 0]])
        pix, fov, _ = vox2pix(T, P[:3, :3], g["voxel_origin"], g["voxel_size"], g["image_width"],
                              g["image_height"], g["scene_size"])
        for vp in sorted(glob.glob(os.path.join(ssc, "data_2d_raw", seq, "voxels", "*.bin"))):
            fid = os.path.splitext(os.path.basename(vp))[0]
            target = np.load(os.path.join(ssc, "preprocess", "labels", seq, fid + "_1_1.npy"))
            assert target.shape == tuple(g["grid_shape"]) and target.dtype == np.uint8
            assert target.max() < g["n_classes"] or target.max() == 255
            counts += np.bincount(target[target != 255], minlength=g["n_classes"])
            occupied = ((target != 0) & (target != 255)).reshape(-1)
            assert occupied.sum() > 1000
            assert fov[occupied].mean() >= 0.99
            # the rounded KITTI projection hits the pixel our COLMAP-convention camera gives
            fr = scene.frames[int(fid)]
            pts = np.asarray(g["voxel_origin"]) + (np.argwhere(target != 0)[:2000] + 0.5)
            uv, _ = fr.camera.project(pts)
            sel = np.argwhere(target.reshape(-1) != 0)[:2000, 0]
            assert np.mean(np.all(np.floor(uv).astype(int) == pix[sel], axis=1)) > 0.99
            img = ssc / "dataset" / "sequences" / seq / "image_2" / f"{fid}.png"  # SemanticKITTI place
            assert img.is_file() and (ssc / "dataset" / "sequences" / seq / "voxels" / f"{fid}.bin").is_file()
            full = np.load(ssc / "depth_full" / "sequences" / seq / f"{fid}.npy")  # CGFormer place
            quarter = np.load(ssc / "depth" / seq / f"{fid}.npy")
            assert full.shape == (48, 64) and full.dtype == np.float32
            assert np.array_equal(full, np.repeat(np.repeat(quarter, 4, 0), 4, 1))
            pts4 = np.fromfile(ssc / "data_2d_raw" / seq / "velodyne_points" / "data" / f"{fid}.bin",
                               dtype=np.float32).reshape(-1, 4)
            assert len(pts4) > 100 and (pts4[:, 2] > 0).all() and ((pts4[:, 3] >= 0) & (pts4[:, 3] <= 1)).all()
            proj = (P @ np.column_stack([pts4[:, :3], np.ones(len(pts4))]).T).T
            u, v = proj[:, 0] / proj[:, 2], proj[:, 1] / proj[:, 2]
            assert np.mean((u > -0.5) & (u < 63.5) & (v > -0.5) & (v < 47.5)) > 0.99
            # MonoScene's preprocessing (.label + .invalid + learning_map) rebuilds _1_1 bit for bit
            remap = np.zeros(max(cfg["learning_map"]) + 100, np.int32)
            remap[list(cfg["learning_map"])] = list(cfg["learning_map"].values())
            remap[remap == 0] = 255
            remap[0] = 0
            raw = np.fromfile(os.path.join(ssc, "data_2d_raw", seq, "voxels", fid + ".label"), np.uint16)
            inv = np.unpackbits(np.fromfile(os.path.join(ssc, "data_2d_raw", seq, "voxels", fid + ".invalid"),
                                            np.uint8))[: raw.size]
            rebuilt = remap[raw.astype(np.int64)]
            rebuilt[inv == 1] = 255
            assert np.array_equal(rebuilt.reshape(target.shape).astype(np.uint8), target)
            # _1_8 follows the LMSCNet rule on the training ids (MonoScene's preprocessing)
            t8 = np.load(os.path.join(ssc, "preprocess", "labels", seq, fid + "_1_8.npy"))
            assert np.array_equal(t8, lmscnet_reference(target, 8))
            checked += 1
    assert checked == 4
    assert counts.tolist() == g["class_voxel_counts"]


# ---- the reader ---------------------------------------------------------------------------------
def test_reader_round_trip_both_layouts(ws, ssc, occ):
    scene = Scene.load(ws)
    grid = make_grid()
    for root in (occ, ssc):
        ds = open_dataset(root)
        assert len(ds) == 4 and ds.layout == ("occufly" if root == occ else "sscbench")
        for key in ds.frames:
            s = ds.read(key)
            i = int(key.frame_id)
            fr = scene.frames[i]
            expect = sample_frame(grid, fr.camera, fr.T_cam_world, scene.origin, SPEC)
            assert np.array_equal(s["label"], expect.label_with_invalid())
            assert np.array_equal(s["invalid"], expect.invalid) and np.array_equal(s["occluded"], expect.occluded)
            assert np.allclose(s["K"], fr.camera.K) and np.allclose(s["pose"], np.linalg.inv(fr.T_cam_world), atol=1e-4)
            from PIL import Image

            assert np.array_equal(s["image"], np.asarray(Image.open(fr.image_path).convert("RGB")))
            assert s["depth"].shape == (12, 16) and s["depth"].dtype == np.float32
            t = ds.target(s)
            lut = ds.learning_lut()
            want = lut[expect.label_with_invalid()]
            assert np.array_equal(t, want)
            if ds.layout == "occufly":
                assert np.array_equal(s["surface"], expect.surface)
                assert set(s["grids"]) == {"1_1", "1_2", "1_4", "1_8", "1_16"}
            else:
                assert s["grids"]["1_8"].shape == (8, 6, 8) and s["points"].shape[1] == 4
                assert s["depth_full"].shape == (48, 64)
    assert len(open_dataset(ssc, split="train")) == 4 and len(open_dataset(ssc, split="val")) == 0
    assert len(open_dataset(occ, split="train")) == 4


def test_torch_dataset_and_collate(ssc, occ):
    import torch  # the torch extra: scripts/setup.sh --test installs it (no skip: run it)
    from torch.utils.data import DataLoader

    from occufly.datasets.torch import OccuFlyDataset, collate

    for root in (ssc, occ):
        ds = OccuFlyDataset(root, split="train", scales=("1_1", "1_8"))
        assert len(ds) == 4 and ds.n_classes == len(TAX) + 1
        batch = next(iter(DataLoader(ds, batch_size=2, collate_fn=collate)))
        assert batch["img"].shape == (2, 3, 48, 64) and batch["img"].dtype == torch.float32
        assert batch["target_1_1"].shape == (2, 64, 48, 64) and batch["target_1_1"].dtype == torch.int64
        assert batch["target_1_8"].shape == (2, 8, 6, 8)
        assert batch["depth"].shape == (2, 12, 16) and batch["K"].shape == (2, 3, 3)
        assert batch["frame_id"] == ["000001", "000003"] and batch["altitude"].tolist() == [30, 30]
        ref = ds.reader.target(ds.reader[0])
        assert torch.equal(batch["target_1_1"][0], torch.from_numpy(ref.astype(np.int64)))


# ---- eval-ssc: predictions in either layout, tables out -----------------------------------------
def test_eval_ssc_either_layout_and_tables(ssc, occ, tmp_path, capsys):
    from occufly.cli import main
    from occufly.metrics import evaluate_depth_dirs, evaluate_ssc_dirs, ssc_report

    ref = evaluate_ssc_dirs(occ, occ)
    assert ref["overall"]["miou"] == 1.0
    # depth too: the two layouts hold the same 1/4 maps (flattened / 2-D)
    dref = evaluate_depth_dirs(occ, occ)
    assert dref["images"] == 4 and dref["overall"]["d1"] == 1.0
    assert evaluate_depth_dirs(occ, ssc)["overall"] == dref["overall"] == evaluate_depth_dirs(ssc, occ)["overall"]
    # the SSCBench ground truth evaluated against OccuFly-layout predictions and vice versa
    assert evaluate_ssc_dirs(occ, ssc)["overall"] == ref["overall"]
    assert evaluate_ssc_dirs(ssc, occ)["overall"] == ref["overall"]
    # training-id _1_1.npy predictions in a flat folder, mapped back through the YAML; one
    # frame predicted "everything empty"
    flat = tmp_path / "flat"
    for p in sorted((ssc / "preprocess" / "labels").glob("*/*_1_1.npy")):
        (flat / p.parent.name).mkdir(parents=True, exist_ok=True)
        shutil.copy(p, flat / p.parent.name / p.name)
    victim = flat / "scene_01_50" / "000000_1_1.npy"
    np.save(victim, np.zeros_like(np.load(victim)))
    res = evaluate_ssc_dirs(flat, ssc)
    assert res["pred_layout"] == "flat" and res["frames"] == 4
    assert res["per_altitude"]["30"]["miou"] == 1.0 and res["per_altitude"]["50"]["miou"] < 1.0
    assert 0 < res["overall"]["completion"]["recall"] < 1.0
    md = ssc_report(res, "markdown")
    assert "| split | frames | IoU |" in md and "| 30 m | 2 | 100.00 |" in md and "| building |" in md
    tex = ssc_report(res, "latex")
    assert r"\begin{tabular}" in tex and r"\toprule" in tex and "30 m" in tex
    assert main(["eval-ssc", str(flat), str(ssc), "--format", "markdown"]) == 0
    assert "SSC per class" in capsys.readouterr().out
    assert main(["eval-ssc", str(flat), str(ssc), "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out)["overall"]["miou"] == res["overall"]["miou"]
    bad = flat / "scene_01_30" / "000001_1_1.npy"
    a = np.load(bad)
    a[0, 0, 0] = 99
    np.save(bad, a)
    assert main(["eval-ssc", str(flat), str(ssc)]) == 2
    assert "training id 99" in capsys.readouterr().err


def test_reader_refuses_code_in_a_pkl_and_bad_ids(occ, ssc, tmp_path, ws):
    from occufly.errors import InputFormatError
    from occufly.export import ExportError

    class Evil:
        def __reduce__(self):
            return (os.system, ("touch " + str(tmp_path / "pwned"),))

    bad = tmp_path / "occ"
    shutil.copytree(occ, bad, symlinks=True)
    pkl = next(bad.glob("OccuFly_Dataset/scene_01/*/preprocess/*.pkl"))
    pkl.write_bytes(pickle.dumps({"frame_id": "000000", "1_1": Evil()}, protocol=4))
    ds = open_dataset(bad)
    key = next(k for k in ds.frames if k.frame_id == pkl.stem)
    with pytest.raises(InputFormatError, match="not allowed"):
        ds.read(key)
    assert not (tmp_path / "pwned").exists()
    bad2 = tmp_path / "ssc"
    shutil.copytree(ssc, bad2, symlinks=True)
    mp = bad2 / "manifests" / "scene_01.json"
    m = json.loads(mp.read_text())
    m["frames"]["../../x"] = {"altitude": 30}
    mp.write_text(json.dumps(m))
    with pytest.raises(InputFormatError, match="not a valid export name"):
        open_dataset(bad2)
    with pytest.raises(ExportError, match="SSCBench"):
        export_dataset(ws, tmp_path / "v", spec=SPEC, workers=1, velodyne=True)


def test_adding_frames_of_another_camera_to_a_scene_is_refused(tmp_path):
    from occufly.export import ExportError

    ws = workspace_with_cameras(tmp_path / "wc", 3, {2: CAM_B})
    out = tmp_path / "oc"
    export_dataset(ws, out, spec=SPEC, workers=1, frames=[0, 1])
    cal = (out / "OccuFly_Dataset/scene_01/calibration.txt").read_bytes()
    with pytest.raises(ExportError, match="another camera"):
        export_dataset(ws, out, spec=SPEC, workers=1, frames=[2])
    assert (out / "OccuFly_Dataset/scene_01/calibration.txt").read_bytes() == cal
    assert export_dataset(ws, out, spec=SPEC, workers=1, frames=[2], scene_id="scene_02")["written"] == 1


def test_example_train_loop_on_an_export(ssc, tmp_path, capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "train_loop", Path(__file__).resolve().parents[1] / "examples" / "04_train_loop.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.run(ssc, "train", 2, tmp_path)
    out = capsys.readouterr().out
    assert "4 frames through the DataLoader" in out
    empty, up = out.split("## baseline: upsample_1_8")
    assert "| all | 4 | 0.00 | n/a | 0.00 | 0.00 |" in empty
    row = next(ln for ln in up.splitlines() if ln.startswith("| all |"))
    iou, rec = float(row.split("|")[3]), float(row.split("|")[5])
    # the coarse grid covers nearly every occupied voxel (LMSCNet rule: blocks < 5 % occupied
    # are empty), and much more
    assert 90 < rec <= 100 and 0 < iou < 50
    assert len(list((tmp_path / "pred_empty").glob("*/*_1_1.npy"))) == 4
