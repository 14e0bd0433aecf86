"""MonoScene (astra-vision/MonoScene f52bbb1) and SSCBench's MonoScene (ai4ce/SSCBench
9e767e1, method/MonoScene): drop-in dataset classes over an SSCBench-layout export.

Neither codebase can take a dataset class from its configuration: the training scripts
construct their DataModule by name (``monoscene/scripts/train_monoscene.py:48-85`` upstream,
``train_monoscene_kitti_360.py:43-60`` in SSCBench), the DataModules construct their Dataset
by name, and Hydra 1.0.5 (their pinned version) has no callbacks. So the port is a
documented patch (docs/ssc-porting.md), the smallest there is:

- the DataModule's dataset import (one line): ``kitti_360_dm.py:2`` (SSCBench) or
  ``semantic_kitti/kitti_dm.py:2`` (upstream) becomes
  ``from occufly.datasets.compat.monoscene import Kitti360Dataset`` / ``KittiDataset``;
- the training script's four geometry/class literals (``full_scene_size``, ``n_classes``,
  ``class_weights``, ``class_names``) come from :func:`training_constants`.

Upstream MonoScene has no KITTI-360 *training* path (its ``kitti_360`` dataset is an
inference reader without labels, and ``train_monoscene.py`` knows only ``kitti`` and
``NYU``), so upstream trains through the SemanticKITTI classes (``dataset: kitti``).

Sample contract (SSCBench ``monoscene/data/kitti_360/kitti_360_dataset.py:142-237``,
upstream ``monoscene/data/semantic_kitti/kitti_dataset.py:83-174``; the two are the same
dict): ``frame_id``, ``sequence`` (str), ``P`` (3, 4), ``T_velo_2_cam`` (4, 4),
``proj_matrix`` (3, 4), ``cam_k`` (3, 3) -- float64 numpy; ``scale_3ds`` list
``[project_scale // 2, project_scale]``; ``projected_pix_<s>`` (N_s, 2) int64, ``fov_mask_<s>``
(N_s,) bool, ``pix_z_<s>`` (N_s,) float64; ``target`` (X, Y, Z) as stored (uint8 here);
``CP_mega_matrix`` (4, N_8, N_8 / 8) uint8; ``frustums_masks`` (size^2, X, Y, Z) bool and
``frustums_class_dists`` (size^2, n_classes) float64, both absent for ``split="test"`` (theirs
sets them to ``None``, which their own ``collate_fn`` cannot batch: it calls
``torch.from_numpy`` on them only ``if "frustums_masks" in input_dict``, upstream
``monoscene/data/semantic_kitti/collate.py:26-30``, SSCBench
``monoscene/data/kitti_360/collate.py:34-38``); ``img`` (3, H, W) float32 torch tensor,
ImageNet-normalised. The codebase's own ``collate_fn`` batches every split.

Memory: the frustum masks are ``frustum_size**2`` bool copies of the full grid, per sample
(at 192 x 128 x 128 and the configs' ``frustum_size: 8``: 64 x 3.1 M = 201 MB); see
docs/ssc-porting.md "Memory" for the measured figures and how to lower them.

Their flip (``fliplr``) mirrors the image and the projected pixels' u (u -> W - 1 - u), not
the target, so it is right for any grid convention; this class does the same. Differences
from theirs, on purpose: each sequence's calib.txt (theirs: one hard-coded calibration,
``read_calib()`` without a path), the export's splits (theirs: KITTI sequence names),
geometry and image size from occufly.yaml (theirs: literals), frames sorted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch  # MonoScene's samples carry a torch image: torch is this adapter's reason to exist
from PIL import Image

from occufly.datasets.compat.common import (
    cp_mega_matrix,
    export_root,
    list_scans,
    load_geometry,
    local_frustums,
    vox2pix,
)

_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_STD = np.array([0.229, 0.224, 0.225], np.float32)


def training_constants(root) -> dict:
    """What the training scripts hard-code, from the export: ``full_scene_size``,
    ``n_classes``, ``class_weights`` (torch float64, 1/log(freq + 0.001)), ``class_names``."""
    g = load_geometry(export_root(root))
    return {"full_scene_size": tuple(g.grid_shape), "n_classes": g.n_classes,
            "class_weights": torch.from_numpy(1.0 / np.log(g.class_voxel_counts + 0.001)),
            "class_names": list(g.class_names)}


class Kitti360Dataset(torch.utils.data.Dataset):
    """SSCBench MonoScene's ``Kitti360Dataset`` interface over an export. ``root``: the
    export (``data_2d_raw/`` under it); ``preprocess_root``: ``<export>/preprocess``."""

    codebase_dataset = "kitti"  # frustums as for KITTI (no NYU axis swap)

    def __init__(self, split, root, preprocess_root=None, project_scale=2, frustum_size=4,
                 color_jitter=None, fliplr=0.0):
        super().__init__()
        self.root = export_root(root)
        pre = Path(preprocess_root) if preprocess_root else self.root / "preprocess"
        self.label_root = pre / "labels"
        self.split = split
        self.project_scale = int(project_scale)
        self.output_scale = int(self.project_scale / 2)
        self.frustum_size = int(frustum_size)
        self.fliplr = float(fliplr)
        g = self.geometry = load_geometry(self.root)
        self.n_classes = g.n_classes
        self.voxel_size = g.voxel_size
        self.vox_origin = g.voxel_origin.copy()
        self.scene_size = g.scene_size
        self.color_jitter = None
        if color_jitter:
            from torchvision import transforms  # optional: only when colour jitter is asked

            self.color_jitter = transforms.ColorJitter(*color_jitter)
        self.scans = list_scans(self.root, split)
        self._rng = np.random

    def __len__(self) -> int:
        return len(self.scans)

    def image_path(self, scan) -> Path:
        return self.root / "data_2d_raw" / scan.sequence / "image_00" / "data_rect" / f"{scan.frame_id}.png"

    def sample(self, index: int, flip: bool = False) -> dict:
        scan = self.scans[index]
        W, H = scan.image_size
        P = np.asarray(scan.P2, np.float64)
        T = np.asarray(scan.Tr, np.float64)
        data = {"frame_id": scan.frame_id, "sequence": scan.sequence, "P": P,
                "T_velo_2_cam": T, "proj_matrix": P @ T}
        scale_3ds = [self.output_scale, self.project_scale]
        data["scale_3ds"] = scale_3ds
        cam_k = P[0:3, 0:3]
        data["cam_k"] = cam_k
        for s in scale_3ds:
            pix, fov, z = vox2pix(T, cam_k, self.vox_origin, self.voxel_size * s, W, H,
                                  self.scene_size)
            data[f"projected_pix_{s}"] = pix
            data[f"fov_mask_{s}"] = fov
            data[f"pix_z_{s}"] = z
        target = np.load(self.label_root / scan.sequence / f"{scan.frame_id}_1_1.npy")
        data["target"] = target
        t8 = np.load(self.label_root / scan.sequence / f"{scan.frame_id}_1_8.npy")
        data["CP_mega_matrix"] = cp_mega_matrix(t8)
        if self.split != "test":
            masks, dists = local_frustums(data[f"projected_pix_{self.output_scale}"],
                                          data[f"pix_z_{self.output_scale}"], target, W, H,
                                          self.n_classes, self.frustum_size)
            data["frustums_masks"] = masks
            data["frustums_class_dists"] = dists
        # test split: no frustum keys at all. Their datasets put None there, which their own
        # collate_fn cannot batch (torch.from_numpy(None)); the collate_fn batches frustums only
        # ``if "frustums_masks" in input_dict`` (collate.py:26 upstream, :34 SSCBench) and the
        # model's frustum loss is skipped for step_type == "test" (monoscene.py:187)
        with Image.open(self.image_path(scan)) as im:
            img = im.convert("RGB")
            if self.color_jitter is not None:
                img = self.color_jitter(img)
            img = np.array(img, dtype=np.float32) / 255.0
        img = img[:H, :W, :]
        if flip:
            img = np.ascontiguousarray(np.fliplr(img))
            for s in scale_3ds:
                data[f"projected_pix_{s}"][:, 0] = img.shape[1] - 1 - data[f"projected_pix_{s}"][:, 0]
        data["img"] = torch.from_numpy(np.ascontiguousarray(((img - _MEAN) / _STD).transpose(2, 0, 1)))
        return data

    def __getitem__(self, index: int) -> dict:
        return self.sample(index, bool(self._rng.rand() < self.fliplr))


class KittiDataset(Kitti360Dataset):
    """Upstream MonoScene's SemanticKITTI ``KittiDataset`` interface over an export: ``root``
    is ``<export>`` or ``<export>/dataset`` (``dataset/sequences/<seq>/`` under it); the
    sample dict is the same as :class:`Kitti360Dataset`'s."""

    def image_path(self, scan) -> Path:
        return self.root / "dataset" / "sequences" / scan.sequence / "image_2" / f"{scan.frame_id}.png"
