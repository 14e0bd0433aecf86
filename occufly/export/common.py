"""Pieces shared by the export layouts: pooling, bit packing, per-frame computation, done
markers, target checks and disk-full handling.

Majority pooling (``1_2`` ... ``1_16`` and SSCBench ``_1_8``): each coarse voxel takes the
most common *non-empty, valid* class of its f x f x f block; ties go to the class earlier in
the taxonomy's tie order (more frequent first, then lower id). A block with no non-empty
valid voxel is 0 (empty) if any of its voxels is valid, and 255 (invalid) if all are invalid.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np

from occufly.errors import WorkspaceError
from occufly.fsutil import atomic_write_bytes, fsync_dir
from occufly.grid import SceneGrid

EXPORT_FORMAT_VERSION = 1
STATE_DIR = ".occufly_export"


class ExportError(WorkspaceError):
    """An export target is unusable (exists and is not ours, disk full, bad frame)."""


# ---- arrays ------------------------------------------------------------------------------------
def pack_bits(mask: np.ndarray) -> bytes:
    """np.packbits of the C-order flattened bool array, MSB first (FORMATS.md section 3)."""
    return np.packbits(np.ascontiguousarray(mask, dtype=bool).reshape(-1), bitorder="big").tobytes()


def unpack_bits(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    n = int(np.prod(shape))
    return np.unpackbits(np.frombuffer(data, np.uint8))[:n].astype(bool).reshape(shape)


def majority_pool(labels: np.ndarray, factor: int, priority_lut: np.ndarray) -> np.ndarray:
    """Majority-pool an (X, Y, Z) uint8 grid (255 = invalid) by ``factor`` per axis.

    priority_lut: (256,) int rank of each raw id in the tie order (0 = most preferred).
    Returns (X/f, Y/f, Z/f) uint8 following the rule in the module docstring.
    """
    if factor == 1:
        return labels.copy()
    X, Y, Z = labels.shape
    if X % factor or Y % factor or Z % factor:
        raise ValueError(f"grid shape {labels.shape} is not divisible by {factor}")
    f = factor
    blocks = labels.reshape(X // f, f, Y // f, f, Z // f, f).transpose(0, 2, 4, 1, 3, 5)
    blocks = blocks.reshape(-1, f * f * f)
    nb = blocks.shape[0]
    present = np.flatnonzero(np.bincount(labels.reshape(-1), minlength=256))
    classes = present[(present != 0) & (present != 255)]
    out = np.zeros(nb, dtype=np.uint8)
    any_valid = (blocks != 255).any(axis=1)
    out[~any_valid] = 255
    if len(classes):
        compact = np.full(256, len(classes), dtype=np.int64)  # empty/invalid -> spare column
        compact[classes] = np.arange(len(classes))
        idx = compact[blocks] + (np.arange(nb) * (len(classes) + 1))[:, None]
        counts = np.bincount(idx.reshape(-1), minlength=nb * (len(classes) + 1))
        counts = counts.reshape(nb, len(classes) + 1)[:, :-1]
        rank = np.asarray(priority_lut, dtype=np.int64)[classes]
        rank = np.where(rank < 0, 255 + classes, rank)  # ids outside the taxonomy: last, by id
        score = counts * 1024 - rank[None, :]
        best = score.argmax(axis=1)
        has = counts.max(axis=1) > 0
        out[has] = classes[best[has]].astype(np.uint8)
    return out.reshape(X // f, Y // f, Z // f)


# ---- hashing / identity ------------------------------------------------------------------------
def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def scene_fingerprint(scene) -> str:
    """Identity of a scene for "is this an earlier export of this scene": origin, frame names,
    cameras and poses."""
    h = hashlib.sha256()
    h.update(np.asarray(scene.origin, np.float64).tobytes())
    for f in scene.frames:
        h.update(f.name.encode())
        h.update(json.dumps(f.camera.to_dict(), sort_keys=True).encode())
        h.update(np.asarray(f.T_cam_world, np.float64).round(9).tobytes())
    return h.hexdigest()[:32]


def grid_digest(grid: SceneGrid) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(grid.labels).tobytes())
    h.update(grid.origin.tobytes())
    h.update(np.float64(grid.voxel_size).tobytes())
    h.update(str(grid.shape).encode())
    return h.hexdigest()[:32]


# ---- disk-full handling ------------------------------------------------------------------------
DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


def is_disk_full(e: BaseException) -> bool:
    return isinstance(e, OSError) and e.errno in DISK_FULL


def write_frame_files(files: dict[Path, bytes], marker: Path, marker_data: dict,
                      write: Callable[[Path, bytes], None] | None = None) -> int:
    """Write one frame: every file atomically, the done marker last.

    On any failure the files of this frame that were already placed are removed again (they
    belong to a frame with no marker, so nothing complete is lost) and the error re-raised
    (disk full as :class:`ExportError`). Returns the number of bytes written.
    """
    write = write or (lambda p, b: atomic_write_bytes(p, b))  # looked up at call time
    placed: list[Path] = []
    path = marker
    try:
        marker.unlink(missing_ok=True)
        for path, data in files.items():
            write(path, data)
            placed.append(path)
        for d in {p.parent for p in files}:
            fsync_dir(d)
        write(marker, json.dumps(marker_data).encode())
    except BaseException as e:
        for p in placed:
            try:
                p.unlink(missing_ok=True)
            except OSError:
                pass
        if is_disk_full(e):
            raise ExportError(
                f"disk full while writing {path}: the frame was not written; frames already "
                "completed are kept -- free space and rerun the same export to resume"
            ) from None
        raise
    return sum(len(b) for b in files.values())


def frame_done(marker: Path, config_hash: str, root: Path) -> bool:
    """True if ``marker`` exists, was written with ``config_hash``, and every file it lists
    exists with the recorded size."""
    try:
        data = json.loads(marker.read_text())
    except (OSError, ValueError):
        return False
    if data.get("config") != config_hash:
        return False
    for rel, size in data.get("files", {}).items():
        p = root / rel
        try:
            if p.stat().st_size != size:
                return False
        except OSError:
            return False
    return True


def clean_stray_temporaries(root: Path) -> int:
    """Remove ``.<name>.*.tmp`` files left by an interrupted atomic write under ``root``."""
    n = 0
    if not root.exists():
        return 0
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            if name.startswith(".") and name.endswith(".tmp"):
                try:
                    os.unlink(os.path.join(dirpath, name))
                    n += 1
                except OSError:
                    pass
    return n


# ---- per-process caches (workers load the scene and grids once) -------------------------------
_cache: dict = {}
_cache_lock = threading.Lock()


def cached(key: tuple, load: Callable):
    with _cache_lock:
        if key not in _cache:
            if len(_cache) > 8:
                _cache.clear()
            _cache[key] = load()
        return _cache[key]
