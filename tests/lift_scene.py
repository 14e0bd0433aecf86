"""A small analytic scene for the lifting / render / selection tests.

Ground plane z = 0 with class regions (grass, a road strip, a parking lot), axis-aligned boxes
(buildings with roofs, a vehicle). Points are sampled on every visible surface with exact
labels; visibility is an exact segment-vs-box occlusion test; truth masks are ray-cast per
pixel. Everything is deterministic for a seed.
"""

from __future__ import annotations

import numpy as np

from occufly.camera import Camera, look_at, project_world
from occufly.scene import Frame, Scene, Visibility
from occufly.taxonomy import default_taxonomy

GRASS, ROAD, PARKING, BUILDING, ROOF, VEHICLE = 6, 1, 33, 16, 17, 13
SIZE = 60.0
# (x0, x1, y0, y1, height, side class, top class)
BOXES = [
    (11.0, 21.0, 10.0, 20.0, 10.0, BUILDING, ROOF),
    (40.0, 50.0, 40.0, 50.0, 6.0, BUILDING, ROOF),
    (30.0, 34.0, 27.0, 29.0, 1.5, VEHICLE, VEHICLE),
]


def ground_class(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    out = np.full(np.shape(x), GRASS, dtype=np.uint8)
    out[(y >= 25.0) & (y < 32.0)] = ROAD
    out[(x >= 42.0) & (y < 18.0)] = PARKING
    return out


def _surface_points(spacing: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    pts, labs = [], []
    g = np.arange(spacing / 2, SIZE, spacing)
    gx, gy = np.meshgrid(g, g)
    gx = gx.ravel() + rng.uniform(-0.2, 0.2, gx.size) * spacing
    gy = gy.ravel() + rng.uniform(-0.2, 0.2, gy.size) * spacing
    inside = np.zeros(gx.size, bool)
    for x0, x1, y0, y1, *_ in BOXES:
        inside |= (gx > x0) & (gx < x1) & (gy > y0) & (gy < y1)
    pts.append(np.column_stack([gx[~inside], gy[~inside], np.zeros((~inside).sum())]))
    labs.append(ground_class(gx[~inside], gy[~inside]))
    for x0, x1, y0, y1, h, side, top in BOXES:
        tx, ty = np.meshgrid(np.arange(x0 + spacing / 2, x1, spacing),
                             np.arange(y0 + spacing / 2, y1, spacing))
        pts.append(np.column_stack([tx.ravel(), ty.ravel(), np.full(tx.size, h)]))
        labs.append(np.full(tx.size, top, np.uint8))
        zs = np.arange(spacing / 2, h, spacing)
        for fixed, lo, hi, axis in ((y0, x0, x1, 1), (y1, x0, x1, 1), (x0, y0, y1, 0),
                                    (x1, y0, y1, 0)):
            a, z = np.meshgrid(np.arange(lo + spacing / 2, hi, spacing), zs)
            a, z = a.ravel(), z.ravel()
            f = np.full(a.size, fixed)
            xyz = np.column_stack([a, f, z]) if axis == 1 else np.column_stack([f, a, z])
            pts.append(xyz)
            labs.append(np.full(a.size, side, np.uint8))
    return np.vstack(pts).astype(np.float32), np.concatenate(labs)


def _box_hit_t(origin: np.ndarray, dirs: np.ndarray, box) -> np.ndarray:
    """Entry parameter t of rays origin + t * dirs into an axis-aligned box (inf if missed)."""
    x0, x1, y0, y1, h = box[:5]
    lo = np.array([x0, y0, 0.0])
    hi = np.array([x1, y1, h])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / dirs
        t2 = (hi - origin) / dirs
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (tmax >= tmin) & (tmax > 0)
    return np.where(hit, np.maximum(tmin, 0.0), np.inf)


def visible_points(frame: Frame, xyz: np.ndarray):
    uv, z, vis = project_world(frame.camera, frame.T_cam_world, xyz)
    c = frame.center
    seg = xyz.astype(np.float64) - c
    dist = np.linalg.norm(seg, axis=1)
    occluded = np.zeros(len(xyz), bool)
    for box in BOXES:
        t = _box_hit_t(c, seg, box)
        occluded |= t * dist < dist - 0.05
    ok = vis & ~occluded
    idx = np.flatnonzero(ok)
    return idx.astype(np.int32), uv[idx].astype(np.float32), z[idx].astype(np.float32)


def truth_mask(frame: Frame, scale: int = 1) -> np.ndarray:
    """(H/scale, W/scale) uint8 ray-cast class ids at pixel centres."""
    cam = frame.camera.scaled(1.0 / scale) if scale != 1 else frame.camera
    rays_cam = cam.pixel_rays()
    R = frame.T_cam_world[:3, :3]
    dirs = rays_cam @ R  # camera -> world: R^T @ d
    c = frame.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(dirs[:, 2] < 0, -c[2] / dirs[:, 2], np.inf)
    best_t = t_ground.copy()
    hit = ground_class(c[0] + t_ground * dirs[:, 0], c[1] + t_ground * dirs[:, 1])
    hit[~np.isfinite(t_ground)] = 0
    outside = ~((np.abs(c[0] + t_ground * dirs[:, 0] - SIZE / 2) < SIZE / 2)
                & (np.abs(c[1] + t_ground * dirs[:, 1] - SIZE / 2) < SIZE / 2))
    hit[outside] = 0
    for box in BOXES:
        t = _box_hit_t(c, dirs, box)
        nearer = t < best_t
        p = c + t[:, None] * dirs
        on_top = np.abs(p[:, 2] - box[4]) < 1e-6
        cls = np.where(on_top, box[6], box[5]).astype(np.uint8)
        hit[nearer] = cls[nearer]
        best_t = np.where(nearer, t, best_t)
    return hit.reshape(cam.height, cam.width)


def make_scene(*, spacing: float = 0.5, seed: int = 0, width: int = 160, height: int = 120,
               focal: float = 150.0, altitude: float = 40.0, grid_step: float = 15.0,
               oblique: bool = True) -> tuple[Scene, np.ndarray]:
    """(scene, truth labels (N,) uint8) with nadir cameras on a grid plus oblique views."""
    rng = np.random.default_rng(seed)
    xyz, labels = _surface_points(spacing, rng)
    cam = Camera("PINHOLE", width, height, np.array([focal, focal, width / 2, height / 2]))
    frames = []
    for gx in np.arange(grid_step / 2, SIZE, grid_step):
        for gy in np.arange(grid_step / 2, SIZE, grid_step):
            T = look_at([gx, gy, altitude], [gx, gy, 0.0], up=(0.0, 1.0, 0.0))
            frames.append(Frame(f"nadir_{len(frames):03d}.jpg", cam, T, nominal_altitude=int(altitude)))
    if oblique:
        for cx, cy in ((-15, 30), (75, 30), (30, -15), (30, 75)):
            T = look_at([cx, cy, 30.0], [30.0, 30.0, 0.0])
            frames.append(Frame(f"oblique_{len(frames):03d}.jpg", cam, T, nominal_altitude=30))
    parts = [visible_points(f, xyz) for f in frames]
    vis = Visibility.from_parts(parts)
    scene = Scene(frames=frames, xyz=xyz, rgb=np.zeros_like(xyz, dtype=np.uint8),
                  origin=np.array([500000.0, 5200000.0, 300.0]), visibility=vis,
                  taxonomy=default_taxonomy())
    return scene, labels
