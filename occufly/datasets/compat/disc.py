"""DISC (Enyu-Liu/DISC 00ecc7f, ICCV 2025): a KITTI-360 dataset class over an SSCBench-layout
export, and the Hydra callback that makes it selectable from the config.

DISC is built on Symphonies: ``tools/train.py`` builds its loaders with
``build_data_loaders(cfg.data)``, which looks the dataset up with
``getattr(ssc_ia.data.datasets, cfg.data.datasets.type)`` (``ssc_ia/data/build.py:8-21``,
``ssc_ia/utils/build.py:55-63``), and ``@hydra.main(..., version_base=None)`` is Hydra >= 1.2,
which runs ``hydra.callbacks`` before the task. So the port is **configuration only**:
:class:`Register` (a Hydra callback) adds :class:`OccuFlyKITTI360` to ``ssc_ia.data.datasets``::

    # tools/train.py --config-name config_360 (the script's default is config_sema), and:
    hydra:
      callbacks:
        occufly:
          _target_: occufly.datasets.compat.disc.Register
    data:
      datasets:
        type: OccuFlyKITTI360
        data_root: /path/to/export
        label_root: /path/to/export/preprocess/labels
        depth_root: /path/to/export/depth_full
        data_config: {input_size: [H, W], ...}
    model: {image_shape: [H, W], scene_size: [X, Y, Z], num_classes: C + 1,
            class_frequencies: [...], decoder: {bk_cls: ..., ins_cls: ...}}
    evaluator: {num_classes: C + 1}

Sample contract (``ssc_ia/data/datasets/kitti_360.py:101-203`` at 00ecc7f): ``(data, label)``;
``data``: ``frame_id``, ``sequence`` (str), ``P`` (3, 4), ``cam_pose`` (4, 4), ``proj_matrix``
(3, 4), ``voxel_origin`` (3,), ``cam_K`` (3, 3) -- float32 tensors; ``scale_3ds`` tuple
``(project_scale // 2, project_scale)``; ``img`` (3, fH, fW) float32 ImageNet-normalised and
``depth`` (fH, fW) float32, both resized / cropped (/ flipped) to ``data_config['input_size']``
by their ``sample_augmentation`` + ``img_transform``; ``post_rot`` (3, 3), ``post_tran`` (3,)
float32, the image augmentation; ``projected_pix_<s>`` (N_s, 2) **float32** (the rounded
projection moved by ``post_rot`` / ``post_tran``), ``pix_z_<s>`` float32, ``fov_mask_<s>`` bool
against (fH, fW). ``label``: ``class_fres`` (C + 1,) int64 class voxel counts,
``bk_cls_info`` / ``ins_cls_info`` (``{"indices": (K,) int64 array starting with 0, "names":
[...]}``: scene and instance classes), ``depth``; and, not for ``split="test"`` (theirs has no
target there), ``target`` (X, Y, Z) uint8, ``bev_seg_bk`` / ``bev_seg_ins`` (X, Y) uint8 and
``seg_img`` (fH, fW) int64 (``ssc_ia/utils/projection.py:213-238`` and ``:80-146``).

Differences from DISC's own class, on purpose: each sequence's calib.txt (theirs: one
hard-coded KITTI-360 calibration), the export's splits and geometry (theirs: KITTI-360
sequence names, 0.2 m / 51.2 m literals -- also ``vox_size=0.2*voxel_scale`` inside
``project_image_to_voxels``), instance / scene classes from the export's taxonomy groups
(``instance`` -> instance stream, ``ground`` / ``other`` -> scene stream; theirs: KITTI-360
index lists), ``seg_img`` pixels whose depth point falls outside the grid are 255 on every side
(theirs checks only ``>= dims``, so a negative index wraps around), the point's voxel is the
one containing it (theirs subtracts half a voxel and truncates), and **the flip**. Theirs draws
the target flip (``np.flip(target, axis=1)``, line 134) and the image flip (in
``sample_augmentation``, line 281) independently, and the image flip already moves the
projections (``post_rot`` goes into ``vox2pix``), so any target flip is wrong -- on KITTI too;
``flip: False`` in their configs. Here a flip mirrors image and depth through ``post_rot``
exactly as theirs and leaves the target alone, which is right for any grid (as MonoScene's).
Their flip maps u -> fW - u in the projections (``b = crop width``, kitti_360.py:312) while the
image's pixel u goes to fW - 1 - u: one pixel off, kept as theirs.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import torch  # this module is the torch adapter: torch is its reason to exist
from PIL import Image
from torch.utils.data import Dataset

from occufly.datasets.compat.common import export_root, list_scans, load_geometry, vox2pix
from occufly.datasets.compat.symphonies import Register as _SymphoniesRegister
from occufly.errors import InputFormatError

_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_STD = np.array([0.229, 0.224, 0.225], np.float32)
DEFAULT_DATA_CONFIG = {"input_size": None, "resize": [0.0, 0.0], "rot": [0.0, 0.0],
                       "flip": False, "crop_h": [0.0, 0.0], "resize_test": 0.0}


def class_streams(root) -> tuple[dict, dict]:
    """(bk_cls_info, ins_cls_info) of the export: the training ids of the taxonomy's
    ``instance`` group (instance stream) and of the others (scene stream), each led by 0
    (empty), with their names -- DISC's decoder sizes are ``len(indices)``."""
    root = export_root(root)
    g = load_geometry(root)
    group: dict[str, str] = {}
    for mp in sorted((root / "manifests").glob("*.json")):
        tax = json.loads(mp.read_text()).get("taxonomy") or {}
        group.update({c["name"]: c.get("group", "") for c in tax.get("classes", [])})
    missing = [n for n in g.class_names[1:] if n not in group]
    if missing:
        raise InputFormatError(f"{root}/manifests: no taxonomy group for classes {missing}; "
                               "DISC needs each class in the instance or the scene stream")
    ins = [0] + [i for i, n in enumerate(g.class_names) if i and group[n] == "instance"]
    bk = [0] + [i for i, n in enumerate(g.class_names) if i and group[n] != "instance"]
    mk = lambda ids: {"indices": np.array(ids, np.int64),  # noqa: E731
                      "names": [g.class_names[i] for i in ids]}
    return mk(bk), mk(ins)


