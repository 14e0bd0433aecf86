"""Compiled kernels of the fill: the denoise's exact k-NN at class boundaries (see
:func:`occufly.lifting.knn._block_knn`) and the voxel hash's keys (:func:`voxel_keys`, for
:class:`occufly.lifting.knn.VoxelGrid`).

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


@numba.njit(nogil=True, cache=True)
def _bounds(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(per-axis minimum (3,), maximum (3,)) of ``xyz`` (n, 3), n >= 1, in one pass (numpy's
    ``min(axis=0)`` of an (n, 3) array walks it with a stride of 3 per axis: ~5x slower)."""
    lo = np.empty(3, xyz.dtype)
    hi = np.empty(3, xyz.dtype)
    for a in range(3):
        lo[a] = xyz[0, a]
        hi[a] = xyz[0, a]
    for i in range(1, xyz.shape[0]):
        for a in range(3):
            v = xyz[i, a]
            if v < lo[a]:
                lo[a] = v
            elif v > hi[a]:
                hi[a] = v
    return lo, hi


@numba.njit(nogil=True, cache=True)
def _voxel_keys(xyz: np.ndarray, mn: np.ndarray, edge: float, pad: int, d1: int, d2: int,
                out: np.ndarray) -> None:
    """``out[i] = (qx * d1 + qy) * d2 + qz`` with ``q = floor((xyz[i] - mn) / edge) + pad``
    in float64, the same operations as numpy's broadcast expression in the same order."""
    for i in range(xyz.shape[0]):
        qx = np.int64(np.floor((np.float64(xyz[i, 0]) - mn[0]) / edge)) + pad
        qy = np.int64(np.floor((np.float64(xyz[i, 1]) - mn[1]) / edge)) + pad
        qz = np.int64(np.floor((np.float64(xyz[i, 2]) - mn[2]) / edge)) + pad
        out[i] = (qx * d1 + qy) * d2 + qz


@numba.njit(nogil=True, cache=True)
def _in_box(xyz: np.ndarray, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray, out: np.ndarray) -> None:
    for j in range(len(ids)):
        i = ids[j]
        out[j] = (lo[0] <= xyz[i, 0] <= hi[0]) and (lo[1] <= xyz[i, 1] <= hi[1]) \
            and (lo[2] <= xyz[i, 2] <= hi[2])


def points_in_box(xyz: np.ndarray, ids: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(len(ids),) bool: ``lo <= xyz[ids] <= hi`` on every axis (bounds inclusive, compared in
    float64), without gathering the points first: one compiled pass."""
    xyz = np.asarray(xyz)
    out = np.empty(len(ids), np.bool_)
    _in_box(xyz, np.asarray(ids, np.int64), np.asarray(lo, np.float64), np.asarray(hi, np.float64), out)
    return out


@numba.njit(nogil=True, cache=True)
def block_sum_sorted(keys: np.ndarray, offsets: np.ndarray, counts: np.ndarray, out: np.ndarray) -> None:
    """``out`` (V, C), holding ``counts`` on entry: for each offset in order, add the counts of
    the voxel whose key is ``keys[v] + offset`` (where occupied) to voxel v's row. ``keys``
    sorted ascending and unique, so each offset is one merge walk of them."""
    V = len(keys)
    C = counts.shape[1]
    for o in offsets:
        j = 0
        for v in range(V):
            t = keys[v] + o
            while j < V and keys[j] < t:
                j += 1
            if j == V:
                break
            if keys[j] == t:
                for c in range(C):
                    out[v, c] += counts[j, c]


def voxel_keys(xyz: np.ndarray, edge: float, pad: int, origin: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The voxel hash's lattice of points ``xyz`` (n, 3), n >= 1: (origin (3,) float64 -- the
    given one or the points' minimum --, dims (3,) int64, key per point (n,) int64), exactly
    what :class:`occufly.lifting.knn.VoxelGrid` computed with numpy (``q = floor((xyz - mn) /
    edge) + pad``, ``dims = q.max(0) + pad + 1``, key row-major in dims) in two compiled
    passes and no (n, 3) temporaries: ~5x less CPU on 1.6 M points."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise ValueError(f"voxel_keys needs (n >= 1, 3) points, got {xyz.shape}")
    if xyz.dtype not in (np.float32, np.float64):
        xyz = xyz.astype(np.float64)
    lo, hi = _bounds(xyz)
    mn = (lo if origin is None else np.asarray(origin)).astype(np.float64)
    # floor and the division are monotone: the largest q is the maximum's q
    qmax = np.floor((hi.astype(np.float64) - mn) / float(edge)).astype(np.int64) + pad
    dims = qmax + pad + 1
    key = np.empty(len(xyz), np.int64)
    _voxel_keys(xyz, mn, float(edge), int(pad), int(dims[1]), int(dims[2]), key)
    return mn, dims, key


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the kernels on a tiny input: the Docker image runs
    this at build time, so a container's first fill does not pay the compilation."""
    for dt in (np.float32, np.float64):
        block_sum_sorted(np.zeros(1, np.int64), np.ones(1, np.int64), np.zeros((1, 1), dt),
                         np.zeros((1, 1), dt))
        voxel_keys(np.zeros((1, 3), dt), 1.0, 1)
        points_in_box(np.zeros((1, 3), dt), np.zeros(1, np.int64), np.zeros(3), np.ones(3))
    xyz = np.zeros((2, 3), np.float32)
    xyz[1, 0] = 1.0
    xyz.flags.writeable = False  # as _block_knn passes it
    one = np.zeros(1, np.int64)
    block_votes(xyz, np.zeros(2, np.int64), np.arange(2, dtype=np.int64), one, one + 2, one,
                np.full((1, 27), -1, np.int64) + np.eye(1, 27, 13, dtype=np.int64), np.ones(2, bool),
                False, 1, 4.0, 1)
