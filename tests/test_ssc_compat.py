"""The SSC codebase adapters (occufly.datasets.compat) against the sample contracts written
down from each codebase at its named commit (docs/ssc-porting.md), without the codebases:
keys, dtypes, shapes, per-sequence calibration, the flip, the splits of one scene."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from occufly.datasets import open_dataset
from occufly.datasets.compat import cgformer
from occufly.datasets.compat.common import (
    FlipRefused,
    cp_mega_matrix,
    depth_consistency,
    flip_K,
    load_geometry,
    local_frustums,
    vox2pix,
)
from occufly.export import export_dataset
from occufly.export.common import ExportError
from occufly.export.splits import assign_splits
from tests.export_fixtures import SPEC, make_grid, make_workspace

REPO = Path(__file__).resolve().parents[1]
COMMITS = {"Symphonies": "4ca4ff2", "MonoScene": "f52bbb1", "SSCBench": "9e767e1",
           "CGFormer": "0331e11", "DISC": "00ecc7f"}


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Path:
    return make_workspace(tmp_path_factory.mktemp("compat"), n_frames=6)


@pytest.fixture(scope="module")
def ssc(ws, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("compat_ssc") / "exp"
    export_dataset(ws, out, spec=SPEC, workers=1, layout="sscbench", velodyne=True,
                   split_by="ratio")
    return out


# ---- the 3D-2D mapping, frustums and context prior, against direct definitions ----------------
def _loop_vox2pix(T, K, origin, r, W, H, scene_size):
    dims = [int(np.ceil(s / r)) for s in scene_size]
    pix, fov, zs = [], [], []
    for i in range(dims[0]):
        for j in range(dims[1]):
            for k in range(dims[2]):
                c = np.float32(origin) + np.array([i, j, k]) * r + r / 2
                p = T[:3, :3] @ np.float32(c) + T[:3, 3]
                u = int(np.round(p[0] * np.float32(K[0, 0]) / p[2] + np.float32(K[0, 2])))
                v = int(np.round(p[1] * np.float32(K[1, 1]) / p[2] + np.float32(K[1, 2])))
                pix.append((u, v))
                fov.append(0 <= u < W and 0 <= v < H and p[2] > 0)
                zs.append(p[2])
    return np.array(pix), np.array(fov), np.array(zs)


def test_vox2pix_matches_the_voxel_by_voxel_definition():
    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 0.0]
    origin, r, size = np.array([-4.0, -3.0, 0.0]), 1.0, (8.0, 6.0, 5.0)
    pix, fov, z = vox2pix(T, K, origin, r, 64, 48, size)
    p2, f2, z2 = _loop_vox2pix(T, K, origin, r, 64, 48, size)
    assert pix.dtype == np.int64 and pix.shape == (8 * 6 * 5, 2) and fov.dtype == bool
    np.testing.assert_array_equal(pix, p2)
    np.testing.assert_array_equal(fov, f2)
    np.testing.assert_allclose(z, z2, rtol=1e-6)


def test_local_frustums_and_cp_matrix_match_their_definitions():
    rng = np.random.default_rng(3)
    target = rng.choice([0, 1, 2, 255], size=(4, 4, 4), p=[0.5, 0.2, 0.2, 0.1]).astype(np.uint8)
    pix = rng.integers(-5, 40, size=(64, 2))
    z = rng.uniform(-1, 5, size=64)
    masks, dists = local_frustums(pix, z, target, 32, 24, n_classes=3, size=2)
    assert masks.shape == (4, 4, 4, 4) and masks.dtype == bool and dists.shape == (4, 3)
    flat = target.reshape(-1)
    for f, (row, col) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        want = ((pix[:, 0] >= col * 16) & (pix[:, 0] < (col + 1) * 16) & (pix[:, 1] >= row * 12)
                & (pix[:, 1] < (row + 1) * 12) & (z > 0) & (flat != 255))
        np.testing.assert_array_equal(masks[f].reshape(-1), want)
        np.testing.assert_array_equal(dists[f], np.bincount(flat[want], minlength=3)[:3])
    # context prior: (4, N, M) relations voxel n vs the 8 children of super voxel m
    m = cp_mega_matrix(target)
    assert m.shape == (4, 64, 8) and m.dtype == np.uint8
    kids = [target[2 * a:2 * a + 2, 2 * b:2 * b + 2, 2 * c:2 * c + 2].reshape(-1)
            for a in range(2) for b in range(2) for c in range(2)]
    for n in range(64):
        ln = flat[n]
        for col, ch in enumerate(kids):
            ch = ch[ch != 255]
            want = np.zeros(4, np.uint8)
            if ln != 255:
                want[0] = any((c == ln) and c != 0 for c in ch)
                want[1] = any((c != ln) and c != 0 and ln != 0 for c in ch)
                want[2] = any((c == ln) and c == 0 for c in ch)
                want[3] = any((c != ln) and (c == 0 or ln == 0) for c in ch)
            np.testing.assert_array_equal(m[:, n, col], want, err_msg=f"voxel {n} super {col}")


# ---- manifest axes, splits of one scene ---------------------------------------------------------
def test_manifest_records_axes_and_frame_splits(ssc):
    m = json.loads((ssc / "manifests" / "scene_01.json").read_text())
    assert m["axes"]["image_left_right"] == 0 and m["axes"]["image_top_bottom"] == 1
    assert m["split_by"]["rule"] == "ratio"
    splits = {s: (ssc / "splits" / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    assert all(splits.values()), splits  # a single scene: every split has sequences
    for s in ("train", "val", "test"):
        ds = open_dataset(ssc, split=s)
        assert len(ds) > 0
        assert {m["frames"][k.frame_id]["split"] for k in ds.frames} == {s}
    assert sum(len(open_dataset(ssc, split=s)) for s in ("train", "val", "test")) == 6
    frames = (ssc / "splits" / "val_frames.txt").read_text().split("\n")
    assert all(len(x.split()) == 2 for x in frames if x)


def test_split_rules():
    frames = {f"{i:06d}": {"altitude": a, "pose": np.eye(4).tolist()}
              for i, a in enumerate([50] * 4 + [40] * 3 + [30] * 3)}
    s = assign_splits(frames, "altitude")
    assert {s[f] for f in frames if frames[f]["altitude"] == 50} == {"train"}
    assert {s[f] for f in frames if frames[f]["altitude"] == 40} == {"val"}
    assert {s[f] for f in frames if frames[f]["altitude"] == 30} == {"test"}
    with pytest.raises(ExportError, match="three altitudes"):
        assign_splits({k: v for k, v in frames.items() if v["altitude"] != 40}, "altitude")
    # region: contiguous strips along the flight direction, per altitude
    line = {f"{i:06d}": {"altitude": 50, "pose": [[1, 0, 0, 10.0 * (9 - i)], [0, 1, 0, 0],
                                                    [0, 0, 1, 0], [0, 0, 0, 1]]} for i in range(10)}
    r = assign_splits(line, "region")
    by_x = [r[f"{i:06d}"] for i in reversed(range(10))]  # increasing x
    assert by_x == ["train"] * 8 + ["val", "test"]
    q = assign_splits(line, "ratio")
    assert [v for _k, v in sorted(q.items())].count("train") == 8
    with pytest.raises(ExportError):
        assign_splits({"000000": {"altitude": 50}}, "ratio")


def test_export_split_by_altitude_end_to_end(tmp_path):
    from occufly.scene import Scene

    ws = make_workspace(tmp_path / "w", n_frames=6)
    sc = Scene.load(ws)
    for i, fr in enumerate(sc.frames):
        fr.nominal_altitude = [50, 40, 30][i % 3]
    sc.save(ws, overwrite=True)
    out = tmp_path / "exp"
    export_dataset(ws, out, spec=SPEC, workers=1, layout="sscbench", split_by="altitude",
                   grid=make_grid())
    got = {s: (out / "splits" / f"{s}.txt").read_text().split() for s in ("train", "val", "test")}
    assert got == {"train": ["scene_01_50"], "val": ["scene_01_40"], "test": ["scene_01_30"]}
    # CGFormer validates on split='test' (its config's val = testset_config): not empty
    ds = cgformer.OccuFlyKITTI360Dataset(
        data_root=out, stereo_depth_root=out / "depth_full", ann_file=out / "preprocess" / "labels",
        pipeline=None, split="test", camera_used=["left"], occ_size=list(SPEC.shape),
        pc_range=cgformer.point_cloud_range(out))
    assert len(ds) == 2
    with pytest.raises(ExportError, match="give one"):
        export_dataset(ws, out, spec=SPEC, workers=1, layout="sscbench", split_by="ratio", split="val",
                       grid=make_grid())


# ---- the adapters' sample contracts ----------------------------------------------------------------
def test_cgformer_input_dict_contract(ssc):
    root = ssc
    ds = cgformer.OccuFlyKITTI360Dataset(
        data_root=root, stereo_depth_root=root / "depth_full", ann_file=root / "preprocess" / "labels",
        pipeline=None, split="train", camera_used=["left"], occ_size=list(SPEC.shape),
        pc_range=cgformer.point_cloud_range(root))
    d = ds[0]
    assert set(d) == {"occ_size", "pc_range", "sequence", "frame_id", "img_filename", "lidar2img",
                      "cam_intrinsic", "lidar2cam", "focal_length", "baseline",
                      "stereo_depth_path", "gt_occ"}
    assert d["lidar2img"][0].shape == (4, 4) and d["cam_intrinsic"][0].shape == (4, 4)
    assert d["gt_occ"].shape == tuple(SPEC.shape) and d["gt_occ"].dtype == np.uint8
    assert Path(d["img_filename"][0]).is_file() and Path(d["stereo_depth_path"]).is_file()
    # CreateDepthFromLiDAR finds velodyne_points from the image path's last four parts
    seq, _, _, fname = d["img_filename"][0].split("/")[-4:]
    assert (root / "data_2d_raw" / seq / "velodyne_points" / "data" / fname.replace(".png", ".bin")).is_file()
    assert d["baseline"] == 0.0 and d["focal_length"] == 40.0
    with pytest.raises(ValueError, match="occ_size"):
        cgformer.OccuFlyKITTI360Dataset(root, root / "depth_full", root / "preprocess" / "labels",
                                        None, "train", ["left"], [256, 256, 32], [0, -25.6, -2, 51.2, 25.6, 4.4])
    # bda flips (their config: flip_dx / flip_dy 0.5) are accepted: CGFormer applies the same
    # bda_rot to its features; what must hold is that the step's range is the export's
    pcr = cgformer.point_cloud_range(root)
    bda = {"type": "LoadAnnotationOcc", "apply_bda": True, "point_cloud_range": pcr,
           "bda_aug_conf": {"flip_dx_ratio": 0.5, "flip_dy_ratio": 0.5, "flip_dz_ratio": 0}}
    args = (root, root / "depth_full", root / "preprocess" / "labels")
    kw = {"split": "train", "camera_used": ["left"], "occ_size": list(SPEC.shape), "pc_range": pcr}
    cgformer._check_pipeline([bda], pcr, "x")
    for bad in ([0, -25.6, -2, 51.2, 25.6, 4.4], None):  # KITTI's range (their default), none
        with pytest.raises(ValueError, match="point_cloud_range"):
            cgformer._check_pipeline([dict(bda, point_cloud_range=bad)], pcr, "x")
    # their voxel_transform: bda = denorm @ flip @ norm about the range's centre, labels flipped
    # as an array (loading_annotation_occ.py:61-124); the voxel centre (i, j, k) moved by bda
    # lies in voxel (X-1-i, Y-1-j, k) of the flipped grid: labels and features stay together
    g = load_geometry(root)
    c = (np.asarray(pcr[:3]) + np.asarray(pcr[3:])) / 2
    flip = np.diag([-1.0, -1.0, 1.0])  # flip_dx and flip_dy
    X, Y, Z = SPEC.shape
    ijk = np.stack(np.meshgrid(np.arange(X), np.arange(Y), np.arange(Z), indexing="ij"), -1).reshape(-1, 3)
    p = g.voxel_origin + (ijk + 0.5) * g.voxel_size
    q = (p - c) @ flip.T + c
    got = np.floor((q - g.voxel_origin) / g.voxel_size).astype(int)
    np.testing.assert_array_equal(got, np.stack([X - 1 - ijk[:, 0], Y - 1 - ijk[:, 1], ijk[:, 2]], 1))
    assert len(cgformer.OccuFlyKITTI360Dataset(*args, pipeline=None, **kw)) == len(ds)


def test_symphonies_sample_contract_and_safe_flip(ssc):
    import torch  # the torch extra: scripts/setup.sh --test installs it (no skip)

    from occufly.datasets.compat.symphonies import OccuFlyKITTI360, Register

    ds = OccuFlyKITTI360("train", ssc, label_root=ssc / "preprocess" / "labels",
                         depth_root=ssc / "depth_full", frustum_size=2, context_prior=True)
    X, Y, Z = SPEC.shape
    g = load_geometry(ssc)
    data, label = ds.sample(0)
    assert set(data) == {"frame_id", "sequence", "P", "cam_pose", "proj_matrix", "voxel_origin",
                         "scale_3ds", "cam_K", "projected_pix_1", "pix_z_1", "fov_mask_1",
                         "projected_pix_2", "pix_z_2", "fov_mask_2", "depth", "img"}
    assert set(label) == {"target", "CP_mega_matrix", "frustums_masks", "frustums_class_dists"}
    assert data["scale_3ds"] == (1, 2)
    assert data["img"].shape == (3, 48, 64) and data["img"].dtype == torch.float32
    assert data["depth"].shape == (48, 64) and data["depth"].dtype == torch.float32
    assert data["P"].shape == (3, 4) and data["P"].dtype == torch.float32
    assert data["projected_pix_1"].shape == (X * Y * Z, 2) and data["projected_pix_1"].dtype == torch.int64
    assert data["projected_pix_2"].shape == (X * Y * Z // 8, 2)
    assert data["pix_z_1"].dtype == torch.float32 and data["fov_mask_1"].dtype == torch.bool
    assert label["target"].shape == (X, Y, Z) and label["target"].dtype == torch.uint8
    assert label["CP_mega_matrix"].shape == (4, X * Y * Z // 512, X * Y * Z // 4096)
    assert label["frustums_masks"].shape == (4, X, Y, Z) and label["frustums_masks"].dtype == torch.float32
    assert label["frustums_class_dists"].shape == (4, g.n_classes)
    assert OccuFlyKITTI360.META_INFO["class_names"] == g.class_names
    assert OccuFlyKITTI360.META_INFO["class_weights"].shape == (g.n_classes,)
    # every occupied voxel of the target projects into the image
    occ = ((label["target"] != 0) & (label["target"] != 255)).reshape(-1).numpy()
    assert data["fov_mask_1"].numpy()[occ].mean() > 0.99

    W, H = 64, 48

    def consistency(d, lab):
        return depth_consistency(lab["target"].numpy(), d["depth"].numpy(), d["cam_K"].numpy(),
                                 (W, H), g.voxel_origin, g.voxel_size, step=1)

    fd, fl = ds.sample(0, flip=True)
    before, after = consistency(data, label), consistency(fd, fl)
    assert before["pixels"] > 100 and before["share"] > 0.5, before
    assert abs(after["share"] - before["share"]) < 0.01, (before, after)
    np.testing.assert_allclose(fd["cam_K"].numpy(), flip_K(data["cam_K"].numpy(), W), atol=1e-4)
    assert torch.equal(fl["target"], torch.flip(label["target"], dims=[0]))
    assert torch.equal(fd["img"], torch.flip(data["img"], dims=[2]))
    # Symphonies' own flip (target along axis 1, K unchanged) breaks the agreement
    wrong = dict(label, target=torch.flip(label["target"], dims=[1]))
    theirs = consistency(dict(data, depth=torch.flip(data["depth"], dims=[1])), wrong)
    assert theirs["share"] < before["share"] - 0.2, (before, theirs)
    # the Hydra callback registers the class in the module Symphonies looks types up in
    import sys
    import types

    mod = types.ModuleType("fake_ssc_datasets")
    sys.modules["fake_ssc_datasets"] = mod
    try:
        Register(data_root=str(ssc), module="fake_ssc_datasets").on_job_start(config=None)
        assert mod.OccuFlyKITTI360 is OccuFlyKITTI360
    finally:
        del sys.modules["fake_ssc_datasets"]


def test_flip_refused_without_an_axis_record(ssc, tmp_path):
    import torch  # noqa: F401 -- the torch extra: scripts/setup.sh --test installs it (no skip)

    from occufly.datasets.compat.symphonies import OccuFlyKITTI360

    root = tmp_path / "old"
    shutil.copytree(ssc, root, symlinks=True)
    mp = root / "manifests" / "scene_01.json"
    m = json.loads(mp.read_text())
    m.pop("axes")
    m["conventions"]["frame_grid"] = "something else"
    mp.write_text(json.dumps(m))
    with pytest.raises(FlipRefused, match="axis convention"):
        OccuFlyKITTI360("train", root, flip=True)
    assert len(OccuFlyKITTI360("train", root, flip=False)) > 0
    # an export before the record, with the camera-centric convention text: axis 0 inferred
    m["conventions"]["frame_grid"] = "camera-centric, x right, y down, z forward; voxel ..."
    mp.write_text(json.dumps(m))
    assert OccuFlyKITTI360("train", root, flip=True).lr_axis == 0


def test_monoscene_sample_contract_and_per_sequence_calibration(ssc, tmp_path):
    import torch  # the torch extra: scripts/setup.sh --test installs it (no skip)

    from occufly.datasets.compat.monoscene import Kitti360Dataset, KittiDataset, training_constants

    root = tmp_path / "two_calibs"
    shutil.copytree(ssc, root, symlinks=True)
    seqs = sorted(p.name for p in (root / "data_2d_raw").iterdir())
    assert len(seqs) == 2
    cal = root / "data_2d_raw" / seqs[1] / "calib.txt"
    text = cal.read_text().replace("4.000000000000e+01", "4.400000000000e+01")
    cal.write_text(text)
    X, Y, Z = SPEC.shape
    for cls in (Kitti360Dataset, KittiDataset):
        ds = cls("train", root, root / "preprocess", frustum_size=2)
        d = ds.sample(0)
        assert set(d) == {"frame_id", "sequence", "P", "T_velo_2_cam", "proj_matrix", "scale_3ds",
                          "cam_k", "projected_pix_1", "fov_mask_1", "pix_z_1", "projected_pix_2",
                          "fov_mask_2", "pix_z_2", "target", "CP_mega_matrix", "frustums_masks",
                          "frustums_class_dists", "img"}
        assert d["scale_3ds"] == [1, 2] and d["cam_k"].dtype == np.float64
        assert d["projected_pix_1"].dtype == np.int64 and d["pix_z_1"].dtype == np.float64
        assert d["frustums_masks"].dtype == bool and d["frustums_masks"].shape == (4, X, Y, Z)
        assert d["frustums_class_dists"].dtype == np.float64
        assert isinstance(d["img"], torch.Tensor) and d["img"].shape == (3, 48, 64)
        fx = {s.sequence: s.P2[0, 0] for s in ds.scans}
        assert fx == {seqs[0]: 40.0, seqs[1]: 44.0}  # each sequence's own calib.txt
        # their flip: image and u mirrored, the target untouched
        f = ds.sample(0, flip=True)
        np.testing.assert_array_equal(f["projected_pix_1"][:, 0], 63 - d["projected_pix_1"][:, 0])
        np.testing.assert_array_equal(f["target"], d["target"])
    c = training_constants(root)
    assert c["full_scene_size"] == tuple(SPEC.shape) and c["n_classes"] == len(c["class_names"])


def _monoscene_collate(batch):
    """MonoScene's ``collate_fn`` reduced to what it does to each field (not its code): it
    mirrors astra-vision/MonoScene f52bbb1 ``monoscene/data/semantic_kitti/collate.py:17-44``
    and ai4ce/SSCBench 9e767e1 ``method/MonoScene/monoscene/data/kitti_360/collate.py:21-46``
    (the same loop): ``torch.from_numpy`` on cam_k, T_velo_2_cam, projected_pix_s, fov_mask_s,
    target and CP_mega_matrix of every sample, on frustums_masks / frustums_class_dists only
    ``if "frustums_masks" in input_dict`` (collate.py:26 / :34), ``torch.stack`` of img and
    target."""
    import torch

    out = {"frustums_masks": [], "frustums_class_dists": [], "cam_k": [], "T_velo_2_cam": [],
           "CP_mega_matrices": [], "img": [], "target": []}
    for s in batch[0]["scale_3ds"]:
        out[f"projected_pix_{s}"], out[f"fov_mask_{s}"] = [], []
    for d in batch:
        out["cam_k"].append(torch.from_numpy(d["cam_k"]).double())
        out["T_velo_2_cam"].append(torch.from_numpy(d["T_velo_2_cam"]).float())
        if "frustums_masks" in d:
            out["frustums_masks"].append(torch.from_numpy(d["frustums_masks"]))
            out["frustums_class_dists"].append(torch.from_numpy(d["frustums_class_dists"]).float())
        for s in d["scale_3ds"]:
            out[f"projected_pix_{s}"].append(torch.from_numpy(d[f"projected_pix_{s}"]))
            out[f"fov_mask_{s}"].append(torch.from_numpy(d[f"fov_mask_{s}"]))
        out["img"].append(d["img"])
        out["target"].append(torch.from_numpy(d["target"]))
        out["CP_mega_matrices"].append(torch.from_numpy(d["CP_mega_matrix"]))
    out["img"], out["target"] = torch.stack(out["img"]), torch.stack(out["target"])
    return out


def test_monoscene_every_split_collates(ssc):
    """The test split collated with TypeError (frustum keys set to None, as their datasets
    do): every split of both MonoScene adapters batches through their collate_fn's logic."""
    import torch  # noqa: F401  (the test set-up installs it: a missing torch fails, not skips)

    from occufly.datasets.compat.monoscene import Kitti360Dataset, KittiDataset

    for cls in (Kitti360Dataset, KittiDataset):
        for split in ("train", "val", "test"):
            ds = cls(split, ssc, ssc / "preprocess", frustum_size=2)
            assert len(ds) >= 1, split
            b = _monoscene_collate([ds[i] for i in range(min(2, len(ds)))])
            assert b["img"].shape[1:] == (3, 48, 64) and b["target"].shape[1:] == tuple(SPEC.shape)
            has = split != "test"  # the model's frustum loss runs for train / val only
            assert bool(b["frustums_masks"]) == has, (cls.__name__, split)
            if has:
                assert b["frustums_masks"][0].shape == (4, *SPEC.shape)
    # what their own dataset returns for test does not collate: the adapter must not do it
    d = Kitti360Dataset("test", ssc, ssc / "preprocess").sample(0)
    with pytest.raises(TypeError):
        _monoscene_collate([dict(d, frustums_masks=None, frustums_class_dists=None)])


