"""COPC (cloud-optimized LAZ) for Potree, QGIS and PDAL, written with copc-lib.

A COPC file is a LAZ 1.4 file whose points are stored in octree nodes (each compressed on its
own) with a hierarchy EVLR, so a viewer streams only the nodes it needs. copc-lib
(Rock Robotic, ``copclib`` on PyPI) writes the container, the LAZ chunks and the hierarchy;
this module decides the octree and hands it each node's raw point records, which laspy builds
(the same records a LAS/LAZ export holds: ASPRS classification, class id, confidence).

Octree: the root is the cube around the points; a node at depth d keeps one point per cell of a
``GRID``^3 grid over its cube (the first in Morton order), the rest go to its children.
Every point lands in exactly one node. Depth stops where a node holds no more than
``MAX_NODE_POINTS`` or at ``MAX_DEPTH``, which takes all that are left.

Two things copc-lib 2.6 does not expose from Python, done here on the finished file:
- the extra-bytes descriptors (its ``EbField`` has no Python attributes): copc-lib writes one
  1-byte "undocumented" descriptor per extra byte; they are overwritten in place, byte for
  byte the same size, by laspy's descriptors of the 1-byte fields we use;
- extra records (the class table): appended as EVLRs after copc-lib's hierarchy EVLR, and the
  header's EVLR count raised. The COPC info VLR keeps its absolute offsets: nothing before the
  end of the file moves.
"""

from __future__ import annotations

import copy
import io
import os
import struct
from pathlib import Path

import laspy
import numpy as np

from occufly.errors import InputFormatError

GRID = 128
MAX_NODE_POINTS = 100_000
MAX_DEPTH = 12
_VLR_HEADER = 54      # user_id 16, reserved 2, record_id 2, length 2, description 32
_EVLR_HEADER = 60     # as a VLR header with a uint64 length
_EB_DESCRIPTOR = 192  # LAS 1.4 extra-bytes descriptor


_CELL_BITS = 7  # GRID = 2**7 cells per node side
_BITS = MAX_DEPTH + _CELL_BITS  # finest cell index bits per axis (19 <= 21: fits a uint64 key)


