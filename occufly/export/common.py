"""Pieces shared by the export layouts: pooling, bit packing, per-frame computation, done
markers, target checks and disk-full handling.

Majority pooling (``1_2`` ... ``1_16`` and SSCBench ``_1_8``): each coarse voxel takes the
most common *non-empty, valid* class of its f x f x f block; ties go to the class earlier in
the taxonomy's tie order (more frequent first, then lower id). A block with no non-empty
valid voxel is 0 (empty) if any of its voxels is valid, and 255 (invalid) if all are invalid.
``--downsample-rule lmscnet`` uses the LMSCNet / MonoScene rule instead (:func:`lmscnet_pool`).
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import struct
import threading
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from occufly.errors import WorkspaceError
from occufly.fsutil import fsync_dir, write_tmp
from occufly.grid import SceneGrid
from occufly.io.masks import png_chunk as _png_chunk

EXPORT_FORMAT_VERSION = 2  # 2: scene-level calibration.txt, depth shape, splits, sscbench calib/geometry
STATE_DIR = ".occufly_export"


class ExportError(WorkspaceError):
    """An export target is unusable (exists and is not ours, disk full, bad frame)."""


class ExportDiskFull(ExportError):
    """The disk (or the quota) filled while an export wrote (ENOSPC / EDQUOT)."""


# ---- arrays ------------------------------------------------------------------------------------
def pack_bits(mask: np.ndarray) -> bytes:
    """np.packbits of the C-order flattened bool array, MSB first (FORMATS.md section 3)."""
    return np.packbits(np.ascontiguousarray(mask, dtype=bool).reshape(-1), bitorder="big").tobytes()


def majority_pool(labels: np.ndarray, factor: int, priority_lut: np.ndarray) -> np.ndarray:
    """Majority-pool an (X, Y, Z) uint8 grid (255 = invalid) by ``factor`` per axis.

    priority_lut: (256,) int rank of each raw id in the tie order (0 = most preferred).
    Returns (X/f, Y/f, Z/f) uint8 following the rule in the module docstring.
    """
    return majority_pyramid(labels, (factor,), priority_lut)[factor]


def majority_pyramid(labels: np.ndarray, factors: tuple[int, ...], priority_lut: np.ndarray
                     ) -> dict[int, np.ndarray]:
    """Majority pooling for several power-of-two factors at once.

    Sparse: only the non-empty valid voxels (a few per cent of a frame grid) are counted,
    per (block, class) with ``np.unique``; "all invalid" blocks come from an any-reduction
    of the valid mask, done hierarchically (exact for *any*). Every level is pooled from
    the full-resolution grid, never from a pooled grid.
    """
    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    X, Y, Z = labels.shape
    out: dict[int, np.ndarray] = {}
    for f in factors:
        if f < 1 or f & (f - 1):
            raise ValueError(f"pooling factor must be a power of two, got {f}")
        if X % f or Y % f or Z % f:
            raise ValueError(f"grid shape {labels.shape} is not divisible by {f}")
        if f == 1:
            out[1] = labels.copy()
    coarse = sorted(f for f in factors if f > 1)
    if not coarse:
        return out
    flat = labels.reshape(-1)
    occ = np.flatnonzero((flat != 0) & (flat != 255))
    cls = flat[occ].astype(np.int64)
    i, rem = np.divmod(occ, Y * Z)
    j, k = np.divmod(rem, Z)
    rank_lut = np.asarray(priority_lut, dtype=np.int64).copy()
    unknown = rank_lut < 0
    rank_lut[unknown] = 255 + np.flatnonzero(unknown)  # ids outside the taxonomy: last, by id
    valid_any = labels != 255
    cur_f = 1
    for f in coarse:
        while cur_f < f:  # OR of the two halves along each axis (cheaper than .any on 6-D)
            v = valid_any[0::2] | valid_any[1::2]
            v = v[:, 0::2] | v[:, 1::2]
            valid_any = v[:, :, 0::2] | v[:, :, 1::2]
            cur_f *= 2
        b, c = Y // f, Z // f
        res = np.where(valid_any, np.uint8(0), np.uint8(255)).astype(np.uint8).reshape(-1)
        if len(occ):
            bid = ((i // f) * b + j // f) * c + k // f
            keys, counts = np.unique(bid * 256 + cls, return_counts=True)
            kb, kc = keys // 256, keys % 256
            # per block: highest count first, then the most preferred class
            order = np.lexsort((rank_lut[kc], -counts, kb))
            kb, kc = kb[order], kc[order]
            first = np.ones(len(kb), dtype=bool)
            first[1:] = kb[1:] != kb[:-1]
            res[kb[first]] = kc[first].astype(np.uint8)
        out[f] = res.reshape(X // f, Y // f, Z // f)
    return out


DOWNSAMPLE_RULES = ("occufly", "lmscnet")


def lmscnet_pool(labels: np.ndarray, factor: int) -> np.ndarray:
    """The LMSCNet / MonoScene downsampling rule (their ``_downsample_label``), vectorised.

    Per f x f x f block: when more than 95 % of its voxels are empty (0) or invalid (255),
    the block is 0 if it has more empty than invalid voxels, else 255; otherwise it is the
    most common id among its other voxels, ties going to the *smallest* id
    (``np.argmax(np.bincount(...))``). MonoScene applies it to training ids, so pool the
    training-id grid to reproduce their ``_1_8.npy`` bit for bit.
    """
    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    f = int(factor)
    X, Y, Z = labels.shape
    if f < 1 or X % f or Y % f or Z % f:
        raise ValueError(f"grid shape {labels.shape} is not divisible by {f}")
    if f == 1:
        return labels.copy()
    bx, by, bz = X // f, Y // f, Z // f
    blocks = labels.reshape(bx, f, by, f, bz, f).transpose(0, 2, 4, 1, 3, 5).reshape(-1, f ** 3)
    n0 = np.count_nonzero(blocks == 0, axis=1)
    n255 = np.count_nonzero(blocks == 255, axis=1)
    out = np.where(n0 > n255, np.uint8(0), np.uint8(255))
    full = (n0 + n255) <= 0.95 * f ** 3
    if full.any():
        sub = blocks[full]
        rows, cols = np.nonzero((sub != 0) & (sub != 255))
        counts = np.bincount(rows * 256 + sub[rows, cols], minlength=len(sub) * 256)
        out[full] = np.argmax(counts.reshape(len(sub), 256), axis=1).astype(np.uint8)  # ties: smallest id
    return out.reshape(bx, by, bz)


def pool_grid(labels: np.ndarray, factor: int, priority_lut: np.ndarray, rule: str = "occufly") -> np.ndarray:
    """Downsample by ``factor`` with the named rule (``occufly``: :func:`majority_pool`;
    ``lmscnet``: :func:`lmscnet_pool`)."""
    if rule == "occufly":
        return majority_pool(labels, factor, priority_lut)
    if rule == "lmscnet":
        return lmscnet_pool(labels, factor)
    raise ValueError(f"unknown downsample rule {rule!r}; expected one of {', '.join(DOWNSAMPLE_RULES)}")


# ---- images ------------------------------------------------------------------------------------
# PNG colour types of the 8-bit PIL modes encoded by :func:`encode_png` (others go through PIL)
_PNG_COLOUR_TYPE = {"L": 0, "RGB": 2, "RGBA": 6}
# The IDAT stream is deflated by ISA-L (``isal``, pinned in pyproject.toml) at its level 1: on
# an Up-filtered 5472 x 3648 photo 0.16 s of one core for 17.2 MB, where zlib's fastest useful
# setting (level 1, Z_RLE, what this encoder used before) took 0.51 s for 16.4 MB and zlib-ng's
# 0.22-0.34 s for 16.4-24.4 MB (same frame, same run). Any inflate reads it: the decoded
# pixels are the same whichever deflate wrote them.
PNG_DEFLATE = "isal"
PNG_ISAL_LEVEL = 1
PNG_ISAL_MEM_LEVEL = 8


def _isal_zlib():
    try:
        from isal import isal_zlib
    except ImportError as e:  # a dependency of the package: only a broken install gets here
        raise ImportError(f"the PNG encoder of the export needs the 'isal' package ({e}); "
                          "reinstall occufly (pip install -e .)") from None
    return isal_zlib


def encode_png(pixels: np.ndarray, *, icc_profile: bytes | None = None,
               palette: np.ndarray | None = None) -> bytes:
    """A PNG of an 8-bit (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA array, fast.
    With ``palette`` ((P, 3) RGB or (P, 4) RGBA uint8, 1 <= P <= 256), (H, W) ``pixels`` are
    indices into it: an indexed-colour PNG (PLTE, and tRNS for RGBA), decoded as
    ``palette[pixels]``; an index past the palette is refused.

    Every row uses the PNG "Up" filter (one vectorised subtraction of the previous row, in
    bands of rows that stay in cache) and the filtered bytes are deflated in one stream by
    ISA-L at level 1. On a 5472 x 3648 photo this takes ~0.2 s of one core (the zlib level-1
    run-length stream before: ~0.5 s; PIL's ``compress_level=1``: 1.3 s, most of it the
    per-row adaptive filter choice) for about the same size (17.2 vs 16.4 and 23.2 MB).
    ``pixels`` may be a strided view (e.g. the RGB of an RGBX buffer): rows are read in place.
    Deterministic: the same pixels give the same bytes in any process of one machine (same
    ISA-L version and instruction set). ``icc_profile`` is stored as an iCCP chunk.
    """
    a = np.asarray(pixels)
    if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise ValueError(f"encode_png: expected uint8 (H, W[, 3|4]), got {a.dtype} {a.shape}")
    h, w = a.shape[:2]
    if h < 1 or w < 1:
        raise ValueError(f"encode_png: empty image {a.shape}")
    ch = 1 if a.ndim == 2 else a.shape[2]
    colour = {1: 0, 3: 2, 4: 6}[ch]
    head = []
    if palette is not None:
        pal = np.asarray(palette)
        if (pal.dtype != np.uint8 or pal.ndim != 2 or pal.shape[1] not in (3, 4)
                or not 1 <= len(pal) <= 256):
            raise ValueError(f"encode_png: palette must be (1..256, 3|4) uint8, got {pal.dtype} "
                             f"{pal.shape}")
        if ch != 1:
            raise ValueError(f"encode_png: a palette image is (H, W) indices, got {a.shape}")
        if len(pal) < 256 and int(a.max()) >= len(pal):
            raise ValueError(f"encode_png: index {int(a.max())} past the {len(pal)}-colour palette")
        colour = 3
        head.append(_png_chunk(b"PLTE", np.ascontiguousarray(pal[:, :3]).tobytes()))
        if pal.shape[1] == 4:
            head.append(_png_chunk(b"tRNS", np.ascontiguousarray(pal[:, 3]).tobytes()))
    isal_zlib = _isal_zlib()
    rows = a.reshape(h, w * ch) if a.flags.c_contiguous else None
    # bands of rows filtered into one small reused buffer (stays in cache, no image-sized
    # allocation) and fed to one deflate stream: the same bytes as filtering all at once
    band = max(1, (1 << 20) // (w * ch + 1))
    filt = np.empty((min(band, h), w * ch + 1), np.uint8)
    filt[:, 0] = 2  # filter type Up: byte - byte above (mod 256); row 0 has a zero row above
    co = isal_zlib.compressobj(PNG_ISAL_LEVEL, isal_zlib.DEFLATED, 15, PNG_ISAL_MEM_LEVEL)
    out = []
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        f = filt[: r1 - r0]
        if rows is not None:
            cur = rows[r0:r1]
            above = rows[r0 - 1 : r1 - 1] if r0 else rows[: r1 - 1]
        else:  # a strided view: subtract in its own shape, written into the band's rows
            cur = a[r0:r1]
            above = a[r0 - 1 : r1 - 1] if r0 else a[: r1 - 1]
        dst = f[:, 1:] if rows is not None else f[:, 1:].reshape((r1 - r0, *a.shape[1:]))
        if r0 == 0:
            dst[0] = cur[0]
            np.subtract(cur[1:], above, out=dst[1:])
        else:
            np.subtract(cur, above, out=dst)
        out.append(co.compress(memoryview(f).cast("B")))
    out.append(co.flush())
    # one IDAT chunk: length and CRC over the pieces, then a single join of the whole file
    crc = isal_zlib.crc32(b"IDAT")
    for piece in out:
        crc = isal_zlib.crc32(piece, crc)
    parts = [b"\x89PNG\r\n\x1a\n", _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))]
    if icc_profile:
        parts.append(_png_chunk(b"iCCP", b"ICC Profile\x00\x00" + zlib.compress(icc_profile)))
    parts += [*head, struct.pack(">I", sum(len(piece) for piece in out)), b"IDAT", *out,
              struct.pack(">I", crc), _png_chunk(b"IEND", b"")]
    return b"".join(parts)


def image_as_png(im) -> bytes:
    """PNG bytes of an opened PIL image: 8-bit grey / RGB / RGBA through :func:`encode_png`
    (its ICC profile kept, as PIL's PNG writer keeps it), any other mode through PIL
    (``compress_level=1``)."""
    if im.mode in _PNG_COLOUR_TYPE:
        return encode_png(np.asarray(im), icc_profile=im.info.get("icc_profile"))
    buf = io.BytesIO()
    im.save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


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
    h.update(memoryview(np.ascontiguousarray(grid.labels)).cast("B"))  # no copy
    h.update(grid.origin.tobytes())
    h.update(np.float64(grid.voxel_size).tobytes())
    h.update(str(grid.shape).encode())
    return h.hexdigest()[:32]


# ---- disk-full handling ------------------------------------------------------------------------
DISK_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


def is_disk_full(e: BaseException) -> bool:
    return isinstance(e, ExportDiskFull) or (isinstance(e, OSError) and e.errno in DISK_FULL)


def write_frame_files(files: dict[Path, bytes], marker: Path, marker_data: dict) -> int:
    """Write one frame so that it never appears half-written.

    1. the old done marker (if any) is removed;
    2. every file is written and fsynced under a hidden temporary name next to its target
       (``.<name>.*.tmp``; leftovers of a killed run are swept by the next run);
    3. only then are all of them renamed into place (a burst of renames, no data writes),
       their folders fsynced, and the done marker written last.

    A failure before step 3 (disk full, an error, a kill) leaves no file of this frame; on a
    failure during the renames the already placed files are removed. Disk full is raised as
    :class:`ExportError`. Returns the number of bytes written.
    """
    staged: list[tuple[Path, Path]] = []
    placed: list[Path] = []
    path = marker
    try:
        marker.unlink(missing_ok=True)
        for path, data in files.items():
            staged.append((write_tmp(path, data), path))
        for tmp, path in staged:
            os.replace(tmp, path)
            placed.append(path)
        for d in {p.parent for p in files}:
            fsync_dir(d)
        path = marker
        tmp = write_tmp(marker, json.dumps(marker_data).encode())
        os.replace(tmp, marker)
        fsync_dir(marker.parent)
    except BaseException as e:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        for p in placed:
            try:
                p.unlink(missing_ok=True)
            except OSError:
                pass
        if is_disk_full(e):
            raise ExportDiskFull(
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
