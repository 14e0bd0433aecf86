"""Symphonies (hustvl/Symphonies, commit 4ca4ff2): a KITTI-360 dataset class over an
SSCBench-layout export, and the Hydra callback that makes it selectable from the config.

Symphonies builds its dataset with ``getattr(ssc_pl.data.datasets, cfg.data.datasets.type)``
(ssc_pl/data/build.py:18-21, ssc_pl/utils/build.py:46-53), so a class from another package
cannot be named in the config directly. The config-only way in: Hydra instantiates
``hydra.callbacks.*._target_`` before the task runs, and :class:`Register` adds
:class:`OccuFlyKITTI360` to ``ssc_pl.data.datasets`` when it is built::

    # configs/datasets/occufly.yaml (a new file; config.yaml: `- datasets: occufly`)
    # @package _global_
    hydra:
      callbacks:
        occufly:
          _target_: occufly.datasets.compat.symphonies.Register
    data:
      datasets:
        type: OccuFlyKITTI360
        splits: [train, val, test]
        data_root: /path/to/export
        label_root: /path/to/export/preprocess/labels
        depth_root: /path/to/export/depth_full
        frustum_size: 8
    model: {scene_size: [X, Y, Z], image_shape: [H, W], voxel_size: r, num_classes: C + 1}
    evaluator: {type: SSCMetrics, num_classes: C + 1}

Sample contract (ssc_pl/data/datasets/kitti_360.py:94-176 at 4ca4ff2): ``__getitem__``
returns ``(data, label)``; ``data``: ``frame_id``, ``sequence`` (str), ``P`` (3, 4) float32,
``cam_pose`` (4, 4) float32, ``proj_matrix`` (3, 4) float32, ``voxel_origin`` (3,) float32,
``scale_3ds`` tuple ``(project_scale // 2, project_scale)``, ``cam_K`` (3, 3) float32,
``projected_pix_<s>`` (N_s, 2) int64, ``pix_z_<s>`` (N_s,) float32, ``fov_mask_<s>`` (N_s,)
bool per scale, ``depth`` (H, W) float32 when ``depth_root``, ``img`` (3, H, W) float32
ImageNet-normalised; ``label``: ``target`` (X, Y, Z) uint8, ``CP_mega_matrix`` (4, N_8, N_8/8)
uint8 when ``context_prior``, ``frustums_masks`` (size^2, X, Y, Z) float32,
``frustums_class_dists`` (size^2, C + 1) float32. Class attribute ``META_INFO`` =
``{"class_weights": 1/log(freq) tensor, "class_names": tuple}`` (ssc_pl/data/build.py:21).

Differences from Symphonies' own KITTI360 class, all on purpose: each sequence's calib.txt
(theirs: one hard-coded KITTI-360 calibration), the export's splits (theirs: KITTI-360
sequence names), geometry from occufly.yaml (theirs: 0.2 m, 51.2 m literals), frames sorted,
and **the flip**: theirs flips image and depth left-right but the target along axis 1, which
in this export's camera-centric grid is the vertical axis -- silent label corruption. Here a
flip mirrors the grid axis the manifest's ``axes`` names as image left-right (axis 0), sets
cx' = W - 1 - cx in ``P`` / ``cam_K`` / ``proj_matrix`` and recomputes the projections, so
geometry and labels stay consistent; without an ``axes`` record the flip is refused
(:class:`~occufly.datasets.compat.common.FlipRefused`).
"""

from __future__ import annotations

import importlib
import random
from pathlib import Path

import numpy as np
import torch  # this module is the torch adapter: torch is its reason to exist
from PIL import Image
from torch.utils.data import Dataset

from occufly.datasets.compat.common import (
    check_flip,
    cp_mega_matrix,
    export_root,
    flip_K,
    list_scans,
    load_geometry,
    local_frustums,
    vox2pix,
)

_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_STD = np.array([0.229, 0.224, 0.225], np.float32)


def _meta_info(root) -> dict:
    g = load_geometry(export_root(root))
    return {"class_weights": torch.from_numpy(g.class_weights()).float(),
            "class_names": g.class_names}


class _MetaInfo:
    """``OccuFlyKITTI360.META_INFO`` is read from the class (ssc_pl/data/build.py:21) before any
    instance exists, so it comes from the export named by the last instance built (or by
    ``OCCUFLY_EXPORT`` / :func:`Register` ``data_root``)."""

    root: str | None = None

    def __get__(self, obj, owner) -> dict:
        if self.root is None:
            raise RuntimeError("OccuFlyKITTI360.META_INFO: no export known yet; pass data_root "
                               "to occufly.datasets.compat.symphonies.Register or build a dataset first")
        return _meta_info(self.root)


_META = _MetaInfo()


