"""``torch.utils.data.Dataset`` over an export (optional extra: ``pip install occufly[torch]``).

>>> from torch.utils.data import DataLoader
>>> from occufly.datasets.torch import OccuFlyDataset, collate
>>> ds = OccuFlyDataset("exports/sscbench", split="train", scales=("1_1", "1_8"))
>>> batch = next(iter(DataLoader(ds, batch_size=2, collate_fn=collate)))
>>> batch["img"].shape, batch["target_1_1"].shape    # (B, 3, H, W), (B, X, Y, Z)

Per sample (tensors unless noted):

``img``            (3, H, W) float32 in [0, 1] (``normalize=True``: ImageNet mean/std)
``target_<s>``     (X/f, Y/f, Z/f) int64 training ids, 255 = ignore, for each scale ``s``
``invalid``        (X, Y, Z) bool
``depth``          (h, w) float32 metres at 1/4 resolution (``depth=True``)
``K``              (3, 3) float32, COLMAP convention (pixel centres at +0.5)
``pose``           (4, 4) float32 camera-to-world (identity when the export has none)
``scene``, ``sequence``, ``frame_id`` (str), ``altitude`` (int)

:func:`collate` stacks tensors of equal shape (a batch of frames from one camera) and keeps
lists otherwise (strings, or images of different sizes).
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from occufly.datasets.reader import ExportReader, open_dataset

_MEAN = torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1)
_STD = torch.tensor([0.229, 0.224, 0.225]).view(3, 1, 1)


class OccuFlyDataset(Dataset):
    """Frames of an export (either layout) as tensors; see the module docstring."""

    def __init__(self, root, *, split: str | None = None, layout: str | None = None,
                 scales: tuple[str, ...] = ("1_1",), depth: bool = True, normalize: bool = False,
                 transform=None) -> None:
        self.reader: ExportReader = open_dataset(root, split=split, layout=layout)
        self.scales = tuple(scales)
        self.depth = depth
        self.normalize = normalize
        self.transform = transform

    def __len__(self) -> int:
        return len(self.reader)

    @property
    def n_classes(self) -> int:
        return len(self.reader.taxonomy) + 1

    def __getitem__(self, i: int) -> dict:
        s = self.reader[i]
        img = torch.from_numpy(np.array(s["image"], dtype=np.float32)).permute(2, 0, 1) / 255.0
        if self.normalize:
            img = (img - _MEAN) / _STD
        out = {"img": img, "invalid": torch.from_numpy(s["invalid"]),
               "K": torch.from_numpy(s["K"].astype(np.float32)),
               "pose": torch.from_numpy(np.asarray(s.get("pose", np.eye(4)), dtype=np.float32)),
               "scene": s["scene"], "sequence": s["sequence"], "frame_id": s["frame_id"],
               "altitude": int(s["altitude"])}
        for sc in self.scales:
            out[f"target_{sc}"] = torch.from_numpy(self.reader.target(s, sc).astype(np.int64))
        if self.depth:
            out["depth"] = torch.from_numpy(np.ascontiguousarray(s["depth"], dtype=np.float32))
        if self.transform is not None:
            out = self.transform(out)
        return out


def collate(batch: list[dict]) -> dict:
    """Stack tensors of equal shape along a new batch axis; keep lists otherwise."""
    if not batch:
        return {}
    out: dict = {}
    for k in batch[0]:
        vals = [b[k] for b in batch]
        if all(isinstance(v, torch.Tensor) for v in vals) and len({tuple(v.shape) for v in vals}) == 1:
            out[k] = torch.stack(vals)
        elif all(isinstance(v, int) for v in vals):
            out[k] = torch.tensor(vals)
        else:
            out[k] = vals
    return out
