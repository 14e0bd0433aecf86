"""Small scene workspaces with an exact scene grid for the export / metrics tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from occufly.camera import Camera, look_at
from occufly.grid import SceneGrid
from occufly.sampling import FrameGridSpec
from occufly.scene import Frame, Scene

SPEC = FrameGridSpec(shape=(64, 48, 64), voxel_size=1.0, near=1.0)
ORIGIN = np.array([500_000.0, 4_000_000.0, 100.0])  # UTM-sized scene origin


def make_grid() -> SceneGrid:
    """Ground (grass, 6) at local z in [-1, 0), a building (16) and a tree (8), 1 m voxels."""
    lab = np.zeros((120, 120, 30), np.uint8)
    lab[:, :, 0] = 6
    lab[40:60, 50:70, 1:15] = 16
    lab[80:84, 30:34, 1:8] = 8
    return SceneGrid(lab, ORIGIN + np.array([-60.0, -60.0, -1.0]), 1.0)


def make_workspace(root: Path, n_frames: int = 4, *, image_ext: str = ".png") -> Path:
    root.mkdir(parents=True, exist_ok=True)
    cam = Camera("PINHOLE", 64, 48, [40.0, 40.0, 32.0, 24.0])
    frames = []
    rng = np.random.default_rng(0)
    for i in range(n_frames):
        alt = 50 if i % 2 == 0 else 30
        c = np.array([-10.0 + 7 * i, 3.0 - 2 * i, float(alt)])
        T = look_at(c, c * [1, 1, 0] + [0.5, 0.3, 0], up=(0.0, 1.0, 0.0))
        img = root / "images" / f"img_{i:03d}{image_ext}"
        img.parent.mkdir(exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)).save(img)
        frames.append(Frame(name=img.name, camera=cam, T_cam_world=T, image_path=str(img),
                            altitude=float(alt), nominal_altitude=alt))
    g = make_grid()
    pts = g.centers() - ORIGIN
    scene = Scene(frames=frames, xyz=pts.astype(np.float32),
                  rgb=np.zeros((len(pts), 3), np.uint8), origin=ORIGIN)
    ws = root / "ws"
    scene.save(ws)
    g.save(ws / "grid" / "scene_grid.npz")
    return ws
