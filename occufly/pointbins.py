"""Points grouped into cubic bins for frustum culling (:class:`PointBins`), used by the
visibility computation and the renderer's cull. Below render and visibility: needs only the camera model."""

from __future__ import annotations

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
        finite = np.isfinite(xyz).all(axis=1) if self.n else np.zeros(0, bool)
        if not finite.any():  # no points, or none with finite coordinates: no bins
            return
        # the bins cover the bulk of the cloud (0.1 .. 99.9 % per axis, widened by 10 %); the
        # few points beyond it (far outliers) are candidates of every frame instead, so a
        # point 10 km away neither coarsens the bins nor gets lost
        fin = xyz[finite]
        sub = fin[:: max(1, len(fin) // 200_000)]
        qlo, qhi = np.quantile(sub, 0.001, axis=0), np.quantile(sub, 0.999, axis=0)
        pad = 0.1 * (qhi - qlo) + 1.0
        lo = (qlo - pad).astype(np.float64)
        hi = (qhi + pad).astype(np.float64)
        inside = finite & np.all((xyz >= lo) & (xyz <= hi), axis=1)
        self.loose = np.flatnonzero(finite & ~inside)
        if cell is None:
            cell = max(float((hi - lo).max()) / 64.0, 1.0)
        self.cell = float(cell)
        inner = np.flatnonzero(inside)
        ijk = np.floor((xyz[inner] - lo) / self.cell).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        o = np.argsort(key, kind="stable")
        self.order = inner[o]
        skey = key[o]
        first = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
        self.starts = np.r_[first, len(inner)].astype(np.int64)
        ukey = skey[first]
        k = ukey % dims[2]
        j = (ukey // dims[2]) % dims[1]
        i = ukey // (dims[1] * dims[2])
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
