"""A small procedural workspace for the viewer's examples and benchmark (not pipeline data).

Ground (road, grass, parking lot), box buildings with roofs, tree blobs, vehicles and a few
persons (a deliberately rare class), placed around a UTM-sized origin so float16 would
visibly lose precision. Writes the scene workspace plus ``lifting/labels.npy``,
``confidence.npy``, ``origin.npy`` and ``grid/scene_grid.npz``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occufly.camera import Camera, look_at
from occufly.grid import SceneGrid
from occufly.scene import Frame, Scene
from occufly.taxonomy import default_taxonomy
from occufly.workspace import Workspace

UTM_ORIGIN = (512_345.0, 5_412_345.0, 230.0)


def demo_points(n_points: int, *, seed: int = 0, size: float = 160.0) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3) float32 scene-local metres, labels (N,) uint8 raw ids)."""
    rng = np.random.default_rng(seed)
    shares = {6: 0.34, 1: 0.12, 33: 0.10, 16: 0.20, 17: 0.08, 8: 0.12, 13: 0.0395, 11: 0.0005}
    counts = {c: max(1, int(round(s * n_points))) for c, s in shares.items()}
    counts[6] += n_points - sum(counts.values())
    half = size / 2
    parts, labs = [], []

    def put(c: int, xyz: np.ndarray) -> None:
        parts.append(xyz)
        labs.append(np.full(len(xyz), c, np.uint8))

    n = counts[6]  # grass everywhere except the road band and the parking lot
    g = rng.uniform(-half, half, (n, 2))
    g[:, 1] = np.where(np.abs(g[:, 1]) < 8, g[:, 1] + 16 * np.sign(g[:, 1] + 1e-9), g[:, 1])
    put(6, np.column_stack([g, rng.normal(0, 0.03, n)]))
    n = counts[1]
    put(1, np.column_stack([rng.uniform(-half, half, n), rng.uniform(-6, 6, n), rng.normal(0, 0.02, n)]))
    n = counts[33]
    put(33, np.column_stack([rng.uniform(20, 60, n), rng.uniform(-40, -12, n), rng.normal(0, 0.02, n)]))
    # buildings: walls (16) and flat roofs (17) of three boxes
    boxes = np.array([[-50, 30, 20, 16, 12], [10, 40, 24, 18, 18], [-40, -40, 14, 14, 9]], float)
    n = counts[16]
    b = boxes[rng.integers(0, 3, n)]
    t = rng.uniform(0, 1, n)
    side = rng.integers(0, 4, n)
    x = np.where(side < 2, b[:, 0] + (t - 0.5) * b[:, 2], b[:, 0] + np.where(side == 2, -0.5, 0.5) * b[:, 2])
    y = np.where(side < 2, b[:, 1] + np.where(side == 0, -0.5, 0.5) * b[:, 3], b[:, 1] + (t - 0.5) * b[:, 3])
    put(16, np.column_stack([x, y, rng.uniform(0, 1, n) * b[:, 4]]))
    n = counts[17]
    b = boxes[rng.integers(0, 3, n)]
    put(17, np.column_stack([b[:, 0] + rng.uniform(-.5, .5, n) * b[:, 2],
                             b[:, 1] + rng.uniform(-.5, .5, n) * b[:, 3], b[:, 4]]))
    n = counts[8]  # trees: 12 ellipsoid crowns
    centres = np.column_stack([rng.uniform(-half + 10, half - 10, 12), rng.choice([-20, 20], 12),
                               np.full(12, 7.0)])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    put(8, centres[rng.integers(0, 12, n)] + d * np.array([3.0, 3.0, 4.0]))
    n = counts[13]  # 10 cars on the parking lot
    cars = np.column_stack([np.linspace(24, 56, 10), np.full(10, -26.0)])
    k = rng.integers(0, 10, n)
    put(13, np.column_stack([cars[k, 0] + rng.uniform(-1, 1, n), cars[k, 1] + rng.uniform(-2.2, 2.2, n),
                             rng.uniform(0, 1.5, n)]))
    n = counts[11]  # three persons on the road
    k = rng.integers(0, 3, n)
    put(11, np.column_stack([np.array([-20.0, 0.0, 30.0])[k] + rng.normal(0, .2, n),
                             rng.normal(0, .2, n) + 2, rng.uniform(0, 1.8, n)]))
    xyz = np.concatenate(parts).astype(np.float32)
    labels = np.concatenate(labs)
    perm = rng.permutation(len(xyz))
    return xyz[perm], labels[perm]


def make_demo_workspace(ws: str | Path, n_points: int = 200_000, *, seed: int = 0,
                        with_lifting: bool = True, with_grid: bool = True,
                        voxel_size: float = 2.0) -> Scene:
    """Write a demo workspace to ``ws`` and return its :class:`Scene`."""
    ws = Path(ws)
    rng = np.random.default_rng(seed + 1)
    xyz, labels = demo_points(n_points, seed=seed)
    tax = default_taxonomy()
    shade = rng.uniform(0.55, 0.95, (len(xyz), 1))
    rgb = np.clip(tax.colour_lut()[labels] * shade + rng.normal(0, 12, (len(xyz), 3)), 0, 255)
    cam = Camera("PINHOLE", 800, 600, np.array([700.0, 700.0, 400.0, 300.0]))
    frames = []
    for i, (x, y) in enumerate([(x, y) for y in (-40, 0, 40) for x in (-40, 0, 40)]):
        T = look_at(np.array([x, y, 50.0]), np.array([x, y, 0.0]), up=np.array([0.0, 1.0, 0.0]))
        frames.append(Frame(name=f"img_{i:04d}.jpg", camera=cam, T_cam_world=T,
                            altitude=50.0, nominal_altitude=50))
    scene = Scene(frames=frames, xyz=xyz, rgb=rgb.astype(np.uint8), origin=np.array(UTM_ORIGIN),
                  taxonomy=tax)
    scene.save(ws)
    if with_lifting:
        conf = rng.uniform(0.3, 1.0, len(xyz)).astype(np.float32)
        origin = rng.choice(np.array([1, 2, 3], np.uint8), len(xyz), p=[0.5, 0.4, 0.1])
        Workspace(ws).write_labels(labels, conf, origin)
    if with_grid:
        lo = xyz.min(axis=0).astype(np.float64) - voxel_size
        shape = np.ceil((xyz.max(axis=0) - lo) / voxel_size).astype(int) + 2
        ijk = np.floor((xyz - lo) / voxel_size).astype(np.int64)
        grid = np.zeros(tuple(shape), np.uint8)
        grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = labels  # last writer wins; fine for a demo
        SceneGrid(grid, lo + np.asarray(UTM_ORIGIN), voxel_size).save(Workspace(ws).grid_path())
    return scene
