"""SSCBench-style layout (FORMATS.md section 4) that MonoScene / SSCBench's MonoScene,
Symphonies and CGFormer read through the adapters of :mod:`occufly.datasets.compat`
(docs/ssc-porting.md).

::

    <root>/occufly.yaml                                   learning_map (raw -> training id),
                                                          learning_map_inv, learning_ignore,
                                                          labels, color_map, geometry
    <root>/splits/{train,val,test}.txt                    sequence names, one per line
    <root>/splits/{train,val,test}_frames.txt             ``<seq> <frame>`` lines (--split-by
                                                          region / ratio only)
    <root>/data_2d_raw/<seq>/calib.txt                    KITTI-style P0..P3 and Tr (see below)
    <root>/data_2d_raw/<seq>/image_00/data_rect/<frame>.png
    <root>/data_2d_raw/<seq>/voxels/<frame>.bin           packbits(occupied & valid & ~occluded)
    <root>/data_2d_raw/<seq>/voxels/<frame>.label         uint16 raw ids (255 where invalid)
    <root>/data_2d_raw/<seq>/voxels/<frame>.invalid       packbits, MSB first
    <root>/data_2d_raw/<seq>/voxels/<frame>.occluded      packbits, MSB first
    <root>/data_2d_raw/<seq>/velodyne_points/data/<frame>.bin   float32 (N, 4), optional
    <root>/dataset/sequences/<seq>/calib.txt              the same calib (SemanticKITTI place)
    <root>/dataset/sequences/<seq>/image_2  -> ../../../data_2d_raw/<seq>/image_00/data_rect
    <root>/dataset/sequences/<seq>/voxels   -> ../../../data_2d_raw/<seq>/voxels
    <root>/preprocess/labels/<seq>/<frame>_1_1.npy        uint8 training ids, 255 = ignore
    <root>/preprocess/labels/<seq>/<frame>_1_8.npy        8x downsampled (--downsample-rule)
    <root>/depth/<seq>/<frame>.npy                        (h, w) float32 metres, 1/4 resolution
    <root>/depth_full/<seq>/<frame>.npy                   (H, W) float32 metres, full resolution
    <root>/depth_full/sequences/<seq> -> ../<seq>         (CGFormer's <depth_root>/sequences/)
    <root>/manifests/<scene_id>.json

``<seq>`` is ``<scene_id>_<altitude>`` (e.g. ``scene_01_50``). ``.bin`` plays the role of
SemanticKITTI's voxelised input scan: the occupied voxels a sensor at the camera would see.
Training ids: 0 = empty, 1..C in taxonomy table order, 255 = ignore (invalid).

``calib.txt``: lines ``P0:`` .. ``P3:`` hold the 12 values of K[I|0] (row-major 3 x 4) and
``Tr:`` the identity 3 x 4 (the frame grid is camera-centric, so "velodyne" = camera frame).
K uses the integer-pixel-centre convention of those loaders' ``vox2pix`` (which rounds the
projection to a pixel index): ``cx = cx_colmap - 0.5``, ``cy = cy_colmap - 0.5``. No comment
lines (their parser splits every line at ``:``).

The ``geometry`` block of ``occufly.yaml``: ``voxel_origin`` (camera-frame metres of voxel
(0, 0, 0)'s corner: (-X/2 r, -Y/2 r, 0)), ``voxel_size``, ``scene_size``, ``grid_shape``,
``image_width`` / ``image_height`` (null when sequences differ; per sequence in
``sequences``), ``n_classes`` (C + 1, empty included), ``class_names``,
``class_voxel_counts`` (per training id over the train split's ``_1_1`` voxels, ignore
excluded; over every frame when there is no train frame) and ``class_voxel_counts_all``.

Velodyne-like points (``velodyne=True``): the fused MVS points the frame sees (its visibility
list, else every point projecting into the image in front of it), in the camera frame,
4th column = grey value of the point colour in [0, 1].
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import numpy as np
import yaml

from occufly.errors import InputFormatError
from occufly.export.common import STATE_DIR, ExportError, pack_bits, pool_grid

NAME = "sscbench"
SPLITS = ("train", "val", "test")


def seq_name(scene_id: str, altitude: int) -> str:
    return f"{scene_id}_{int(altitude)}"


def manifest_path(root: Path, scene_id: str) -> Path:
    return root / "manifests" / f"{scene_id}.json"


def scene_dir(root: Path, scene_id: str) -> Path:
    return root / "manifests"


def state_dir(root: Path, scene_id: str) -> Path:
    return root / STATE_DIR / NAME / scene_id


def yaml_path(root: Path) -> Path:
    return root / "occufly.yaml"


def is_export_root(root: Path) -> bool:
    names = {p.name for p in root.iterdir()}
    return "manifests" in names and names <= {
        "occufly.yaml", "data_2d_raw", "preprocess", "depth", "depth_full", "dataset", "splits",
        "manifests", STATE_DIR}


# ---- calibration -----------------------------------------------------------------------------
def kitti_K(camera) -> np.ndarray:
    """(3, 3) K in the integer-pixel-centre convention (COLMAP principal point - 0.5)."""
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    return np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])


def calib_text(camera) -> str:
    P = np.hstack([kitti_K(camera), np.zeros((3, 1))])
    Tr = np.hstack([np.eye(3), np.zeros((3, 1))])

    def row(a: np.ndarray) -> str:
        return " ".join(f"{float(v):.12e}" for v in a.reshape(-1))

    return "".join(f"P{i}: {row(P)}\n" for i in range(4)) + f"Tr: {row(Tr)}\n"


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """{"P2": (3, 4), "Tr": (4, 4)} the way SemanticKITTI-style loaders parse calib.txt."""
    vals: dict[str, np.ndarray] = {}
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            break
        key, _, rest = line.partition(":")
        try:
            vals[key.strip()] = np.array([float(x) for x in rest.split()])
        except ValueError:
            raise InputFormatError(f"{path}: line {line!r} is not 'KEY: numbers'") from None
    if "P2" not in vals or vals["P2"].size != 12 or "Tr" not in vals or vals["Tr"].size != 12:
        raise InputFormatError(f"{path}: expected P2 and Tr lines with 12 numbers each")
    tr = np.eye(4)
    tr[:3, :4] = vals["Tr"].reshape(3, 4)
    return {"P2": vals["P2"].reshape(3, 4), "Tr": tr}


# ---- YAML ------------------------------------------------------------------------------------
def geometry(spec, taxonomy, seq_images: dict[str, tuple[int, int]], counts_train, counts_all) -> dict:
    X, Y, Z = (int(v) for v in spec.shape)
    r = float(spec.voxel_size)
    sizes = set(seq_images.values())
    w, h = sizes.pop() if len(sizes) == 1 else (None, None)
    return {
        "voxel_origin": [-X / 2 * r, -Y / 2 * r, 0.0],
        "voxel_size": r,
        "scene_size": [X * r, Y * r, Z * r],
        "grid_shape": [X, Y, Z],
        "grid_shape_1_8": [X // 8, Y // 8, Z // 8],
        "image_width": w,
        "image_height": h,
        "n_classes": len(taxonomy) + 1,
        "class_names": ["empty"] + [c.name for c in taxonomy.classes],
        "class_voxel_counts": [int(v) for v in counts_train],
        "class_voxel_counts_all": [int(v) for v in counts_all],
        "sequences": {s: {"image_width": int(iw), "image_height": int(ih)}
                      for s, (iw, ih) in sorted(seq_images.items())},
        "frame": "camera-centric: x right, y down, z forward (Tr = identity)",
    }


def learning_map_yaml(taxonomy, geom: dict | None = None) -> str:
    lm = taxonomy.learning_map()
    inv = {v: k for k, v in lm.items() if v != 255}
    inv[255] = 255
    train_ids = sorted(set(lm.values()) | {255})
    doc = {
        "labels": {0: "empty", 255: "invalid", **{c.id: c.name for c in taxonomy.classes}},
        "color_map": {0: [0, 0, 0], **{c.id: list(c.rgb) for c in taxonomy.classes}},
        "learning_map": {int(k): int(v) for k, v in sorted(lm.items())},
        "learning_map_inv": {int(k): int(v) for k, v in sorted(inv.items())},
        # SSC: empty (0) is a class to learn; only 255 (invalid) is ignored
        "learning_ignore": {int(v): v == 255 for v in train_ids},
    }
    if geom is not None:
        doc["geometry"] = geom
    return "# OccuFly taxonomy for SSCBench-style loaders (raw id -> training id)\n" + yaml.safe_dump(
        doc, sort_keys=False)


def learning_lut(taxonomy) -> np.ndarray:
    """(256,) uint8 raw id -> training id; unknown ids -> 255."""
    lut = np.full(256, 255, dtype=np.uint8)
    for k, v in taxonomy.learning_map().items():
        lut[k] = v
    return lut


# ---- static files and links ------------------------------------------------------------------
def static_files(root: Path, scene_id: str, camera, depth_shape, *, altitudes=(), **_) -> dict[Path, bytes]:
    text = calib_text(camera).encode()
    out: dict[Path, bytes] = {}
    for alt in altitudes:
        seq = seq_name(scene_id, alt)
        out[root / "data_2d_raw" / seq / "calib.txt"] = text
        out[root / "dataset" / "sequences" / seq / "calib.txt"] = text
    return out


def _ensure_link(link: Path, target: str) -> None:
    """A relative directory symlink ``link -> target``; an existing correct one is kept."""
    if link.is_symlink():
        if os.readlink(link) == target:
            return
        raise ExportError(f"{link}: a link to {os.readlink(link)!r}, expected {target!r}")
    if link.exists():
        raise ExportError(f"{link}: exists and is not the link to {target!r} the layout needs")
    link.parent.mkdir(parents=True, exist_ok=True)
    (link.parent / target).resolve().mkdir(parents=True, exist_ok=True)
    os.symlink(target, link, target_is_directory=True)


def make_links(root: Path, scene_id: str, altitudes) -> None:
    for alt in altitudes:
        seq = seq_name(scene_id, alt)
        sk = root / "dataset" / "sequences" / seq
        _ensure_link(sk / "image_2", f"../../../data_2d_raw/{seq}/image_00/data_rect")
        _ensure_link(sk / "voxels", f"../../../data_2d_raw/{seq}/voxels")
        _ensure_link(root / "depth_full" / "sequences" / seq, f"../{seq}")


# ---- per frame -------------------------------------------------------------------------------
def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def frame_files(
    root: Path, scene_id: str, altitude: int, frame_id: str, gt, pose: np.ndarray,
    image_png: bytes, depth: np.ndarray, priority_lut: np.ndarray, *, taxonomy=None,
    downsample_rule: str = "occufly", depth_full: np.ndarray | None = None,
    points: np.ndarray | None = None, **_,
) -> dict[Path, bytes]:
    seq = seq_name(scene_id, altitude)
    vox = root / "data_2d_raw" / seq / "voxels"
    raw = gt.label_with_invalid()
    lut = learning_lut(taxonomy)
    train = lut[raw]
    if downsample_rule == "lmscnet":
        # MonoScene's preprocessing pools the training-id grid (ties: smallest training id)
        train8 = pool_grid(train, 8, priority_lut, "lmscnet")
    else:
        # 8x pooling on raw ids (tie order follows the taxonomy), then mapped to training ids
        train8 = lut[pool_grid(raw, 8, priority_lut, "occufly")]
    visible = (gt.labels != 0) & ~gt.invalid & ~gt.occluded
    lab = root / "preprocess" / "labels" / seq
    files = {
        vox / f"{frame_id}.bin": pack_bits(visible),
        vox / f"{frame_id}.label": np.ascontiguousarray(raw, dtype="<u2").tobytes(),
        vox / f"{frame_id}.invalid": pack_bits(gt.invalid),
        vox / f"{frame_id}.occluded": pack_bits(gt.occluded),
        lab / f"{frame_id}_1_1.npy": _npy(train),
        lab / f"{frame_id}_1_8.npy": _npy(train8),
        root / "data_2d_raw" / seq / "image_00" / "data_rect" / f"{frame_id}.png": image_png,
        root / "depth" / seq / f"{frame_id}.npy": _npy(np.ascontiguousarray(depth, dtype=np.float32)),
    }
    if depth_full is not None:
        files[root / "depth_full" / seq / f"{frame_id}.npy"] = _npy(
            np.ascontiguousarray(depth_full, dtype=np.float32))
    if points is not None:
        files[root / "data_2d_raw" / seq / "velodyne_points" / "data" / f"{frame_id}.bin"] = (
            np.ascontiguousarray(points, dtype="<f4").tobytes())
    return files


def class_counts(gt, taxonomy) -> list[int]:
    """Voxels per training id 0..C in the frame's ``_1_1`` (ignore excluded)."""
    train = learning_lut(taxonomy)[gt.label_with_invalid()]
    c = np.bincount(train.reshape(-1), minlength=256)
    return [int(v) for v in c[: len(taxonomy) + 1]]