class OccuFlyKITTI360(Dataset):
    META_INFO = _META

    def __init__(self, split, data_root, label_root=None, depth_root=None, project_scale=2,
                 frustum_size=4, context_prior=False, flip=True, **_ignored):
        super().__init__()
        self.root = export_root(data_root)
        _META.root = str(self.root)
        self.label_root = Path(label_root) if label_root else self.root / "preprocess" / "labels"
        self.depth_root = Path(depth_root) if depth_root else None
        self.split = split
        self.project_scale = int(project_scale)
        self.output_scale = int(self.project_scale / 2)
        self.frustum_size = int(frustum_size)
        self.context_prior = bool(context_prior)
        self.flip = bool(flip)
        g = self.geometry = load_geometry(self.root)
        self.num_classes = g.n_classes
        self.voxel_origin = g.voxel_origin.copy()
        self.voxel_size = g.voxel_size
        self.scene_size = g.scene_size
        self.scans = list_scans(self.root, split)
        if self.flip and split == "train":
            self.lr_axis = check_flip(g, str(self.root))

    def __len__(self) -> int:
        return len(self.scans)

    def sample(self, idx: int, flip: bool = False) -> tuple[dict, dict]:
        """The sample of frame ``idx``, left-right flipped when ``flip`` (deterministic)."""
        scan = self.scans[idx]
        W, H = scan.image_size
        P = np.asarray(scan.P2, np.float64)
        T = np.asarray(scan.Tr, np.float64)
        if flip:
            axis = check_flip(self.geometry, str(self.root))
            P = flip_K(P, W)
        proj = P @ T
        data: dict = {"frame_id": scan.frame_id, "sequence": scan.sequence, "P": P,
                      "cam_pose": T, "proj_matrix": proj, "voxel_origin": self.voxel_origin}
        label: dict = {}
        scale_3ds = (self.output_scale, self.project_scale)
        data["scale_3ds"] = scale_3ds
        cam_K = P[:3, :3]
        data["cam_K"] = cam_K
        for s in scale_3ds:
            pix, fov, z = vox2pix(T, cam_K, self.voxel_origin, self.voxel_size * s, W, H,
                                  self.scene_size)
            data[f"projected_pix_{s}"] = pix
            data[f"pix_z_{s}"] = z
            data[f"fov_mask_{s}"] = fov
        target = np.load(self.label_root / scan.sequence / f"{scan.frame_id}_1_1.npy")
        if flip:
            target = np.flip(target, axis=axis).copy()
        label["target"] = target
        if self.context_prior:
            t8 = np.load(self.label_root / scan.sequence / f"{scan.frame_id}_1_8.npy")
            if flip:
                t8 = np.flip(t8, axis=axis).copy()
            label["CP_mega_matrix"] = cp_mega_matrix(t8)
        if self.depth_root is not None:
            depth = np.load(self.depth_root / scan.sequence / f"{scan.frame_id}.npy")[:H, :W]
            if flip:
                depth = np.flip(depth, axis=1).copy()
            data["depth"] = depth
        masks, dists = local_frustums(data[f"projected_pix_{self.output_scale}"],
                                      data[f"pix_z_{self.output_scale}"], target, W, H,
                                      self.num_classes, self.frustum_size)
        label["frustums_masks"] = masks.astype(np.float32)
        label["frustums_class_dists"] = dists.astype(np.float32)
        img_path = self.root / "data_2d_raw" / scan.sequence / "image_00" / "data_rect" / f"{scan.frame_id}.png"
        with Image.open(img_path) as im:
            img = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
        if flip:
            img = np.flip(img, axis=1)
        img = (img[:H, :W] - _MEAN) / _STD
        data["img"] = np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32)
        for d in (data, label):
            for k, v in d.items():
                if isinstance(v, np.ndarray):
                    d[k] = torch.from_numpy(v.astype(np.float32) if v.dtype == np.float64 else v)
        return data, label

    def __getitem__(self, idx: int) -> tuple[dict, dict]:
        flip = random.random() > 0.5 if self.flip and self.split == "train" else False
        return self.sample(idx, flip)


class Register:
    """Hydra callback (``hydra.callbacks.<name>._target_``): adds :class:`OccuFlyKITTI360` to
    ``ssc_pl.data.datasets`` so ``data.datasets.type: OccuFlyKITTI360`` finds it. Building it
    is the registration; the callback methods do nothing."""

    dataset_class = OccuFlyKITTI360
    default_module = "ssc_pl.data.datasets"

    def __init__(self, data_root: str | None = None, module: str | None = None) -> None:
        if data_root is not None:
            # the META_INFO descriptor itself (reading the attribute would call it)
            self.dataset_class.__dict__["META_INFO"].root = str(export_root(data_root))
        module = module or self.default_module
        try:
            mod = importlib.import_module(module)
        except ImportError as e:
            raise ImportError(f"{type(self).__module__}.Register: cannot import {module} ({e}); "
                              "run from the codebase's checkout (PYTHONPATH=.)") from e
        setattr(mod, self.dataset_class.__name__, self.dataset_class)

    def __getattr__(self, name: str):
        if name.startswith("on_"):
            return lambda *a, **k: None
        raise AttributeError(name)
