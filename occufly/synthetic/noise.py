"""A second noise model for masks: the sloppy crew (issue 37).

:mod:`occufly.synthetic.degrade` makes every frame's errors the same kind and symmetric
(road <-> parking lot both ways, independently per region and frame). Real crews are
different: errors are correlated within an annotator and one-directional. This model deals
each frame to one of ``annotators`` people by a seeded draw on (seed, frame index); annotator
0 is systematically sloppy, the others are careful. It was written down in ``docs/lifting.md``
before any measurement with it and is not tuned on.

Careful annotators
    boundaries drift up to 2 px; objects under 40 px skipped with probability 0.3; one
    unpainted ellipse; whole-object swaps vehicle <-> truck and person <-> bicycle with
    probability 0.1 per connected object.
The sloppy annotator
    boundaries drift up to 6 px on a coarse 128 px field; every object under 120 px skipped;
    every grass region painted vegetation, every parking-lot region road and every roof region
    building (one way only); vehicles painted truck with probability 0.5 per object; cables
    never painted (the class around them instead); three unpainted ellipses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from occufly.synthetic.degrade import shift_boundaries, skip_small, unpaint
from occufly.taxonomy import Taxonomy

#: whole-object swaps of the careful annotators (both directions)
OBJECT_SWAPS = (("vehicle", "truck"), ("person", "bicycle"))
#: the sloppy annotator's one-way region confusions (every region of the first class)
SLOPPY_CONFUSIONS = (("grass", "vegetation"), ("parking_lot", "road"), ("roof", "building"))
#: the sloppy annotator's one-way object swaps (probability per object)
SLOPPY_SWAPS = (("vehicle", "truck", 0.5),)
#: classes the sloppy annotator never paints
SLOPPY_OMITS = ("cable",)


@dataclass
class Annotator:
    """How one member of the crew paints (pixel sizes at the mask's resolution)."""

    shift_px: float
    cell: int
    min_blob: int
    skip_prob: float
    patches: int
    patch_frac: float
    swap_rate: float = 0.0                      # OBJECT_SWAPS, per object, both ways
    regions: tuple = ()                          # (from, to): every region, one way
    swaps: tuple = ()                            # (from, to, probability) per object, one way
    omits: tuple = ()                            # classes painted over by their surroundings


CAREFUL = Annotator(shift_px=2.0, cell=64, min_blob=40, skip_prob=0.3, patches=1, patch_frac=0.05,
                    swap_rate=0.1)
SLOPPY = Annotator(shift_px=6.0, cell=128, min_blob=120, skip_prob=1.0, patches=3, patch_frac=0.10,
                   regions=SLOPPY_CONFUSIONS, swaps=SLOPPY_SWAPS, omits=SLOPPY_OMITS)


@dataclass
class Crew:
    """``annotators`` people, the first ``sloppy`` of them painting like :data:`SLOPPY`."""

    annotators: int = 4
    sloppy: int = 1
    careful: Annotator = field(default_factory=lambda: CAREFUL)
    sloppy_annotator: Annotator = field(default_factory=lambda: SLOPPY)


def _ids(taxonomy: Taxonomy) -> dict[str, int]:
    return {c.name: c.id for c in taxonomy.classes}


def _swap_objects(mask: np.ndarray, rng: np.random.Generator, pairs: list[tuple[int, int, float]]
                  ) -> np.ndarray:
    """Each connected object of class ``a`` painted ``b`` with probability ``p`` (per pair)."""
    out = mask.copy()
    for a, b, prob in pairs:
        lab, n = ndimage.label(mask == a)
        if n == 0 or prob <= 0:
            continue
        flip = np.flatnonzero(rng.random(n) < prob) + 1
        if len(flip):
            out[np.isin(lab, flip)] = b
    return out


def _omit(mask: np.ndarray, ids: list[int]) -> np.ndarray:
    drop = np.isin(mask, ids)
    if not drop.any() or drop.all():
        return mask
    _, (ir, ic) = ndimage.distance_transform_edt(drop, return_indices=True)
    return mask[ir, ic]


def paint(mask: np.ndarray, taxonomy: Taxonomy, rng: np.random.Generator, who: Annotator
          ) -> np.ndarray:
    """(h, w) uint8 truth mask -> the mask as annotator ``who`` paints it."""
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.uint8:
        raise ValueError(f"paint: expected an (h, w) uint8 mask, got {mask.shape} {mask.dtype}")
    ids = _ids(taxonomy)
    out = shift_boundaries(mask, rng, who.shift_px, who.cell)
    omit = [ids[n] for n in who.omits if n in ids]
    if omit:
        out = _omit(out, omit)
    out = skip_small(out, rng, who.min_blob, who.skip_prob)
    pairs: list[tuple[int, int, float]] = []
    if who.swap_rate > 0:
        for a, b in OBJECT_SWAPS:
            if a in ids and b in ids:
                pairs += [(ids[a], ids[b], who.swap_rate), (ids[b], ids[a], who.swap_rate)]
    pairs += [(ids[a], ids[b], p) for a, b, p in who.swaps if a in ids and b in ids]
    if pairs:
        # decided on the mask before any swap, so a swapped object is not swapped back
        base = out
        out = base.copy()
        for a, b, prob in pairs:
            sw = _swap_objects(base, rng, [(a, b, prob)])
            changed = (sw != base) & (base == a)
            out[changed] = b
    for a, b in who.regions:
        if a in ids and b in ids:
            out[out == ids[a]] = ids[b]
    return unpaint(out, rng, who.patches, who.patch_frac)


def annotator_of(frame: int, seed: int, crew: Crew) -> int:
    """The crew member (0 .. annotators - 1; below ``crew.sloppy``: sloppy) who paints ``frame``."""
    return int(np.random.default_rng([seed, int(frame), 7919]).integers(crew.annotators))


def crew_masks(masks: dict[int, np.ndarray], taxonomy: Taxonomy, seed: int = 0,
               crew: Crew | None = None) -> tuple[dict[int, np.ndarray], dict[int, int]]:
    """Every mask of ``masks`` (frame index -> truth mask) painted by its crew member, each
    with its own seed (seed, index): (masks, frame -> annotator)."""
    c = crew or Crew()
    out: dict[int, np.ndarray] = {}
    who: dict[int, int] = {}
    for f, m in masks.items():
        a = annotator_of(f, seed, c)
        who[int(f)] = a
        rng = np.random.default_rng([seed, int(f), 31])
        out[int(f)] = paint(m, taxonomy, rng, c.sloppy_annotator if a < c.sloppy else c.careful)
    return out, who
