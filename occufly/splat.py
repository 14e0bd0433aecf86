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
def sparse_at(ids: np.ndarray, values: np.ndarray, at: np.ndarray, out: np.ndarray) -> bool:
    """``out[k]`` = the value of point ``at[k]`` in the sparse labels (``ids`` strictly
    increasing, ``values`` theirs; 0 where a point is not among them), ``at`` ascending: one
    merge walk instead of an (N,) array per label set. Returns False (``out`` incomplete)
    when ``ids`` or ``at`` is not sorted."""
    n = ids.shape[0]
    for i in range(1, n):
        if ids[i] <= ids[i - 1]:
            return False
    j = 0
    prev = -1
    for k in range(at.shape[0]):
        a = at[k]
        if a < prev:
            return False
        prev = a
        while j < n and ids[j] < a:
            j += 1
        out[k] = values[j] if j < n and ids[j] == a else 0
    return True


@numba.njit(nogil=True, cache=True)
def sparse_at_columns(ids: np.ndarray, values: np.ndarray, at: np.ndarray, out: np.ndarray,
                      cols: np.ndarray) -> bool:
    """:func:`sparse_at` of several value columns over the same ids in one merge walk:
    ``out[k, cols[j]]`` = ``values[i, j]`` where ``ids[i] == at[k]``, else 0."""
    n = ids.shape[0]
    for i in range(1, n):
        if ids[i] <= ids[i - 1]:
            return False
    m = cols.shape[0]
    j = 0
    prev = -1
    for k in range(at.shape[0]):
        a = at[k]
        if a < prev:
            return False
        prev = a
        while j < n and ids[j] < a:
            j += 1
        if j < n and ids[j] == a:
            for c in range(m):
                out[k, cols[c]] = values[j, c]
        else:
            for c in range(m):
                out[k, cols[c]] = 0
    return True


@numba.njit(nogil=True, cache=True)
def finish_keys(depth: np.ndarray, best: np.ndarray, cls: np.ndarray) -> None:
    """The end of the two passes in one sweep: ``depth`` (P,) float32 set to 0 where not
    finite (in place); ``cls`` (L, P) uint8 the low byte of each key of ``best`` (L, P)
    uint64, 0 where no fragment matched (the key is the uint64 maximum) -- what
    ``render._finish`` computed with masks and casts."""
    for p in range(depth.shape[0]):
        if not np.isfinite(depth[p]):
            depth[p] = 0.0
    none = np.uint64(0xFFFFFFFFFFFFFFFF)
    low = np.uint64(255)
    for j in range(best.shape[0]):
        for p in range(best.shape[1]):
            k = best[j, p]
            cls[j, p] = 0 if k == none else np.uint8(k & low)


