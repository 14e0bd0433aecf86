"""Load an SSCBench-layout export with five SSC codebases' own loading code through the
adapters of occufly.datasets.compat, and print one JSON object (docs/bench/ssc_loaders.json,
docs/ssc-porting.md).

    python bench/bench_ssc_loaders.py EXPORT --symphonies DIR --monoscene DIR \
        --sscbench DIR --cgformer DIR --disc DIR [--commits a,b,c,d,e] > docs/bench/ssc_loaders.json

Run outside CI; it fetches nothing: DIR are checkouts of hustvl/Symphonies 4ca4ff2,
astra-vision/MonoScene f52bbb1, ai4ce/SSCBench 9e767e1, pkqbajng/CGFormer 0331e11 and
Enyu-Liu/DISC 00ecc7f. The export should be ``occufly export WS OUT --layout sscbench
--velodyne --split-by altitude`` (train = 50 m, val = 40 m, test = 30 m). Python deps beside
occufly's: hydra-core, omegaconf, lightning / pytorch-lightning, numba, scikit-image.

Per codebase: does its loader load the export (the codebase's DataLoader / DataModule /
pipeline code, with the adapter as dataset), does **every split** produce a batch, the
configuration edits and code edits that takes, the batch shapes, the memory of one training
sample (at the configs' frustum_size and at the bench's), the share of occupied voxels inside
the image (fov mask), the depth-consistency share per altitude through **the codebase's own
projection** (its ``vox2pix``; for CGFormer the camera matrices of its pipeline as its model
uses them) on ``--frames-per-altitude`` frames: per pixel the nearest occupied voxel whose
centre projects there vs the depth map, within 1 m; and whether that projection equals the
adapter's. Before / after a flip: the adapter's, and the codebase's own flip on the same frame.

What cannot be imported here is stubbed, and the JSON says so (``stubs``): torchvision (the
CPU torch 2.13 wheel has no matching torchvision; ToTensor / Normalize / Compose are
re-implemented, ColorJitter is the identity), Symphonies' / DISC's package ``__init__`` (imports
the models: MaskDINO, mmdet), and for CGFormer mmcv / mmdet (mmcv-full 1.4 needs CUDA ops): a
registry and Compose stand in for mmdet's, CGFormer's own pipeline steps run unchanged.
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
           "cgformer": "0331e11", "disc": "00ecc7f"}
NAMES = {"symphonies": "Symphonies", "monoscene": "MonoScene",
         "sscbench_monoscene": "SSCBench", "cgformer": "CGFormer", "disc": "DISC"}


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


N_PER_ALTITUDE = 10


def nbytes(obj) -> int:
    """Bytes of the arrays / tensors in a sample (dicts, lists, tuples walked)."""
    if hasattr(obj, "nbytes") and hasattr(obj, "shape"):
        return int(obj.nbytes)
    if hasattr(obj, "element_size") and hasattr(obj, "numel"):
        return int(obj.element_size() * obj.numel())
    if isinstance(obj, dict):
        return sum(nbytes(v) for v in obj.values())
    if isinstance(obj, list | tuple):
        return sum(nbytes(v) for v in obj)
    return 0


def zbuffer_consistency(target, depth, pix, fov, z, tol: float = 1.0) -> dict:
    """Depth vs grid through a codebase's own projection: per pixel, the nearest occupied voxel
    whose centre the codebase projects there (its projected_pix / fov_mask / pix_z, rounded
    where they are float), against the depth map at that pixel; the share within ``tol`` m
    over pixels with depth > 0 that an occupied voxel centre reaches."""
    t = np.asarray(target).reshape(-1)
    pix = np.asarray(pix)
    pix = np.round(pix).astype(np.int64) if pix.dtype.kind == "f" else pix.astype(np.int64)
    z = np.asarray(z, np.float64).reshape(-1)
    depth = np.asarray(depth, np.float64)
    H, W = depth.shape
    sel = np.asarray(fov).reshape(-1) & (t != 0) & (t != 255)
    sel &= (pix[:, 0] >= 0) & (pix[:, 0] < W) & (pix[:, 1] >= 0) & (pix[:, 1] < H)
    lin = pix[sel, 1] * W + pix[sel, 0]
    zb = np.full(H * W, np.inf)
    np.minimum.at(zb, lin, z[sel])
    d = depth.reshape(-1)
    ok = np.isfinite(zb) & (d > 0)
    if not ok.any():
        return {"share": float("nan"), "pixels": 0}
    return {"share": float(np.mean(np.abs(zb[ok] - d[ok]) <= tol)), "pixels": int(ok.sum())}


def per_altitude(make_ds, sample_fn, n=None) -> dict:
    """Depth consistency through the codebase's projection over n frames of each split (=
    altitude with --split-by altitude). ``sample_fn(ds, i)`` -> (target, depth, pix, fov, z,
    sequence, same) where ``same`` says whether the codebase's own projection function gave
    the adapter's projection on that frame (None: not checked)."""
    n = n or N_PER_ALTITUDE
    out, frames, same = {}, {}, []
    for split in ("train", "val", "test"):
        ds = make_ds(split)
        if not len(ds):
            out[split] = None
            continue
        idx = np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int)
        shares, alt = [], None
        for i in idx:
            target, depth, pix, fov, z, seq, eq = sample_fn(ds, int(i))
            alt = seq.rsplit("_", 1)[-1]
            shares.append(zbuffer_consistency(target, depth, pix, fov, z)["share"])
            if eq is not None:
                same.append(bool(eq))
        key = f"{alt} m ({split})"
        out[key] = round(float(np.mean(shares)), 4)
        frames[key] = {"n": len(shares), "min": round(float(np.min(shares)), 4),
                       "max": round(float(np.max(shares)), 4)}
    return {"mean": out, "frames": frames,
            "own_projection_equals_adapter": (all(same) if same else None), "checked": len(same)}


