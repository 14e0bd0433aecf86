"""Ray-cast rendering of the synthetic world with Open3D's ``RaycastingScene``.

Per image: RGB (Lambertian sun + ambient, cast shadows, per-class procedural texture from value
noise on world coordinates so texture is consistent across views, road and parking markings,
windows, sensor grain, vignetting), the exact per-pixel class id, the instance id, metric
z-depth and the surface normal. Pixel (r, c) is sampled at its centre (c + 0.5, r + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occufly.camera import Camera, camera_center
from occufly.synthetic.world import (
    BUILDING,
    DIRT,
    GRASS,
    GRAVEL,
    GROUND_RGB,
    PARKING,
    ROAD,
    ROCK,
    ROOF,
    TERRAIN,
    TREE,
    VEGETATION,
    WALKWAY,
    WATER,
    World,
)

SKY_RGB = np.array([178.0, 198.0, 226.0])
AMBIENT = 0.42
_LATTICE = 256

# texture amplitude per class: (low ~4 m, mid ~0.8 m, fine ~0.15 m)
_TEXTURE = {
    ROAD: (0.06, 0.05, 0.08), WALKWAY: (0.05, 0.05, 0.06), DIRT: (0.12, 0.10, 0.10),
    GRAVEL: (0.05, 0.10, 0.22), GRASS: (0.16, 0.12, 0.10), VEGETATION: (0.22, 0.20, 0.18),
    WATER: (0.05, 0.06, 0.02), PARKING: (0.05, 0.04, 0.06), TREE: (0.10, 0.18, 0.22),
    ROCK: (0.08, 0.12, 0.12), BUILDING: (0.04, 0.03, 0.04), ROOF: (0.05, 0.05, 0.08),
}
_DEFAULT_TEXTURE = (0.04, 0.04, 0.05)


@dataclass
class RenderResult:
    """rgb (H, W, 3) uint8; cls (H, W) uint8 raw class id (0 = no surface / sky);
    inst (H, W) int32; depth (H, W) float32 camera z in metres (0 = no surface);
    normal (H, W, 3) float32 world unit normals facing the camera; xyz (H, W, 3) float32
    scene-local hit points (NaN where no surface)."""

    rgb: np.ndarray
    cls: np.ndarray
    inst: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    xyz: np.ndarray


class Renderer:
    """Holds the ray-casting scene and texture lattices of one world."""

    def __init__(self, world: World, seed: int) -> None:
        import open3d as o3d  # here, not at module level: every CLI command imports this package
        if world.vertices is None:
            world.build_mesh()
        self.world = world
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(world.vertices, dtype=o3d.core.float32),
            o3d.core.Tensor(world.triangles, dtype=o3d.core.uint32),
        )
        rng = np.random.default_rng([seed, 0x7E57])
        self.lattice = rng.uniform(-1.0, 1.0, (3, _LATTICE, _LATTICE)).astype(np.float32)
        tex = np.zeros((256, 3), np.float32)
        tex[:] = _DEFAULT_TEXTURE
        for k, v in _TEXTURE.items():
            tex[k] = v
        self.texture_lut = tex
        ground_rgb = np.zeros((256, 3), np.float32)
        for k, v in GROUND_RGB.items():
            ground_rgb[k] = v
        self.ground_rgb = ground_rgb
        self.markings = np.array(world.markings, np.float32).reshape(-1, 4)
        self._rays: dict[Camera, tuple[np.ndarray, np.ndarray]] = {}

    def _camera_rays(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(H*W, 3) float32 unit-z pixel-centre rays and (H*W,) float32 vignetting factors."""
        if camera not in self._rays:
            rays = camera.pixel_rays(1).astype(np.float32)
            r2 = (rays[:, 0] ** 2 + rays[:, 1] ** 2) / max(float((rays[:, 0] ** 2).max()), 1e-9)
            self._rays[camera] = (rays, (1.0 - 0.12 * r2).astype(np.float32))
        return self._rays[camera]

    # ---- ray casting -------------------------------------------------------------------
    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """origins, dirs: (N, 3) float32 local. Returns t_hit (N,) (inf on miss), prim (N,) int64
        triangle index (-1 on miss), normal (N, 3) float32 raw triangle normals."""
        import open3d as o3d  # here, not at module level: every CLI command imports this package
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim[~np.isfinite(t)] = -1
        return {"t_hit": t, "prim": prim, "normal": ans["primitive_normals"].numpy()}

    def classify(self, prim: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """Raw class ids of hits: prim (N,) triangle ids (-1 = miss), xyz (N, 3) local hit points."""
        w = self.world
        hit = prim >= 0
        cls = np.where(hit, w.tri_class[np.where(hit, prim, 0)], 0).astype(np.uint8)
        terr = np.flatnonzero(hit & (cls == TERRAIN))
        cls[terr] = w.ground.lookup(xyz[terr, 0], xyz[terr, 1])
        return cls

    def render(self, camera: Camera, T_cam_world: np.ndarray, rng: np.random.Generator,
               rows: tuple[int, int] | None = None) -> RenderResult:
        """Render the whole image, or only its pixel rows ``rows = (r0, r1)`` (a band of the
        image: every field then has ``r1 - r0`` rows; vignetting is that of the whole image)."""
        H, W = camera.height, camera.width
        rays_cam, vignette = self._camera_rays(camera)  # (H*W, 3), z = 1
        if rows is not None:
            r0, r1 = int(rows[0]), int(rows[1])
            if not 0 <= r0 < r1 <= H:
                raise ValueError(f"rows {rows} outside the image's 0..{H}")
            rays_cam, vignette = rays_cam[r0 * W : r1 * W], vignette[r0 * W : r1 * W]
            H = r1 - r0
        R = T_cam_world[:3, :3].astype(np.float32)
        # world direction with unit camera z (= rays_cam @ R, written out: numpy's float32
        # (N, 3) @ (3, 3) takes a slow path)
        dirs = rays_cam[:, 0:1] * R[0] + rays_cam[:, 1:2] * R[1] + rays_cam[:, 2:3] * R[2]
        c = camera_center(T_cam_world).astype(np.float32)
        origins = np.broadcast_to(c, dirs.shape)
        hitinfo = self.cast(origins, dirs)
        t, prim = hitinfo["t_hit"], hitinfo["prim"]
        hit = prim >= 0
        t0 = np.where(hit, t, np.float32(0.0)).astype(np.float32)
        depth = t0
        xyz = c + t0[:, None] * dirs
        xyz[~hit] = np.nan
        n = hitinfo["normal"]
        sgn = np.where(np.einsum("ij,ij->i", n, dirs) > 0, np.float32(-1.0), np.float32(1.0))
        sgn[~hit] = 0.0
        n = n * sgn[:, None]
        cls = self.classify(prim, xyz)
        inst = np.where(hit, self.world.tri_inst[np.where(hit, prim, 0)], 0).astype(np.int32)
        rgb = self._shade(xyz, n, prim, cls, hit, dirs)
        # sensor: vignetting and grain
        rgb *= vignette[:, None]
        rgb += rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(2.2)
        return RenderResult(
            rgb=np.clip(rgb, 0, 255).astype(np.uint8).reshape(H, W, 3),
            cls=cls.reshape(H, W),
            inst=inst.reshape(H, W),
            depth=depth.reshape(H, W),
            normal=n.reshape(H, W, 3),
            xyz=xyz.reshape(H, W, 3),
        )

    # ---- shading -----------------------------------------------------------------------
    def _noise(self, u: np.ndarray, v: np.ndarray, octave: int) -> np.ndarray:
        """Smooth value noise in [-1, 1] on a periodic 256 x 256 lattice."""
        L = self.lattice[octave]
        u = u.astype(np.float32, copy=False)
        v = v.astype(np.float32, copy=False)
        iu, iv = np.floor(u), np.floor(v)
        fu, fv = u - iu, v - iv
        fu = fu * fu * (3 - 2 * fu)
        fv = fv * fv * (3 - 2 * fv)
        i0 = iu.astype(np.int32) & (_LATTICE - 1)
        j0 = iv.astype(np.int32) & (_LATTICE - 1)
        i1, j1 = (i0 + 1) & (_LATTICE - 1), (j0 + 1) & (_LATTICE - 1)
        a = L[i0, j0] * (1 - fu) + L[i1, j0] * fu
        b = L[i0, j1] * (1 - fu) + L[i1, j1] * fu
        return a * (1 - fv) + b * fv

    def _shade(self, xyz: np.ndarray, n: np.ndarray, prim: np.ndarray, cls: np.ndarray,
               hit: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        import open3d as o3d  # here, not at module level: every CLI command imports this package
        w = self.world
        # full-array arithmetic (most rays hit); misses are overwritten with the sky at the end
        p = np.nan_to_num(xyz)
        c = cls
        pr = np.where(hit, prim, 0)
        nn = n
        terr = w.tri_class[pr] == TERRAIN
        base = np.where(terr[:, None], self.ground_rgb[c], w.tri_rgb[pr].astype(np.float32))
        # texture coordinates: world xy, sheared by z so walls get texture too
        u = p[:, 0] + np.float32(0.6) * p[:, 2]
        v = p[:, 1] - np.float32(0.45) * p[:, 2]
        amp = self.texture_lut[c]
        tex = (amp[:, 0] * self._noise(u * np.float32(0.25), v * np.float32(0.25), 0)
               + amp[:, 1] * self._noise(u * np.float32(1.25) + 17.3, v * np.float32(1.25) + 5.1, 1)
               + amp[:, 2] * self._noise(u * np.float32(6.667) + 3.7, v * np.float32(6.667) + 11.9, 2))
        col = base * (1.0 + tex)[:, None]
        # road markings: dashed centre line and edge lines
        white = np.zeros(len(p), bool)
        sub = np.flatnonzero(c == ROAD)
        if len(sub):
            q = p[sub]
            m = np.zeros(len(sub), bool)
            for r in w.roads:
                a = q[:, 0] if r.axis == "x" else q[:, 1]
                o = np.abs((q[:, 1] if r.axis == "x" else q[:, 0]) - r.c)
                m |= ((o < 0.08) & (np.mod(a, 6.0) < 3.0)) | (np.abs(o - (r.width / 2 - 0.35)) < 0.08)
            white[sub] = m
        sub = np.flatnonzero(c == PARKING)
        if len(sub) and len(self.markings):
            q = p[sub]
            m = np.zeros(len(sub), bool)
            mk = self.markings
            # markings are few dozen thin rects: test them in one broadcast, in chunks of pixels
            for s0 in range(0, len(sub), 20000):
                qq = q[s0 : s0 + 20000, None, :2]
                inside = ((qq[..., 0] >= mk[:, 0]) & (qq[..., 0] < mk[:, 1])
                          & (qq[..., 1] >= mk[:, 2]) & (qq[..., 1] < mk[:, 3]))
                m[s0 : s0 + 20000] = inside.any(axis=1)
            white[sub] = m
        col[white] = (222.0, 222.0, 214.0)
        # windows on building walls (vertical faces)
        sub = np.flatnonzero((c == BUILDING) & (np.abs(nn[:, 2]) < 0.3))
        if len(sub):
            q, qn = p[sub], nn[sub]
            s_ = np.where(np.abs(qn[:, 0]) > np.abs(qn[:, 1]), q[:, 1], q[:, 0])
            zm = np.mod(q[:, 2], 3.0)
            sm = np.mod(s_, 2.6)
            win = (zm > 1.0) & (zm < 2.3) & (sm > 0.7) & (sm < 1.9)
            col[sub[win]] = (62.0, 72.0, 88.0)
        # Lambert with cast shadows
        sun = w.sun.astype(np.float32)
        lam = np.clip(nn[:, 0] * sun[0] + nn[:, 1] * sun[1] + nn[:, 2] * sun[2], 0.0, 1.0)
        lit = np.flatnonzero(lam > 0)
        shadow = np.zeros(len(p), bool)
        if len(lit):
            rays = np.empty((len(lit), 6), np.float32)
            rays[:, :3] = p[lit] + nn[lit] * np.float32(0.02)
            rays[:, 3:] = sun
            occ = self.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.01, tfar=1e4).numpy()
            shadow[lit] = occ.astype(bool)
        light = AMBIENT + (1 - AMBIENT) * lam * (~shadow)
        # water: darker, with a faint sky reflection
        wat = np.flatnonzero(c == WATER)
        col[wat] = col[wat] * 0.8 + 0.15 * SKY_RGB
        out = col * light[:, None]
        miss = np.flatnonzero(~hit)
        if len(miss):  # sky with a faint vertical gradient
            up = dirs[miss, 2] / np.linalg.norm(dirs[miss], axis=1)
            out[miss] = SKY_RGB * (0.9 + 0.1 * np.clip(up + 1, 0, 1))[:, None]
        return out.astype(np.float32)


def render_banded(renderer: Renderer, camera: Camera, T_cam_world: np.ndarray, rng: np.random.Generator,
                  *, band_pixels: int = 1 << 21) -> RenderResult:
    """:meth:`Renderer.render` of the whole image, cast in bands of about ``band_pixels`` pixels
    so that a 20 MP frame needs a few hundred MB of temporaries instead of several GB. An image
    of at most ``band_pixels`` pixels is rendered in one call (identical to ``render``)."""
    H, W = camera.height, camera.width
    if H * W <= band_pixels:
        return renderer.render(camera, T_cam_world, rng)
    step = max(1, band_pixels // W)
    parts = [renderer.render(camera, T_cam_world, rng, rows=(r0, min(H, r0 + step)))
             for r0 in range(0, H, step)]
    return RenderResult(**{k: np.concatenate([getattr(p, k) for p in parts])
                           for k in ("rgb", "cls", "inst", "depth", "normal", "xyz")})


def noisy_depth(depth: np.ndarray, cls: np.ndarray, rng: np.random.Generator, *, sigma: float,
                invalid_near_edges: float = 0.5, invalid_random: float = 0.005,
                invalid_water: float = 0.3) -> np.ndarray:
    """MVS-like depth map from the exact one.

    depth: (H, W) float32 true z-depth (0 = no surface); cls: (H, W) uint8 true classes.
    Multiplies by (1 + sigma * N(0, 1)); pixels within one pixel of a depth discontinuity
    (relative jump > 3 %) are set to 0 with probability ``invalid_near_edges`` (where COLMAP's
    geometric consistency check rejects them), plus ``invalid_random`` of all pixels and
    ``invalid_water`` of the (specular, texture-poor) water pixels.
    """
    d = depth.astype(np.float32)
    valid = d > 0
    out = d * (1.0 + sigma * rng.standard_normal(d.shape).astype(np.float32))
    jump = np.zeros(d.shape, bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        dv = np.abs(d[1:, :] - d[:-1, :]) / np.maximum(np.minimum(d[1:, :], d[:-1, :]), 1e-6)
        dh = np.abs(d[:, 1:] - d[:, :-1]) / np.maximum(np.minimum(d[:, 1:], d[:, :-1]), 1e-6)
    ev = (dv > 0.03) | (valid[1:, :] != valid[:-1, :])
    eh = (dh > 0.03) | (valid[:, 1:] != valid[:, :-1])
    jump[1:, :] |= ev
    jump[:-1, :] |= ev
    jump[:, 1:] |= eh
    jump[:, :-1] |= eh
    u = rng.random(d.shape)
    drop = (jump & (u < invalid_near_edges)) | (u > 1.0 - invalid_random)
    drop |= (cls == WATER) & (rng.random(d.shape) < invalid_water)
    out[drop | ~valid] = 0.0
    return out