def _spread(v: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of v so they occupy every third bit (Morton interleave)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _compact(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_spread`."""
    v = v.astype(np.uint64) & np.uint64(0x1249249249249249)
    for shift, mask in ((2, 0x10C30C30C30C30C3), (4, 0x100F00F00F00F00F), (8, 0x1F0000FF0000FF),
                        (16, 0x1F00000000FFFF), (32, 0x1FFFFF)):
        v = (v ^ (v >> np.uint64(shift))) & np.uint64(mask)
    return v


def _octree(xyz: np.ndarray, center: np.ndarray, halfsize: float) -> list[tuple[tuple, np.ndarray]]:
    """[((d, x, y, z), point indices)] covering every point once, parents before children.

    One sort: points in Morton order of their finest cell, so the points of any node or cell
    at any depth are contiguous (a key prefix); each depth is then a linear pass over the
    points still unplaced: the first of each occupied cell of the node's GRID^3 grid stays,
    a node with at most MAX_NODE_POINTS unplaced points keeps them all."""
    lo = center - halfsize
    cells = 1 << _BITS
    q = np.clip(((xyz - lo) / (2.0 * halfsize) * cells).astype(np.int64), 0, cells - 1)
    key = (_spread(q[:, 0]) << np.uint64(2)) | (_spread(q[:, 1]) << np.uint64(1)) | _spread(q[:, 2])
    order = np.argsort(key, kind="stable")
    key = key[order]
    out: list[tuple[tuple, np.ndarray]] = []
    remaining = np.arange(len(key), dtype=np.int64)  # positions in Morton order
    for d in range(MAX_DEPTH + 1):
        if not len(remaining):
            break
        k = key[remaining]
        node = k >> np.uint64(3 * (_BITS - d))
        node_start = np.r_[True, node[1:] != node[:-1]]
        if d == MAX_DEPTH:
            keep = np.ones(len(k), bool)
        else:
            cell = k >> np.uint64(3 * (_BITS - d - _CELL_BITS))
            keep = np.r_[True, cell[1:] != cell[:-1]]
            starts = np.flatnonzero(node_start)
            counts = np.diff(np.append(starts, len(k)))
            keep |= np.repeat(counts <= MAX_NODE_POINTS, counts)
        kept = remaining[keep]
        kn = node[keep]
        run = np.flatnonzero(np.r_[True, kn[1:] != kn[:-1]])
        ends = np.append(run[1:], len(kn))
        ids = kn[run]
        xs = _compact(ids >> np.uint64(2)).tolist()
        ys = _compact(ids >> np.uint64(1)).tolist()
        zs = _compact(ids).tolist()
        for x, y, z, a, b in zip(xs, ys, zs, run.tolist(), ends.tolist(), strict=True):
            out.append(((d, x, y, z), order[kept[a:b]]))
        remaining = remaining[~keep]
    return out


def _walk_vlrs(f, offset: int, count: int, extended: bool):
    """Yield (header offset, user_id, record_id, payload offset, payload length)."""
    pos = offset
    for _ in range(count):
        f.seek(pos)
        head = f.read(_EVLR_HEADER if extended else _VLR_HEADER)
        user_id = head[2:18].rstrip(b"\0").decode("ascii", "replace")
        (record_id,) = struct.unpack_from("<H", head, 18)
        if extended:
            (length,) = struct.unpack_from("<Q", head, 20)
        else:
            (length,) = struct.unpack_from("<H", head, 20)
        payload = pos + len(head)
        yield pos, user_id, record_id, payload, length
        pos = payload + length


def _evlr_bytes(user_id: str, record_id: int, description: str, data: bytes) -> bytes:
    return (struct.pack("<H16sHQ32s", 0, user_id.encode("ascii")[:16], record_id, len(data),
                        description.encode("ascii", "replace")[:32]) + data)


def write_copc(path: str | Path, las, *, wkt: str | None = None,
               extra_vlrs: list | None = None) -> dict:
    """Write ``las`` (a laspy ``LasData``, point format 6-8 with 1-byte extra dimensions only)
    as COPC at ``path`` (atomically: a temporary file renamed into place).

    ``extra_vlrs``: laspy VLRs (user_id, record_id, description, record_data) stored as EVLRs.
    Returns {"nodes", "depth", "points"}.
    """
    import copclib  # copc-lib's binary module: only the COPC export needs it

    path = Path(path)
    pf = las.header.point_format
    if pf.id not in (6, 7, 8):
        raise InputFormatError(f"{path}: COPC needs point format 6, 7 or 8, got {pf.id}")
    extra = list(pf.extra_dimension_names)
    eb_bytes = pf.num_extra_bytes
    if any(las.point_format.dimension_by_name(n).num_bits != 8 for n in extra):
        raise ValueError("write_copc: only 1-byte extra dimensions can be described in COPC here")
    n = len(las.points)
    if n == 0:
        raise InputFormatError(f"{path}: no points to write")
    scale = np.asarray(las.header.scales, np.float64)
    offset = np.asarray(las.header.offsets, np.float64)
    xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
    mn, mx = xyz.min(axis=0), xyz.max(axis=0)
    center = (mn + mx) / 2.0
    halfsize = float(max((mx - mn).max() / 2.0, 1e-3)) * 1.0001
    nodes = _octree(xyz, center, halfsize)

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        cfg = copclib.CopcConfigWriter(pf.id, copclib.Vector3(*scale.tolist()),
                                       copclib.Vector3(*offset.tolist()), wkt or "",
                                       copclib.EbVlr(eb_bytes))
        writer = copclib.FileWriter(str(tmp), cfg)
        info = writer.copc_config.copc_info
        info.center_x, info.center_y, info.center_z = center.tolist()
        info.halfsize = halfsize
        info.spacing = 2.0 * halfsize / GRID
        hdr = writer.copc_config.las_header
        hdr.min = copclib.Vector3(*mn.tolist())
        hdr.max = copclib.Vector3(*mx.tolist())
        raw = las.points.array  # the point records as laspy packs them (format + extra bytes)
        for (d, x, y, z), idx in nodes:
            writer.AddNode(copclib.VoxelKey(d, x, y, z), copclib.VectorChar(np.frombuffer(raw[idx].tobytes(), np.int8)))
        writer.Close()
        _finish_copc(tmp, las, extra, extra_vlrs or [])
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return {"nodes": len(nodes), "depth": max(k[0] for k, _ in nodes), "points": n}


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def _finish_copc(path: Path, las, extra: list[str], extra_vlrs: list) -> None:
    """Describe the extra bytes with laspy's descriptors and append the extra EVLRs."""
    with open(path, "r+b") as f:
        head = f.read(375)
        (header_size,) = struct.unpack_from("<H", head, 94)
        (n_vlrs,) = struct.unpack_from("<I", head, 100)
        evlr_start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if extra:
            payload = _extra_bytes_payload(las)
            for _, uid, rid, at, length in _walk_vlrs(f, header_size, n_vlrs, extended=False):
                if uid == "LASF_Spec" and rid == 4:
                    if length != len(payload):
                        raise RuntimeError(f"{path}: extra-bytes VLR is {length} bytes, "
                                           f"expected {len(payload)}")
                    f.seek(at)
                    f.write(payload)
                    break
            else:
                raise RuntimeError(f"{path}: copc-lib wrote no extra-bytes VLR")
        if extra_vlrs:
            f.seek(0, os.SEEK_END)
            for v in extra_vlrs:
                f.write(_evlr_bytes(v.user_id, v.record_id, v.description, v.record_data_bytes()))
            f.seek(243)
            f.write(struct.pack("<I", n_evlrs + len(extra_vlrs)))
        f.flush()
        os.fsync(f.fileno())


def _extra_bytes_payload(las) -> bytes:
    """The extra-bytes VLR payload laspy writes for ``las``'s point format (names, types,
    scales): a header-only copy written to memory and read back."""
    hdr = copy.deepcopy(las.header)
    hdr.point_count = 0
    buf = io.BytesIO()
    laspy.LasData(hdr).write(buf)
    buf.seek(0)
    return laspy.read(buf).header.vlrs.get("ExtraBytesVlr")[0].record_data_bytes()