def batch_every_split(loaders: dict) -> dict:
    """One batch of each split through the codebase's own loader: shapes, or the error."""
    out = {}
    for split, make in loaders.items():
        try:
            b = make()
            out[split] = {"batched": True, "keys": len(b) if isinstance(b, dict) else None}
        except Exception as e:  # noqa: BLE001 - a split that does not batch is the finding
            out[split] = {"batched": False, "error": f"{type(e).__name__}: {e}"[:200]}
    return out


# ---- Symphonies and DISC (a Symphonies fork): Hydra configs, getattr(datasets, type) ---------
def run_hydra_codebase(root: Path, export: Path, frustum: int, *, disc: bool) -> dict:
    stubs = stub_torchvision()
    pkg = "ssc_ia" if disc else "ssc_pl"
    sys.path.insert(0, str(root))
    # <pkg>/__init__ imports the models (MaskDINO / mmdet); only its data and utils are needed
    top = package_stub(pkg, root / pkg)
    if disc:  # data/datasets/kitti_360.py -> utils/projection.py -> models/utils/utils.py (torch only)
        package_stub(f"{pkg}.models", root / pkg / "models")
        package_stub(f"{pkg}.models.utils", root / pkg / "models" / "utils")
    utils = importlib.import_module(f"{pkg}.utils")
    top.build_from_configs = utils.build_from_configs
    data = importlib.import_module(f"{pkg}.data")
    helper = importlib.import_module(f"{pkg}.utils.helper")  # their vox2pix (numba)
    stubs.append(f"{pkg}/__init__.py not run (imports the models: MaskDINO, mmdet); "
                 f"{pkg}.data and {pkg}.utils import unchanged")
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    geom = load_geometry(export)
    W, H = next(iter(geom.image_sizes.values()))
    mod = "disc" if disc else "symphonies"
    edits = [] if disc else ["datasets=kitti_360"]  # Symphonies' default `datasets: semantic_kitti`
    edits += [
        f"+hydra.callbacks.occufly._target_=occufly.datasets.compat.{mod}.Register",
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
    if disc:
        from occufly.datasets.compat.disc import training_constants

        tc = training_constants(export)
        edits += [f"data.datasets.data_config.input_size=[{H},{W}]",
                  f"model.class_frequencies=[{','.join(map(str, tc['class_frequencies']))}]",
                  f"model.decoder.bk_cls={tc['bk_cls']}", f"model.decoder.ins_cls={tc['ins_cls']}"]
    bench_only = ["data.loader.num_workers=0"] + ([] if disc else [f"data.datasets.frustum_size={frustum}"])
    with initialize_config_dir(config_dir=str(root / "configs"), version_base=None):
        cfg = compose(config_name="config_360" if disc else "config", overrides=edits + bench_only,
                      return_hydra_config=True)
    instantiate(cfg.hydra.callbacks.occufly)  # what Hydra does with hydra.callbacks at start
    from omegaconf import OmegaConf

    OmegaConf.set_struct(cfg, False)
    cfg.pop("hydra")
    dls, meta = data.build_data_loaders(cfg.data)
    splits = ("train", "val", "test")
    batches = {}

    def first(split, dl):
        batches[split] = next(iter(dl))
        return {**batches[split][0], **batches[split][1]}

    res = {"loads": True, "lengths": {s: len(dl.dataset) for s, dl in zip(splits, dls, strict=True)},
           "splits_batched": batch_every_split({s: (lambda s=s, dl=dl: first(s, dl)) for s, dl in zip(splits, dls, strict=True)})}
    inputs, labels = batches["train"]
    res.update(batch={**shapes(inputs), **shapes(labels)},
               fov_share=round(fov_share(labels["target"][0].numpy(), inputs["fov_mask_1"][0].numpy()), 4),
               meta_info=sorted(meta))
    ds = dls[0].dataset
    cls = type(ds)
    # memory of one training sample: the configs' frustum_size 8 (Symphonies), the bench's
    if disc:
        res["memory_mb_per_sample"] = {"config": round(nbytes(ds.sample(0)) / 2**20, 1)}
    else:
        res["memory_mb_per_sample"] = {
            f"frustum_size={f}": round(nbytes(cls("train", export, depth_root=export / "depth_full", flip=False,
                                                  frustum_size=f, context_prior=True).sample(0)) / 2**20, 1)
            for f in (8, 2)}

    def samp(d, i):
        a, b = d.sample(i)
        if disc:
            pix, fov, z = helper.vox2pix(a["cam_pose"].numpy().astype(np.float64), a["cam_K"].numpy().astype(np.float64),
                                         d.voxel_origin, d.voxel_size, d.img_shape, d.scene_size,
                                         a["post_rot"].numpy().astype(np.float64), a["post_tran"].numpy().astype(np.float64))
        else:
            pix, fov, z = helper.vox2pix(a["cam_pose"].numpy().astype(np.float64), a["cam_K"].numpy().astype(np.float64),
                                         d.voxel_origin, d.voxel_size, (W, H), d.scene_size)
        same = bool(np.array_equal(np.asarray(pix, np.float64), a["projected_pix_1"].numpy().astype(np.float64))
                    and np.array_equal(fov, a["fov_mask_1"].numpy()))
        tgt = b.get("target")
        if tgt is None:  # DISC's test samples carry no target (as theirs): read the label file
            tgt = np.load(d.label_root / a["sequence"] / f"{a['frame_id']}_1_1.npy")
        return np.asarray(tgt), a["depth"].numpy(), pix, fov, z, a["sequence"], same

    if disc:
        make = lambda s: cls(s, export, depth_root=export / "depth_full", data_config={"input_size": [H, W]})  # noqa: E731
    else:
        make = lambda s: cls(s, export, depth_root=export / "depth_full", flip=False, frustum_size=1)  # noqa: E731
    res["depth_consistency"] = per_altitude(make, samp)
    if disc:
        return res | run_disc_flip(ds, export, geom, W, H, edits, bench_only, stubs, helper)
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




def run_disc_flip(ds, export, geom, W, H, edits, bench_only, stubs, helper) -> dict:
    """DISC's flip on frame 0 of train: image + depth through post_rot, the target kept (the
    adapter); the share before / after through DISC's own vox2pix with the flipped post_rot,
    and with DISC's own target flip (np.flip(target, axis=1), kitti_360.py:134) added."""
    a0, l0 = ds.sample(0, False)
    a1, l1 = ds.sample(0, True)

    def share(a, tgt):
        pix, fov, z = helper.vox2pix(a["cam_pose"].numpy().astype(np.float64), a["cam_K"].numpy().astype(np.float64),
                                     ds.voxel_origin, ds.voxel_size, ds.img_shape, ds.scene_size,
                                     a["post_rot"].numpy().astype(np.float64), a["post_tran"].numpy().astype(np.float64))
        return round(zbuffer_consistency(tgt, a["depth"].numpy(), pix, fov, z)["share"], 4)

    t0 = l0["target"].numpy()
    flip = {"kind": "image + depth mirrored through post_rot (theirs), target kept",
            "before": share(a0, t0), "after_adapter": share(a1, l1["target"].numpy()),
            "after_own_flip": share(a1, np.flip(t0, axis=1)),
            "target_unchanged": bool(np.array_equal(l1["target"].numpy(), t0)),
            "frame": f"{ds.scans[0].sequence}/{ds.scans[0].frame_id}"}
    return {"flip": flip, "config_edits": len(edits), "config": edits, "code_edits": 0,
            "bench_only_overrides": bench_only, "stubs": stubs,
            "command_line": "tools/train.py --config-name config_360 (its default is config_sema)"}


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
                     "dataset: kitti_360",
                     "kitti_360_logdir: <a writable folder> (was /home/duan/...: TensorBoard logs, "
                     "checkpoints and the last.ckpt resume path; enable_log: true writes there, "
                     "false writes no logs and no checkpoints)"]
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
    got = {}

    def first(split, make):
        got[split] = next(iter(make()))
        return got[split]

    batched = batch_every_split({"train": lambda: first("train", dm.train_dataloader),
                                 "val": lambda: first("val", dm.val_dataloader),
                                 "test": lambda: first("test", dm.test_dataloader)})
    batch = got["train"]
    res = {"loads": True,
           "lengths": {"train": len(dm.train_ds), "val": len(dm.val_ds), "test": len(dm.test_ds)},
           "splits_batched": batched, "batch": shapes(batch),
           "fov_share": round(fov_share(batch["target"][0].numpy(), batch["fov_mask_1"][0].numpy()), 4)}
    ds = dm.val_ds
    ds_cls = type(ds)
    res["memory_mb_per_sample"] = {
        f"frustum_size={f}": round(nbytes(ds_cls("train", str(droot), str(export / "preprocess"),
                                                 frustum_size=f).sample(0)) / 2**20, 1) for f in (8, 2)}
    helpers = importlib.import_module("monoscene.data.utils.helpers")  # their vox2pix (numba)

    def samp(d, i):
        s = d.sample(i)
        pix, fov, z = helpers.vox2pix(s["T_velo_2_cam"], s["cam_k"], d.vox_origin, d.voxel_size,
                                      W, H, d.scene_size)
        same = bool(np.array_equal(pix, s["projected_pix_1"]) and np.array_equal(fov, s["fov_mask_1"]))
        depth = np.load(export / "depth_full" / s["sequence"] / f"{s['frame_id']}.npy")
        return s["target"], depth, pix, fov, z, s["sequence"], same

    res["depth_consistency"] = per_altitude(
        lambda s: ds_cls(s, str(droot), str(export / "preprocess"), frustum_size=1), samp)
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
    res = {"loads": True, "batch": {}, "lengths": {}, "splits_batched": {}}
    built = {}
    for split, key in (("train", "train"), ("val (split='test')", "val"), ("test", "test")):
        built[split] = DATASETS.build(dict(cfg["data"][key]))
        res["lengths"][split] = len(built[split])
    # every split through its own pipeline (mmcv's collate is stubbed with the rest of mmcv)
    res["splits_batched"] = batch_every_split({s: (lambda d=d: d[0]) for s, d in built.items()})
    ds = built["train"]
    out = ds[0]
    meta = out["img_metas"]  # CollectData: keys, and meta_keys under img_metas
    imgs, rots, trans, intrins, post_rots, post_trans, bda, s2s = out["img_inputs"]
    res["batch"] = {"img_inputs[0] imgs": [list(imgs.shape), str(imgs.dtype)],
                    "gt_occ": [list(out["gt_occ"].shape), str(out["gt_occ"].dtype)],
                    "gt_depths": [list(meta["gt_depths"].shape), str(meta["gt_depths"].dtype)],
                    "stereo_depth": [list(meta["stereo_depth"].shape), str(meta["stereo_depth"].dtype)]}
    res["memory_mb_per_sample"] = {"config": round(nbytes(out) / 2**20, 1)}
    info = ds.get_data_info(0)
    from occufly.datasets.compat.common import voxel_centres

    centres, _ = voxel_centres(geom.voxel_origin, geom.voxel_size, geom.scene_size)

    def project(o):
        """Voxel centres to pixels the way CGFormer's model does (transformer_utils/encoder.py
        :127-133: inverse(bda) on the reference points, then the camera from rots / trans,
        intrins, post_rots / post_trans of img_inputs)."""
        _, R, t, K, pr, pt, b, _ = [np.asarray(x, np.float64) for x in o["img_inputs"]]
        binv = np.linalg.inv(b)
        p = centres.astype(np.float64) @ binv[:3, :3].T + binv[:3, 3]
        cam = (p - t[0]) @ R[0]  # R^T (p - t): rots / trans are camera -> lidar
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam @ K[0][:3, :3].T)[:, :2] / z[:, None]
        uv = uv @ pr[0][:2, :2].T + pt[0][:2]
        uv = np.where(np.isfinite(uv), uv, -1)
        h, w = o["img_inputs"][0].shape[-2:]
        fov = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h) & (z > 0)
        return uv, fov, z

    _, fov, _ = project(out)
    res["fov_share"] = round(fov_share(out["gt_occ"].numpy(), fov), 4)
    # depth consistency against the depth CGFormer builds from velodyne_points (its gt_depths)
    K = info["cam_intrinsic"][0][:3, :3]
    res["depth_consistency_lidar_gt_depths"] = consistency(out["gt_occ"].numpy(), meta["gt_depths"][0].numpy(), K, W, H, geom)["share"]

    def samp(d, i):
        o = d[i]
        uv, fv, z = project(o)
        return (o["gt_occ"].numpy(), np.load(d.get_data_info(i)["stereo_depth_path"]), uv, fv, z,
                d.get_data_info(i)["sequence"], None)

    res["depth_consistency"] = per_altitude(
        lambda s: DATASETS.build(dict(cfg["data"]["test"], split=s)), samp)
    # bda: apply_bda with the config's ratios is accepted; forced flip_dx + flip_dy through their
    # LoadAnnotationOcc on frame 0, projected as the model does (inverse bda): before / after
    flipped = [dict(st) for st in cfg["train_pipeline"]]
    for st in flipped:
        if st["type"] == "LoadAnnotationOcc":
            st.update(apply_bda=True, bda_aug_conf=dict(st["bda_aug_conf"], flip_dx_ratio=1.0,
                                                        flip_dy_ratio=1.0, rot_lim=(0, 0), scale_lim=(1, 1)))
    fds = DATASETS.build(dict(cfg["data"]["train"], pipeline=flipped))
    fo = fds[0]
    depth0 = np.load(ds.get_data_info(0)["stereo_depth_path"])

    def share(o):
        uv, fv, z = project(o)
        return round(zbuffer_consistency(o["gt_occ"].numpy(), depth0, uv, fv, z)["share"], 4)

    res["flip"] = {"kind": "bda flip_dx + flip_dy (LoadAnnotationOcc apply_bda=True), features placed "
                           "with inverse(bda_rot) as the model does",
                   "apply_bda_true_with_config_ratios": "accepted",
                   "before": share(out), "after_adapter": share(fo),
                   "bda_rot": np.asarray(fo["img_inputs"][6]).round(3).tolist()}
    res.update(config_edits=len(edits), config=[f"{k} = {v}" for k, v in edits.items()], code_edits=0,
               stubs=stubs, note="the model's literals that repeat the geometry (proposal_layer "
               "point_cloud_range, input_dimensions, volume_h/w/z, grid_config dbound) are "
               "model configuration, listed in docs/ssc-porting.md, not needed to load data")
    return res


