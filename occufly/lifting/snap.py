"""Image-guided boundary snapping of a hurried mask before it votes (issue 37).

A hurried annotator paints class boundaries a few pixels off but the inside of each region
right. :func:`snap_mask` re-decides the pixels of a band around the mask's class boundaries
from the photo itself, with a marker-based watershed (``cv2.watershed``):

markers
    every painted pixel farther than ``band`` pixels (chessboard) from a pixel of another id
    -- the confident interior of its region -- keeps its class and seeds the flood; a
    connected same-class region with no such pixel (a person, a cable, a blob narrower than
    ``2 * band``) is kept whole as a marker, so small objects are never erased; unpainted
    (:data:`~occufly.taxonomy.EMPTY`) and ignored (:data:`~occufly.taxonomy.INVALID`) pixels
    are one barrier marker and stay what they are.
unknown
    the rest: the band of up to ``band`` pixels on either side of every painted boundary. The
    watershed floods it from the markers in the order of the image's colour gradient, so two
    regions meet on the strongest edge between their cores; where the photo has no edge the
    fronts meet about where the mask put the boundary. A band pixel the barrier reaches keeps
    its painted id (an unpainted area neither grows nor shrinks).
colour check
    a band pixel the watershed gave another class keeps it only if its colour is closer
    (:data:`SNAP_COLOUR_RATIO`) to that class's mean over the core pixels of a (4 band + 1)
    window than to its painted class's: texture, shadows and road markings inside a region
    are edges too, and without the check the snapping moved 1.2 % of the pixels of *exact*
    synthetic masks (0.5 % with it; band 2, 15 masks of ``small``).

Only ids already in the mask are ever written. ``band`` defaults to
:data:`SNAP_SHARE` of the mask's longer side (2 px of a 480 px mask, 23 px of a 5472 px
one): degrade.py drifts boundaries by up to 3 px, and wider bands let the flood wander
along texture (on ``small``'s drifted-only masks, band 2 / 3 left 1.74 / 2.01 % of the
pixels wrong, from 3.05 %, and moved 0.48 / 0.80 % of the exact masks' pixels). Masks over :data:`SNAP_MAX_PIXELS` are snapped on a subsample (every f-th row and
column, the photo averaged to the same grid) and the decisions carried back only to the
full-resolution pixels of the class the subsample held there, so thin objects that the
subsample misses keep their pixels.

:func:`frame_image` reads a frame's photo at a mask's resolution (JPEG decoded reduced when
it can be). The vote state applies both when its ``vote_weighting`` is ``"snap"``
(:mod:`occufly.lifting.votes`). Measured in docs/lifting.md and **not the default**: with
exact masks it costs up to 0.87 mIoU points (shadows, facades and lattices are edges that
are no class boundary, the same in every view), and with hurried ones its gains (up to
+0.36 accuracy points, +0.9 mIoU points) are not larger than the run-to-run noise;
:data:`SNAP_ABSTAIN` (the pixels it would move cast no vote) costs less and gains no more.
Cost: 0.30 s CPU for a 20 MP mask (plus 0.12 s to read its JPEG).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occufly.taxonomy import EMPTY, INVALID

#: band half-width as a share of the mask's longer side, rounded (2 px of a 480 px mask,
#: 3 of a 600 px one, 23 of a 5472 px one)
SNAP_SHARE = 1.0 / 240.0
#: a pixel the watershed moved to another class keeps it only if its colour is closer than
#: this many times to that class's local core mean than to its painted class's
SNAP_COLOUR_RATIO = 0.7
#: :func:`snap_frame_mask`: True = the pixels snapping would move cast no vote (unpainted)
#: instead of voting the snapped class (measured as a variant in docs/lifting.md)
SNAP_ABSTAIN = False
#: masks with more pixels are snapped on a subsample of every f-th row and column
SNAP_MAX_PIXELS = 1 << 21


def snap_band(shape: tuple[int, int], share: float = SNAP_SHARE) -> int:
    """Default band half-width in pixels of a (h, w) mask (at least 1)."""
    return max(1, int(share * max(int(shape[0]), int(shape[1])) + 0.5))


def _factor(h: int, w: int, max_pixels: int) -> int:
    f = 1
    while (h // f) * (w // f) > max_pixels:
        f += 1
    return f


def snap_mask(mask: np.ndarray, image: np.ndarray, *, band: int | None = None,
              ratio: float | None = SNAP_COLOUR_RATIO,
              max_pixels: int = SNAP_MAX_PIXELS) -> np.ndarray:
    """(h, w) uint8 raw ids -> the same mask with its class boundaries moved onto the
    edges of ``image`` ((h, w, 3) or (h, w) uint8, the photo at the mask's resolution)
    within ``band`` pixels (None: :func:`snap_band`); ``ratio``: the colour check
    (:data:`SNAP_COLOUR_RATIO`; None = the watershed's decision alone). See the module
    docstring."""
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    if m.ndim != 2:
        raise ValueError(f"snap_mask: expected an (h, w) mask, got shape {m.shape}")
    img = np.asarray(image)
    if img.shape[:2] != m.shape:
        raise ValueError(f"snap_mask: image {img.shape[:2]} and mask {m.shape} differ in size")
    h, w = m.shape
    b = snap_band(m.shape) if band is None else int(band)
    if b < 1 or h < 2 or w < 2:
        return m.copy()
    f = _factor(h, w, max_pixels)
    if f == 1:
        return _snap(m, img, b, ratio)
    import cv2  # OpenCV: a heavy import (~0.5 s) only the snapping needs

    hl, wl = h // f, w // f
    lo = np.ascontiguousarray(m[: hl * f: f, : wl * f: f])
    img_lo = cv2.resize(np.ascontiguousarray(img[: hl * f, : wl * f]), (wl, hl),
                        interpolation=cv2.INTER_AREA)
    snapped = _snap(lo, img_lo, max(1, int(b / f + 0.5)), ratio)
    changed = snapped != lo
    out = m.copy()
    if not changed.any():
        return out
    # carry a decision back to the full-resolution pixels of the class the subsample held
    # there (a thin object between the sampled rows and columns keeps its pixels)
    up = np.repeat(np.repeat(np.where(changed, snapped, 0).astype(np.uint8), f, 0), f, 1)
    src = np.repeat(np.repeat(np.where(changed, lo, 0).astype(np.uint8), f, 0), f, 1)
    view = out[: hl * f, : wl * f]
    sel = (up != 0) & (view == src)
    view[sel] = up[sel]
    return out


def _snap(m: np.ndarray, img: np.ndarray, b: int, ratio: float | None) -> np.ndarray:
    """:func:`snap_mask` at the working resolution."""
    import cv2  # OpenCV: a heavy import (~0.5 s) only the snapping needs

    painted = (m != EMPTY) & (m != INVALID)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * b + 1, 2 * b + 1))
    core = (cv2.erode(m, kernel) == cv2.dilate(m, kernel)) & painted
    keep = core.copy()
    # regions with no core (narrower than the band) are kept whole
    for cid in np.unique(m[painted & ~core]):
        sel = (m == cid).view(np.uint8)
        n, lab = cv2.connectedComponents(sel, connectivity=4)
        if n <= 1:
            continue
        has = np.bincount(lab[core & (m == cid)], minlength=n) > 0
        has[0] = True
        thin = ~has[lab]
        keep |= thin
    if keep.all() or not painted.any():
        return m.copy()
    markers = np.zeros(m.shape, np.int32)
    markers[keep] = m[keep].astype(np.int32) + 1
    markers[~painted] = 1  # one barrier for the unpainted and ignored pixels
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    src = cv2.GaussianBlur(np.ascontiguousarray(img, dtype=np.uint8), (3, 3), 0)
    cv2.watershed(src, markers)
    _resolve_ridges(markers, img)
    out = m.copy()
    sel = painted & ~keep & (markers > 1)
    out[sel] = (markers[sel] - 1).astype(np.uint8)
    if ratio is not None:
        _colour_check(m, out, core, src, b, ratio)
    return out


def _resolve_ridges(markers: np.ndarray, img: np.ndarray) -> None:
    """Give each watershed ridge pixel (-1, where two floods met: on the edge itself) the
    label of the 4-neighbour closest to it in colour among the flooded ones (> 1); a ridge
    pixel with none stays -1 (it keeps its painted id)."""
    # cv2.watershed draws its ridge all round the image's frame: the pixel inside decides
    h, w = markers.shape
    if h > 2 and w > 2:
        for dst, srcl in ((np.s_[0, :], np.s_[1, :]), (np.s_[-1, :], np.s_[-2, :]),
                          (np.s_[:, 0], np.s_[:, 1]), (np.s_[:, -1], np.s_[:, -2])):
            frame = markers[dst]
            inner = markers[srcl]
            fix = (frame == -1) & (inner > 1)
            frame[fix] = inner[fix]
    ridge = markers == -1
    if not ridge.any():
        return
    rr, cc = np.nonzero(ridge)
    px = img[rr, cc].astype(np.int32).reshape(len(rr), -1)
    best = np.full(len(rr), np.iinfo(np.int32).max, np.int64)
    lab = np.full(len(rr), -1, np.int32)
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r2, c2 = rr + dr, cc + dc
        ok = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
        r2, c2 = np.clip(r2, 0, h - 1), np.clip(c2, 0, w - 1)
        nl = markers[r2, c2]
        d = np.abs(img[r2, c2].astype(np.int32).reshape(len(rr), -1) - px).sum(axis=1)
        take = ok & (nl > 1) & (d < best)
        best[take], lab[take] = d[take], nl[take]
    markers[rr, cc] = lab


def _colour_check(m: np.ndarray, out: np.ndarray, core: np.ndarray, img: np.ndarray, b: int,
                  ratio: float) -> None:
    """Undo (in ``out``) every change of the watershed whose pixel's colour is not closer
    than ``ratio`` times to its new class's local core mean than to its painted class's
    (means over the core pixels of a (4b+1)^2 window; no core of a class there: no change)."""
    import cv2  # OpenCV: a heavy import (~0.5 s) only the snapping needs

    changed = out != m
    if not changed.any():
        return
    rr, cc = np.nonzero(changed)
    old, new = m[rr, cc], out[rr, cc]
    px = img[rr, cc].astype(np.float32)
    d_old = np.full(len(rr), np.inf, np.float32)
    d_new = np.full(len(rr), np.inf, np.float32)
    f = img.astype(np.float32)
    win = (4 * b + 1, 4 * b + 1)
    for cid in np.unique(np.concatenate([old, new])):
        c = (core & (m == cid)).astype(np.float32)
        n = cv2.boxFilter(c, -1, win, normalize=False)
        s = cv2.boxFilter(f * c[:, :, None], -1, win, normalize=False)
        for which, d in ((old == cid, d_old), (new == cid, d_new)):
            if which.any():
                r, k = rr[which], cc[which]
                nn = n[r, k]
                mu = s[r, k] / np.maximum(nn, 1.0)[:, None]
                d[which] = np.where(nn > 0.5, np.linalg.norm(px[which] - mu, axis=1), np.inf)
    undo = ~(d_new < ratio * d_old)
    out[rr[undo], cc[undo]] = old[undo]



def frame_image(path: str | Path | None, shape: tuple[int, int]) -> np.ndarray | None:
    """The photo at ``path`` as (h, w, 3) uint8 at a mask's (h, w) resolution (an integer
    downscale of the photo: area-averaged; a JPEG is decoded at 1/2, 1/4 or 1/8 when that
    is still at least the mask's size), or None when there is no readable photo there."""
    import cv2  # OpenCV: a heavy import (~0.5 s) only the snapping needs

    if not path or not Path(path).is_file():
        return None
    h, w = int(shape[0]), int(shape[1])
    flag = cv2.IMREAD_COLOR
    if str(path).lower().endswith((".jpg", ".jpeg")):
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
        size = _jpeg_size(head)
        if size is not None:
            W, H = size
            for r, fl in ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
                          (2, cv2.IMREAD_REDUCED_COLOR_2)):
                if W // r >= w and H // r >= h:
                    flag = fl
                    break
    img = cv2.imread(str(path), flag)
    if img is None:
        return None
    if img.shape[:2] != (h, w):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    return img


def _jpeg_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's first SOF marker in ``head``, or None."""
    i = 2
    while i + 9 < len(head):
        if head[i] != 0xFF:
            return None
        kind = head[i + 1]
        seg = int.from_bytes(head[i + 2:i + 4], "big")
        if kind in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            return int.from_bytes(head[i + 7:i + 9], "big"), int.from_bytes(head[i + 5:i + 7], "big")
        i += 2 + seg
    return None



def snap_frame_mask(frame, mask: np.ndarray) -> np.ndarray:  # noqa: ANN001 (a scene Frame)
    """``mask`` snapped to the photo of ``frame`` (:attr:`~occufly.scene.Frame.image_path`,
    read at the mask's resolution); the mask itself when the frame has no readable photo."""
    img = frame_image(getattr(frame, "image_path", None), np.shape(mask))
    if img is None:
        return np.asarray(mask)
    # the module's settings at call time (the bench varies them)
    out = snap_mask(mask, img, band=snap_band(np.shape(mask), SNAP_SHARE),
                    ratio=SNAP_COLOUR_RATIO)
    if SNAP_ABSTAIN:  # a pixel the photo disagrees with casts no vote instead of another
        out = np.where(out != np.asarray(mask), np.uint8(EMPTY), out)
    return out
