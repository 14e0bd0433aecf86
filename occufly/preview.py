"""PNG preview of one exported frame (OccuFly layout).

Panels: ``image`` (the frame's PNG), ``depth`` (1/4-resolution depth map, turbo-like
colour ramp, black = no depth), ``grid`` (two projections of the camera-centric voxel grid
coloured by class: *view* = the first occupied valid voxel along +z per (i, j) column, i.e.
what the camera sees, drawn with x right / y down like the image; *side* = the first occupied
valid voxel looking along +y per (i, k), depth increasing downwards) and the three masks
side by side (per (i, j) column, grey levels, same orientation as the view panel: share of
invalid voxels; nearness of the first surface voxel; number of occluded voxels).
``panels`` picks any subset in any order.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from occufly.errors import InputFormatError
from occufly.export.occufly import read_calibration
from occufly.fsutil import atomic_write_bytes
from occufly.taxonomy import Taxonomy, default_taxonomy

PANELS = ("image", "depth", "grid", "masks")


def find_frame(root: Path, frame: str) -> tuple[Path, str]:
    fid = f"{int(frame):06d}" if frame.isdigit() else frame
    hits = sorted((root / "OccuFly_Dataset").glob(f"*/*/ground_truth/{fid}/{fid}.label"))
    if not hits:
        raise InputFormatError(f"{root}: frame {fid} not found (expected OccuFly_Dataset/<scene>/<alt>/ground_truth/{fid}/)")
    return hits[0].parents[2], fid


def _first_hit(occ: np.ndarray, labels: np.ndarray, axis: int) -> np.ndarray:
    """Label of the first True along ``axis`` (0 where none)."""
    idx = np.argmax(occ, axis=axis)
    lab = np.take_along_axis(labels, np.expand_dims(idx, axis), axis=axis).squeeze(axis)
    return np.where(occ.any(axis=axis), lab, 0)


def depth_colour(depth: np.ndarray) -> np.ndarray:
    """(h, w) metres -> (h, w, 3) uint8, near = red/yellow, far = blue, 0 = black."""
    d = np.asarray(depth, dtype=np.float64)
    m = d > 0
    out = np.zeros((*d.shape, 3), np.uint8)
    if m.any():
        lo, hi = np.percentile(d[m], [2, 98])
        t = np.clip((d - lo) / max(hi - lo, 1e-6), 0, 1)
        rgb = np.stack([1.0 - t, 1.0 - np.abs(2 * t - 1), t], axis=-1)
        out[m] = (255 * rgb[m]).astype(np.uint8)
    return out


def _fit(img: Image.Image, height: int) -> Image.Image:
    w = max(1, round(img.width * height / img.height))
    return img.resize((w, height), Image.NEAREST)


def _depth_shape(alt_dir: Path, fid: str) -> tuple[int, int] | None:
    """(h, w) of a frame's flattened depth map: the manifest's per-frame record, else the
    scene-level calibration.txt (or a per-altitude one of export format 1)."""
    manifest = alt_dir.parent / "manifest.json"
    if manifest.is_file():
        fr = json.loads(manifest.read_text()).get("frames", {}).get(fid, {})
        if "depth_shape" in fr:
            return int(fr["depth_shape"][0]), int(fr["depth_shape"][1])
    for cp in (alt_dir.parent / "calibration.txt", alt_dir / "calibration.txt"):
        if cp.is_file():
            cal = read_calibration(cp)
            if cal["depth_shape"] is not None:
                return cal["depth_shape"]
            return max(1, round(cal["height"] / 4)), max(1, round(cal["width"] / 4))
    return None


def render_preview(export_root: str | Path, frame: str, *, panels: tuple[str, ...] = PANELS,
                   height: int = 256) -> Image.Image:
    root = Path(export_root)
    alt_dir, fid = find_frame(root, str(frame))
    manifest = alt_dir.parent / "manifest.json"
    tax: Taxonomy = default_taxonomy()
    shape = (192, 128, 128)
    if manifest.is_file():
        m = json.loads(manifest.read_text())
        tax = Taxonomy.from_dict(m["taxonomy"], source=str(manifest))
        shape = tuple(m["grid_spec"]["shape"])
    lut = tax.colour_lut()
    lut[255] = (40, 40, 40)
    gtd = alt_dir / "ground_truth" / fid
    n = int(np.prod(shape))
    label = np.fromfile(gtd / f"{fid}.label", np.uint8)
    if label.size != n:
        raise InputFormatError(f"{gtd}/{fid}.label: {label.size} voxels, manifest grid is {shape}")
    label = label.reshape(shape)
    masks = {k: np.unpackbits(np.fromfile(gtd / f"{fid}.{k}", np.uint8))[:n].reshape(shape).astype(bool)
             for k in ("invalid", "surface", "occluded")}
    tiles: list[tuple[str, Image.Image]] = []
    for p in panels:
        if p not in PANELS:
            raise InputFormatError(f"unknown preview panel {p!r}; expected {', '.join(PANELS)}")
        if p == "image":
            ip = alt_dir / "images" / "visual" / f"{fid}.png"
            if ip.is_file():
                tiles.append(("image", _fit(Image.open(ip).convert("RGB"), height)))
        elif p == "depth":
            dp = alt_dir / "depth_maps" / f"{fid}.npy"
            dshape = _depth_shape(alt_dir, fid)
            if dp.is_file() and dshape is not None:
                d = np.load(dp)
                h, w = dshape
                if d.size == w * h:
                    tiles.append(("depth", _fit(Image.fromarray(depth_colour(d.reshape(h, w))), height)))
        elif p == "grid":
            occ = (label != 0) & (label != 255)
            view = lut[_first_hit(occ, label, axis=2)]  # (X, Y, 3)
            tiles.append(("grid: view", _fit(Image.fromarray(view.transpose(1, 0, 2).copy()), height)))
            side = lut[_first_hit(occ, label, axis=1)]  # (X, Z, 3)
            tiles.append(("grid: side", _fit(Image.fromarray(side.transpose(1, 0, 2).copy()), height)))
        else:
            Z = shape[2]
            for k in ("invalid", "surface", "occluded"):
                mk = masks[k]
                if k == "invalid":
                    v = mk.mean(axis=2)
                elif k == "surface":  # nearness of the first surface voxel (white = near)
                    v = np.where(mk.any(axis=2), 1.0 - np.argmax(mk, axis=2) / Z, 0.0)
                else:  # number of occluded voxels in the column
                    c = mk.sum(axis=2)
                    v = c / max(int(c.max()), 1)
                g = (255 * np.asarray(v, float)).astype(np.uint8).T
                tiles.append((k, _fit(Image.fromarray(g).convert("RGB"), height)))
    if not tiles:
        raise InputFormatError(f"{alt_dir}: nothing to preview for frame {fid}")
    pad, title = 6, 16
    W = sum(t.width for _, t in tiles) + pad * (len(tiles) + 1)
    canvas = Image.new("RGB", (W, height + title + 2 * pad), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    x = pad
    for name, t in tiles:
        canvas.paste(t, (x, title + pad))
        draw.text((x, 2), name, fill=(0, 0, 0))
        x += t.width + pad
    return canvas


def write_preview(export_root: str | Path, frame: str, out: str | Path, **kw) -> dict:
    img = render_preview(export_root, frame, **kw)
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(out, buf.getvalue())
    return {"out": str(out), "width": img.width, "height": img.height}
