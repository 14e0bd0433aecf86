"""Load an SSCBench-layout export with four SSC codebases' own loading code through the
adapters of occufly.datasets.compat, and print one JSON object (docs/bench/ssc_loaders.json,
docs/ssc-porting.md).

    python bench/bench_ssc_loaders.py EXPORT --symphonies DIR --monoscene DIR \
        --sscbench DIR --cgformer DIR [--commits a,b,c,d] > docs/bench/ssc_loaders.json

Run outside CI; it fetches nothing: DIR are checkouts of hustvl/Symphonies 4ca4ff2,
astra-vision/MonoScene f52bbb1, ai4ce/SSCBench 9e767e1 and pkqbajng/CGFormer 0331e11. The
export should be ``occufly export WS OUT --layout sscbench --velodyne --split-by altitude``
(train = 50 m, val = 40 m, test = 30 m).

Per codebase: does its loader load the export (the codebase's DataLoader / DataModule /
pipeline code, with the adapter as dataset), the configuration edits and code edits that
takes, the batch shapes, the share of occupied voxels inside the image (fov mask), the
depth-consistency share per altitude (nearest occupied voxel along each pixel's ray vs the
depth map, within 1 m), and before / after a left-right flip -- the adapter's, and the
codebase's own flip run on the same frame.

What cannot be imported here is stubbed, and the JSON says so (``stubs``): torchvision (the
CPU torch 2.13 wheel has no matching torchvision; ToTensor / Normalize / Compose are
re-implemented, ColorJitter is the identity), and for CGFormer mmcv / mmdet (mmcv-full 1.4
needs CUDA ops): a registry and Compose stand in for mmdet's, CGFormer's own pipeline steps
run unchanged.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import random
import sys
import types
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from occufly.datasets.compat.common import depth_consistency, load_geometry  # noqa: E402

COMMITS = {"symphonies": "4ca4ff2", "monoscene": "f52bbb1", "sscbench_monoscene": "9e767e1",
           "cgformer": "0331e11"}
NAMES = {"symphonies": "Symphonies", "monoscene": "MonoScene",
         "sscbench_monoscene": "SSCBench", "cgformer": "CGFormer"}


# ---- stubs -------------------------------------------------------------------------------------
def stub_torchvision() -> list[str]:
    try:
        import torchvision.transforms  # noqa: F401
        return []
    except Exception:  # noqa: BLE001 - any import failure: stub
        pass
    import torch

    tv = types.ModuleType("torchvision")
    tr = types.ModuleType("torchvision.transforms")

    class Compose:
        def __init__(self, ts):
            self.ts = ts

        def __call__(self, x):
            for t in self.ts:
                x = t(x)
            return x

    class ToTensor:
        def __call__(self, x):
            from PIL import Image

            if isinstance(x, Image.Image):
                a = np.array(x)
                if a.ndim == 2:
                    a = a[:, :, None]
                t = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))
                return t.float().div(255) if a.dtype == np.uint8 else t.float()
            a = np.asarray(x)
            if a.ndim == 2:
                a = a[:, :, None]
            t = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))
            return t.float().div(255) if a.dtype == np.uint8 else t

    class Normalize:
        def __init__(self, mean, std):
            self.mean = torch.tensor(mean).view(-1, 1, 1)
            self.std = torch.tensor(std).view(-1, 1, 1)

        def __call__(self, t):
            return (t - self.mean.to(t.dtype)) / self.std.to(t.dtype)

    class ColorJitter:
        def __init__(self, *a, **k):
            pass

        def __call__(self, x):
            return x

    tr.Compose, tr.ToTensor, tr.Normalize, tr.ColorJitter = Compose, ToTensor, Normalize, ColorJitter
    tv.transforms = tr
    import importlib.machinery

    tv.__spec__ = importlib.machinery.ModuleSpec("torchvision", None)
    tr.__spec__ = importlib.machinery.ModuleSpec("torchvision.transforms", None)
    sys.modules["torchvision"], sys.modules["torchvision.transforms"] = tv, tr
    return ["torchvision.transforms (ToTensor, Normalize, Compose re-implemented; ColorJitter = identity)"]


def stub_mmdet() -> list[str]:
    try:
        import mmdet.datasets  # noqa: F401
        return []
    except Exception:  # noqa: BLE001
        pass
    import torch

    class Registry:
        def __init__(self, name):
            self.name, self.modules = name, {}

        def register_module(self, name=None):
            def deco(cls):
                self.modules[name or cls.__name__] = cls
                return cls
            return deco

        def build(self, cfg):
            cfg = dict(cfg)
            return self.modules[cfg.pop("type")](**cfg)

    DATASETS, PIPELINES = Registry("dataset"), Registry("pipeline")

    class Compose:
        def __init__(self, steps):
            self.steps = [PIPELINES.build(s) if isinstance(s, dict) else s for s in steps]

        def __call__(self, d):
            for s in self.steps:
                d = s(d)
                if d is None:
                    return None
            return d

    def to_tensor(x):
        return x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x))

    mm = types.ModuleType("mmdet")
    ds = types.ModuleType("mmdet.datasets")
    bd = types.ModuleType("mmdet.datasets.builder")
    pl = types.ModuleType("mmdet.datasets.pipelines")
    ds.DATASETS, ds.PIPELINES, bd.DATASETS, bd.PIPELINES = DATASETS, PIPELINES, DATASETS, PIPELINES
    pl.Compose, pl.to_tensor = Compose, to_tensor
    mm.datasets, ds.builder, ds.pipelines = ds, bd, pl
    for n, m in (("mmdet", mm), ("mmdet.datasets", ds), ("mmdet.datasets.builder", bd),
                 ("mmdet.datasets.pipelines", pl), ("mmcv", types.ModuleType("mmcv"))):
        sys.modules[n] = m
    return ["mmcv (imported, unused by the pipeline steps)",
            "mmdet registry, Compose, to_tensor (a dict registry; mmcv-full 1.4 needs CUDA ops)"]


def load_file(name: str, path: Path, source: str | None = None):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    if source is None:
        spec.loader.exec_module(mod)
    else:
        exec(compile(source, str(path), "exec"), mod.__dict__)
    return mod


def package_stub(name: str, path: Path) -> types.ModuleType:
    """A package whose __init__ is not run (its submodules import as usual)."""
    m = types.ModuleType(name)
    m.__path__ = [str(path)]
    sys.modules[name] = m
    return m


# ---- measurements ------------------------------------------------------------------------------
def shapes(d) -> dict:
    out = {}
    for k, v in d.items():
        if hasattr(v, "shape"):
            out[k] = [list(v.shape), str(v.dtype).replace("torch.", "")]
        elif isinstance(v, list | tuple) and v and hasattr(v[0], "shape"):
            out[k] = [[list(x.shape) for x in v[:1]], f"list of {len(v)}"]
    return out


def fov_share(target, fov) -> float:
    t = np.asarray(target).reshape(-1)
    occ = (t != 0) & (t != 255)
    return float(np.asarray(fov).reshape(-1)[occ].mean()) if occ.any() else float("nan")


def consistency(target, depth, K, W, H, geom, T=None, step=2) -> dict:
    """step 1 for flips: with every pixel, the mirrored pixel set is the same set."""
    r = depth_consistency(np.asarray(target), np.asarray(depth, np.float32), np.asarray(K, np.float64),
                          (W, H), geom.voxel_origin, geom.voxel_size, step=step, T_velo_2_cam=T)
    return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}


N_PER_ALTITUDE = 3


def per_altitude(make_ds, sample_fn, geom, n=None) -> dict:
    """Depth consistency over up to n frames of each split (= altitude with --split-by altitude)."""
    n = n or N_PER_ALTITUDE
    out = {}
    for split in ("train", "val", "test"):
        ds = make_ds(split)
        if not len(ds):
            out[split] = None
            continue
        idx = np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int)
        shares, alt = [], None
        for i in idx:
            target, depth, K, W, H, seq = sample_fn(ds, int(i))
            alt = seq.rsplit("_", 1)[-1]
            shares.append(consistency(target, depth, K, W, H, geom)["share"])
        out[f"{alt} m ({split})"] = round(float(np.mean(shares)), 4)
    return out


# ---- Symphonies ---------------------------------------------------------------------------------
def run_symphonies(root: Path, export: Path, frustum: int) -> dict:
    stubs = stub_torchvision()
    sys.path.insert(0, str(root))
    # ssc_pl/__init__ imports the models (MaskDINO / mmdet); only its data and utils are needed
    ssc_pl = package_stub("ssc_pl", root / "ssc_pl")
    utils = importlib.import_module("ssc_pl.utils")
    ssc_pl.build_from_configs = utils.build_from_configs
    data = importlib.import_module("ssc_pl.data")
    stubs.append("ssc_pl/__init__.py not run (imports the models: MaskDINO, mmdet); "
                 "ssc_pl.data and ssc_pl.utils import unchanged")
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    geom = load_geometry(export)
    W, H = next(iter(geom.image_sizes.values()))
    edits = [
        "datasets=kitti_360",  # the default `datasets: semantic_kitti` must change
        "+hydra.callbacks.occufly._target_=occufly.datasets.compat.symphonies.Register",
        "data.datasets.type=OccuFlyKITTI360",
        f"data.datasets.data_root={export}",
        f"data.datasets.label_root={export}/preprocess/labels",
        f"data.datasets.depth_root={export}/depth_full",
        f"model.scene_size=[{','.join(map(str, geom.grid_shape))}]",
        f"model.image_shape=[{H},{W}]",
        f"+model.voxel_size={geom.voxel_size}",
        f"model.num_classes={geom.n_classes}",
        f"evaluator.num_classes={geom.n_classes}",
    ]
    bench_only = [f"data.datasets.frustum_size={frustum}", "data.loader.num_workers=0"]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base=None):
        cfg = compose(config_name="config", overrides=edits + bench_only, return_hydra_config=True)
    instantiate(cfg.hydra.callbacks.occufly)  # what Hydra does with hydra.callbacks at start
    from omegaconf import OmegaConf

    OmegaConf.set_struct(cfg, False)
    cfg.pop("hydra")
    dls, meta = data.build_data_loaders(cfg.data)
    inputs, labels = next(iter(dls[0]))
    res = {"loads": True, "lengths": {s: len(dl.dataset) for s, dl in zip(("train", "val", "test"), dls, strict=True)},
           "batch": {**shapes(inputs), **shapes(labels)},
           "fov_share": round(fov_share(labels["target"][0].numpy(), inputs["fov_mask_1"][0].numpy()), 4),
           "meta_info": sorted(meta)}
    ds = dls[0].dataset
    res["depth_consistency"] = per_altitude(
        lambda s: type(ds)(s, export, depth_root=export / "depth_full", flip=False, frustum_size=1),
        lambda d, i: (lambda a, b: (b["target"].numpy(), a["depth"].numpy(), a["cam_K"].numpy(),
                                    W, H, a["sequence"]))(*d.sample(i)), geom)
    # flips on frame 0 of train: the adapter's, and Symphonies' own KITTI360 on the same frame
    a0, l0 = ds.sample(0, False)
    a1, l1 = ds.sample(0, True)
    res["flip"] = {
        "before": consistency(l0["target"].numpy(), a0["depth"].numpy(), a0["cam_K"].numpy(), W, H, geom, step=1)["share"],
        "after_adapter": consistency(l1["target"].numpy(), a1["depth"].numpy(), a1["cam_K"].numpy(), W, H, geom, step=1)["share"],
    }
    k360 = sys.modules["ssc_pl.data.datasets.kitti_360"]
    own = k360.KITTI360("train", str(export), str(export / "preprocess/labels"), str(export / "depth_full"))
    res["own_class_len_on_export"] = len(own)  # its SPLITS are KITTI-360 sequence names
    # their class made to read this frame (sequence list, calibration, geometry patched here only)
    seq = ds.scans[0].sequence
    k360.SPLITS = {"train": (seq,)}
    P, T = ds.scans[0].P2, ds.scans[0].Tr
    k360.KITTI360.read_calib = staticmethod(lambda: {"P2": P, "Tr": T})
    own = k360.KITTI360("train", str(export), str(export / "preprocess/labels"), str(export / "depth_full"),
                        frustum_size=1)
    own.voxel_origin, own.voxel_size, own.scene_size = geom.voxel_origin, geom.voxel_size, geom.scene_size
    own.img_shape, own.num_classes = (W, H), geom.n_classes
    own.scans = [s for s in own.scans if Path(s["voxel_path"]).stem == ds.scans[0].frame_id]
    real = random.random
    try:
        random.random = lambda: 0.9  # flip = random.random() > 0.5
        fa, fl = own[0]
    finally:
        random.random = real
    res["flip"]["after_own_flip"] = consistency(fl["target"].numpy(), fa["depth"].numpy(), fa["cam_K"].numpy(), W, H, geom, step=1)["share"]
    res["flip"]["frame"] = f"{seq}/{ds.scans[0].frame_id}"
    res.update(config_edits=len(edits), config=edits, code_edits=0, bench_only_overrides=bench_only,
               stubs=stubs)
    return res


# ---- MonoScene family --------------------------------------------------------------------------
def run_monoscene(root: Path, export: Path, frustum: int, *, sscbench: bool) -> dict:
    stubs = stub_torchvision()
    for m in [m for m in sys.modules if m == "monoscene" or m.startswith("monoscene.")]:
        del sys.modules[m]
    sys.path.insert(0, str(root))
    geom = load_geometry(export)
    W, H = next(iter(geom.image_sizes.values()))
    if sscbench:
        dm_file = root / "monoscene" / "data" / "kitti_360" / "kitti_360_dm.py"
        old = "from monoscene.data.kitti_360.kitti_360_dataset import Kitti360Dataset"
        new = "from occufly.datasets.compat.monoscene import Kitti360Dataset"
        own_mod, own_cls = "monoscene.data.kitti_360.kitti_360_dataset", "Kitti360Dataset"
        dm_name, droot = "Kitti360DataModule", export
        cfg_edits = ["kitti_360_root: <export>", "kitti_360_preprocess_root: <export>/preprocess",
                     "dataset: kitti_360"]
        script = "monoscene/scripts/train_monoscene_kitti_360.py:43-52"
    else:
        dm_file = root / "monoscene" / "data" / "semantic_kitti" / "kitti_dm.py"
        old = "from monoscene.data.semantic_kitti.kitti_dataset import KittiDataset"
        new = "from occufly.datasets.compat.monoscene import KittiDataset"
        own_mod, own_cls = "monoscene.data.semantic_kitti.kitti_dataset", "KittiDataset"
        dm_name, droot = "KittiDataModule", export
        cfg_edits = ["dataset: kitti (upstream trains only kitti / NYU)", "kitti_root: <export>",
                     "kitti_preprocess_root: <export>/preprocess"]
        script = "monoscene/scripts/train_monoscene.py:49-58"
    src = dm_file.read_text()
    assert src.count(old) == 1, f"{dm_file}: the import line to patch is not there"
    dm_mod = load_file(f"_occufly_bench_{dm_name}", dm_file, src.replace(old, new))
    code_edits = [f"{dm_file.relative_to(root)}: `{old}` -> `{new}`",
                  f"{script}: full_scene_size, n_classes, class_weights, class_names from "
                  "occufly.datasets.compat.monoscene.training_constants(<export>)"]
    dm = getattr(dm_mod, dm_name)(root=str(droot), preprocess_root=str(export / "preprocess"),
                                  frustum_size=frustum, project_scale=2, batch_size=1, num_workers=0)
    dm.setup()
    batch = next(iter(dm.train_dataloader()))
    res = {"loads": True,
           "lengths": {"train": len(dm.train_ds), "val": len(dm.val_ds), "test": len(dm.test_ds)},
           "batch": shapes(batch),
           "fov_share": round(fov_share(batch["target"][0].numpy(), batch["fov_mask_1"][0].numpy()), 4)}
    ds = dm.val_ds
    ds_cls = type(ds)

    def samp(d, i):
        s = d.sample(i)
        return s["target"], np.load(export / "depth_full" / s["sequence"] / f"{s['frame_id']}.npy"), s["cam_k"], W, H, s["sequence"]

    res["depth_consistency"] = per_altitude(
        lambda s: ds_cls(s, str(droot), str(export / "preprocess"), frustum_size=1), samp, geom)
    # their flip mirrors image and u, not the target: the label-to-pixel map stays right
    tr = dm.train_ds
    a, b = tr.sample(0, False), tr.sample(0, True)
    Wi = W
    u0, u1 = a["projected_pix_1"][:, 0], b["projected_pix_1"][:, 0]
    res["flip"] = {"kind": "image + projected u mirrored, target unchanged (theirs, kept)",
                   "u_mirrored": bool(np.array_equal(u1, Wi - 1 - u0)),
                   "target_unchanged": bool(np.array_equal(a["target"], b["target"]))}
    own = importlib.import_module(own_mod)
    try:  # its hard-coded split lists KITTI sequence names
        res["own_class_len_on_export"] = len(getattr(own, own_cls)(
            "train", str(droot), str(export / "preprocess")))
    except OSError as e:
        res["own_class_len_on_export"] = f"{type(e).__name__}: {e}"
    res.update(config_edits=len(cfg_edits), config=cfg_edits, code_edits=len(code_edits),
               code=code_edits, stubs=stubs,
               why_code_edits="the DataModule constructs its Dataset by name and the training "
                              "script hard-codes geometry and classes; Hydra 1.0.5 (pinned) has no callbacks")
    return res


# ---- CGFormer ----------------------------------------------------------------------------------
def run_cgformer(root: Path, export: Path) -> dict:
    stubs = stub_torchvision() + stub_mmdet()
    package_stub("mmdet3d_plugin", root / "mmdet3d_plugin")
    package_stub("mmdet3d_plugin.datasets", root / "mmdet3d_plugin" / "datasets")
    importlib.import_module("mmdet3d_plugin.datasets.pipelines")
    stubs.append("mmdet3d_plugin/__init__.py and datasets/__init__.py not run (import the models "
                 "and mmdet3d); datasets/pipelines import unchanged")
    from mmdet.datasets import DATASETS

    geom = load_geometry(export)
    W, H = next(iter(geom.image_sizes.values()))
    pcr = [*geom.voxel_origin.tolist(), *(geom.voxel_origin + np.asarray(geom.scene_size)).tolist()]
    edits = {
        "custom_imports": "dict(imports=['occufly.datasets.compat.cgformer'], allow_failed_imports=False)",
        "dataset_type": "'OccuFlyKITTI360Dataset'",
        "data_root": f"'{export}'",
        "ann_file": f"'{export}/preprocess/labels'",
        "stereo_depth_root": f"'{export}/depth_full'",
        "point_cloud_range": repr(pcr),
        "occ_size": repr(list(geom.grid_shape)),
        "data_config['input_size']": repr((H, W)),
    }
    cfg_file = root / "configs" / "CGFormer-Efficient-Swin-KITTI360.py"
    text = cfg_file.read_text()
    lines = text.splitlines()
    for k in ("data_root", "ann_file", "stereo_depth_root", "dataset_type", "point_cloud_range", "occ_size"):
        i = next(j for j, ln in enumerate(lines) if ln.startswith(f"{k} ="))
        lines[i] = f"{k} = {edits[k]}"
    lines.insert(0, f"custom_imports = {edits['custom_imports']}")
    size = edits["data_config['input_size']"]
    text = "\n".join(lines).replace("'input_size': (384, 1408),", f"'input_size': {size},")
    cfg: dict = {}
    exec(compile(text, str(cfg_file), "exec"), cfg)
    for mod in cfg["custom_imports"]["imports"]:  # what mmcv's Config.fromfile does
        importlib.import_module(mod)
    res = {"loads": True, "batch": {}, "lengths": {}}
    for split, key in (("train", "train"), ("val (split='test')", "val"), ("test", "test")):
        c = dict(cfg["data"][key])
        ds = DATASETS.build(c)
        res["lengths"][split] = len(ds)
    ds = DATASETS.build(dict(cfg["data"]["train"]))
    out = ds[0]
    meta = out["img_metas"]  # CollectData: keys, and meta_keys under img_metas
    imgs, rots, trans, intrins, post_rots, post_trans, bda, s2s = out["img_inputs"]
    res["batch"] = {"img_inputs[0] imgs": [list(imgs.shape), str(imgs.dtype)],
                    "gt_occ": [list(out["gt_occ"].shape), str(out["gt_occ"].dtype)],
                    "gt_depths": [list(meta["gt_depths"].shape), str(meta["gt_depths"].dtype)],
                    "stereo_depth": [list(meta["stereo_depth"].shape), str(meta["stereo_depth"].dtype)]}
    info = ds.get_data_info(0)
    from occufly.datasets.compat.common import vox2pix

    _, fov, _ = vox2pix(info["lidar2cam"][0], info["cam_intrinsic"][0][:3, :3], geom.voxel_origin,
                        geom.voxel_size, W, H, geom.scene_size)
    res["fov_share"] = round(fov_share(out["gt_occ"].numpy(), fov), 4)
    # depth consistency against the depth CGFormer builds from velodyne_points (its gt_depths)
    K = info["cam_intrinsic"][0][:3, :3]
    res["depth_consistency_lidar_gt_depths"] = consistency(out["gt_occ"].numpy(), meta["gt_depths"][0].numpy(), K, W, H, geom)["share"]

    def samp(d, i):
        inf = d.get_data_info(i)
        return inf["gt_occ"], np.load(inf["stereo_depth_path"]), inf["cam_intrinsic"][0], W, H, inf["sequence"]

    res["depth_consistency"] = per_altitude(
        lambda s: DATASETS.build(dict(cfg["data"]["train"], split=s, pipeline=None)), samp, geom)
    from occufly.datasets.compat.common import FlipRefused

    bad = [dict(s) for s in cfg["train_pipeline"]]
    for s in bad:
        if s["type"] == "LoadAnnotationOcc":
            s["apply_bda"] = True
    try:
        DATASETS.build(dict(cfg["data"]["train"], pipeline=bad))
        refused = None
    except FlipRefused as e:
        refused = str(e).split(": ", 1)[1][:160]
    res["flip"] = {"kind": "image flip via post_rot (theirs; off in the config); bda 3-D flips: "
                           "flip_dy would mirror the vertical axis here",
                   "apply_bda_true_with_config_ratios": f"refused: {refused}" if refused else "accepted"}
    res.update(config_edits=len(edits), config=[f"{k} = {v}" for k, v in edits.items()], code_edits=0,
               stubs=stubs, note="the model's literals that repeat the geometry (proposal_layer "
               "point_cloud_range, input_dimensions, volume_h/w/z, grid_config dbound) are "
               "model configuration, listed in docs/ssc-porting.md, not needed to load data")
    return res


def render_table(run: dict) -> str:
    """The Markdown table docs/ssc-porting.md carries (checked against the JSON by a test)."""
    rows = ["| codebase | commit | loads | config edits | code edits | train / val / test frames | occupied voxels in the image | depth consistency 50 / 40 / 30 m | flip: before → after |",
            "|---|---|---|---|---|---|---|---|---|"]
    for cb in run["codebases"].values():
        if not cb.get("loads"):
            rows.append(f"| {cb['name']} | {cb['commit'][:7]} | no: {cb.get('error', '')[:80]} | | | | | | |")
            continue
        L = list(cb["lengths"].values())
        dc = " / ".join(f"{v:.2f}" if v is not None else "–" for v in cb["depth_consistency"].values())
        fl = cb.get("flip", {})
        if "after_adapter" in fl:
            flip = f"{fl['before']:.2f} → {fl['after_adapter']:.2f} (own flip: {fl['after_own_flip']:.2f})"
        elif "u_mirrored" in fl:
            flip = "image + u mirrored, target kept" if fl["u_mirrored"] and fl["target_unchanged"] else "inconsistent"
        else:
            flip = "bda flip_dy refused" if "refused" in str(fl.get("apply_bda_true_with_config_ratios")) else "–"
        rows.append(f"| {cb['name']} | {cb['commit'][:7]} | yes | {cb['config_edits']} | {cb['code_edits']} | "
                    f"{' / '.join(map(str, L))} | {cb['fov_share']:.3f} | {dc} | {flip} |")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export", type=Path)
    for k in ("symphonies", "monoscene", "sscbench", "cgformer"):
        ap.add_argument(f"--{k}", type=Path, help=f"checkout of {k}")
    ap.add_argument("--commits", help="the checkouts' commits, comma-separated in the order above")
    ap.add_argument("--frustum-size", type=int, default=2,
                    help="frustum_size for the loaded batch (their configs use 8: 64 masks of the "
                         "full grid, ~0.8 GB per sample at 192x128x128)")
    ap.add_argument("--frames-per-altitude", type=int, default=3,
                    help="frames per altitude for the depth-consistency means (default 3)")
    a = ap.parse_args()
    global N_PER_ALTITUDE
    N_PER_ALTITUDE = a.frames_per_altitude
    export = a.export.absolute()
    commits = dict(zip(COMMITS, (a.commits or ",,,").split(","), strict=True))
    run = {"export": str(export), "frames_per_altitude": a.frames_per_altitude, "geometry": {},
           "codebases": {}}
    g = load_geometry(export)
    run["geometry"] = {"grid_shape": list(g.grid_shape), "voxel_size": g.voxel_size,
                       "n_classes": g.n_classes, "axes": g.axes,
                       "images": {k: list(v) for k, v in g.image_sizes.items()}}
    # Lightning probes for torchvision (find_spec): import it before the torchvision stub exists
    for m in ("lightning.pytorch", "pytorch_lightning", "torchmetrics"):
        try:
            importlib.import_module(m)
        except ImportError:
            pass
    jobs = {"symphonies": lambda: run_symphonies(a.symphonies, export, a.frustum_size),
            "monoscene": lambda: run_monoscene(a.monoscene, export, a.frustum_size, sscbench=False),
            "sscbench_monoscene": lambda: run_monoscene(a.sscbench / "method" / "MonoScene", export,
                                                        a.frustum_size, sscbench=True),
            "cgformer": lambda: run_cgformer(a.cgformer, export)}
    for key, job in jobs.items():
        try:
            r = job()
        except Exception as e:  # noqa: BLE001 - one codebase failing is a result, not a crash
            import traceback

            r = {"loads": False, "error": f"{type(e).__name__}: {e}",
                 "trace": traceback.format_exc().splitlines()[-6:]}
        r["name"] = NAMES[key]
        r["commit"] = commits[key] or COMMITS[key]
        run["codebases"][key] = r
    run["table"] = render_table(run)
    print(json.dumps(run, indent=1, default=str))


if __name__ == "__main__":
    main()
