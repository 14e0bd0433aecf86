"""Compiled splat passes of the label renderer (:func:`occufly.render._render`).

Each projected point covers the ``size x size`` pixels whose centres lie within ``size / 2`` of
it, starting at (``row0``, ``col0``). Pass 1 keeps the nearest depth per pixel; pass 2, among
the fragments of the front surface (depth within ``tol + 0.005 z`` of the nearest), keeps the
point projecting closest to the pixel centre, packed with its label into one uint64 key (the
smaller label wins a tie). Both are order-independent minima, so the images are those of the
numpy version these loops replaced (``np.minimum.at`` over per-offset fragment arrays), with
the same float32 rounding of the tolerance and of the key, in one pass over the points instead
of up to 64 array passes each. Compiled by numba on first use, cached like
:mod:`occufly.lifting.blockknn`.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def splat_pass(depth: np.ndarray, best: np.ndarray, uv: np.ndarray, z: np.ndarray,
               size: np.ndarray, col0: np.ndarray, row0: np.ndarray, lab: np.ndarray,
               tol: np.float32, h: int, w: int, label_pass: bool) -> None:
    """One pass over every in-image pixel of every point's splat.

    Pass 1 (``label_pass`` False): ``depth`` ((h * w,) float32) is lowered in place to each
    fragment's z. Pass 2: ``best`` ((h * w,) uint64) is lowered in place to
    ``d2 * 65536 << 8 | label`` of each front fragment (d2: squared distance of the projected
    point to the pixel centre); ``depth`` is read only."""
    k005 = np.float32(0.005)
    k65536 = np.float32(65536.0)
    cap = np.float32(2.0 ** 31)
    for i in range(z.shape[0]):
        s = size[i]
        zi = z[i]
        for dy in range(s):
            r = row0[i] + dy
            if r < 0 or r >= h:
                continue
            for dx in range(s):
                c = col0[i] + dx
                if c < 0 or c >= w:
                    continue
                p = r * w + c
                if not label_pass:
                    if zi < depth[p]:
                        depth[p] = zi
                    continue
                zf = depth[p]
                if not zi <= zf + (tol + k005 * zf):
                    continue
                ex = c + 0.5 - uv[i, 0]
                ey = r + 0.5 - uv[i, 1]
                d2 = np.float32(ex * ex + ey * ey)
                key = (np.uint64(min(d2 * k65536, cap)) << np.uint64(8)) | np.uint64(lab[i])
                if key < best[p]:
                    best[p] = key


@numba.njit(nogil=True, cache=True)
def splat_label_pass_multi(depth: np.ndarray, best: np.ndarray, uv: np.ndarray, z: np.ndarray,
                           size: np.ndarray, col0: np.ndarray, row0: np.ndarray,
                           lab: np.ndarray, tol: np.float32, h: int, w: int) -> None:
    """Pass 2 of :func:`splat_pass` for L label arrays at once (one geometry, several label
    sets: the review's leave-one-out and self renderings of one frame). ``lab``: (n, L)
    uint8; ``best``: (L, h * w) uint64, row j lowered exactly as :func:`splat_pass` lowers
    ``best`` with ``lab[:, j]`` (the same key, the same smaller-label tie rule), so each row
    is that label set's own rendering; ``depth`` from pass 1 is read only."""
    k005 = np.float32(0.005)
    k65536 = np.float32(65536.0)
    cap = np.float32(2.0 ** 31)
    n_lab = lab.shape[1]
    for i in range(z.shape[0]):
        s = size[i]
        zi = z[i]
        for dy in range(s):
            r = row0[i] + dy
            if r < 0 or r >= h:
                continue
            for dx in range(s):
                c = col0[i] + dx
                if c < 0 or c >= w:
                    continue
                p = r * w + c
                zf = depth[p]
                if not zi <= zf + (tol + k005 * zf):
                    continue
                ex = c + 0.5 - uv[i, 0]
                ey = r + 0.5 - uv[i, 1]
                d2 = np.float32(ex * ex + ey * ey)
                base = np.uint64(min(d2 * k65536, cap)) << np.uint64(8)
                for j in range(n_lab):
                    key = base | np.uint64(lab[i, j])
                    if key < best[j, p]:
                        best[j, p] = key


@numba.njit(nogil=True, cache=True)
def upsample_u8(img: np.ndarray, k: int, h: int, w: int) -> np.ndarray:
    """(h, w) uint8: every pixel of ``img`` repeated k x k, rows / columns past the end
    repeating the last one -- :func:`occufly.render._upsample` for uint8 images, in one pass
    writing each output byte once (the broadcast copy reads it through a 4-D view)."""
    h0, w0 = img.shape
    out = np.empty((h, w), np.uint8)
    for y in range(h):
        sy = min(y // k, h0 - 1)
        row = img[sy]
        o = out[y]
        for x in range(w):
            o[x] = row[min(x // k, w0 - 1)]
    return out


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the pass on a one-point input."""
    depth = np.full(4, np.inf, np.float32)
    best = np.full(4, np.iinfo(np.uint64).max, np.uint64)
    one = np.ones(1, np.int64)
    z = np.ones(1, np.float32)
    for label_pass in (False, True):
        splat_pass(depth, best, np.full((1, 2), 0.5), z, one, one - 1, one - 1,
                   np.ones(1, np.uint8), np.float32(0.1), 2, 2, label_pass)
    splat_label_pass_multi(depth, np.full((2, 4), np.iinfo(np.uint64).max, np.uint64),
                           np.full((1, 2), 0.5), z, one, one - 1, one - 1,
                           np.ones((1, 2), np.uint8), np.float32(0.1), 2, 2)
    upsample_u8(np.ones((1, 1), np.uint8), 2, 2, 2)