def test_disc_sample_contract_streams_and_flip(ssc):
    """DISC (Enyu-Liu/DISC 00ecc7f, ssc_ia/data/datasets/kitti_360.py:101-203): keys, dtypes,
    shapes, the instance / scene streams from the taxonomy, no target for test, the flip
    through post_rot with the target kept, the Hydra callback."""
    import sys
    import types

    import torch  # the test set-up installs it: a missing torch fails, not skips

    from occufly.datasets.compat.disc import (
        OccuFlyKITTI360,
        Register,
        class_streams,
        training_constants,
    )

    X, Y, Z = SPEC.shape
    g = load_geometry(ssc)
    ds = OccuFlyKITTI360("train", ssc, depth_root=ssc / "depth_full",
                         data_config={"input_size": [48, 64], "flip": True})
    data, label = ds.sample(0)
    assert set(data) == {"frame_id", "sequence", "P", "cam_pose", "proj_matrix", "voxel_origin",
                         "scale_3ds", "cam_K", "img", "depth", "post_tran", "post_rot",
                         "projected_pix_1", "pix_z_1", "fov_mask_1", "projected_pix_2", "pix_z_2",
                         "fov_mask_2"}
    assert set(label) == {"class_fres", "bk_cls_info", "ins_cls_info", "target", "depth",
                          "bev_seg_bk", "bev_seg_ins", "seg_img"}
    assert data["img"].shape == (3, 48, 64) and data["depth"].shape == (48, 64)
    assert data["projected_pix_1"].dtype == torch.float32 and data["projected_pix_1"].shape == (X * Y * Z, 2)
    assert data["fov_mask_2"].dtype == torch.bool and data["projected_pix_2"].shape == (X * Y * Z // 8, 2)
    assert data["post_rot"].shape == (3, 3) and data["post_tran"].shape == (3,)
    assert label["target"].shape == (X, Y, Z) and label["target"].dtype == torch.uint8
    assert label["bev_seg_bk"].shape == (X, Y) and label["seg_img"].shape == (48, 64)
    assert label["seg_img"].dtype == torch.int64 and label["class_fres"].shape == (g.n_classes,)
    bk, ins = class_streams(ssc)
    # every class in exactly one stream, each led by empty (0); instance = the taxonomy group
    assert bk["indices"][0] == 0 and ins["indices"][0] == 0
    assert sorted([*bk["indices"][1:], *ins["indices"][1:]]) == list(range(1, g.n_classes))
    assert {g.class_names[i] for i in ins["indices"][1:]} >= {"vehicle", "building", "person"}
    assert "road" in bk["names"] and training_constants(ssc)["ins_cls"] == len(ins["indices"])
    # bev: the last layer along axis 2 with a class of the stream, as its position in the stream
    t = label["target"].numpy()
    i, j = np.argwhere(np.isin(t[:, :, :-1], ins["indices"][1:]).any(2))[0]
    col = t[i, j, :-1]
    want = col[np.flatnonzero(np.isin(col, ins["indices"][1:]))[-1]]
    assert label["bev_seg_ins"][i, j] == list(ins["indices"]).index(want)
    # seg_img: instance labels, 0 and 255 only
    assert set(np.unique(label["seg_img"].numpy())) <= {0, 255, *ins["indices"][1:].tolist()}
    # no identity augmentation drift at the native size: projections are the rounded pixels
    pix, fov, _ = vox2pix(ds.scans[0].Tr, ds.scans[0].P2[:3, :3], g.voxel_origin, g.voxel_size,
                          64, 48, g.scene_size)
    np.testing.assert_array_equal(data["projected_pix_1"].numpy(), pix.astype(np.float32))
    np.testing.assert_array_equal(data["fov_mask_1"].numpy(), fov)
    # their flip: image and depth mirrored, projections u -> fW - u through post_rot, target kept
    fd, fl = ds.sample(0, flip=True)
    assert torch.equal(fd["img"], torch.flip(data["img"], dims=[2]))
    assert torch.equal(fd["depth"], torch.flip(data["depth"], dims=[1]))
    np.testing.assert_allclose(fd["projected_pix_1"][:, 0].numpy(), 64 - data["projected_pix_1"][:, 0].numpy())
    assert torch.equal(fl["target"], label["target"]) and torch.equal(fl["bev_seg_ins"], label["bev_seg_ins"])
    # test split: no target and nothing computed from it (theirs: with_target = split != 'test')
    td, tl = OccuFlyKITTI360("test", ssc).sample(0)
    assert set(tl) == {"class_fres", "bk_cls_info", "ins_cls_info", "depth"}
    # the callback registers the class where DISC looks types up
    mod = types.ModuleType("fake_ssc_ia_datasets")
    sys.modules["fake_ssc_ia_datasets"] = mod
    try:
        Register(data_root=str(ssc), module="fake_ssc_ia_datasets")
        assert mod.OccuFlyKITTI360 is OccuFlyKITTI360
        assert OccuFlyKITTI360.META_INFO["class_names"] == g.class_names
    finally:
        del sys.modules["fake_ssc_ia_datasets"]
    assert Register.default_module == "ssc_ia.data.datasets"


# ---- the porting guide and its benchmark run -----------------------------------------------------
def test_porting_guide_names_the_commits_and_matches_the_bench_run():
    doc = (REPO / "docs" / "ssc-porting.md").read_text()
    for name, commit in COMMITS.items():
        assert name in doc and commit in doc, name
    run = json.loads((REPO / "docs" / "bench" / "ssc_loaders.json").read_text())
    assert set(run["codebases"]) == {"symphonies", "monoscene", "sscbench_monoscene", "cgformer", "disc"}
    for key, cb in run["codebases"].items():
        assert cb["commit"].startswith(COMMITS[cb["name"]]), key
        assert cb["loads"], (key, cb.get("error"))
        # every split of every codebase went through its own loader to a batch
        assert set(cb["splits_batched"]) == set(cb["lengths"]) and len(cb["lengths"]) == 3, key
        assert all(v["batched"] for v in cb["splits_batched"].values()), (key, cb["splits_batched"])
        assert all(n > 0 for n in cb["lengths"].values()), key
        # depth vs grid through the codebase's own projection, >= 10 frames per altitude
        dc = cb["depth_consistency"]
        assert len(dc["mean"]) == 3 and all(f["n"] >= 10 for f in dc["frames"].values()), key
        assert dc["own_projection_equals_adapter"] in (True, None), key
        assert cb["memory_mb_per_sample"], key
    # the training smoke run: the guide carries its figures, the SSC loss fell
    train = json.loads((REPO / "docs" / "bench" / "ssc_train.json").read_text())
    assert train["steps"] >= 25 and (REPO / train["plot"]).is_file()
    assert f"{train['steps']} steps" in doc  # the guide says how short the run was
    for k in ("monoscene", "monoscene_ssc_ce", "baseline"):
        assert train["loss"][k]["last_25"] < train["loss"][k]["first_25"], k
    for k, t in train["test"].items():
        ours, theirs = t["occufly_metrics"], t["monoscene_sscmetrics"]
        assert abs(ours["completion_iou"] - theirs["completion_iou"]) < 1e-3, k  # the same IoU
        assert f"{ours['completion_iou'] * 100:.1f}" in doc, k
    # the guide's table is the run's table (bench_ssc_loaders.render_table), not a copy by hand
    assert "<!-- ssc-bench-table -->\n\n" + run["table"] + "\n" in doc
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_ssc_sampling", REPO / "bench" / "bench_ssc_sampling.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    filled = json.loads((REPO / "docs" / "bench" / "ssc_sampling.json").read_text())
    shell = json.loads((REPO / "docs" / "bench" / "ssc_sampling_shell.json").read_text())
    assert "<!-- ssc-sampling-table -->\n\n" + bench.render_table(filled, shell) + "\n" in doc
    for res in filled["frames"].values():  # the fix: no fewer occupied voxels than the old rule
        assert (res["fine grid, sub-voxel (after)"]["occupied_voxels"]
                > res["fine grid, nearest centre (before)"]["occupied_voxels"])
    assert "ssc-porting.md" in (REPO / "mkdocs.yml").read_text()
    guide = (REPO / "docs" / "guide" / "researcher.md").read_text()
    assert "ssc-porting.md" in guide and "core/" not in guide


# ---- sampling a finer scene grid (the 30 m finding) -----------------------------------------------
def test_a_finer_scene_grid_keeps_thin_surfaces():
    """A 0.25 m layer between the 0.5 m frame voxels' centres: nearest-centre sampling missed
    it (every frame voxel empty); sub-voxel sampling finds it in the voxel that contains it."""
    from occufly.grid import SceneGrid
    from occufly.sampling import FrameGridSpec, sample_labels

    lab = np.zeros((8, 8, 8), np.uint8)
    lab[:, :, 2] = 6  # z in [0.5, 0.75): inside frame voxel k = 1 ([0.5, 1.0)), centre z = 0.75
    g = SceneGrid(lab, np.array([-1.0, -1.0, 0.0]), 0.25)
    spec = FrameGridSpec(shape=(4, 4, 4), voxel_size=0.5, near=0.1)
    labels, inside = sample_labels(g, np.eye(4), np.zeros(3), spec)
    assert inside.all()
    assert (labels[:, :, 1] == 6).all() and (labels[:, :, [0, 2, 3]] == 0).all()
    assert not sample_labels(g, np.eye(4), np.zeros(3), spec, subvoxel=False)[0].any()  # the old rule
    # same voxel size: the plain nearest-centre rule, unchanged
    g2 = SceneGrid(np.repeat(np.repeat(np.repeat(lab[::2, ::2, ::2], 2, 0), 2, 1), 2, 2)[::2, ::2, ::2],
                   np.array([-1.0, -1.0, 0.0]), 0.5)
    l2, _ = sample_labels(g2, np.eye(4), np.zeros(3), spec)
    np.testing.assert_array_equal(l2, g2.labels)