def training_constants(root) -> dict:
    """The config values DISC repeats as literals: ``num_classes``, ``class_frequencies``,
    ``bk_cls``, ``ins_cls`` (decoder), ``scene_size`` (grid shape)."""
    g = load_geometry(export_root(root))
    bk, ins = class_streams(root)
    return {"num_classes": g.n_classes, "class_frequencies": g.class_voxel_counts.tolist(),
            "bk_cls": len(bk["indices"]), "ins_cls": len(ins["indices"]),
            "scene_size": list(g.grid_shape)}


class _MetaInfo:
    root: str | None = None

    def __get__(self, obj, owner) -> dict:
        if self.root is None:
            raise RuntimeError("OccuFlyKITTI360.META_INFO: no export known yet; pass data_root "
                               "to occufly.datasets.compat.disc.Register or build a dataset first")
        g = load_geometry(self.root)
        return {"class_weights": 1 / torch.log(torch.from_numpy(g.class_voxel_counts) + 1e-6),
                "class_names": g.class_names}


_META = _MetaInfo()


def _rot2(h: float) -> torch.Tensor:
    return torch.tensor([[np.cos(h), np.sin(h)], [-np.sin(h), np.cos(h)]], dtype=torch.float32)


class OccuFlyKITTI360(Dataset):
    """DISC's ``KITTI360`` interface over an export (see the module docstring)."""

    META_INFO = _META

    def __init__(self, split, data_root, label_root=None, depth_root=None, data_config=None,
                 project_scale=2, frustum_size=4, context_prior=False, **_ignored):
        super().__init__()
        self.root = export_root(data_root)
        _META.root = str(self.root)
        self.label_root = Path(label_root) if label_root else self.root / "preprocess" / "labels"
        self.depth_root = Path(depth_root) if depth_root else self.root / "depth_full"
        self.split = split
        self.project_scale = int(project_scale)
        self.output_scale = int(self.project_scale / 2)
        self.frustum_size = frustum_size  # unused by DISC's loader too
        self.context_prior = context_prior
        g = self.geometry = load_geometry(self.root)
        self.data_config = dict(DEFAULT_DATA_CONFIG, **dict(data_config or {}))
        self.flip = bool(self.data_config["flip"])
        self.num_classes = g.n_classes
        self.voxel_origin = g.voxel_origin.copy()
        self.voxel_size = g.voxel_size
        self.scene_size = g.scene_size
        self.scans = list_scans(self.root, split)
        sizes = {s.image_size for s in self.scans}
        if self.data_config["input_size"] is None:
            if len(sizes) > 1:
                raise InputFormatError(f"{self.root}: sequences have different image sizes {sorted(sizes)}; "
                                       "set data_config.input_size [H, W]")
            W, H = next(iter(sizes)) if sizes else (0, 0)
            self.data_config["input_size"] = [H, W]
        self.img_shape = tuple(int(v) for v in self.data_config["input_size"])
        self.class_fres = torch.from_numpy(g.class_voxel_counts.astype(np.int64))
        self.bk_cls_info, self.ins_cls_info = class_streams(self.root)

    def __len__(self) -> int:
        return len(self.scans)

    # -- their augmentation (kitti_360.py:265-331), same arithmetic --------------------------
    def sample_augmentation(self, H, W, flip=None):
        fH, fW = self.img_shape
        c = self.data_config
        if self.split == "train":
            resize = float(fW) / float(W) + np.random.uniform(*c["resize"])
            resize_dims = (int(W * resize), int(H * resize))
            newW, newH = resize_dims
            crop_h = int((1 - np.random.uniform(*c["crop_h"])) * newH) - fH
            crop_w = int(np.random.uniform(0, max(0, newW - fW)))
            rotate = np.random.uniform(*c["rot"])
        else:
            resize = float(fW) / float(W) + c.get("resize_test", 0.0)
            resize_dims = (int(W * resize), int(H * resize))
            newW, newH = resize_dims
            crop_h = int((1 - np.mean(c["crop_h"])) * newH) - fH
            crop_w = int(max(0, newW - fW) / 2)
            rotate = 0
        crop = (crop_w, crop_h, crop_w + fW, crop_h + fH)
        return resize, resize_dims, crop, bool(flip), rotate

    @staticmethod
    def _core(img, resize_dims, crop, flip, rotate):
        img = img.resize(resize_dims).crop(crop)
        if flip:
            img = img.transpose(method=Image.FLIP_LEFT_RIGHT)
        return img.rotate(rotate)

    def img_transform(self, img, depth, resize, resize_dims, crop, flip, rotate):
        img = self._core(img, resize_dims, crop, flip, rotate)
        depth = self._core(depth, resize_dims, crop, flip, rotate)
        post_rot = torch.eye(2) * resize
        post_tran = -torch.tensor(crop[:2], dtype=torch.float32)
        if flip:
            A = torch.tensor([[-1.0, 0.0], [0.0, 1.0]])
            b = torch.tensor([crop[2] - crop[0], 0.0])
            post_rot, post_tran = A @ post_rot, A @ post_tran + b
        A = _rot2(rotate / 180 * np.pi)
        b = torch.tensor([crop[2] - crop[0], crop[3] - crop[1]], dtype=torch.float32) / 2
        b = A @ -b + b
        return img, depth, A @ post_rot, A @ post_tran + b

    # -- the sample ----------------------------------------------------------------------------
    def depth_path(self, scan) -> Path:
        p = self.depth_root / "sequences" / scan.sequence / f"{scan.frame_id}.npy"
        return p if p.exists() else self.depth_root / scan.sequence / f"{scan.frame_id}.npy"

    def sample(self, idx: int, flip: bool = False) -> tuple[dict, dict]:
        """The sample of frame ``idx``; ``flip``: image and depth mirrored (deterministic)."""
        scan = self.scans[idx]
        W, H = scan.image_size
        P = np.asarray(scan.P2, np.float64)
        T = np.asarray(scan.Tr, np.float64)
        data: dict = {"frame_id": scan.frame_id, "sequence": scan.sequence, "P": P,
                      "cam_pose": T, "proj_matrix": P @ T, "voxel_origin": self.voxel_origin}
        label: dict = {"class_fres": self.class_fres, "bk_cls_info": self.bk_cls_info,
                       "ins_cls_info": self.ins_cls_info}
        scale_3ds = (self.output_scale, self.project_scale)
        data["scale_3ds"] = scale_3ds
        cam_K = P[:3, :3]
        data["cam_K"] = cam_K
        target = None
        if self.split != "test":
            target = np.load(self.label_root / scan.sequence / f"{scan.frame_id}_1_{scale_3ds[0]}.npy")
            label["target"] = target
        depth = Image.fromarray(np.load(self.depth_path(scan)).astype(np.float32)[:H, :W])
        img_path = self.root / "data_2d_raw" / scan.sequence / "image_00" / "data_rect" / f"{scan.frame_id}.png"
        with Image.open(img_path) as im:
            img = im.convert("RGB")
        resize, dims, crop, flip, rotate = self.sample_augmentation(img.height, img.width, flip)
        img, depth, pr2, pt2 = self.img_transform(img, depth, resize, dims, crop, flip, rotate)
        post_rot, post_tran = np.eye(3), np.zeros(3)
        post_rot[:2, :2], post_tran[:2] = pr2.numpy(), pt2.numpy()
        depth = np.array(depth, dtype=np.float32)
        img = (np.asarray(img, dtype=np.float32) / 255.0 - _MEAN) / _STD
        data["img"] = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))
        data["depth"] = depth
        data["post_tran"], data["post_rot"] = post_tran, post_rot
        label["depth"] = depth
        fH, fW = self.img_shape
        for s in scale_3ds:
            pix, _, z = vox2pix(T, cam_K, self.voxel_origin, self.voxel_size * s, W, H, self.scene_size)
            pix = pix @ post_rot[:2, :2].T + post_tran[:2]
            data[f"projected_pix_{s}"] = pix
            data[f"pix_z_{s}"] = z
            data[f"fov_mask_{s}"] = ((pix[:, 0] >= 0) & (pix[:, 0] < fW) & (pix[:, 1] >= 0)
                                     & (pix[:, 1] < fH) & (z > 0))
        if target is not None:
            label["bev_seg_bk"] = self.bev(target, self.bk_cls_info["indices"])
            label["bev_seg_ins"] = self.bev(target, self.ins_cls_info["indices"])
            label["seg_img"] = self.seg_img(target, depth, cam_K, T, post_rot, post_tran,
                                            self.voxel_size * scale_3ds[0])
        for d in (data, label):
            for k, v in d.items():
                if isinstance(v, np.ndarray):
                    d[k] = torch.from_numpy(v.astype(np.float32) if v.dtype == np.float64 else v)
        return data, label

    @staticmethod
    def bev(target: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """``project_voxels_to_single_bev``: per (x, y) column, the label of the last layer
        along axis 2 (layers 0 .. Z-2, as theirs) in ``indices``, remapped to its position in
        ``indices`` (0 = none)."""
        layers = target[:, :, :-1]
        hit = np.isin(layers, indices[1:])
        any_hit = hit.any(axis=2)
        last = layers.shape[2] - 1 - np.argmax(hit[:, :, ::-1], axis=2)
        lab = np.take_along_axis(layers, last[..., None], axis=2)[..., 0]
        remap = np.zeros(256, np.uint8)
        remap[indices] = np.arange(len(indices), dtype=np.uint8)
        return np.where(any_hit, remap[lab], 0).astype(np.uint8)

    def seg_img(self, target, depth, K, T, post_rot, post_tran, vox_size) -> np.ndarray:
        """``project_image_to_voxels`` (mode 'ins'): each pixel's depth point (through the
        inverse image augmentation, K and the extrinsic) looked up in the grid; the label when
        it is an instance class, 255 outside the grid or invalid, else 0."""
        fH, fW = depth.shape
        v, u = np.mgrid[0:fH, 0:fW].astype(np.float64)
        uv = np.stack([u.ravel(), v.ravel()], 1) - post_tran[:2]
        uv = uv @ np.linalg.inv(post_rot[:2, :2]).T
        d = depth.reshape(-1).astype(np.float64)
        cam = np.linalg.solve(np.asarray(K, np.float64), np.stack([uv[:, 0] * d, uv[:, 1] * d, d]))
        pw = np.linalg.inv(T) @ np.vstack([cam, np.ones(len(d))])
        idx = np.floor((pw[:3].T - self.voxel_origin) / vox_size).astype(np.int64)
        X, Y, Z = target.shape
        inside = ((idx >= 0) & (idx < (X, Y, Z))).all(1)
        lab = np.full(len(d), 255, np.int64)
        ic = idx[inside]
        lab[inside] = target[ic[:, 0], ic[:, 1], ic[:, 2]]
        ins = np.isin(lab, self.ins_cls_info["indices"][1:])
        out = np.where(ins | (lab == 255), lab, 0)
        return out.reshape(fH, fW)

    def __getitem__(self, idx: int) -> tuple[dict, dict]:
        flip = random.random() > 0.5 if self.flip and self.split == "train" else False
        return self.sample(idx, flip)


class Register(_SymphoniesRegister):
    """Hydra callback (``hydra.callbacks.<name>._target_``): adds :class:`OccuFlyKITTI360` to
    ``ssc_ia.data.datasets`` so ``data.datasets.type: OccuFlyKITTI360`` finds it."""

    dataset_class = OccuFlyKITTI360
    default_module = "ssc_ia.data.datasets"
