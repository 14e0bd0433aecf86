"""Build small reconstructions on disk, in COLMAP's own file formats, for importer tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from occufly.camera import Camera, look_at, project_world, rotation_to_quaternion
from occufly.io.colmap_dense import write_depth_map, write_fused_ply, write_fused_vis

UTM = np.array([512345.0, 5401234.0, 250.0])


def ground_points(n_side: int = 60, size: float = 40.0) -> np.ndarray:
    """(N, 3) float64 local points: a flat ground grid plus a 6 m high box (a 'building')."""
    g = np.linspace(-size / 2, size / 2, n_side)
    xx, yy = np.meshgrid(g, g)
    ground = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    inside = (np.abs(ground[:, 0]) < 5) & (np.abs(ground[:, 1]) < 5)
    ground = ground[~inside]
    b = np.linspace(-5, 5, 15)
    bx, by = np.meshgrid(b, b)
    roof = np.column_stack([bx.ravel(), by.ravel(), np.full(bx.size, 6.0)])
    return np.vstack([ground, roof])


def make_reconstruction(
    root: Path, *, georef: bool = True, text: bool = True, depth_maps: bool = True,
    vis: bool = False, n_cams: int = 3,
) -> dict:
    """Write images/, sparse/ (text or binary), dense/fused.ply [+ .vis], depth maps."""
    import pycolmap

    root.mkdir(parents=True, exist_ok=True)
    offset = UTM if georef else np.zeros(3)
    xyz_local = ground_points()
    xyz = xyz_local + offset
    cam = Camera("PINHOLE", 96, 64, [80.0, 80.0, 48.0, 32.0])
    poses = []
    xs = np.linspace(-6, 6, n_cams)
    for i, x in enumerate(xs):
        c = np.array([x, 0.0, 30.0 + 10.0 * (i % 2)])
        poses.append(look_at(c + offset, np.array([x, 0.0, 0.0]) + offset, up=[0.0, 1.0, 0.0]))
    (root / "images").mkdir(exist_ok=True)
    names = [f"img_{i:03d}.png" for i in range(n_cams)]
    for n in names:
        Image.fromarray(np.full((cam.height, cam.width, 3), 90, np.uint8)).save(root / "images" / n)
    # true visibility by z-buffer (roof occludes ground)
    depth_list, seen = [], []
    for T in poses:
        uv, z, ok = project_world(cam, T, xyz)
        dm = np.zeros((cam.height, cam.width), np.float32)
        idx = np.flatnonzero(ok)
        r = uv[idx, 1].astype(int)
        c = uv[idx, 0].astype(int)
        zb = np.full(dm.size, np.inf)
        np.minimum.at(zb, r * cam.width + c, z[idx])
        # dense depth: the analytic surface (ground 0, roof 6) along each pixel ray
        rays = cam.pixel_rays()
        R, t = T[:3, :3], T[:3, 3]
        centre = -R.T @ t
        d_world = rays @ R  # camera -> world directions (scaled so camera z = 1)
        t_ground = (offset[2] - centre[2]) / d_world[:, 2]
        t_roof = (offset[2] + 6.0 - centre[2]) / d_world[:, 2]
        hit_r = centre + t_roof[:, None] * d_world
        on_roof = (np.abs(hit_r[:, 0] - offset[0]) < 5.2) & (np.abs(hit_r[:, 1] - offset[1]) < 5.2)
        dm = np.where(on_roof, t_roof, t_ground).reshape(cam.height, cam.width).astype(np.float32)
        depth_list.append(dm)
        s = np.zeros(len(xyz), bool)
        s[idx] = np.abs(z[idx] - dm[r, c]) < 0.02 * dm[r, c]
        seen.append(s)
    sparse = root / "sparse"
    sparse.mkdir(exist_ok=True)
    _write_text_model(sparse, cam, names, poses, xyz[::50])
    if not text:
        rec = pycolmap.Reconstruction(str(sparse))
        for f in ("cameras.txt", "images.txt", "points3D.txt"):
            (sparse / f).unlink()
        rec.write_binary(str(sparse))
    dense = root / "dense"
    dense.mkdir(exist_ok=True)
    rgb = np.full((len(xyz), 3), 100, np.uint8)
    write_fused_ply(dense / "fused.ply", xyz, None, rgb, double=True)
    if vis:
        lists = [np.flatnonzero([s[p] for s in seen]) for p in range(len(xyz))]
        offsets = np.r_[0, np.cumsum([len(v) for v in lists])]
        write_fused_vis(dense / "fused.ply.vis", offsets, np.concatenate(lists))
    if depth_maps:
        dd = dense / "stereo" / "depth_maps"
        dd.mkdir(parents=True, exist_ok=True)
        for n, dm in zip(names, depth_list, strict=True):
            write_depth_map(dd / f"{n}.geometric.bin", dm)
    return {"names": names, "poses": poses, "camera": cam, "xyz": xyz, "seen": np.array(seen),
            "offset": offset}


def _write_text_model(sparse: Path, cam: Camera, names, poses, pts) -> None:
    (sparse / "cameras.txt").write_text(
        f"# Camera list\n1 PINHOLE {cam.width} {cam.height} {_fmt(cam.params)}\n"
    )
    lines = ["# Image list"]
    tracks: dict[int, list[tuple[int, int]]] = {}
    for i, (n, T) in enumerate(zip(names, poses, strict=True)):
        q = rotation_to_quaternion(T[:3, :3])
        t = T[:3, 3]
        lines.append(f"{i + 1} {_fmt(q)} {_fmt(t)} 1 {n}")
        uv, z, ok = project_world(cam, T, pts)
        obs = []
        for j in np.flatnonzero(ok):
            tracks.setdefault(j + 1, []).append((i + 1, len(obs)))
            obs.append(f"{_fmt(uv[j])} {j + 1}")
        lines.append(" ".join(obs))
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    plines = ["# 3D point list"]
    for pid, tr in tracks.items():
        x = pts[pid - 1]
        plines.append(f"{pid} {_fmt(x)} 100 100 100 0.5 " + " ".join(f"{a} {b}" for a, b in tr))
    (sparse / "points3D.txt").write_text("\n".join(plines) + "\n")


def _fmt(values) -> str:
    return " ".join(repr(float(v)) for v in values)
