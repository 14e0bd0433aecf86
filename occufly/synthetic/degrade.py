"""Degraded masks: exact truth masks painted the way real annotators paint them.

For tests and benchmarks of lifting robustness. Each effect is seeded and can be turned off:

boundaries
    The mask is resampled through a smooth random displacement field of up to ``shift_px``
    pixels that varies over ``cell``-pixel blocks, so borders move by different amounts in
    different directions (a few pixels off, as with a brush).
skipped objects
    Each connected component smaller than ``min_blob`` pixels is, with probability
    ``skip_prob``, painted over with the nearest surrounding class (a tiny object the
    annotator did not bother with in this frame).
class confusions
    Whole connected regions of a confusable class are painted as its look-alike with
    probability ``confusion_rate`` per region: road <-> parking lot, grass <-> vegetation,
    building <-> roof (:data:`CONFUSIONS`, by class name, so any taxonomy that has them).
unpainted patches
    ``patches`` random ellipses (each up to ``patch_frac`` of the image's shorter side in
    radius) are left unpainted (id 0, which casts no vote).

:func:`degrade_mask` returns the mask; :func:`degrade_masks` degrades a whole set with one
seed per frame (``seed`` and the frame index), so results do not depend on the order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from occufly.taxonomy import EMPTY, INVALID, Taxonomy

#: pairs of classes annotators mix up (by name; both directions)
CONFUSIONS = (("road", "parking_lot"), ("grass", "vegetation"), ("building", "roof"))


@dataclass
class Degradation:
    """Parameters of :func:`degrade_mask` (pixel sizes refer to the mask's resolution)."""

    shift_px: float = 3.0
    cell: int = 64
    min_blob: int = 60
    skip_prob: float = 0.5
    confusion_rate: float = 0.15
    patches: int = 2
    patch_frac: float = 0.08


def _confusion_lut(taxonomy: Taxonomy) -> np.ndarray:
    lut = np.arange(256, dtype=np.uint8)
    by_name = {c.name: c.id for c in taxonomy.classes}
    for a, b in CONFUSIONS:
        if a in by_name and b in by_name:
            lut[by_name[a]] = by_name[b]
            lut[by_name[b]] = by_name[a]
    return lut


def shift_boundaries(mask: np.ndarray, rng: np.random.Generator, shift_px: float,
                      cell: int) -> np.ndarray:
    if shift_px <= 0:
        return mask.copy()
    h, w = mask.shape
    gh, gw = h // cell + 2, w // cell + 2
    field = rng.uniform(-shift_px, shift_px, (2, gh, gw))
    rows = np.arange(h) / (h / (gh - 1))
    cols = np.arange(w) / (w / (gw - 1))
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    dy = ndimage.map_coordinates(field[0], [rr, cc], order=1)
    dx = ndimage.map_coordinates(field[1], [rr, cc], order=1)
    r = np.clip(np.rint(np.arange(h)[:, None] + dy), 0, h - 1).astype(np.int64)
    c = np.clip(np.rint(np.arange(w)[None, :] + dx), 0, w - 1).astype(np.int64)
    return mask[r, c]


def skip_small(mask: np.ndarray, rng: np.random.Generator, min_blob: int, prob: float
                ) -> np.ndarray:
    if min_blob <= 1 or prob <= 0:
        return mask
    drop = np.zeros(mask.shape, bool)
    for cid in np.unique(mask):
        if cid in (EMPTY, INVALID):
            continue
        lab, n = ndimage.label(mask == cid)
        if n == 0:
            continue
        sizes = np.bincount(lab.ravel())
        small = np.flatnonzero(sizes < min_blob)
        small = small[small > 0]
        if prob < 1.0:  # (no draw at 1: the same stream as a generator without the option)
            small = small[rng.random(len(small)) < prob]
        if len(small):
            drop |= np.isin(lab, small)
    if drop.any() and not drop.all():
        _, (ir, ic) = ndimage.distance_transform_edt(drop, return_indices=True)
        mask = mask[ir, ic]
    return mask


def _confuse(mask: np.ndarray, rng: np.random.Generator, lut: np.ndarray,
             rate: float) -> np.ndarray:
    if rate <= 0:
        return mask
    out = mask.copy()
    for cid in np.unique(mask):
        if lut[cid] == cid:
            continue
        lab, n = ndimage.label(mask == cid)
        if n == 0:
            continue
        flip = np.flatnonzero(rng.random(n) < rate) + 1
        if len(flip):
            out[np.isin(lab, flip)] = lut[cid]
    return out


def unpaint(mask: np.ndarray, rng: np.random.Generator, patches: int, frac: float
             ) -> np.ndarray:
    if patches <= 0 or frac <= 0:
        return mask
    h, w = mask.shape
    out = mask.copy()
    rmax = max(2.0, frac * min(h, w))
    yy, xx = np.ogrid[:h, :w]
    for _ in range(patches):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        ry, rx = rng.uniform(0.3, 1.0, 2) * rmax
        out[((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1.0] = EMPTY
    return out


def degrade_stages(mask: np.ndarray, taxonomy: Taxonomy, rng: np.random.Generator | int,
                   params: Degradation | None = None) -> list[tuple[str, np.ndarray]]:
    """The mask after each effect in turn: ``boundaries``, ``skipped``, ``confused``,
    ``unpainted`` (the last is :func:`degrade_mask`'s result; a benchmark tells which effect
    made a pixel wrong by comparing neighbouring stages)."""
    p = params or Degradation()
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.uint8:
        raise ValueError(f"degrade_mask: expected an (h, w) uint8 mask, got {mask.shape} {mask.dtype}")
    out = [("boundaries", shift_boundaries(mask, rng, p.shift_px, p.cell))]
    out.append(("skipped", skip_small(out[-1][1], rng, p.min_blob, p.skip_prob)))
    out.append(("confused", _confuse(out[-1][1], rng, _confusion_lut(taxonomy), p.confusion_rate)))
    out.append(("unpainted", unpaint(out[-1][1], rng, p.patches, p.patch_frac)))
    return out


def degrade_mask(mask: np.ndarray, taxonomy: Taxonomy, rng: np.random.Generator | int,
                 params: Degradation | None = None) -> np.ndarray:
    """(h, w) uint8 raw-id mask -> the same mask as an imperfect annotator paints it."""
    return degrade_stages(mask, taxonomy, rng, params)[-1][1]


def degrade_masks(masks: dict[int, np.ndarray], taxonomy: Taxonomy, seed: int = 0,
                  params: Degradation | None = None) -> dict[int, np.ndarray]:
    """Degrade every mask of ``masks`` (frame index -> mask) with its own seed (seed, index)."""
    return {int(f): degrade_mask(m, taxonomy, np.random.default_rng([seed, int(f)]), params)
            for f, m in masks.items()}
