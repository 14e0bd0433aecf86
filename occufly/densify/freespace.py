"""Free-space check of carved voxels against the survey's real cameras.

The visual hull of an instance (:mod:`.carve`) is built from 24 *virtual* silhouettes; it
cannot tell that a region inside every silhouette was in fact seen empty by the real cameras:
the gap between two buildings DBSCAN merged into one instance, the triangle between a crane's
mast and its jib, the air over a row of parked cars. The survey saw through those regions:
its images observed the ground or a wall *behind* them.

For every frame, the depths of the points it sees (the workspace visibility: uv + camera
depth) are splatted into a coarse raster (pixel ≈ ``pixel_voxels`` voxel edges on the ground
at the frame's median depth), keeping the *nearest* depth per pixel, so a pixel only claims
free space in front of everything it saw. A carved voxel centre that projects onto an observed
pixel is

- **free** in that frame when it lies more than ``tolerance`` voxel edges in front of the
  observed depth (the ray passed through it),
- **on the surface** when it lies within ``tolerance`` of it (evidence of matter).

A carved voxel is removed when it is free in at least ``min_free_views`` frames and in more
frames than it is on the surface. Voxels that hold points are never tested (the caller keeps
them). Cost: one projection per (voxel, frame), vectorised over voxels, a Python loop over the
frames only, and each frame tests only the voxels inside the box around its frustum (found
by a binary search over the x-sorted centres), so thousands of frames over a large area cost
about the frames that see each voxel, not all of them. Memory: one float32 raster per frame, at most ``max_raster`` pixels on its long
side (a 20 MP frame at 50 m: ~300 x 200 = 0.23 MB; 3,000 frames: ~0.7 GB).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occufly.camera import camera_center, transform


@dataclass(frozen=True)
class FreeSpaceParams:
    pixel_voxels: float = 0.5  # raster pixel edge on the surface, in voxel edges
    tolerance: float = 1.5  # voxel edges in front of the observed depth that count as free
    min_free_views: int = 2
    max_raster: int = 512  # cap on the raster's long side (<= 1 MB per frame)
    chunk: int = 1_000_000  # voxels per projection batch


class FrameDepths:
    """Nearest observed depth per coarse pixel, for every frame of a scene.

    frames: the scene's :class:`occufly.scene.Frame` list; visibility: its
    :class:`occufly.scene.Visibility`; voxel_size: metres.
    """

    def __init__(self, frames, visibility, voxel_size: float, params: FreeSpaceParams = FreeSpaceParams()):
        self.params = params
        self.voxel_size = float(voxel_size)
        self.frames = []  # (scaled camera, T_cam_world, raster (h, w) float32 inf = not seen)
        # uv/depth not stored: frames without distortion take the compiled projection (the
        # same values, without the per-correspondence temporaries of the numpy one)
        cloud = visibility.projected_on_demand()
        if cloud is not None:
            from occufly.densify.depthraster import frame_depths, frame_raster

            xyz = np.asarray(cloud)
        for f, fr in enumerate(frames):
            cam = fr.camera
            T = np.ascontiguousarray(fr.T_cam_world, dtype=np.float64)
            fast = cloud is not None and not cam.has_distortion
            if fast:
                ids = np.asarray(visibility.frame_ids(f))
                depth = frame_depths(xyz, ids, T) if len(ids) else np.zeros(0, np.float32)
            else:
                _, uv, depth = visibility.frame(f)
            if len(depth) == 0:
                continue
            med = float(np.median(depth))
            focal = float(np.mean(cam.focal))
            # pixels per raster pixel: the footprint of pixel_voxels voxel edges at the median depth
            px = max(1.0, params.pixel_voxels * self.voxel_size * focal / max(med, 1e-6))
            px = max(px, max(cam.width, cam.height) / params.max_raster)
            scale = 1.0 / px
            small = cam.scaled(scale)
            w, h = small.width, small.height
            raster = np.full(h * w, np.inf, np.float32)
            if fast:
                (fx, fy), (cx, cy) = cam.focal, cam.principal_point
                zmax = float(frame_raster(xyz, ids, T, float(fx), float(fy), float(cx),
                                          float(cy), float(cam.skew), float(scale), raster, h, w))
            else:
                c = np.floor(np.asarray(uv, np.float64) * scale).astype(np.int64)
                ok = (c[:, 0] >= 0) & (c[:, 0] < w) & (c[:, 1] >= 0) & (c[:, 1] < h) & (depth > 0)
                np.minimum.at(raster, c[ok, 1] * w + c[ok, 0], np.asarray(depth, np.float32)[ok])
                zmax = float(np.max(np.asarray(depth)[ok])) if ok.any() else 0.0
            self.frames.append((small, T, raster.reshape(h, w), self._frustum_box(cam, T, zmax)))

    def _frustum_box(self, cam, T: np.ndarray, zmax: float) -> tuple[np.ndarray, np.ndarray]:
        """Scene-local (lo, hi) box around the frustum up to depth zmax + tolerance: every voxel
        centre that can get a vote from this frame lies inside it (plus one voxel of margin for
        lens distortion between the sampled border points)."""
        W, H = cam.width, cam.height
        border = np.array([[0, 0], [W / 2, 0], [W, 0], [W, H / 2], [W, H], [W / 2, H], [0, H], [0, H / 2]], float)
        far = zmax + (self.params.tolerance + 1.0) * self.voxel_size
        pc = cam.unproject(border, far)
        Tinv = np.linalg.inv(T)
        pw = transform(Tinv, pc)
        pts = np.vstack([pw, camera_center(T)[None]])
        m = self.voxel_size
        return pts.min(axis=0) - m, pts.max(axis=0) + m

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def votes(self, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free (V,) int32, surface (V,) int32) frame counts for voxel centres (V, 3) scene-local."""
        tol = self.params.tolerance * self.voxel_size
        n = len(centres)
        free = np.zeros(n, np.int32)
        surf = np.zeros(n, np.int32)
        for a in range(0, n, self.params.chunk):
            p = np.asarray(centres[a : a + self.params.chunk], np.float64)
            fv = free[a : a + len(p)]
            sv = surf[a : a + len(p)]
            order = np.argsort(p[:, 0], kind="stable")
            xs = p[order, 0]
            for cam, T, raster, (lo, hi) in self.frames:
                # only the centres inside the frame's frustum box (x by binary search)
                i0, i1 = np.searchsorted(xs, [lo[0], hi[0]])
                sub = order[i0:i1]
                q = p[sub]
                inb = np.all((q[:, 1:] >= lo[1:]) & (q[:, 1:] <= hi[1:]), axis=1)
                sub = sub[inb]
                if not len(sub):
                    continue
                h, w = raster.shape
                uv, z = cam.project(transform(T, p[sub]))
                with np.errstate(invalid="ignore"):
                    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
                idx = np.flatnonzero(ok)
                if not len(idx):
                    continue
                obs = raster[uv[idx, 1].astype(np.int64), uv[idx, 0].astype(np.int64)]
                seen = np.isfinite(obs)
                d = obs[seen] - z[idx[seen]]
                hit = sub[idx[seen]]
                fv[hit[d > tol]] += 1
                sv[hit[np.abs(d) <= tol]] += 1
        return free, surf

    def free_mask(self, centres: np.ndarray) -> np.ndarray:
        """(V,) bool: voxel centres the cameras saw through (see the module docstring)."""
        free, surf = self.votes(centres)
        return (free >= self.params.min_free_views) & (free > surf)
