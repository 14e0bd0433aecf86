"""PLY point clouds: a small, vectorised reader/writer for the ``vertex`` element.

Reads ascii, binary_little_endian and binary_big_endian files with any scalar vertex
properties (float/double/uchar/... and their ``float32``-style aliases); elements after the
vertex block (faces) are ignored. Large binary files are memory-mapped.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.fsutil import atomic_write_bytes

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_NP_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int",
              "u4": "uint", "f4": "float", "f8": "double"}


@dataclass
class PlyVertices:
    """The vertex element of a PLY file. data: structured array, one field per property."""

    path: Path
    data: np.ndarray

    @property
    def count(self) -> int:
        return len(self.data)

    @property
    def names(self) -> tuple[str, ...]:
        return self.data.dtype.names or ()

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) float64 coordinates."""
        missing = [n for n in "xyz" if n not in self.names]
        if missing:
            raise InputFormatError(
                f"{self.path}: PLY vertices have no {'/'.join(missing)} property "
                f"(found: {', '.join(self.names) or 'none'}); expected x, y, z coordinates"
            )
        return np.column_stack([np.asarray(self.data[n], dtype=np.float64) for n in "xyz"])

    @property
    def rgb(self) -> np.ndarray | None:
        """(N, 3) uint8 colours, or None."""
        for names in (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
            if all(n in self.names for n in names):
                cols = [np.asarray(self.data[n]) for n in names]
                if cols[0].dtype.kind == "f":
                    cols = [np.clip(c * (255.0 if c.max(initial=0) <= 1.0 else 1.0), 0, 255) for c in cols]
                return np.column_stack(cols).astype(np.uint8)
        return None

    @property
    def normals(self) -> np.ndarray | None:
        if all(n in self.names for n in ("nx", "ny", "nz")):
            return np.column_stack([np.asarray(self.data[n], dtype=np.float32) for n in ("nx", "ny", "nz")])
        return None

    def field(self, name: str) -> np.ndarray | None:
        return np.asarray(self.data[name]) if name in self.names else None


def read_ply(path: str | Path) -> PlyVertices:
    path = Path(path)
    if not path.is_file():
        raise InputFormatError(f"{path}: point cloud file not found")
    with open(path, "rb") as f:
        first = f.readline()
        if first.strip() != b"ply":
            raise InputFormatError(f"{path}: not a PLY file (first line is not 'ply')")
        fmt = None
        elements: list[tuple[str, int, list[tuple[str, str]]]] = []
        while True:
            line = f.readline()
            if not line:
                raise InputFormatError(f"{path}: PLY header has no end_header")
            tok = line.decode("ascii", "replace").split()
            if not tok or tok[0] in ("comment", "obj_info"):
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append((tok[1], int(tok[2]), []))
            elif tok[0] == "property":
                if not elements:
                    raise InputFormatError(f"{path}: property before any element")
                if tok[1] == "list":
                    elements[-1][2].append((tok[-1], "list"))
                else:
                    if tok[1] not in _PLY_TYPES:
                        raise InputFormatError(f"{path}: unknown PLY property type {tok[1]!r}")
                    elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
            elif tok[0] == "end_header":
                break
        offset = f.tell()
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputFormatError(f"{path}: unsupported PLY format {fmt!r}")
    vertex = [e for e in elements if e[0] == "vertex"]
    if not vertex:
        raise InputFormatError(f"{path}: PLY has no vertex element")
    before = elements[: elements.index(vertex[0])]
    if before:
        raise InputFormatError(f"{path}: elements before 'vertex' are not supported")
    _, count, props = vertex[0]
    if any(t == "list" for _, t in props):
        raise InputFormatError(f"{path}: list properties in the vertex element are not supported")
    if fmt == "ascii":
        dtype = np.dtype([(n, t) for n, t in props])
        try:
            table = np.loadtxt(path, skiprows=_header_lines(path), max_rows=count, ndmin=2)
        except ValueError as e:
            raise InputFormatError(f"{path}: malformed ASCII PLY body ({e})") from None
        if table.shape != (count, len(props)):
            raise InputFormatError(f"{path}: expected {count} vertices with {len(props)} values")
        data = np.empty(count, dtype=dtype)
        for i, (n, _t) in enumerate(props):
            data[n] = table[:, i]
        return PlyVertices(path, data)
    endian = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, endian + t) for n, t in props])
    size = path.stat().st_size
    if offset + count * dtype.itemsize > size:
        raise InputFormatError(
            f"{path}: truncated: header announces {count} vertices "
            f"({count * dtype.itemsize} bytes) but the file has {size - offset}"
        )
    data = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(count,)) if count else np.zeros(0, dtype)
    return PlyVertices(path, data)


def _header_lines(path: Path) -> int:
    n = 0
    with open(path, "rb") as f:
        for line in f:
            n += 1
            if line.strip() == b"end_header":
                return n
    return n


def write_ply(path: str | Path, fields: dict[str, np.ndarray]) -> None:
    """Write a binary little-endian PLY with one vertex property per entry of ``fields``."""
    names = list(fields)
    if not names:
        raise ValueError("write_ply needs at least one field")
    n = len(fields[names[0]])
    dtype = np.dtype([(k, np.asarray(v).dtype.newbyteorder("<")) for k, v in fields.items()])
    data = np.empty(n, dtype=dtype)
    for k, v in fields.items():
        if len(v) != n:
            raise ValueError(f"field {k} has {len(v)} values, expected {n}")
        data[k] = v
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    for k in names:
        code = dtype[k].str.lstrip("<>|=")
        lines.append(f"property {_NP_TO_PLY[code]} {k}")
    lines.append("end_header")
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode() + data.tobytes())
