"""The OccuFly dataset layout (FORMATS.md section 3), as the official repository documents it
since 2026-08-03 (``calibration.txt`` at scene level).

::

    <root>/OccuFly_Dataset/splits/{train,val,test}.txt         scene ids, one per line
    <root>/OccuFly_Dataset/<scene_id>/calibration.txt           one camera for the whole scene
    <root>/OccuFly_Dataset/<scene_id>/manifest.json             taxonomy, provenance, frames
    <root>/OccuFly_Dataset/<scene_id>/<altitude>/
        ground_truth/<frame>/<frame>.label     uint8 raw ids, 0 empty, 255 invalid, C order
        ground_truth/<frame>/<frame>.invalid   np.packbits (MSB first) of the flat bool mask
        ground_truth/<frame>/<frame>.occluded
        ground_truth/<frame>/<frame>.surface
        preprocess/<frame>.pkl                 dict: frame_id, sequence, altitude, pose,
                                               1_1, 1_2, 1_4, 1_8, 1_16 (uint8, invalid 255)
        images/visual/<frame>.png
        depth_maps/<frame>.npy                 float32 metres, flattened (h*w,), h, w = H/4, W/4

``calibration.txt`` line layout (FORMATS.md leaves it open; this is ours)::

    # OccuFly calibration: one camera for every frame of this scene
    # fx fy cx cy width height: pixels of the FULL-resolution image, COLMAP convention (pixel centres at +0.5)
    # depth_maps: <h> <w>  (rows, columns of depth_maps/<frame>.npy = image / 4, flattened C order)
    <fx> <fy> <cx> <cy> <width> <height>

``numpy.loadtxt`` reads it as a (6,) array (the ``#`` lines are comments); the depth-map shape
line is parsed by :func:`read_calibration` and is also in the manifest (``depth_map_shape``
and per frame), so a depth map of any aspect ratio can be reshaped exactly.

**One camera per scene.** When the selected frames use more than one camera (model, size or
intrinsics differ), :func:`occufly.export.export_dataset` writes each camera's frames as its
own scene: the camera with the most frames keeps ``<scene_id>``, the others become
``<scene_id>_cam2``, ``<scene_id>_cam3``, ... in order of their first frame. So every
scene-level ``calibration.txt`` is right for every frame under it.

**Splits** (``splits/<split>.txt``) are rebuilt from every scene manifest in the root after
each export; a scene's split is the one given to the export, or by default the release's
rule on the scene number: ``scene_01``-``05`` train, ``06``-``07`` val, ``08``-``09`` test
(anything else: train).

``pose`` in the ``.pkl`` is the (4, 4) float32 camera-to-world transform in scene-local metres
(``x_local = pose @ [x_cam, 1]``); the scene's float64 origin is in the manifest.
Done markers live in ``<root>/.occufly_export/occufly/<scene_id>/done/``.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.export.common import STATE_DIR, majority_pyramid, pack_bits, pool_grid

NAME = "occufly"
POOL_FACTORS = (1, 2, 4, 8, 16)


def scene_dir(root: Path, scene_id: str) -> Path:
    return root / "OccuFly_Dataset" / scene_id


def manifest_path(root: Path, scene_id: str) -> Path:
    return scene_dir(root, scene_id) / "manifest.json"


def state_dir(root: Path, scene_id: str) -> Path:
    return root / STATE_DIR / NAME / scene_id


def calibration_path(root: Path, scene_id: str) -> Path:
    return scene_dir(root, scene_id) / "calibration.txt"


def is_export_root(root: Path) -> bool:
    """A folder that only holds OccuFly exports (and our state)."""
    names = {p.name for p in root.iterdir()}
    return names <= {"OccuFly_Dataset", STATE_DIR} and "OccuFly_Dataset" in names


def calibration_text(camera, depth_shape: tuple[int, int]) -> str:
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    h, w = depth_shape
    return (
        "# OccuFly calibration: one camera for every frame of this scene\n"
        "# fx fy cx cy width height: pixels of the FULL-resolution image, COLMAP convention "
        "(pixel centres at +0.5)\n"
        f"# depth_maps: {h} {w}  (rows, columns of depth_maps/<frame>.npy = image / 4, flattened C order)\n"
        f"{fx!r} {fy!r} {cx!r} {cy!r} {camera.width} {camera.height}\n"
    )


def read_calibration(path: Path) -> dict:
    """{"fx", "fy", "cx", "cy", "width", "height", "depth_shape": (h, w) or None} of a
    ``calibration.txt`` (ours, or one holding just the six numbers)."""
    try:
        text = Path(path).read_text()
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read calibration ({e.strerror})") from None
    depth_shape = None
    values: list[float] = []
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("#"):
            parts = s[1:].split()
            if len(parts) >= 3 and parts[0] == "depth_maps:":
                try:
                    depth_shape = (int(parts[1]), int(parts[2]))
                except ValueError:
                    raise InputFormatError(f"{path}: depth_maps line must hold two integers: {s!r}") from None
            continue
        if s:
            try:
                values.extend(float(v) for v in s.split())
            except ValueError:
                raise InputFormatError(f"{path}: expected numbers, got {s!r}") from None
    if len(values) != 6:
        raise InputFormatError(f"{path}: expected 6 numbers (fx fy cx cy width height), got {len(values)}")
    fx, fy, cx, cy, w, h = values
    if not (w >= 1 and h >= 1 and w == int(w) and h == int(h) and fx > 0 and fy > 0):
        raise InputFormatError(f"{path}: width/height must be positive integers and fx, fy > 0")
    if depth_shape is not None and min(depth_shape) < 1:
        raise InputFormatError(f"{path}: depth_maps shape must be positive, got {depth_shape}")
    return {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": int(w), "height": int(h),
            "depth_shape": depth_shape}


def static_files(root: Path, scene_id: str, camera, depth_shape: tuple[int, int], **_) -> dict[Path, bytes]:
    return {calibration_path(root, scene_id): calibration_text(camera, depth_shape).encode()}


def frame_files(
    root: Path, scene_id: str, altitude: int, frame_id: str, gt, pose: np.ndarray,
    image_png: bytes, depth: np.ndarray, priority_lut: np.ndarray, *,
    downsample_rule: str = "occufly", **_,
) -> dict[Path, bytes]:
    """All files of one frame. gt: :class:`occufly.sampling.FrameGT`; pose: (4, 4) float32
    camera-to-world, scene-local; depth: (h, w) float32."""
    base = scene_dir(root, scene_id) / str(altitude)
    gtd = base / "ground_truth" / frame_id
    label = gt.label_with_invalid()
    pkl = {
        "frame_id": frame_id,
        "sequence": scene_id,
        "altitude": int(altitude),
        "pose": np.asarray(pose, dtype=np.float32),
    }
    if downsample_rule == "occufly":
        for f, grid in majority_pyramid(label, POOL_FACTORS, priority_lut).items():
            pkl[f"1_{f}"] = grid
    else:
        for f in POOL_FACTORS:
            pkl[f"1_{f}"] = pool_grid(label, f, priority_lut, downsample_rule)
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth, dtype=np.float32).reshape(-1), allow_pickle=False)
    return {
        gtd / f"{frame_id}.label": np.ascontiguousarray(label, dtype=np.uint8).tobytes(),
        gtd / f"{frame_id}.invalid": pack_bits(gt.invalid),
        gtd / f"{frame_id}.occluded": pack_bits(gt.occluded),
        gtd / f"{frame_id}.surface": pack_bits(gt.surface),
        base / "preprocess" / f"{frame_id}.pkl": pickle.dumps(pkl, protocol=4),
        base / "images" / "visual" / f"{frame_id}.png": image_png,
        base / "depth_maps" / f"{frame_id}.npy": buf.getvalue(),
    }


def marker(root: Path, scene_id: str, altitude: int, frame_id: str) -> Path:
    return state_dir(root, scene_id) / "done" / f"{altitude}_{frame_id}.json"


def split_files(root: Path, splits: dict[str, list[str]]) -> dict[Path, bytes]:
    """``splits/<split>.txt`` from {split: [scene ids]} (all three files, maybe empty)."""
    d = root / "OccuFly_Dataset" / "splits"
    return {d / f"{name}.txt": "".join(f"{s}\n" for s in sorted(splits.get(name, ()))).encode()
            for name in ("train", "val", "test")}


def read_splits(root: Path) -> dict[str, list[str]]:
    d = Path(root) / "OccuFly_Dataset" / "splits"
    out = {}
    for name in ("train", "val", "test"):
        p = d / f"{name}.txt"
        out[name] = [ln.strip() for ln in p.read_text().splitlines() if ln.strip()] if p.is_file() else []
    return out


# ---- reading back (used by metrics and preview) ------------------------------------------------
def list_frames(root: Path, scene_id: str | None = None) -> list[tuple[str, int, str]]:
    """[(scene_id, altitude, frame_id)] of every frame with a .label file, sorted."""
    ds = root / "OccuFly_Dataset"
    out = []
    scenes = [ds / scene_id] if scene_id else sorted(p for p in ds.glob("*") if p.is_dir())
    for sd in scenes:
        for alt_dir in sorted(p for p in sd.glob("*") if p.is_dir() and p.name.isdigit()):
            for lab in sorted(alt_dir.glob("ground_truth/*/*.label")):
                out.append((sd.name, int(alt_dir.name), lab.stem))
    return out


def read_frame(root: Path, scene_id: str, altitude: int, frame_id: str,
               shape: tuple[int, int, int] = (192, 128, 128)) -> dict[str, np.ndarray]:
    """label (X, Y, Z) uint8 and invalid / occluded / surface (X, Y, Z) bool, read following
    FORMATS.md section 3 literally."""
    gtd = scene_dir(root, scene_id) / str(altitude) / "ground_truth" / frame_id
    n = int(np.prod(shape))
    out = {"label": np.fromfile(gtd / f"{frame_id}.label", dtype=np.uint8)}
    if out["label"].size != n:
        from occufly.errors import InputFormatError

        raise InputFormatError(
            f"{gtd / (frame_id + '.label')}: {out['label'].size} values, expected {n} for grid {shape}"
        )
    out["label"] = out["label"].reshape(shape)
    for m in ("invalid", "occluded", "surface"):
        p = gtd / f"{frame_id}.{m}"
        if p.is_file():
            out[m] = np.unpackbits(np.fromfile(p, dtype=np.uint8))[:n].reshape(shape).astype(bool)
    return out
