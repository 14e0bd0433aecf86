"""Dense point clouds from PLY, LAS and LAZ, in float64 world (often UTM) coordinates."""

from __future__ import annotations

import io
from pathlib import Path

import laspy
import numpy as np

from occufly.errors import InputFormatError
from occufly.fsutil import atomic_write_bytes
from occufly.io.ply import read_ply


def read_point_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a cloud -> (xyz (N, 3) float64 world metres, rgb (N, 3) uint8; grey if absent).

    NaN or infinite coordinates are an error naming the file and the first bad point.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFormatError(f"{path}: point cloud file not found")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        v = read_ply(path)
        xyz = v.xyz
        rgb = v.rgb
    elif suffix in (".las", ".laz"):
        xyz, rgb = _read_las(path)
    else:
        raise InputFormatError(f"{path}: unsupported point cloud type {suffix!r}; expected .ply, .las or .laz")
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputFormatError(
            f"{path}: {int(bad.sum())} points have NaN or infinite coordinates (first: point {i})"
        )
    if rgb is None:
        rgb = np.full((len(xyz), 3), 128, np.uint8)
    return xyz, rgb


def _read_las(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        raise InputFormatError(
            f"{path}: cannot decompress LAZ: no LAZ backend is installed (pip install 'laspy[lazrs]')"
        )
    try:
        las = laspy.read(path)
    except laspy.errors.LaspyException as e:
        text = str(e)
        if "LazBackend" in text or "laz" in text.lower() and "backend" in text.lower():
            raise InputFormatError(
                f"{path}: cannot decompress LAZ: no LAZ backend is installed "
                f"(pip install 'laspy[lazrs]'); {text}"
            ) from None
        raise InputFormatError(f"{path}: not a valid LAS/LAZ file ({text})") from None
    except (OSError, ValueError) as e:
        raise InputFormatError(f"{path}: not a valid LAS/LAZ file ({e})") from None
    # scaled coordinates as float64: x = X * scale + offset, exact for UTM at mm scale
    xyz = np.column_stack([np.asarray(las.x, np.float64), np.asarray(las.y, np.float64),
                           np.asarray(las.z, np.float64)])
    rgb = None
    dims = set(las.point_format.dimension_names)
    if {"red", "green", "blue"} <= dims:
        cols = np.column_stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)])
        # LAS stores 16-bit colour; 8-bit values stored unscaled are kept as they are
        rgb = (cols >> 8).astype(np.uint8) if cols.max(initial=0) > 255 else cols.astype(np.uint8)
    return xyz, rgb


def write_las(path: str | Path, xyz_world: np.ndarray, rgb: np.ndarray | None = None,
              classification: np.ndarray | None = None) -> None:
    """Write LAS/LAZ (by suffix) with mm scale and an offset near the data (atomic).

    xyz_world: (N, 3) float64 world metres; rgb: (N, 3) uint8; classification: (N,) uint8.
    """
    path = Path(path)
    xyz_world = np.asarray(xyz_world, dtype=np.float64)
    # LAS 1.4 point formats 6/7: 8-bit classification, so raw ids up to 254 fit
    header = laspy.LasHeader(point_format=7 if rgb is not None else 6, version="1.4")
    header.offsets = np.floor(xyz_world.min(axis=0)) if len(xyz_world) else np.zeros(3)
    header.scales = np.array([0.001, 0.001, 0.001])
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz_world[:, 0], xyz_world[:, 1], xyz_world[:, 2]
    if rgb is not None:
        rgb16 = np.asarray(rgb, dtype=np.uint16) * 257
        las.red, las.green, las.blue = rgb16[:, 0], rgb16[:, 1], rgb16[:, 2]
    if classification is not None:
        las.classification = np.asarray(classification, dtype=np.uint8)
    buf = io.BytesIO()
    las.write(buf, do_compress=path.suffix.lower() == ".laz")
    atomic_write_bytes(path, buf.getvalue())
