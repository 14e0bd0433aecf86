"""Points grouped into cubic bins for frustum culling (:class:`PointBins`), used by the
visibility computation and the renderer's cull. Below render and visibility: needs only the camera model."""

from __future__ import annotations

import numba
import numpy as np

from occufly.camera import Camera, transform


class PointBins:
    """Points grouped into cubic bins of edge ``cell`` for frustum culling.

    xyz: (N, 3) float32, scene-local metres.
    """

    def __init__(self, xyz: np.ndarray, cell: float | None = None) -> None:
        xyz = np.asarray(xyz)
        self.n = len(xyz)
        self.cell = 1.0
        self.order = np.zeros(0, np.int64)
        self.starts = np.zeros(1, np.int64)
        self.centers = np.zeros((0, 3))
        self.loose = np.zeros(0, np.int64)
        if not self.n:
            return
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"points: expected (N, 3) coordinates, got {xyz.shape}")
        # compiled passes over the rows (a memory-mapped cloud is read, never copied): a
        # 32 M-point survey's bins took 8.3 s of numpy (the finite copy, a stable argsort of
        # 32 M keys), the first review open or render of every API process waited for them
        n_fin, sub = _finite_subsample(xyz, 200_000)
        if n_fin == 0:  # no finite coordinates: no bins
            return
        # the bins cover the bulk of the cloud (0.1 .. 99.9 % per axis, widened by 10 %); the
        # few points beyond it (far outliers) are candidates of every frame instead, so a
        # point 10 km away neither coarsens the bins nor gets lost
        qlo, qhi = np.quantile(sub, 0.001, axis=0), np.quantile(sub, 0.999, axis=0)
        pad = 0.1 * (qhi - qlo) + 1.0
        lo = (qlo - pad).astype(np.float64)
        hi = (qhi + pad).astype(np.float64)
        if cell is None:
            cell = max(float((hi - lo).max()) / 64.0, 1.0)
        self.cell = float(cell)
        dims, n_inner, self.loose = _bin_extent(xyz, lo, hi, self.cell)
        if n_inner == 0:
            return
        if int(np.prod(dims)) <= max(4 * n_inner, 1 << 22):
            # a stable counting sort by bin key: the order numpy's stable argsort gave
            self.order, nonempty, self.starts = _bin_sort(xyz, lo, hi, self.cell, dims,
                                                          n_inner)
        else:  # a small cell of a caller's over a wide box: too many keys to count, sort them
            inner, key = _bin_keys(xyz, lo, hi, self.cell, dims, n_inner)
            o = np.argsort(key, kind="stable")
            self.order, skey = inner[o], key[o]
            first = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
            self.starts = np.r_[first, n_inner].astype(np.int64)
            nonempty = skey[first]
        k = nonempty % dims[2]
        j = (nonempty // dims[2]) % dims[1]
        i = nonempty // (dims[1] * dims[2])
        self.centers = lo + (np.column_stack([i, j, k]) + 0.5) * self.cell

    def candidate_count(self, camera: Camera, T_cam_world: np.ndarray, far: float = np.inf) -> int:
        """len(:meth:`candidates`) without gathering them (an upper bound of what the frame
        sees)."""
        if self.n == 0 or not len(self.centers):
            return int(len(self.loose))
        sel = self._bins_in_view(camera, T_cam_world, far)
        return int((self.starts[sel + 1] - self.starts[sel]).sum()) + int(len(self.loose))

    def candidates(self, camera: Camera, T_cam_world: np.ndarray, far: float = np.inf) -> np.ndarray:
        """(K,) int64 ids of points in bins that may project into the image (plus the far
        outliers outside the bins, always)."""
        if self.n == 0 or not len(self.centers):
            return self.loose.copy()
        sel = self._bins_in_view(camera, T_cam_world, far)
        if not len(sel):
            return self.loose.copy()
        a, b = self.starts[sel], self.starts[sel + 1]
        lens = b - a
        idx = np.repeat(a - np.r_[0, np.cumsum(lens)[:-1]], lens) + np.arange(lens.sum())
        if len(self.loose):
            return np.concatenate([self.order[idx], self.loose])
        return self.order[idx]

    def _bins_in_view(self, camera: Camera, T_cam_world: np.ndarray, far: float) -> np.ndarray:
        """(B,) int64 indices of the bins that may project into the image."""
        c_cam = transform(T_cam_world, self.centers)
        r = self.cell * 0.8661  # half diagonal
        z = c_cam[:, 2]
        near = z > -r
        fx, fy = camera.focal
        cx, cy = camera.principal_point
        zc = np.maximum(z, 1e-3)
        u = fx * c_cam[:, 0] / zc + cx
        v = fy * c_cam[:, 1] / zc + cy
        mu = fx * r / zc
        mv = fy * r / zc
        inside = (
            near
            & (z - r < far)
            & (u + mu >= 0)
            & (u - mu < camera.width)
            & (v + mv >= 0)
            & (v - mv < camera.height)
        )
        # bins the camera is inside or right next to: always candidates
        inside |= np.linalg.norm(c_cam, axis=1) < 2 * r
        if camera.has_distortion:
            inside |= near  # be generous: distortion moves points near the border
        return np.flatnonzero(inside)


# ---- compiled passes (the same float64 arithmetic as the numpy expressions they replaced) ----
@numba.njit(nogil=True, cache=True)
def _finite_rows(xyz: np.ndarray) -> int:
    n = 0
    for r in range(xyz.shape[0]):
        if np.isfinite(xyz[r, 0]) and np.isfinite(xyz[r, 1]) and np.isfinite(xyz[r, 2]):
            n += 1
    return n


@numba.njit(nogil=True, cache=True)
def _every_kth_finite(xyz: np.ndarray, step: int, n_out: int) -> np.ndarray:
    out = np.empty((n_out, 3), xyz.dtype)
    seen = 0
    k = 0
    for r in range(xyz.shape[0]):
        if np.isfinite(xyz[r, 0]) and np.isfinite(xyz[r, 1]) and np.isfinite(xyz[r, 2]):
            if seen % step == 0:
                out[k] = xyz[r]
                k += 1
            seen += 1
    return out


def _finite_subsample(xyz: np.ndarray, target: int) -> tuple[int, np.ndarray]:
    """(count of rows with finite coordinates, ``xyz[finite][::max(1, count // target)]``)
    without the (N, 3) copy of the finite rows."""
    n = _finite_rows(xyz)
    if n == 0:
        return 0, np.zeros((0, 3), xyz.dtype)
    step = max(1, n // target)
    return n, _every_kth_finite(xyz, step, -(-n // step))


@numba.njit(nogil=True, cache=True, inline="always")
def _inside(xyz: np.ndarray, r: int, lo: np.ndarray, hi: np.ndarray) -> int:
    """1 inside the box, 0 outside (finite), -1 not finite."""
    ok = 1
    for a in range(3):
        v = xyz[r, a]
        if not np.isfinite(v):
            return -1
        x = np.float64(v)
        if not (x >= lo[a] and x <= hi[a]):
            ok = 0
    return ok


@numba.njit(nogil=True, cache=True, inline="always")
def _bin_index(xyz: np.ndarray, r: int, lo: np.ndarray, cell: float, a: int) -> int:
    return np.int64(np.floor((np.float64(xyz[r, a]) - lo[a]) / cell))


@numba.njit(nogil=True, cache=True, inline="always")
def _bin_key(xyz: np.ndarray, r: int, lo: np.ndarray, cell: float, dims: np.ndarray) -> int:
    """The row-major key of point ``r``'s bin (``(i * dims[1] + j) * dims[2] + k``)."""
    return ((_bin_index(xyz, r, lo, cell, 0) * dims[1] + _bin_index(xyz, r, lo, cell, 1))
            * dims[2] + _bin_index(xyz, r, lo, cell, 2))


@numba.njit(nogil=True, cache=True)
def _bin_extent_kernel(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell: float) -> tuple:
    mx = np.zeros(3, np.int64)
    n_inner = 0
    n_loose = 0
    for r in range(xyz.shape[0]):
        s = _inside(xyz, r, lo, hi)
        if s == 1:
            n_inner += 1
            for a in range(3):
                mx[a] = max(mx[a], _bin_index(xyz, r, lo, cell, a))
        elif s == 0:
            n_loose += 1
    return mx + 1, n_inner, n_loose


@numba.njit(nogil=True, cache=True)
def _loose_rows(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, n_loose: int) -> np.ndarray:
    out = np.empty(n_loose, np.int64)
    k = 0
    for r in range(xyz.shape[0]):
        if _inside(xyz, r, lo, hi) == 0:
            out[k] = r
            k += 1
    return out


def _bin_extent(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell: float
                ) -> tuple[np.ndarray, int, np.ndarray]:
    """(dims (3,) int64: the bins spanned by the points inside ``lo..hi``, their count, the
    finite points outside (int64 ids, ascending))."""
    dims, n_inner, n_loose = _bin_extent_kernel(xyz, lo, hi, float(cell))
    loose = _loose_rows(xyz, lo, hi, n_loose) if n_loose else np.zeros(0, np.int64)
    return dims, int(n_inner), loose


@numba.njit(nogil=True, cache=True)
def _bin_sort(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell: float, dims: np.ndarray,
              n_inner: int) -> tuple:
    """(order (n_inner,) the inside points' ids by bin key, ascending ids within a bin; the
    non-empty bins' keys ascending; their starts in ``order``, plus n_inner at the end)."""
    n_keys = dims[0] * dims[1] * dims[2]
    count = np.zeros(n_keys + 1, np.int64)
    for r in range(xyz.shape[0]):
        if _inside(xyz, r, lo, hi) == 1:
            key = _bin_key(xyz, r, lo, cell, dims)
            count[key + 1] += 1
    n_full = 0
    for b in range(n_keys):
        if count[b + 1] > 0:
            n_full += 1
        count[b + 1] += count[b]
    nonempty = np.empty(n_full, np.int64)
    starts = np.empty(n_full + 1, np.int64)
    k = 0
    for b in range(n_keys):
        if count[b + 1] > count[b]:
            nonempty[k] = b
            starts[k] = count[b]
            k += 1
    starts[n_full] = n_inner
    pos = count[:n_keys].copy()
    order = np.empty(n_inner, np.int64)
    for r in range(xyz.shape[0]):
        if _inside(xyz, r, lo, hi) == 1:
            key = _bin_key(xyz, r, lo, cell, dims)
            order[pos[key]] = r
            pos[key] += 1
    return order, nonempty, starts


@numba.njit(nogil=True, cache=True)
def _bin_keys(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, cell: float, dims: np.ndarray,
              n_inner: int) -> tuple:
    """(the inside points' ids ascending, their bin keys)."""
    ids = np.empty(n_inner, np.int64)
    keys = np.empty(n_inner, np.int64)
    k = 0
    for r in range(xyz.shape[0]):
        if _inside(xyz, r, lo, hi) == 1:
            ids[k] = r
            keys[k] = _bin_key(xyz, r, lo, cell, dims)
            k += 1
    return ids, keys
