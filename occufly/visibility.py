"""2D-3D correspondences: which points each frame sees, where they land and at what depth.

Three sources, best first:

1. the reconstruction's own visibility (``fused.ply.vis`` lists, COLMAP tracks);
2. a depth test against MVS depth maps: a point is seen by a frame if it projects inside the
   image and its camera depth ``z`` agrees with the depth map there, ``|z - d| <= rel_tol * d``;
3. the same test against depth maps *rendered from the cloud* by z-buffer splatting.

Everything is vectorised. Candidate points per frame come from a coarse spatial binning
(:class:`PointBins`) so the cost is proportional to what a frame can see, not to the scene.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np

from occufly.camera import Camera, transform
from occufly.progress import ProgressFn, noop
from occufly.scene import Frame, Visibility

log = logging.getLogger(__name__)


class PointBins:
    """Points grouped into cubic bins of edge ``cell`` for frustum culling.

    xyz: (N, 3) float32, scene-local metres.
    """

    def __init__(self, xyz: np.ndarray, cell: float | None = None) -> None:
        xyz = np.asarray(xyz)
        self.n = len(xyz)
        if self.n == 0:
            self.cell = 1.0
            self.order = np.zeros(0, np.int64)
            self.starts = np.zeros(1, np.int64)
            self.centers = np.zeros((0, 3))
            return
        lo = xyz.min(axis=0).astype(np.float64)
        hi = xyz.max(axis=0).astype(np.float64)
        if cell is None:
            cell = max(float((hi - lo).max()) / 64.0, 1.0)
        self.cell = float(cell)
        ijk = np.floor((xyz - lo) / self.cell).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        self.order = np.argsort(key, kind="stable")
        skey = key[self.order]
        first = np.flatnonzero(np.r_[True, skey[1:] != skey[:-1]])
        self.starts = np.r_[first, self.n].astype(np.int64)
        ukey = skey[first]
        k = ukey % dims[2]
        j = (ukey // dims[2]) % dims[1]
        i = ukey // (dims[1] * dims[2])
        self.centers = lo + (np.column_stack([i, j, k]) + 0.5) * self.cell

    def candidates(self, camera: Camera, T_cam_world: np.ndarray, far: float = np.inf) -> np.ndarray:
        """(K,) int64 ids of points in bins that may project into the image."""
        if self.n == 0:
            return np.zeros(0, np.int64)
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
        sel = np.flatnonzero(inside)
        if not len(sel):
            return np.zeros(0, np.int64)
        a, b = self.starts[sel], self.starts[sel + 1]
        lens = b - a
        idx = np.repeat(a - np.r_[0, np.cumsum(lens)[:-1]], lens) + np.arange(lens.sum())
        return self.order[idx]


def project_ids(
    frame: Frame, xyz: np.ndarray, ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project points ``ids`` into ``frame``; keep those in the image and in front.

    Returns (ids (m,) int64, uv (m, 2) float64 pixels, z (m,) float64 camera depth).
    """
    pts = np.asarray(xyz[ids], dtype=np.float64)
    uv, z = frame.camera.project(transform(frame.T_cam_world, pts))
    with np.errstate(invalid="ignore"):
        ok = (z > 0) & frame.camera.in_image(uv)
    return ids[ok], uv[ok], z[ok]


def depth_test(
    uv: np.ndarray, z: np.ndarray, depth_map: np.ndarray, image_size: tuple[int, int],
    rel_tol: float,
) -> np.ndarray:
    """(m,) bool: camera depth ``z`` agrees with ``depth_map`` (h, w) at pixel ``uv``.

    The depth map may be a downscaled version of the (width, height) image.
    """
    h, w = depth_map.shape
    sx = w / image_size[0]
    sy = h / image_size[1]
    col = np.clip((uv[:, 0] * sx).astype(np.int64), 0, w - 1)
    row = np.clip((uv[:, 1] * sy).astype(np.int64), 0, h - 1)
    d = depth_map[row, col]
    return (d > 0) & (np.abs(z - d) <= rel_tol * d)


