"""COLMAP sparse models (text or binary), read with pycolmap and checked for what we need."""

from __future__ import annotations

import logging
import signal
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occufly.camera import CAMERA_MODELS, Camera, make_pose
from occufly.errors import InputFormatError

log = logging.getLogger(__name__)

_TEXT = ("cameras.txt", "images.txt", "points3D.txt")
_BIN = ("cameras.bin", "images.bin", "points3D.bin")


@dataclass
class SparseImage:
    """One registered image: world-to-camera pose in the model's (world) frame."""

    image_id: int
    name: str
    camera: Camera
    T_cam_world: np.ndarray  # (4, 4) float64, model world frame
    point3D_ids: np.ndarray  # (K,) int64 ids of observed 3D points (tracks)
    uv: np.ndarray  # (K, 2) float64 pixel coordinates of those observations


@dataclass
class SparseModel:
    """The in-memory reconstruction every reader returns (COLMAP, ODM, Metashape, Pix4D).

    crs: pyproj CRS of the world frame of ``T_cam_world``/``xyz``, or None when unknown --
    then the world is assumed to be the cloud's frame (COLMAP), unless ``local_frame`` says
    it is a local frame that cannot be related to a georeferenced cloud (Metashape
    ``LOCAL_CS``). output_crs: the CRS the tool writes its clouds in (used when the cloud
    declares none). has_tracks: ``point3D_ids``/``uv`` are real observations.
    """

    images: list[SparseImage]  # sorted by image id (COLMAP's dense-workspace order)
    point_ids: np.ndarray  # (P,) int64
    xyz: np.ndarray  # (P, 3) float64 world
    rgb: np.ndarray  # (P, 3) uint8
    path: Path
    kind: str = "colmap"
    crs: object | None = None
    output_crs: object | None = None
    local_frame: bool = False
    has_tracks: bool = True
    default_cloud: Path | None = None
    default_images: Path | None = None
    notes: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)


def find_sparse_dir(source: Path) -> Path:
    """The folder holding cameras/images/points3D: ``source``, ``source/sparse`` or ``sparse/0``."""
    for cand in (source, source / "sparse", source / "sparse" / "0", source / "0"):
        if all((cand / n).is_file() for n in _BIN) or all((cand / n).is_file() for n in _TEXT):
            return cand
    present = [str(p.relative_to(source)) for p in source.rglob("cameras.*")] if source.is_dir() else []
    hint = f" (found {', '.join(present)})" if present else ""
    raise InputFormatError(
        f"{source}: no COLMAP model: expected cameras, images and points3D as .bin or .txt in "
        f"{source}, {source}/sparse or {source}/sparse/0{hint}"
    )


def import_pycolmap():
    """``import pycolmap`` keeping Python's SIGTERM handler.

    pycolmap's glog installs a failure handler for SIGTERM at import that aborts the process
    with a stack dump, replacing the CLI's handler (SIGTERM unwinds like Ctrl-C so that a
    stopped command removes its temporary output). The Python handler is put back."""
    before = signal.getsignal(signal.SIGTERM)
    import pycolmap

    if threading.current_thread() is threading.main_thread() and before is not None:
        signal.signal(signal.SIGTERM, before)
    return pycolmap


def read_sparse_model(source: str | Path) -> SparseModel:
    source = Path(source)
    if not source.exists():
        raise InputFormatError(f"{source}: reconstruction folder not found")
    sparse = find_sparse_dir(source)
    pycolmap = import_pycolmap()

    try:
        rec = pycolmap.Reconstruction(str(sparse))
    except Exception as e:  # noqa: BLE001 - pycolmap raises plain RuntimeError/ValueError
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise InputFormatError(
            f"{sparse}: malformed COLMAP model ({msg}); expected cameras, images and points3D "
            f"written by COLMAP"
        ) from None
    cameras: dict[int, Camera] = {}
    for cid, cam in rec.cameras.items():
        model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
        if model not in CAMERA_MODELS:
            raise InputFormatError(
                f"{sparse}: camera {cid} uses model {model}; supported: {', '.join(CAMERA_MODELS)}"
            )
        cameras[cid] = Camera(model, cam.width, cam.height, np.asarray(cam.params, float))
    images: list[SparseImage] = []
    for iid in sorted(rec.images):
        im = rec.images[iid]
        if hasattr(im, "has_pose") and not im.has_pose:
            log.warning("%s: image %s has no pose; skipped", sparse, im.name)
            continue
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        T = make_pose(pose.rotation.matrix(), pose.translation)
        if not np.all(np.isfinite(T)):
            raise InputFormatError(f"{sparse}: image {im.name} has a non-finite pose")
        if im.camera_id not in cameras:
            raise InputFormatError(f"{sparse}: image {im.name} refers to unknown camera {im.camera_id}")
        pts = im.points2D
        tracked = [p for p in pts if p.has_point3D()]
        ids = np.array([p.point3D_id for p in tracked], dtype=np.int64)
        uv = np.array([p.xy for p in tracked], dtype=np.float64).reshape(-1, 2)
        images.append(SparseImage(iid, im.name, cameras[im.camera_id], T, ids, uv))
    if not images:
        raise InputFormatError(f"{sparse}: the model has no registered images")
    pids = np.array(sorted(rec.points3D), dtype=np.int64)
    if len(pids):
        xyz = np.array([rec.points3D[int(i)].xyz for i in pids], dtype=np.float64)
        rgb = np.array([rec.points3D[int(i)].color for i in pids], dtype=np.uint8)
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return SparseModel(images, pids, xyz, rgb, sparse)
