"""PNG preview of a scene grid: top-down and oblique renders coloured by class, with a legend.

- Top-down: for each (x, y) column the highest occupied voxel, coloured by its class and
  shaded by its height (x to the right, y up).
- Oblique: an orthographic view from azimuth ``azimuth_deg`` and elevation ``elevation_deg``;
  surface voxels (at least one empty 6-neighbour) are splatted as squares, nearest wins
  (depth-sorted z-buffer), lit by the face of the voxel that points most toward the viewer.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from occufly.fsutil import atomic_write_bytes
from occufly.grid import SceneGrid
from occufly.taxonomy import Taxonomy


def surface_mask(labels: np.ndarray) -> np.ndarray:
    """(X, Y, Z) bool: occupied voxels with at least one empty (or out-of-grid) 6-neighbour."""
    occ = labels != 0
    pad = np.pad(occ, 1, constant_values=False)
    inner = np.ones_like(occ)
    for ax in range(3):
        for s in (-1, 1):
            inner &= np.roll(pad, s, axis=ax)[1:-1, 1:-1, 1:-1]
    return occ & ~inner


def top_down(labels: np.ndarray, lut: np.ndarray) -> np.ndarray:
    """(Y, X, 3) uint8 image of the highest occupied voxel per column (north up)."""
    occ = labels != 0
    z = labels.shape[2]
    any_occ = occ.any(axis=2)
    top = z - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    lab = np.take_along_axis(labels, top[:, :, None], axis=2)[:, :, 0]
    shade = 0.45 + 0.55 * (top + 1) / z
    rgb = lut[lab].astype(np.float32) * shade[:, :, None]
    rgb[~any_occ] = 255
    return np.clip(rgb, 0, 255).astype(np.uint8).transpose(1, 0, 2)[::-1]


def oblique(
    labels: np.ndarray, lut: np.ndarray, *, azimuth_deg: float = 35.0, elevation_deg: float = 35.0,
    max_side: int = 1000,
) -> np.ndarray:
    """(H, W, 3) uint8 orthographic oblique render of the surface voxels."""
    ijk = np.argwhere(surface_mask(labels)).astype(np.float64)
    if len(ijk) == 0:
        return np.full((64, 64, 3), 255, np.uint8)
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    # viewing direction (into the scene): from the south-west and above
    view = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), -np.sin(el)])
    right = np.cross(view, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, view)
    c = ijk + 0.5
    u = c @ right
    v = -(c @ up)
    depth = c @ view
    scale = max_side / max(u.max() - u.min() + 2, v.max() - v.min() + 2)
    scale = max(1.0, min(scale, 12.0))
    px = ((u - u.min() + 1) * scale).astype(np.int64)
    py = ((v - v.min() + 1) * scale).astype(np.int64)
    w = int(px.max() + scale + 2)
    h = int(py.max() + scale + 2)
    lab = labels[ijk[:, 0].astype(int), ijk[:, 1].astype(int), ijk[:, 2].astype(int)]
    # shading: which neighbours are empty decides the visible face (top brightest)
    occ = np.pad(labels != 0, 1)
    ii, jj, kk = (ijk.astype(int) + 1).T
    top_free = ~occ[ii, jj, kk + 1]
    shade = np.where(top_free, 1.0, 0.72)
    shade = shade * (0.7 + 0.3 * (ijk[:, 2] + 1) / labels.shape[2])
    col = np.clip(lut[lab].astype(np.float32) * shade[:, None], 0, 255).astype(np.uint8)
    s = int(np.ceil(scale))
    dx, dy = np.meshgrid(np.arange(s), np.arange(s))
    dx, dy = dx.ravel(), dy.ravel()
    qx = (px[:, None] + dx[None, :]).ravel()
    qy = (py[:, None] + dy[None, :]).ravel()
    qd = np.repeat(depth, len(dx))
    qc = np.repeat(np.arange(len(ijk)), len(dx))
    key = qy * w + qx
    order = np.lexsort((qd, key))  # per pixel nearest first
    key, qc = key[order], qc[order]
    first = np.ones(len(key), bool)
    first[1:] = key[1:] != key[:-1]
    img = np.full((h * w, 3), 255, np.uint8)
    img[key[first]] = col[qc[first]]
    return img.reshape(h, w, 3)


def render_preview(grid: SceneGrid, taxonomy: Taxonomy, *, max_side: int = 900) -> bytes:
    """PNG bytes: top-down | oblique side by side with a legend of the classes present."""
    lut = taxonomy.colour_lut()
    td = top_down(grid.labels, lut)
    f = max(1, int(max_side // max(td.shape[:2])))
    td_img = Image.fromarray(td).resize((td.shape[1] * f, td.shape[0] * f), Image.NEAREST)
    if max(td_img.size) > max_side:
        r = max_side / max(td_img.size)
        td_img = td_img.resize((max(1, int(td_img.size[0] * r)), max(1, int(td_img.size[1] * r))), Image.NEAREST)
    ob_img = Image.fromarray(oblique(grid.labels, lut, max_side=max_side))
    if max(ob_img.size) > max_side:
        r = max_side / max(ob_img.size)
        ob_img = ob_img.resize((max(1, int(ob_img.size[0] * r)), max(1, int(ob_img.size[1] * r))), Image.LANCZOS)
    counts = grid.class_counts()
    present = [c for c in taxonomy.classes if counts.get(c.id, 0) > 0]
    legend_h = 24 + 18 * ((len(present) + 3) // 4)
    W = td_img.size[0] + ob_img.size[0] + 30
    H = max(td_img.size[1], ob_img.size[1]) + legend_h + 30
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    canvas.paste(td_img, (10, 25))
    canvas.paste(ob_img, (td_img.size[0] + 20, 25))
    d = ImageDraw.Draw(canvas)
    d.text((10, 6), f"top-down (north up), {grid.shape} voxels @ {grid.voxel_size} m", fill=(0, 0, 0))
    d.text((td_img.size[0] + 20, 6), "oblique", fill=(0, 0, 0))
    y0 = max(td_img.size[1], ob_img.size[1]) + 35
    for i, c in enumerate(present):
        x = 10 + (i % 4) * 220
        y = y0 + (i // 4) * 18
        d.rectangle([x, y, x + 12, y + 12], fill=tuple(c.rgb), outline=(0, 0, 0))
        d.text((x + 18, y), f"{c.id} {c.name}: {counts[c.id]}", fill=(0, 0, 0))
    buf = io.BytesIO()
    canvas.save(buf, format="PNG")
    return buf.getvalue()


def save_preview(grid: SceneGrid, taxonomy: Taxonomy, path: str | Path, **kw) -> Path:
    path = Path(path)
    atomic_write_bytes(path, render_preview(grid, taxonomy, **kw))
    return path