def render_table(run: dict) -> str:
    """The Markdown table docs/ssc-porting.md carries (checked against the JSON by a test)."""
    rows = ["| codebase | commit | loads | every split batches | config edits | code edits | train / val / test frames | MB per sample | occupied voxels in the image | depth consistency 50 / 40 / 30 m (own projection) | flip: before → after |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for cb in run["codebases"].values():
        if not cb.get("loads"):
            rows.append(f"| {cb['name']} | {cb['commit'][:7]} | no: {cb.get('error', '')[:80]} | | | | | | | | |")
            continue
        L = list(cb["lengths"].values())
        dc = " / ".join(f"{v:.2f}" if v is not None else "–" for v in cb["depth_consistency"]["mean"].values())
        ok = all(v.get("batched") for v in cb.get("splits_batched", {}).values())
        mem = cb.get("memory_mb_per_sample", {})
        mem = " / ".join(f"{v:.0f}" for v in mem.values()) if mem else "–"
        fl = cb.get("flip", {})
        if "after_own_flip" in fl:
            flip = f"{fl['before']:.2f} → {fl['after_adapter']:.2f} (own flip: {fl['after_own_flip']:.2f})"
        elif "after_adapter" in fl:
            flip = f"bda flip_dx + flip_dy: {fl['before']:.2f} → {fl['after_adapter']:.2f}"
        elif "u_mirrored" in fl:
            flip = "image + u mirrored, target kept" if fl["u_mirrored"] and fl["target_unchanged"] else "inconsistent"
        else:
            flip = "–"
        rows.append(f"| {cb['name']} | {cb['commit'][:7]} | yes | {'yes' if ok else 'NO'} | {cb['config_edits']} | "
                    f"{cb['code_edits']} | {' / '.join(map(str, L))} | {mem} | {cb['fov_share']:.3f} | {dc} | {flip} |")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export", type=Path)
    for k in ("symphonies", "monoscene", "sscbench", "cgformer", "disc"):
        ap.add_argument(f"--{k}", type=Path, help=f"checkout of {k}")
    ap.add_argument("--commits", help="the checkouts' commits, comma-separated in the order above")
    ap.add_argument("--frustum-size", type=int, default=2,
                    help="frustum_size for the loaded batch (their configs use 8: 64 masks of the "
                         "full grid, ~0.8 GB per sample at 192x128x128)")
    ap.add_argument("--frames-per-altitude", type=int, default=10,
                    help="frames per altitude for the depth-consistency means (default 10)")
    a = ap.parse_args()
    global N_PER_ALTITUDE
    N_PER_ALTITUDE = a.frames_per_altitude
    export = a.export.absolute()
    commits = dict(zip(COMMITS, (a.commits or ",,,,").split(","), strict=True))
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
    jobs = {"symphonies": lambda: run_hydra_codebase(a.symphonies, export, a.frustum_size, disc=False),
            "monoscene": lambda: run_monoscene(a.monoscene, export, a.frustum_size, sscbench=False),
            "sscbench_monoscene": lambda: run_monoscene(a.sscbench / "method" / "MonoScene", export,
                                                        a.frustum_size, sscbench=True),
            "cgformer": lambda: run_cgformer(a.cgformer, export),
            "disc": lambda: run_hydra_codebase(a.disc, export, a.frustum_size, disc=True)}
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
