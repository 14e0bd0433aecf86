"""COLMAP dense-workspace files: depth maps, ``fused.ply`` and ``fused.ply.vis``.

- ``stereo/depth_maps/<image>.geometric.bin``: ASCII header ``width&height&channels&`` then
  little-endian float32 values in column-major order; 0 means no depth.
- ``fused.ply``: binary PLY, x y z (float, or double for georeferenced clouds we write),
  nx ny nz, red green blue.
- ``fused.ply.vis``: uint64 point count, then per point a uint32 count followed by that many
  uint32 indices into the dense workspace's image list (images sorted by image id).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.fsutil import atomic_write_bytes
from occufly.io.ply import read_ply, write_ply


# ---- depth maps ------------------------------------------------------------------------------
def depth_map_layout(path: str | Path, head: bytes, size: int) -> tuple[int, int, int]:
    """(width, height, data offset) of a COLMAP ``.bin`` depth map from its first bytes
    ``head`` (at least 64, or the whole file) and its ``size`` in bytes; an
    :class:`InputFormatError` naming the problem when it is not a one-channel map whose data
    fills the rest of the file exactly."""
    header_end = 0
    amps = 0
    for i in range(min(len(head), 64)):
        if head[i : i + 1] == b"&":
            amps += 1
            if amps == 3:
                header_end = i + 1
                break
    if amps != 3:
        raise InputFormatError(
            f"{path}: not a COLMAP depth map (expected an ASCII header 'width&height&channels&')"
        )
    try:
        width, height, channels = (int(v) for v in head[: header_end - 1].decode().split("&"))
    except ValueError:
        raise InputFormatError(f"{path}: malformed depth-map header {head[:header_end]!r}") from None
    if width <= 0 or height <= 0 or channels != 1:
        raise InputFormatError(
            f"{path}: depth map header says {width}x{height}x{channels}; expected one channel"
        )
    expected = width * height * channels * 4
    body = size - header_end
    if body != expected:
        raise InputFormatError(
            f"{path}: depth map is truncated or padded: {body} bytes of data, expected "
            f"{expected} for {width}x{height}"
        )
    return width, height, header_end


def no_depth_where_invalid(depth: np.ndarray) -> np.ndarray:
    """``depth`` with NaN, inf and negative values set to 0 (no depth); a new array when any
    (the input may be a read-only view), else the input."""
    bad = ~np.isfinite(depth) | (depth < 0)
    return np.where(bad, np.float32(0.0), depth) if bad.any() else depth


def read_depth_map(path: str | Path) -> np.ndarray:
    """Read a COLMAP ``.bin`` depth map -> (H, W) float32 metres (0 = no depth)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read depth map ({e.strerror})") from None
    width, height, header_end = depth_map_layout(path, raw[:64], len(raw))
    data = np.frombuffer(raw, dtype="<f4", offset=header_end)
    depth = data.reshape((width, height), order="F").T  # column-major -> (H, W)
    return no_depth_where_invalid(np.ascontiguousarray(depth, dtype=np.float32))


def write_depth_map(path: str | Path, depth: np.ndarray) -> None:
    """Write ``depth`` (H, W) float32 metres as a COLMAP ``.bin`` depth map (atomic)."""
    depth = np.asarray(depth, dtype="<f4")
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    h, w = depth.shape
    header = f"{w}&{h}&1&".encode()
    atomic_write_bytes(path, header + np.asfortranarray(depth.T).tobytes(order="F"))


