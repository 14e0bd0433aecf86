"""SSCBench-style layout (FORMATS.md section 4), readable by MonoScene / Symphonies / CGFormer
style loaders.

::

    <root>/occufly.yaml                                  learning_map (raw -> training id),
                                                         learning_map_inv, labels, color_map
    <root>/data_2d_raw/<seq>/image_00/data_rect/<frame>.png
    <root>/data_2d_raw/<seq>/voxels/<frame>.bin          packbits(occupied & valid & ~occluded)
    <root>/data_2d_raw/<seq>/voxels/<frame>.label        uint16 raw ids (255 where invalid)
    <root>/data_2d_raw/<seq>/voxels/<frame>.invalid      packbits, MSB first
    <root>/data_2d_raw/<seq>/voxels/<frame>.occluded     packbits, MSB first
    <root>/preprocess/labels/<seq>/<frame>_1_1.npy       uint8 training ids, 255 = ignore
    <root>/preprocess/labels/<seq>/<frame>_1_8.npy       8x majority-pooled, same ids
    <root>/depth/<seq>/<frame>.npy                       (h, w) float32 metres, 1/4 resolution
    <root>/manifests/<scene_id>.json

``<seq>`` is ``<scene_id>_<altitude>`` (e.g. ``scene_01_50``). ``.bin`` plays the role of
SemanticKITTI's voxelised input scan: the occupied voxels a sensor at the camera would see.
Training ids: 0 = empty, 1..C in taxonomy table order, 255 = ignore (invalid).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import yaml

from occufly.export.common import STATE_DIR, majority_pool, pack_bits

NAME = "sscbench"


def seq_name(scene_id: str, altitude: int) -> str:
    return f"{scene_id}_{int(altitude)}"


def manifest_path(root: Path, scene_id: str) -> Path:
    return root / "manifests" / f"{scene_id}.json"


def scene_dir(root: Path, scene_id: str) -> Path:
    return root / "manifests"


def state_dir(root: Path, scene_id: str) -> Path:
    return root / STATE_DIR / NAME / scene_id


def is_export_root(root: Path) -> bool:
    names = {p.name for p in root.iterdir()}
    return "manifests" in names and names <= {
        "occufly.yaml", "data_2d_raw", "preprocess", "depth", "manifests", STATE_DIR}


def learning_map_yaml(taxonomy) -> str:
    lm = taxonomy.learning_map()
    inv = {v: k for k, v in lm.items() if v != 255}
    doc = {
        "labels": {0: "empty", 255: "invalid", **{c.id: c.name for c in taxonomy.classes}},
        "color_map": {0: [0, 0, 0], **{c.id: list(c.rgb) for c in taxonomy.classes}},
        "learning_map": {int(k): int(v) for k, v in sorted(lm.items())},
        "learning_map_inv": {int(k): int(v) for k, v in sorted(inv.items())},
        "learning_ignore": {int(v): (v == 0) for v in sorted(set(lm.values())) if v != 255},
    }
    return "# OccuFly taxonomy for SSCBench-style loaders (raw id -> training id)\n" + yaml.safe_dump(
        doc, sort_keys=False)


def learning_lut(taxonomy) -> np.ndarray:
    """(256,) uint8 raw id -> training id; unknown ids -> 255."""
    lut = np.full(256, 255, dtype=np.uint8)
    for k, v in taxonomy.learning_map().items():
        lut[k] = v
    return lut


def static_files(root: Path, scene_id: str, altitude_cameras: dict, taxonomy) -> dict[Path, bytes]:
    return {root / "occufly.yaml": learning_map_yaml(taxonomy).encode()}


def frame_files(
    root: Path, scene_id: str, altitude: int, frame_id: str, gt, pose: np.ndarray,
    image_png: bytes, depth: np.ndarray, priority_lut: np.ndarray, taxonomy=None,
) -> dict[Path, bytes]:
    seq = seq_name(scene_id, altitude)
    vox = root / "data_2d_raw" / seq / "voxels"
    raw = gt.label_with_invalid()
    lut = learning_lut(taxonomy)
    train = lut[raw]
    # 8x pooling on raw ids (tie order follows the taxonomy), then mapped to training ids
    train8 = lut[majority_pool(raw, 8, priority_lut)]
    visible = (gt.labels != 0) & ~gt.invalid & ~gt.occluded

    def npy(a: np.ndarray) -> bytes:
        buf = io.BytesIO()
        np.save(buf, a, allow_pickle=False)
        return buf.getvalue()

    lab = root / "preprocess" / "labels" / seq
    return {
        vox / f"{frame_id}.bin": pack_bits(visible),
        vox / f"{frame_id}.label": np.ascontiguousarray(raw, dtype="<u2").tobytes(),
        vox / f"{frame_id}.invalid": pack_bits(gt.invalid),
        vox / f"{frame_id}.occluded": pack_bits(gt.occluded),
        lab / f"{frame_id}_1_1.npy": npy(train),
        lab / f"{frame_id}_1_8.npy": npy(train8),
        root / "data_2d_raw" / seq / "image_00" / "data_rect" / f"{frame_id}.png": image_png,
        root / "depth" / seq / f"{frame_id}.npy": npy(np.ascontiguousarray(depth, dtype=np.float32)),
    }


def marker(root: Path, scene_id: str, altitude: int, frame_id: str) -> Path:
    return state_dir(root, scene_id) / "done" / f"{altitude}_{frame_id}.json"
