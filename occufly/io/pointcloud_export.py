"""Semantic point cloud export in the original (georeferenced) coordinates.

``xyz_world = scene.origin + xyz`` in float64, so UTM coordinates survive.

- PLY (binary little endian): ``x, y, z`` double, ``red, green, blue`` uchar (point colours),
  ``label`` uchar (raw class id, 0 = unlabelled), ``confidence`` float, ``origin`` uchar
  (0 none, 1 direct, 2 filled, 3 denoised) when given.
- LAS / LAZ 1.4, point format 7 (8-bit classification, RGB): ``classification`` = raw class
  id, RGB scaled to 16 bit, offsets = floor of the minimum, scales 0.001 (millimetres). LAZ
  is compressed with laspy's lazrs backend. The taxonomy's ids are written verbatim (they are
  not the ASPRS codes); ``user_data`` holds the label origin. When the scene's cloud was a
  LAS/LAZ whose point format can hold these fields (7, 8, 10; or 2, 3, 5 with 5-bit
  classification when every id is <= 31) that format is kept.

CRS: the scene's CRS (the imported cloud's) goes into the LAS/LAZ as a WKT VLR (laspy
``add_crs``); a PLY gets a side-car ``<name>.prj`` (ESRI WKT) and header comments naming the
CRS and the scene origin (``comment origin x y z``: scene-local = world - origin).

Writes are atomic: a temporary file in the target folder, renamed into place when complete;
the files get ordinary permissions (0666 minus the umask, 0644 usually), not mkstemp's 0600.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.fsutil import fsync_dir, ordinary_mode

LAS_SCALE = 0.001


def _tmp_for(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _finish(tmp: Path, path: Path) -> None:
    os.chmod(tmp, ordinary_mode())
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def _check(xyz_world: np.ndarray, labels: np.ndarray, rgb: np.ndarray | None,
           extra: dict[str, np.ndarray | None]) -> int:
    xyz_world = np.asarray(xyz_world)
    if xyz_world.ndim != 2 or xyz_world.shape[1] != 3:
        raise ValueError(f"xyz_world must be (N, 3), got {xyz_world.shape}")
    n = len(xyz_world)
    if np.asarray(labels).shape != (n,):
        raise ValueError(f"labels must be ({n},), got {np.asarray(labels).shape}")
    if rgb is not None and np.asarray(rgb).shape != (n, 3):
        raise ValueError(f"rgb must be ({n}, 3), got {np.asarray(rgb).shape}")
    for k, v in extra.items():
        if v is not None and np.asarray(v).shape != (n,):
            raise ValueError(f"{k} must be ({n},), got {np.asarray(v).shape}")
    return n


def write_semantic_ply(path: str | Path, xyz_world: np.ndarray, labels: np.ndarray,
                       rgb: np.ndarray | None = None, confidence: np.ndarray | None = None,
                       origin: np.ndarray | None = None, *, chunk: int = 2_000_000,
                       crs=None, scene_origin: np.ndarray | None = None) -> None:
    """xyz_world: (N, 3) float64 georeferenced metres; labels: (N,) uint8 raw ids;
    rgb: (N, 3) uint8; confidence: (N,) float32; origin: (N,) uint8 label origin;
    crs: pyproj CRS (side-car .prj + comment); scene_origin: (3,) float64 for the comment."""
    path = Path(path)
    n = _check(xyz_world, labels, rgb, {"confidence": confidence, "origin": origin})
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    fields.append(("label", "u1"))
    if confidence is not None:
        fields.append(("confidence", "<f4"))
    if origin is not None:
        fields.append(("origin", "u1"))
    ply_type = {"<f8": "double", "<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment OccuFly semantic point cloud",
              "comment coordinates: original georeferenced metres"]
    if crs is not None:
        code = crs.to_epsg(min_confidence=70)
        header.append(f"comment crs {crs.name}" + (f" (EPSG:{code})" if code else ""))
    if scene_origin is not None:
        header.append("comment origin " + " ".join(repr(float(v)) for v in scene_origin))
    header.append(f"element vertex {n}")
    header += [f"property {ply_type[t]} {name}" for name, t in fields]
    header.append("end_header")
    dt = np.dtype(fields)
    tmp = _tmp_for(path)
    try:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            for a in range(0, n, chunk):
                b = min(n, a + chunk)
                rec = np.empty(b - a, dtype=dt)
                xyz = np.asarray(xyz_world[a:b], dtype=np.float64)
                rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
                if rgb is not None:
                    c = np.asarray(rgb[a:b])
                    rec["red"], rec["green"], rec["blue"] = c[:, 0], c[:, 1], c[:, 2]
                rec["label"] = np.asarray(labels[a:b])
                if confidence is not None:
                    rec["confidence"] = np.asarray(confidence[a:b])
                if origin is not None:
                    rec["origin"] = np.asarray(origin[a:b])
                f.write(rec.tobytes())
        if crs is not None:
            _write_prj(path.with_suffix(".prj"), crs)
        _finish(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_prj(path: Path, crs) -> None:
    """ESRI-style WKT (what GIS tools read from a .prj), atomically."""
    try:
        text = crs.to_wkt(version="WKT1_ESRI")
    except Exception:  # noqa: BLE001 - pyproj: not every CRS has an ESRI form
        text = crs.to_wkt()
    tmp = _tmp_for(path)
    try:
        tmp.write_text(text)
        _finish(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_semantic_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read back a binary little-endian PLY written by :func:`write_semantic_ply`."""
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputFormatError(f"{path}: not a PLY file")
        n = 0
        fields = []
        types = {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4", "uint": "<u4"}
        while True:
            line = f.readline()
            if not line:
                raise InputFormatError(f"{path}: PLY header has no end_header")
            parts = line.decode("ascii").split()
            if parts[:1] == ["format"] and parts[1] != "binary_little_endian":
                raise InputFormatError(f"{path}: expected binary_little_endian PLY")
            if parts[:2] == ["element", "vertex"]:
                n = int(parts[2])
            elif parts[:1] == ["property"]:
                fields.append((parts[2], types[parts[1]]))
            elif parts[:1] == ["end_header"]:
                break
        data = np.fromfile(f, dtype=np.dtype(fields), count=n)
    return {name: data[name] for name, _ in fields}


RGB_FORMATS = (7, 8, 10)
LEGACY_RGB_FORMATS = (2, 3, 5)  # 5-bit classification


def choose_point_format(input_format: int | None, labels: np.ndarray) -> int:
    """The input cloud's LAS point format if it can hold RGB + our class ids, else 7."""
    if input_format in RGB_FORMATS:
        return int(input_format)
    if input_format in LEGACY_RGB_FORMATS and (not len(labels) or int(np.max(labels)) <= 31):
        return int(input_format)
    return 7


def write_semantic_las(path: str | Path, xyz_world: np.ndarray, labels: np.ndarray,
                       rgb: np.ndarray | None = None, origin: np.ndarray | None = None, *,
                       compress: bool | None = None, crs=None, point_format: int = 7) -> None:
    """LAS/LAZ (1.4 for formats >= 6, else 1.2); ``compress`` defaults to the ``.laz`` suffix.

    xyz_world: (N, 3) float64 georeferenced metres; labels: (N,) uint8 raw ids;
    rgb: (N, 3) uint8; origin: (N,) uint8 label origin (stored in user_data);
    crs: pyproj CRS written as the file's CRS record; point_format: see
    :func:`choose_point_format`.
    """
    import laspy

    path = Path(path)
    n = _check(xyz_world, labels, rgb, {"origin": origin})
    if compress is None:
        compress = path.suffix.lower() == ".laz"
    if point_format not in RGB_FORMATS + LEGACY_RGB_FORMATS:
        raise ValueError(f"point_format {point_format}: expected one of "
                         f"{RGB_FORMATS + LEGACY_RGB_FORMATS}")
    xyz = np.asarray(xyz_world, dtype=np.float64)
    hdr = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    if crs is not None:
        hdr.add_crs(crs)
    mn = np.floor(xyz.min(axis=0)) if n else np.zeros(3)
    hdr.offsets = mn
    hdr.scales = np.array([LAS_SCALE] * 3)
    las = laspy.LasData(hdr)
    # integer coordinates directly: round to the millimetre grid, no float drift
    las.X = np.rint((xyz[:, 0] - mn[0]) / LAS_SCALE).astype(np.int32)
    las.Y = np.rint((xyz[:, 1] - mn[1]) / LAS_SCALE).astype(np.int32)
    las.Z = np.rint((xyz[:, 2] - mn[2]) / LAS_SCALE).astype(np.int32)
    las.classification = np.asarray(labels, dtype=np.uint8)
    if rgb is not None:
        c = np.asarray(rgb, dtype=np.uint16) * 257
        las.red, las.green, las.blue = c[:, 0], c[:, 1], c[:, 2]
    if origin is not None:
        las.user_data = np.asarray(origin, dtype=np.uint8)
    tmp = _tmp_for(path)
    try:
        with open(tmp, "wb") as f:
            las.write(f, do_compress=compress)
        _finish(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _input_point_format(scene) -> int | None:
    """The LAS point format of the cloud the scene was imported from, if it was LAS/LAZ."""
    cloud = (scene.meta or {}).get("cloud")
    if not cloud or Path(cloud).suffix.lower() not in (".las", ".laz") or not Path(cloud).is_file():
        return None
    import laspy

    try:
        with laspy.open(cloud) as f:
            return int(f.header.point_format.id)
    except Exception:  # noqa: BLE001 - the source may have changed since the import; not fatal
        return None


def export_scene_points(scene, labels: np.ndarray, out: str | Path, *,
                        confidence: np.ndarray | None = None,
                        origin: np.ndarray | None = None) -> dict:
    """Write the scene's points with ``labels`` to ``out`` (.ply, .las or .laz) in world coords,
    with the scene's CRS (LAS record / PLY side-car .prj)."""
    from occufly.io.crs import crs_from_record, crs_label

    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".ply", ".las", ".laz"):
        raise InputFormatError(f"{out}: unsupported export format {suffix!r}; expected .ply, .las or .laz")
    xyz_world = scene.xyz_world()
    rgb = np.asarray(scene.rgb)
    crs = crs_from_record(getattr(scene, "crs", None))
    extra: dict = {}
    if suffix == ".ply":
        write_semantic_ply(out, xyz_world, labels, rgb, confidence, origin, crs=crs,
                           scene_origin=scene.origin)
        if crs is not None:
            extra["prj"] = str(out.with_suffix(".prj"))
    else:
        fmt = choose_point_format(_input_point_format(scene), np.asarray(labels))
        write_semantic_las(out, xyz_world, labels, rgb, origin, crs=crs, point_format=fmt)
        extra["point_format"] = fmt
    counts = np.bincount(np.asarray(labels), minlength=256)
    return {"path": str(out), "format": suffix.lstrip("."), "points": int(len(labels)),
            "crs": crs_label(crs) if crs is not None else None, **extra,
            "labelled": int(len(labels) - counts[0]),
            "classes": {scene.taxonomy[int(i)].name: int(counts[i])
                        for i in np.flatnonzero(counts) if int(i) in scene.taxonomy}}