# ---- fused.ply + .vis --------------------------------------------------------------------------
def read_fused_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Read a dense cloud PLY -> (xyz (N, 3) float64, rgb (N, 3) uint8 | None, normals | None)."""
    v = read_ply(path)
    return v.xyz, v.rgb, v.normals


def write_fused_ply(
    path: str | Path,
    xyz: np.ndarray,
    normals: np.ndarray | None = None,
    rgb: np.ndarray | None = None,
    *,
    double: bool = True,
) -> None:
    """Write a COLMAP-style ``fused.ply``.

    xyz: (N, 3) float64 world metres; normals: (N, 3) float; rgb: (N, 3) uint8. ``double``
    stores x, y, z as double so UTM-scale coordinates keep millimetre precision (COLMAP itself
    writes float; our reader accepts both).
    """
    fields: dict[str, np.ndarray] = {}
    xyz = np.asarray(xyz)
    ctype = np.float64 if double else np.float32
    for i, n in enumerate("xyz"):
        fields[n] = xyz[:, i].astype(ctype)
    if normals is not None:
        for i, n in enumerate(("nx", "ny", "nz")):
            fields[n] = np.asarray(normals)[:, i].astype(np.float32)
    if rgb is not None:
        for i, n in enumerate(("red", "green", "blue")):
            fields[n] = np.asarray(rgb)[:, i].astype(np.uint8)
    write_ply(path, fields)


def read_fused_vis(path: str | Path, n_points: int | None = None, *,
                   window_words: int = 1 << 20) -> tuple[np.ndarray, np.ndarray]:
    """Read ``fused.ply.vis`` -> (offsets (N + 1,) int64, image_indices (M,) uint32), CSR by point.

    Streamed: the file is read in windows of ``window_words`` uint32 values, so memory is the
    output (8 bytes per point + 4 per entry) plus one window, never the file itself or int64
    temporaries per entry (a 32 M-point survey's .vis holds ~250 M entries).
    """
    path = Path(path)
    try:
        fh = open(path, "rb")
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read visibility file ({e.strerror})") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        if size < 8:
            raise InputFormatError(f"{path}: too short for a fused.ply.vis file (need a uint64 count)")
        n = int(np.frombuffer(fh.read(8), dtype="<u8")[0])
        if n_points is not None and n != n_points:
            raise InputFormatError(f"{path}: lists {n} points but the cloud has {n_points}")
        if (size - 8) % 4:
            raise InputFormatError(f"{path}: body is not a whole number of uint32 values")
        total = (size - 8) // 4
        if total < n:
            raise InputFormatError(f"{path}: truncated: {total} values for {n} points")
        # a well-formed file holds one count word per point and the entries: M = total - N
        offsets = np.zeros(n + 1, np.int64)
        idx = np.empty(total - n, np.uint32)
        i = 0  # points read
        e = 0  # entries written
        start = 0  # word position of point i's count
        width = max(2, int(window_words))
        while i < n:
            fh.seek(8 + 4 * start)
            window = np.fromfile(fh, dtype="<u4", count=width)
            wlen = len(window)
            if wlen == 0:
                raise InputFormatError(f"{path}: truncated after {i} of {n} points")
            heads = _vis_heads_in(window.tolist(), n - i)
            if not heads:  # one point longer than the window: widen it
                if start + wlen >= total:
                    raise InputFormatError(f"{path}: truncated after {i} of {n} points")
                width = max(width * 2, int(window[0]) + 1)
                continue
            h = np.asarray(heads, dtype=np.int64)
            counts = window[h].astype(np.int64)
            k, m = len(h), int(counts.sum())
            if e + m > len(idx):
                raise InputFormatError(f"{path}: truncated after {i} of {n} points")
            ends = np.cumsum(counts)
            offsets[i + 1:i + 1 + k] = e + ends
            rank = np.arange(m, dtype=np.int64) - np.repeat(ends - counts, counts)
            idx[e:e + m] = window[np.repeat(h + 1, counts) + rank]
            i += k
            e += m
            start += int(h[-1]) + 1 + int(counts[-1])
        if start != total:
            raise InputFormatError(f"{path}: {total - start} trailing values after {n} points")
    return offsets, idx


def _vis_heads_in(window: list[int], limit: int) -> list[int]:
    """Positions of the count words of the (at most ``limit``) points lying wholly inside
    ``window`` (a sequential walk: each count says where the next point starts)."""
    heads: list[int] = []
    add = heads.append
    pos, wlen, k = 0, len(window), 0
    while k < limit and pos < wlen:
        nxt = pos + 1 + window[pos]
        if nxt > wlen:
            break
        add(pos)
        pos = nxt
        k += 1
    return heads


def write_fused_vis(path: str | Path, offsets: np.ndarray, image_indices: np.ndarray) -> None:
    """Write ``fused.ply.vis`` from CSR arrays: offsets (N + 1,) int64, image_indices (M,)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    idx = np.asarray(image_indices, dtype="<u4")
    n = len(offsets) - 1
    counts = np.diff(offsets)
    out = np.empty(n + len(idx), dtype="<u4")
    heads = offsets[:-1] + np.arange(n)
    out[heads] = counts
    mask = np.ones(len(out), dtype=bool)
    mask[heads] = False
    out[mask] = idx
    atomic_write_bytes(path, np.array([n], dtype="<u8").tobytes() + out.tobytes())


def find_depth_map(depth_dir: Path, image_name: str) -> Path | None:
    """``<dir>/<image name>.geometric.bin`` (COLMAP), else ``.photometric.bin``."""
    for kind in ("geometric", "photometric"):
        p = depth_dir / f"{image_name}.{kind}.bin"
        if p.is_file():
            return p
    base = os.path.basename(image_name)
    for kind in ("geometric", "photometric"):
        p = depth_dir / f"{base}.{kind}.bin"
        if p.is_file():
            return p
    return None