def marker(root: Path, scene_id: str, altitude: int, frame_id: str) -> Path:
    return state_dir(root, scene_id) / "done" / f"{altitude}_{frame_id}.json"


# ---- dataset-wide files (rebuilt from every manifest after each export) ------------------------
def dataset_files(root: Path, taxonomy, spec) -> dict[Path, bytes]:
    """occufly.yaml (with the geometry block) and splits/*.txt from all manifests in ``root``."""
    splits: dict[str, set[str]] = {s: set() for s in SPLITS}
    frame_splits: dict[str, set[str]] = {}
    seq_images: dict[str, tuple[int, int]] = {}
    n = len(taxonomy) + 1
    counts = {"train": np.zeros(n, np.int64), "all": np.zeros(n, np.int64)}
    for mp in sorted((root / "manifests").glob("*.json")):
        try:
            m = json.loads(mp.read_text())
        except ValueError:
            continue
        if m.get("layout") != NAME:
            continue
        sid = m["scene_id"]
        scene_split = m.get("split", "train")
        for fid, fr in m.get("frames", {}).items():
            seq = seq_name(sid, fr["altitude"])
            split = fr.get("split") or scene_split  # --split-by: per frame
            splits.setdefault(split, set()).add(seq)
            if fr.get("split"):
                frame_splits.setdefault(split, set()).add(f"{seq} {fid}")
            cam = fr.get("camera", {})
            seq_images[seq] = (int(cam.get("width", 0)), int(cam.get("height", 0)))
            mk = marker(root, sid, fr["altitude"], fid)
            try:
                c = np.asarray(json.loads(mk.read_text()).get("class_counts", []), np.int64)
            except (OSError, ValueError):
                continue
            if c.shape == (n,):
                counts["all"] += c
                if split == "train":
                    counts["train"] += c
    train_counts = counts["train"] if counts["train"].sum() else counts["all"]
    geom = geometry(spec, taxonomy, seq_images, train_counts, counts["all"])
    out = {yaml_path(root): learning_map_yaml(taxonomy, geom).encode()}
    for s in SPLITS:
        out[root / "splits" / f"{s}.txt"] = "".join(f"{q}\n" for q in sorted(splits.get(s, ()))).encode()
        if frame_splits:  # a sequence split between train / val / test: which frames where
            out[root / "splits" / f"{s}_frames.txt"] = "".join(
                f"{q}\n" for q in sorted(frame_splits.get(s, ()))).encode()
    return out
