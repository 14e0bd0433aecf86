"""The OccuFly dataset layout (FORMATS.md section 3).

::

    <root>/OccuFly_Dataset/<scene_id>/manifest.json           taxonomy, provenance, frames
    <root>/OccuFly_Dataset/<scene_id>/<altitude>/
        ground_truth/<frame>/<frame>.label     uint8 raw ids, 0 empty, 255 invalid, C order
        ground_truth/<frame>/<frame>.invalid   np.packbits (MSB first) of the flat bool mask
        ground_truth/<frame>/<frame>.occluded
        ground_truth/<frame>/<frame>.surface
        preprocess/<frame>.pkl                 dict: frame_id, sequence, altitude, pose,
                                               1_1, 1_2, 1_4, 1_8, 1_16 (uint8, invalid 255)
        images/visual/<frame>.png
        depth_maps/<frame>.npy                 float32, flattened (h*w,), h, w = H/4, W/4
        calibration.txt

``calibration.txt`` line layout (our choice, FORMATS.md leaves it open): a ``#`` comment line
naming the columns, then one line ``fx fy cx cy width height`` in pixels of the full-resolution
image (COLMAP pixel convention: pixel centres at +0.5). ``numpy.loadtxt`` reads it as a (6,)
array. When frames of one altitude have different intrinsics, the manifest lists each frame's
camera (the file holds the first frame's).

``pose`` in the ``.pkl`` is the (4, 4) float32 camera-to-world transform in scene-local metres
(``x_local = pose @ [x_cam, 1]``); the scene's float64 origin is in the manifest.
Done markers live in ``<root>/.occufly_export/occufly/<scene_id>/done/``.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np

from occufly.export.common import STATE_DIR, majority_pyramid, pack_bits

NAME = "occufly"
POOL_FACTORS = (1, 2, 4, 8, 16)


def scene_dir(root: Path, scene_id: str) -> Path:
    return root / "OccuFly_Dataset" / scene_id


def manifest_path(root: Path, scene_id: str) -> Path:
    return scene_dir(root, scene_id) / "manifest.json"


def state_dir(root: Path, scene_id: str) -> Path:
    return root / STATE_DIR / NAME / scene_id


def is_export_root(root: Path) -> bool:
    """A folder that only holds OccuFly exports (and our state)."""
    names = {p.name for p in root.iterdir()}
    return names <= {"OccuFly_Dataset", STATE_DIR} and "OccuFly_Dataset" in names


def calibration_text(camera) -> str:
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    return (
        "# fx fy cx cy width height  (pixels, full image resolution)\n"
        f"{fx!r} {fy!r} {cx!r} {cy!r} {camera.width} {camera.height}\n"
    )


def static_files(root: Path, scene_id: str, altitude_cameras: dict[int, object], taxonomy) -> dict[Path, bytes]:
    d = scene_dir(root, scene_id)
    return {d / str(alt) / "calibration.txt": calibration_text(cam).encode()
            for alt, cam in altitude_cameras.items()}


def frame_files(
    root: Path, scene_id: str, altitude: int, frame_id: str, gt, pose: np.ndarray,
    image_png: bytes, depth: np.ndarray, priority_lut: np.ndarray,
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
    for f, grid in majority_pyramid(label, POOL_FACTORS, priority_lut).items():
        pkl[f"1_{f}"] = grid
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
