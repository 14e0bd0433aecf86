"""Semantic point cloud export in the original (georeferenced) coordinates.

``xyz_world = scene.origin + xyz`` in float64, so UTM coordinates survive.

- PLY (binary little endian): ``x, y, z`` double, ``red, green, blue`` uchar (point colours),
  ``label`` uchar (raw class id, 0 = unlabelled), ``confidence`` float, ``origin`` uchar
  (0 none, 1 direct, 2 filled, 3 denoised) when given.
- LAS / LAZ 1.4, point format 7 (8-bit classification, RGB), scales 0.001 (millimetres),
  offsets = floor of the minimum; LAZ is compressed with laspy's lazrs backend. With the
  scene's taxonomy (every export of labels):

  - ``classification`` = the class's **ASPRS LAS 1.4 code** where it has one (ground 2,
    low/medium/high vegetation 3/4/5, building 6, water 9, road surface 11, wire 14,
    transmission tower 15, ...); classes without get user-definable codes 64, 65, ... in table
    order; unlabelled points are 1 (unclassified). :meth:`Taxonomy.asprs_lut` decides.
  - extra dimension ``class_id`` (uint8) = the full taxonomy id (0 = unlabelled), so no
    class is lost where several share an ASPRS code (building and roof are both 6);
    ``confidence`` (uint8, scale 1/255) when given.
  - ``user_data`` = the label origin (0 none, 1 direct, 2 filled, 3 denoised, 4 corrected).
  - VLRs: the LAS 1.4 *Classification Lookup* (``LASF_Spec`` / 0: code and a 15-character
    description per code used) and ``OccuFly`` / 1, the class table as JSON (taxonomy name;
    per class id, name, ASPRS code, RGB, group; what the extra dimensions and user_data mean).

  Without a taxonomy (the synthetic tools' *input* clouds) ``classification`` holds the raw
  id. A scene whose cloud was LAS/LAZ of point format 8 or 10 keeps that format (NIR kept);
  every other gives 7.
- COPC (``.copc.laz``): the same point records and class table, in a cloud-optimized octree
  for Potree, QGIS and PDAL, written by copc-lib (:mod:`occufly.io.copc`).

CRS: the scene's CRS (the imported cloud's) goes into the LAS/LAZ as a WKT VLR (laspy
``add_crs``); a PLY gets a side-car ``<name>.prj`` (ESRI WKT) and header comments naming the
CRS and the scene origin (``comment origin x y z``: scene-local = world - origin).

Writes are atomic: a temporary file in the target folder, renamed into place when complete;
the files get ordinary permissions (0666 minus the umask, 0644 usually), not mkstemp's 0600.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import laspy
import numpy as np

from occufly.errors import InputFormatError
from occufly.fsutil import fsync_dir, ordinary_mode
from occufly.io.copc import write_copc
from occufly.io.crs import crs_from_record, crs_label
from occufly.taxonomy import ASPRS_NAMES, ASPRS_UNCLASSIFIED

LAS_SCALE = 0.001
COPC_SUFFIX = ".copc.laz"
OCCUFLY_VLR_USER = "OccuFly"
CLASS_TABLE_RECORD = 1


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


def choose_point_format(input_format: int | None, labels: np.ndarray, *,
                        asprs: bool = False) -> int:
    """The input cloud's LAS point format if it can hold RGB + our fields, else 7.

    ``asprs``: the output carries ASPRS codes, user codes 64+ and extra dimensions, which only
    LAS 1.4 point formats 6-10 hold: the legacy 5-bit formats (2, 3, 5) give 7."""
    if input_format in RGB_FORMATS:
        return int(input_format)
    if (not asprs and input_format in LEGACY_RGB_FORMATS
            and (not len(labels) or int(np.max(labels)) <= 31)):
        return int(input_format)
    return 7


def write_semantic_las(path: str | Path, xyz_world: np.ndarray, labels: np.ndarray,
                       rgb: np.ndarray | None = None, origin: np.ndarray | None = None, *,
                       compress: bool | None = None, crs=None, point_format: int = 7,
                       taxonomy=None, confidence: np.ndarray | None = None) -> dict:
    """LAS/LAZ (1.4 for formats >= 6, else 1.2) or COPC (``.copc.laz``); ``compress``
    defaults to the ``.laz`` suffix.

    xyz_world: (N, 3) float64 georeferenced metres; labels: (N,) uint8 raw ids;
    rgb: (N, 3) uint8; origin: (N,) uint8 label origin (stored in user_data);
    crs: pyproj CRS written as the file's CRS record; point_format: see
    :func:`choose_point_format`; taxonomy: write ASPRS codes, the ``class_id`` (and
    ``confidence``) extra dimensions and the class table (module docstring).
    Returns what was written beyond the points (COPC nodes).
    """
    path = Path(path)
    n = _check(xyz_world, labels, rgb, {"origin": origin, "confidence": confidence})
    copc = path.name.lower().endswith(COPC_SUFFIX)
    if compress is None:
        compress = path.suffix.lower() == ".laz"
    if point_format not in RGB_FORMATS + LEGACY_RGB_FORMATS:
        raise ValueError(f"point_format {point_format}: expected one of "
                         f"{RGB_FORMATS + LEGACY_RGB_FORMATS}")
    if taxonomy is not None and point_format < 6:
        raise ValueError(f"point_format {point_format} cannot hold ASPRS user codes and extra "
                         f"dimensions; use 7")
    if copc and point_format not in (6, 7, 8):
        point_format = 7  # COPC allows 6, 7, 8 only
    labels = np.asarray(labels, dtype=np.uint8)
    xyz = np.asarray(xyz_world, dtype=np.float64)
    hdr = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    if taxonomy is not None:
        dims = [laspy.ExtraBytesParams("class_id", "u1", description="OccuFly class id")]
        if confidence is not None:
            dims.append(laspy.ExtraBytesParams("confidence", "u1",
                                               description="label confidence 0..1",
                                               scales=np.array([1 / 255]),
                                               offsets=np.array([0.0])))
        hdr.add_extra_dims(dims)
    class_vlrs = _class_vlrs(taxonomy, labels, confidence is not None) if taxonomy is not None else []
    if crs is not None and not copc:
        hdr.add_crs(crs)
    if not copc:
        hdr.vlrs.extend(class_vlrs)
    mn = np.floor(xyz.min(axis=0)) if n else np.zeros(3)
    hdr.offsets = mn
    hdr.scales = np.array([LAS_SCALE] * 3)
    las = laspy.LasData(hdr)
    # integer coordinates directly: round to the millimetre grid, no float drift
    las.X = np.rint((xyz[:, 0] - mn[0]) / LAS_SCALE).astype(np.int32)
    las.Y = np.rint((xyz[:, 1] - mn[1]) / LAS_SCALE).astype(np.int32)
    las.Z = np.rint((xyz[:, 2] - mn[2]) / LAS_SCALE).astype(np.int32)
    if taxonomy is not None:
        las.classification = taxonomy.asprs_lut()[labels]
        las.class_id = labels
        if confidence is not None:
            las.confidence = np.clip(np.asarray(confidence, np.float64), 0.0, 1.0)
    else:
        las.classification = labels
    if rgb is not None:
        c = np.asarray(rgb, dtype=np.uint16) * 257
        las.red, las.green, las.blue = c[:, 0], c[:, 1], c[:, 2]
    if origin is not None:
        las.user_data = np.asarray(origin, dtype=np.uint8)
    if copc:
        return write_copc(path, las, wkt=crs.to_wkt() if crs is not None else None,
                          extra_vlrs=class_vlrs)
    tmp = _tmp_for(path)
    try:
        with open(tmp, "wb") as f:
            las.write(f, do_compress=compress)
        _finish(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return {}


def _class_vlrs(taxonomy, labels: np.ndarray, with_confidence: bool) -> list:
    """The LAS 1.4 Classification Lookup VLR and the OccuFly class-table VLR."""
    lut = taxonomy.asprs_lut()
    entries: dict[int, str] = {ASPRS_UNCLASSIFIED: ASPRS_NAMES[ASPRS_UNCLASSIFIED]}
    for c in taxonomy.classes:
        code = int(lut[c.id])
        entries.setdefault(code, ASPRS_NAMES.get(code, c.name) if c.asprs is not None else c.name)
    lookup = laspy.vlrs.known.ClassificationLookupVlr()
    lookup.lookups = {code: name.encode("ascii", "replace")[:15].decode()
                      for code, name in sorted(entries.items())}
    table = {
        "taxonomy": taxonomy.name,
        "classification": "ASPRS LAS 1.4 code; 64+ = user-definable code of a class with none",
        "unlabelled_code": ASPRS_UNCLASSIFIED,
        "extra_dimensions": {"class_id": "OccuFly class id (0 = unlabelled)",
                             **({"confidence": "label confidence 0..1 (uint8, scale 1/255)"}
                                if with_confidence else {})},
        "user_data": "label origin: 0 none, 1 direct, 2 filled, 3 denoised, 4 corrected",
        "classes": [{"id": c.id, "name": c.name, "asprs": int(lut[c.id]),
                     "asprs_standard": c.asprs is not None, "rgb": list(c.rgb), "group": c.group}
                    for c in taxonomy.classes],
    }
    return [lookup,
            laspy.VLR(OCCUFLY_VLR_USER, CLASS_TABLE_RECORD, "OccuFly class table (JSON)",
                      json.dumps(table, separators=(",", ":")).encode())]


def read_class_table(path: str | Path) -> dict | None:
    """The OccuFly class table of a LAS/LAZ/COPC file written here (VLR or EVLR), or None."""
    with laspy.open(path) as f:
        records = list(f.header.vlrs) + list(f.header.evlrs or [])
    for v in records:
        if v.user_id == OCCUFLY_VLR_USER and v.record_id == CLASS_TABLE_RECORD:
            return json.loads(bytes(v.record_data).decode())
    return None


def _input_point_format(scene) -> int | None:
    """The LAS point format of the cloud the scene was imported from, if it was LAS/LAZ."""
    cloud = (scene.meta or {}).get("cloud")
    if not cloud or Path(cloud).suffix.lower() not in (".las", ".laz") or not Path(cloud).is_file():
        return None
    try:
        with laspy.open(cloud) as f:
            return int(f.header.point_format.id)
    except Exception:  # noqa: BLE001 - the source may have changed since the import; not fatal
        return None


def export_scene_points(scene, labels: np.ndarray, out: str | Path, *,
                        confidence: np.ndarray | None = None,
                        origin: np.ndarray | None = None) -> dict:
    """Write the scene's points with ``labels`` to ``out`` (.ply, .las, .laz or .copc.laz) in
    world coords, with the scene's CRS (LAS record / PLY side-car .prj); LAS/LAZ/COPC carry
    ASPRS codes, the class id and confidence and the class table (module docstring)."""
    out = Path(out)
    suffix = ".copc.laz" if out.name.lower().endswith(COPC_SUFFIX) else out.suffix.lower()
    if suffix not in (".ply", ".las", ".laz", ".copc.laz"):
        raise InputFormatError(f"{out}: unsupported export format {suffix!r}; expected .ply, "
                               f".las, .laz or .copc.laz")
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
        fmt = choose_point_format(_input_point_format(scene), np.asarray(labels), asprs=True)
        if suffix == ".copc.laz" and fmt not in (6, 7, 8):
            fmt = 7
        written = write_semantic_las(out, xyz_world, labels, rgb, origin, crs=crs,
                                     point_format=fmt, taxonomy=scene.taxonomy,
                                     confidence=confidence)
        extra["point_format"] = fmt
        if written:
            extra["copc"] = written
        lut = scene.taxonomy.asprs_lut()
        extra["asprs"] = {c.name: int(lut[c.id]) for c in scene.taxonomy.classes}
    counts = np.bincount(np.asarray(labels), minlength=256)
    return {"path": str(out), "format": suffix.lstrip("."), "points": int(len(labels)),
            "crs": crs_label(crs) if crs is not None else None, **extra,
            "labelled": int(len(labels) - counts[0]),
            "classes": {scene.taxonomy[int(i)].name: int(counts[i])
                        for i in np.flatnonzero(counts) if int(i) in scene.taxonomy}}
