"""Compiled kernel of the denoise's exact k-NN at class boundaries (see
:func:`occufly.lifting.knn._block_knn`).

For every labelled query point of a chunk of voxels it counts, per class column, its k nearest
labelled points (one more on an exact distance tie) within the radius, searched among the
labelled points of its voxel's 3x3x3 block, and returns the squared distance of its k-th
neighbour. Per point that is one pass over the block's ~800 candidates for the distances and
one selection (quickselect) for the k-th: ~4x less CPU than the per-voxel numpy version it
replaced (matrix product, ``np.partition`` over the whole distance matrix, ``reduceat``),
and it runs without the GIL, so the threads of ``_block_knn`` use every core.

Compiled by numba on first use and cached next to this file (or numba's user cache when that
is not writable), so only the first fill on a machine pays the ~5 s of compilation.
"""

from __future__ import annotations

import numba
import numpy as np

NBINS = 64


@numba.njit(nogil=True, cache=True)
def _select(buf: np.ndarray, n: int, kth: int) -> float:
    """The ``kth`` smallest (0-based) of ``buf[:n]``, reordering ``buf`` in place
    (Hoare quickselect, median-of-three pivot)."""
    lo, hi = 0, n - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        a, b, c = buf[lo], buf[mid], buf[hi]
        if a < b:
            pivot = b if b < c else (c if a < c else a)
        else:
            pivot = a if a < c else (c if b < c else b)
        i, j = lo, hi
        while i <= j:
            while buf[i] < pivot:
                i += 1
            while buf[j] > pivot:
                j -= 1
            if i <= j:
                t = buf[i]
                buf[i] = buf[j]
                buf[j] = t
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            return buf[kth]
    return buf[kth]


@numba.njit(nogil=True, cache=True)
def block_votes(xyz: np.ndarray, cols: np.ndarray, order: np.ndarray, starts: np.ndarray,
                ends: np.ndarray, todo: np.ndarray, nb: np.ndarray, only: np.ndarray,
                use_only: bool, k: int, r2: float, n_cols: int):
    """Voxels ``todo`` (their 27 block neighbours ``nb``, -1 = empty) -> (query point ids (m,),
    votes (m, n_cols) int32, squared k-th neighbour distance (m,) float64, full (m,) bool: the
    block held at least k candidates).

    xyz: (N, 3) float32; cols: (N,) class column per point; ``order[starts[v]:ends[v]]``: the
    labelled points of voxel v; only: (N,) bool, the points to answer (when ``use_only``).
    Distances in float64 from float32 coordinates."""
    T = todo.shape[0]
    m = 0
    cmax = 0
    for t in range(T):
        u = todo[t]
        for i in range(starts[u], ends[u]):
            if not use_only or only[order[i]]:
                m += 1
        c = 0
        for j in range(27):
            v = nb[t, j]
            if v >= 0:
                c += ends[v] - starts[v]
        cmax = max(cmax, c)
    qids = np.empty(m, np.int64)
    votes = np.zeros((m, n_cols), np.int32)
    kth2 = np.empty(m, np.float64)
    full = np.empty(m, np.bool_)
    cx = np.empty(cmax, np.float64)
    cy = np.empty(cmax, np.float64)
    cz = np.empty(cmax, np.float64)
    cc = np.empty(cmax, np.int64)
    d2 = np.empty(cmax, np.float64)
    buf = np.empty(cmax, np.float64)
    hist = np.empty(NBINS + 1, np.int64)
    r = 0
    for t in range(T):
        u = todo[t]
        nc = 0
        for j in range(27):
            v = nb[t, j]
            if v < 0:
                continue
            for i in range(starts[v], ends[v]):
                p = order[i]
                cx[nc] = xyz[p, 0]
                cy[nc] = xyz[p, 1]
                cz[nc] = xyz[p, 2]
                cc[nc] = cols[p]
                nc += 1
        kk = min(k, nc)
        for i in range(starts[u], ends[u]):
            p = order[i]
            if use_only and not only[p]:
                continue
            px, py, pz = np.float64(xyz[p, 0]), np.float64(xyz[p, 1]), np.float64(xyz[p, 2])
            dmax = 0.0
            for c in range(nc):
                dx = cx[c] - px
                dy = cy[c] - py
                dz = cz[c] - pz
                d = dx * dx + dy * dy + dz * dz
                d2[c] = d
                if d > dmax:
                    dmax = d
            if kk < nc and dmax > 0.0:
                # the bin of a 64-bin histogram of the distances that holds the k-th, then
                # quickselect among that bin's few values only (exact: the k-th itself)
                for h in range(NBINS + 1):
                    hist[h] = 0
                scale = NBINS / dmax
                for c in range(nc):
                    hist[min(int(d2[c] * scale), NBINS)] += 1
                below = 0
                h = 0
                while below + hist[h] < kk:
                    below += hist[h]
                    h += 1
                m_in = 0
                for c in range(nc):
                    if min(int(d2[c] * scale), NBINS) == h:
                        buf[m_in] = d2[c]
                        m_in += 1
                kd = _select(buf, m_in, kk - 1 - below)
            else:
                kd = dmax  # every candidate counts (or they all coincide)
            lim = min(kd, r2)
            for c in range(nc):
                if d2[c] <= lim:
                    votes[r, cc[c]] += 1
            qids[r] = p
            kth2[r] = kd
            full[r] = kk == k
            r += 1
    return qids, votes, kth2, full


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the kernels on a tiny input: the Docker image runs
    this at build time, so a container's first fill does not pay the compilation."""
    xyz = np.zeros((2, 3), np.float32)
    xyz[1, 0] = 1.0
    xyz.flags.writeable = False  # as _block_knn passes it
    one = np.zeros(1, np.int64)
    block_votes(xyz, np.zeros(2, np.int64), np.arange(2, dtype=np.int64), one, one + 2, one,
                np.full((1, 27), -1, np.int64) + np.eye(1, 27, 13, dtype=np.int64), np.ones(2, bool),
                False, 1, 4.0, 1)