@numba.njit(nogil=True, cache=True)
def pair_lookup(table: np.ndarray, a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out[i] = table[a[i], b[i]]`` for uint8 ``a``, ``b`` and a (256, 256) uint8 table
    (what ``table.ravel()[(a << 8) | b]`` gives, without the uint16 key array)."""
    for i in range(a.shape[0]):
        out[i] = table[a[i], b[i]]


@numba.njit(nogil=True, cache=True)
def upsample_u8(img: np.ndarray, k: int, h: int, w: int) -> np.ndarray:
    """(h, w) uint8: every pixel of ``img`` repeated k x k, rows / columns past the end
    repeating the last one -- :func:`occufly.render._upsample` for uint8 images. Each output
    row of a source row is written once (runs of k bytes, no division per byte) and copied
    to the k - 1 rows below it."""
    h0, w0 = img.shape
    out = np.empty((h, w), np.uint8)
    y = 0
    while y < h:
        sy = min(y // k, h0 - 1)
        row = img[sy]
        o = out[y]
        x = 0
        for sx in range(w0):
            if x >= w:
                break
            val = row[sx]
            e = min(x + k, w)
            for xx in range(x, e):
                o[xx] = val
            x = e
        last = row[w0 - 1]
        for xx in range(x, w):
            o[xx] = last
        y2 = y + 1
        while y2 < h and min(y2 // k, h0 - 1) == sy:
            out[y2, :] = o
            y2 += 1
        y = y2
    return out


@numba.njit(nogil=True, cache=True, inline="always")
def _project_point(xyz: np.ndarray, q: int, T: np.ndarray, fx: float, fy: float, cx: float,
                   cy: float, skew: float, ksize: np.float32, margin: int, max_splat: int,
                   h: int, w: int) -> tuple:
    """(kept, u, v, float32 depth, splat side) of point ``xyz[q]`` for the compiled splat
    passes: the float64 operations of the numpy path in their order (see
    :func:`project_splat_pass`); kept False behind the camera or ``margin`` px or more
    outside the image."""
    x = np.float64(xyz[q, 0])
    y = np.float64(xyz[q, 1])
    zw = np.float64(xyz[q, 2])
    zc = ((x * T[2, 0] + T[2, 1] * y) + T[2, 2] * zw) + T[2, 3]
    if not zc > 1e-6:
        return False, 0.0, 0.0, np.float32(0.0), np.int64(0)
    xc = ((x * T[0, 0] + T[0, 1] * y) + T[0, 2] * zw) + T[0, 3]
    yc = ((x * T[1, 0] + T[1, 1] * y) + T[1, 2] * zw) + T[1, 3]
    xn = xc / zc
    yn = yc / zc
    u = (fx * xn + skew * yn) + cx
    v = fy * yn + cy
    if not (u >= -np.float64(margin) and u < np.float64(w + margin)
            and v >= -np.float64(margin) and v < np.float64(h + margin)):
        return False, 0.0, 0.0, np.float32(0.0), np.int64(0)
    zi = np.float32(zc)
    sf = np.ceil(ksize / zi)
    if sf < np.float32(1.0):
        sf = np.float32(1.0)
    if sf > np.float32(max_splat):
        sf = np.float32(max_splat)
    return True, u, v, zi, np.int64(sf)


@numba.njit(nogil=True, cache=True)
def project_splat_pass(depth: np.ndarray, best: np.ndarray, xyz: np.ndarray, ids: np.ndarray,
                       T: np.ndarray, fx: float, fy: float, cx: float, cy: float, skew: float,
                       ksize: np.float32, margin: int, max_splat: int, lab: np.ndarray,
                       tol: np.float32, h: int, w: int, label_pass: bool,
                       lab_by_pos: bool = False) -> None:
    """:func:`splat_pass` (``label_pass`` False) / :func:`splat_label_pass_multi` straight
    from the cloud, for an undistorted camera: each point ``xyz[ids[k]]`` ((N, 3) scene-local
    metres) is projected with the float64 operations of the numpy path in their order
    (``render._to_camera``: ``((x R0 + R1 y) + R2 z) + t``; ``Camera.project``: ``x / z``,
    ``(fx x + skew y) + cx``), its depth rounded to float32, its splat side
    ``clip(ceil(ksize / z), 1, max_splat)`` in float32, points ``margin`` px or more outside
    the image dropped -- and splatted at once, without the per-point arrays (uv, z, size,
    corners, labels) the numpy path builds. ``lab``: (N, L) uint8 label sets (with
    ``lab_by_pos``: (len(ids), L), row k the labels of point ``ids[k]``); ``best``:
    (L, h * w) uint64, row j lowered as :func:`splat_label_pass_multi` lowers it."""
    k005 = np.float32(0.005)
    k65536 = np.float32(65536.0)
    cap = np.float32(2.0 ** 31)
    n_lab = lab.shape[1]
    for k in range(ids.shape[0]):
        q = ids[k]
        ok, u, v, zi, s = _project_point(xyz, q, T, fx, fy, cx, cy, skew, ksize, margin,
                                         max_splat, h, w)
        if not ok:
            continue
        half = np.float64(s) / 2.0
        col0 = np.int64(np.ceil((u - half) - 0.5))
        row0 = np.int64(np.ceil((v - half) - 0.5))
        for dy in range(s):
            r = row0 + dy
            if r < 0 or r >= h:
                continue
            for dx in range(s):
                c = col0 + dx
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
                ex = c + 0.5 - u
                ey = r + 0.5 - v
                d2 = np.float32(ex * ex + ey * ey)
                base = np.uint64(min(d2 * k65536, cap)) << np.uint64(8)
                lq = k if lab_by_pos else q
                for j in range(n_lab):
                    key = base | np.uint64(lab[lq, j])
                    if key < best[j, p]:
                        best[j, p] = key


@numba.njit(nogil=True, cache=True)
def project_depth_pass(depth: np.ndarray, xyz: np.ndarray, ids: np.ndarray, T: np.ndarray,
                       fx: float, fy: float, cx: float, cy: float, skew: float,
                       ksize: np.float32, margin: int, max_splat: int, h: int, w: int,
                       rec_k: np.ndarray, rec_uv: np.ndarray, rec_z: np.ndarray,
                       rec_s: np.ndarray) -> int:
    """:func:`project_splat_pass`'s depth pass (the same projection, depth and splat side
    of each point, in the same order), recording each point it keeps -- its position k in
    ``ids``, (u, v), float32 depth and splat side -- for :func:`splat_labels_recorded`, so
    the label pass neither reads the cloud again nor projects. Returns how many it kept."""
    n = 0
    for k in range(ids.shape[0]):
        q = ids[k]
        ok, u, v, zi, s = _project_point(xyz, q, T, fx, fy, cx, cy, skew, ksize, margin,
                                         max_splat, h, w)
        if not ok:
            continue
        rec_k[n] = k
        rec_uv[n, 0] = u
        rec_uv[n, 1] = v
        rec_z[n] = zi
        rec_s[n] = s
        n += 1
        half = np.float64(s) / 2.0
        col0 = np.int64(np.ceil((u - half) - 0.5))
        row0 = np.int64(np.ceil((v - half) - 0.5))
        for dy in range(s):
            r = row0 + dy
            if r < 0 or r >= h:
                continue
            for dx in range(s):
                c = col0 + dx
                if c < 0 or c >= w:
                    continue
                p = r * w + c
                if zi < depth[p]:
                    depth[p] = zi
    return n


@numba.njit(nogil=True, cache=True)
def splat_labels_recorded(depth: np.ndarray, best: np.ndarray, n: int, rec_k: np.ndarray,
                          rec_uv: np.ndarray, rec_z: np.ndarray, rec_s: np.ndarray,
                          ids: np.ndarray, lab: np.ndarray, lab_by_pos: bool, tol: np.float32,
                          h: int, w: int) -> None:
    """:func:`project_splat_pass`'s label pass over the points :func:`project_depth_pass`
    recorded (in its order, with its projections): the same keys, the same minima."""
    k005 = np.float32(0.005)
    k65536 = np.float32(65536.0)
    cap = np.float32(2.0 ** 31)
    n_lab = lab.shape[1]
    for i in range(n):
        k = rec_k[i]
        lq = k if lab_by_pos else ids[k]
        u = rec_uv[i, 0]
        v = rec_uv[i, 1]
        zi = rec_z[i]
        s = np.int64(rec_s[i])
        half = np.float64(s) / 2.0
        col0 = np.int64(np.ceil((u - half) - 0.5))
        row0 = np.int64(np.ceil((v - half) - 0.5))
        for dy in range(s):
            r = row0 + dy
            if r < 0 or r >= h:
                continue
            for dx in range(s):
                c = col0 + dx
                if c < 0 or c >= w:
                    continue
                p = r * w + c
                zf = depth[p]
                if not zi <= zf + (tol + k005 * zf):
                    continue
                ex = c + 0.5 - u
                ey = r + 0.5 - v
                d2 = np.float32(ex * ex + ey * ey)
                base = np.uint64(min(d2 * k65536, cap)) << np.uint64(8)
                for j in range(n_lab):
                    key = base | np.uint64(lab[lq, j])
                    if key < best[j, p]:
                        best[j, p] = key


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
    sparse_at(one, np.ones(1, np.uint8), one, np.zeros(1, np.uint8))
    sparse_at_columns(one, np.ones((1, 1), np.uint8), one, np.zeros((1, 1), np.uint8), one - 1)
    finish_keys(depth, best.reshape(1, -1), np.zeros((1, 4), np.uint8))
    rk, ruv = np.zeros(1, np.int64), np.zeros((1, 2), np.float64)
    rz, rs = np.zeros(1, np.float32), np.zeros(1, np.int8)
    m = project_depth_pass(depth, np.zeros((1, 3), np.float32), one - 1, np.eye(4)[:3], 1.0,
                           1.0, 1.0, 1.0, 0.0, np.float32(1.0), 8, 8, 2, 2, rk, ruv, rz, rs)
    for by_pos in (False, True):
        splat_labels_recorded(depth, best.reshape(1, -1), m, rk, ruv, rz, rs, one - 1,
                              np.ones((1, 1), np.uint8), by_pos, np.float32(0.1), 2, 2)
    pair_lookup(np.zeros((256, 256), np.uint8), np.ones(2, np.uint8), np.ones(2, np.uint8),
                np.zeros(2, np.uint8))
    for label_pass in (False, True):
        for by_pos in (False, True):
            project_splat_pass(depth, best.reshape(1, -1), np.zeros((1, 3), np.float32), one - 1,
                               np.eye(4)[:3], 1.0, 1.0, 1.0, 1.0, 0.0, np.float32(1.0), 8, 8,
                               np.ones((1, 1), np.uint8), np.float32(0.1), 2, 2, label_pass,
                               by_pos)

