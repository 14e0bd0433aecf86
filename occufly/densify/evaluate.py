"""Scene-grid evaluation against a truth grid (FORMATS.md section 5 definitions).

The two grids are aligned by their WORLD origins; they may have different extents. By default
(``region="truth"``) the evaluation covers the truth grid's extent -- the truth says nothing
beyond it -- and predicted voxels outside it are only counted (``pred_voxels_outside_truth``);
with ``region="union"`` the box is the union of both extents and a voxel outside a grid's
extent counts as empty in that grid. Voxels whose truth is 255 (invalid) are ignored. Per-class IoU =
TP / (TP + FP + FN) from one confusion matrix (:class:`occufly.confusion.Confusion`, shared
by every label metric); a class absent from both grids is reported as ``None`` (n/a) and left
out of the mIoU; the mIoU averages the classes present in either grid. A predicted 255 counts
as empty; a raw id outside the taxonomy counts as occupied but matches no class.
Completion IoU / precision / recall are over occupied-vs-empty.
"""

from __future__ import annotations

import numpy as np

from occufly.confusion import Confusion
from occufly.errors import InputFormatError
from occufly.grid import SceneGrid
from occufly.taxonomy import EMPTY, INVALID, Taxonomy


def _offset(pred: SceneGrid, truth: SceneGrid) -> np.ndarray:
    """(3,) int64 index offset of pred's voxel (0,0,0) in truth's lattice."""
    if abs(pred.voxel_size - truth.voxel_size) > 1e-9 * truth.voxel_size:
        raise InputFormatError(
            f"grids have different voxel sizes ({pred.voxel_size} vs truth {truth.voxel_size}); "
            "voxelize with --voxel matching the truth grid"
        )
    off = (pred.origin - truth.origin) / truth.voxel_size
    r = np.round(off)
    if np.any(np.abs(off - r) > 1e-3):
        raise InputFormatError(
            f"grid origins {pred.origin.tolist()} and {truth.origin.tolist()} are not on the same "
            f"{truth.voxel_size} m lattice"
        )
    return r.astype(np.int64)


def aligned_pair(pred: SceneGrid, truth: SceneGrid) -> tuple[np.ndarray, np.ndarray]:
    """Both grids' labels resampled onto the union box: two (X, Y, Z) uint8 arrays."""
    off = _offset(pred, truth)
    ps, ts = np.asarray(pred.shape), np.asarray(truth.shape)
    lo = np.minimum(0, off)
    hi = np.maximum(ts, off + ps)
    shape = tuple(int(s) for s in hi - lo)
    a = np.zeros(shape, np.uint8)
    b = np.zeros(shape, np.uint8)
    po = off - lo
    to = -lo
    a[po[0] : po[0] + ps[0], po[1] : po[1] + ps[1], po[2] : po[2] + ps[2]] = pred.labels
    b[to[0] : to[0] + ts[0], to[1] : to[1] + ts[1], to[2] : to[2] + ts[2]] = truth.labels
    return a, b


def evaluate_grids(pred: SceneGrid, truth: SceneGrid, taxonomy: Taxonomy, *, region: str = "truth") -> dict:
    """Completion IoU / precision / recall, per-class IoU and mIoU of ``pred`` vs ``truth``."""
    if region not in ("truth", "union"):
        raise ValueError(f"region must be 'truth' or 'union', got {region!r}")
    a, b = aligned_pair(pred, truth)
    outside = 0
    if region == "truth":
        off = _offset(pred, truth)
        to = -np.minimum(0, off)
        ts = truth.shape
        crop = (slice(to[0], to[0] + ts[0]), slice(to[1], to[1] + ts[1]), slice(to[2], to[2] + ts[2]))
        outside = int((a != 0).sum() - (a[crop] != 0).sum())
        a, b = a[crop], b[crop]
    # truth 255 is not evaluated; a 255 prediction counts as empty
    p = np.where(a == INVALID, np.uint8(EMPTY), a)
    del a
    conf = Confusion(taxonomy.ids).add(b, p, b != INVALID)
    del b, p
    comp = conf.completion()
    m = conf.matrix
    return {
        "completion_iou": comp["iou"] or 0.0,
        "precision": comp["precision"] or 0.0,
        "recall": comp["recall"] or 0.0,
        "miou": conf.miou(),
        "classes_evaluated": conf.classes_evaluated(),
        "per_class_iou": conf.per_class_iou([c.name for c in taxonomy.classes]),
        "voxels_pred": int(m[:, 1:].sum()),
        "voxels_truth": int(m[1:, :].sum()),
        "evaluated_voxels": conf.total(),
        "region": region,
        "pred_voxels_outside_truth": outside,
    }