def render_depth(
    camera: Camera, uv: np.ndarray, z: np.ndarray, radius_px: np.ndarray | float
) -> np.ndarray:
    """Z-buffer splatting of projected points -> (H, W) float32 depth, 0 where empty.

    uv: (m, 2) pixels, z: (m,) depth, radius_px: splat half-size per point (or scalar).
    Each point covers the square of pixels within ``radius_px`` of its pixel.
    """
    h, w = camera.height, camera.width
    zbuf = np.full(h * w, np.inf, dtype=np.float32)
    col = uv[:, 0].astype(np.int64)
    row = uv[:, 1].astype(np.int64)
    rad = np.broadcast_to(np.asarray(np.round(radius_px), dtype=np.int64), z.shape)
    rmax = int(rad.max(initial=0))
    zf = z.astype(np.float32)
    for dr in range(-rmax, rmax + 1):
        for dc in range(-rmax, rmax + 1):
            sel = (np.abs(dr) <= rad) & (np.abs(dc) <= rad) if rmax else slice(None)
            r = row[sel] + dr
            c = col[sel] + dc
            ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            np.minimum.at(zbuf, (r[ok] * w + c[ok]), zf[sel][ok])
    zbuf[~np.isfinite(zbuf)] = 0.0
    return zbuf.reshape(h, w)


def point_spacing(xyz: np.ndarray, sample: int = 20000, seed: int = 0) -> float:
    """Median nearest-neighbour distance of a random sample of points (metres)."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    if n < 2:
        return 0.1
    rng = np.random.default_rng(seed)
    sub = np.asarray(xyz[rng.choice(n, size=min(n, 200_000), replace=False)], dtype=np.float64)
    tree = cKDTree(sub)
    q = sub[: min(sample, len(sub))]
    d, _ = tree.query(q, k=2)
    return float(np.median(d[:, 1])) or 0.05


def visibility_from_depth(
    frames: Sequence[Frame],
    xyz: np.ndarray,
    depth_for: Callable[[int], np.ndarray | None] | None,
    *,
    rel_tol: float = 0.02,
    render_rel_tol: float = 0.05,
    progress: ProgressFn | None = None,
) -> tuple[Visibility, dict]:
    """Visibility by depth test. ``depth_for(f)`` gives frame f's depth map or None, in which
    case a depth map is rendered from the cloud itself (z-buffer splats)."""
    report = progress or noop
    bins = PointBins(xyz)
    spacing = None
    parts = []
    stats = {"frames_with_depth_maps": 0, "frames_rendered": 0}
    for f, frame in enumerate(frames):
        report(f / max(len(frames), 1), "visibility")
        ids, uv, z = project_ids(frame, xyz, bins.candidates(frame.camera, frame.T_cam_world))
        dm = depth_for(f) if depth_for is not None else None
        if dm is not None:
            stats["frames_with_depth_maps"] += 1
            ok = depth_test(uv, z, dm, (frame.camera.width, frame.camera.height), rel_tol)
        else:
            if spacing is None:
                spacing = point_spacing(xyz)
            stats["frames_rendered"] += 1
            fx = frame.camera.focal[0]
            radius = np.clip(0.5 * fx * spacing / np.maximum(z, 1e-6), 0, 3)
            dm = render_depth(frame.camera, uv, z, radius)
            ok = depth_test(uv, z, dm, (frame.camera.width, frame.camera.height), render_rel_tol)
        parts.append((ids[ok], uv[ok], z[ok]))
    report(1.0, "visibility")
    return Visibility.from_parts(parts), stats


def visibility_from_point_lists(
    frames: Sequence[Frame],
    xyz: np.ndarray,
    offsets: np.ndarray,
    frame_indices: np.ndarray,
) -> tuple[Visibility, dict]:
    """Visibility from per-point lists of frames (``fused.ply.vis`` or tracks).

    offsets: (N + 1,) int64 CSR over points; frame_indices: (M,) index into ``frames``, -1 to
    drop. Entries whose point does not project into the frame (behind it, outside the image)
    are dropped and counted.
    """
    n = len(offsets) - 1
    counts = np.diff(offsets)
    point_of = np.repeat(np.arange(n, dtype=np.int64), counts)
    fidx = np.asarray(frame_indices, dtype=np.int64)
    keep = fidx >= 0
    point_of, fidx = point_of[keep], fidx[keep]
    order = np.argsort(fidx, kind="stable")
    point_of, fidx = point_of[order], fidx[order]
    bounds = np.searchsorted(fidx, np.arange(len(frames) + 1))
    parts = []
    dropped = 0
    for f, frame in enumerate(frames):
        ids = point_of[bounds[f] : bounds[f + 1]]
        kept_ids, uv, z = project_ids(frame, xyz, ids)
        dropped += len(ids) - len(kept_ids)
        parts.append((kept_ids, uv, z))
    return Visibility.from_parts(parts), {"entries_outside_image": int(dropped)}
