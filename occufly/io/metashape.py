"""Agisoft Metashape camera XML ("Export Cameras", or a project's internal ``doc.xml``) ->
:class:`SparseModel`.

Elements read (root ``<document><chunk>`` or, for a project's ``doc.xml``, ``<chunk>``):

- ``<sensors><sensor id type>`` with ``<calibration class="adjusted">`` (else the initial one):
  ``resolution``, ``f``, ``cx``/``cy`` (offsets from the image centre: pixel cx = W/2 + cx,
  Metashape's pixels have the top-left corner at (0, 0) like COLMAP's), ``b1`` (fx = f + b1),
  ``b2`` (skew), ``k1``-``k4``, ``p1``-``p4`` (Metashape's tangential order) -> the
  ``METASHAPE`` camera model, exactly. ``type="fisheye"`` with radial terms only ->
  ``OPENCV_FISHEYE``; spherical / cylindrical / RPC sensors are an error.
- ``<cameras>`` (groups included) ``<camera id sensor_id component_id label enabled>`` with
  ``<transform>``: 16 numbers, row-major camera-to-chunk (x right, y down, z forward). A camera
  without a transform is not aligned; it is skipped like a disabled one, and both are listed.
- ``<components><component><transform>`` (``rotation``, ``translation``, ``scale``): a
  camera's component transform maps it to the world; without one, the chunk ``<transform>``
  does; without either the world is the chunk frame. ``x_world = s R x_chunk + T``.
- ``<reference>``: the CRS as WKT. For a georeferenced chunk the world of the transform is
  geocentric (ECEF, EPSG:4978) and the cloud is normally exported in a projected CRS; for
  ``LOCAL_CS`` the world is a local frame that cannot be related to a georeferenced cloud.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np

from occufly.camera import Camera
from occufly.errors import InputFormatError
from occufly.io import crs as crsmod
from occufly.io.colmap import SparseImage, SparseModel

log = logging.getLogger(__name__)

MAX_XML_BYTES = 512 * 1024**2
_DIST = ("k1", "k2", "k3", "k4", "p1", "p2", "p3", "p4")


def is_metashape_xml(path: Path) -> bool:
    if not path.is_file() or path.suffix.lower() != ".xml":
        return False
    with open(path, "rb") as f:
        head = f.read(4096).decode("utf-8", "replace")
    return "<document" in head or "<chunk" in head


def find_metashape_xml(source: Path) -> Path | None:
    """``source`` itself (an XML or a ``.psx`` project), or the one Metashape XML in a folder."""
    if source.is_file():
        if source.suffix.lower() == ".psx":
            return source
        return source if is_metashape_xml(source) else None
    if source.is_dir():
        found = [p for p in sorted(source.glob("*.xml")) if is_metashape_xml(p)]
        found = found or sorted(p for p in source.glob("*.psx") if p.is_file())
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise InputFormatError(f"{source}: several Metashape XML files "
                                   f"({', '.join(p.name for p in found)}); pass one of them")
    return None


def _floats(text: str | None, n: int, where: str) -> np.ndarray:
    try:
        a = np.array([float(v) for v in (text or "").split()], dtype=np.float64)
    except ValueError:
        raise InputFormatError(f"{where}: expected {n} numbers, got {text!r:.80}") from None
    if a.size != n or not np.isfinite(a).all():
        raise InputFormatError(f"{where}: expected {n} finite numbers, got {a.size}")
    return a


def _similarity(el: ET.Element | None, where: str) -> np.ndarray | None:
    """<transform> with rotation/translation/scale -> (4, 4) similarity, or None."""
    if el is None:
        return None
    rot, tr, sc = el.find("rotation"), el.find("translation"), el.find("scale")
    if rot is None and tr is None and sc is None:
        if el.text and el.text.strip():
            return _floats(el.text, 16, where).reshape(4, 4)
        return None
    R = _floats(rot.text, 9, f"{where} rotation").reshape(3, 3) if rot is not None else np.eye(3)
    t = _floats(tr.text, 3, f"{where} translation") if tr is not None else np.zeros(3)
    s = float(_floats(sc.text, 1, f"{where} scale")[0]) if sc is not None else 1.0
    if s <= 0:
        raise InputFormatError(f"{where}: scale must be positive, got {s}")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        raise InputFormatError(f"{where}: rotation is not orthonormal")
    M = np.eye(4)
    M[:3, :3] = s * R
    M[:3, 3] = t
    return M


def _sensor_camera(sensor: ET.Element, where: str) -> Camera | str:
    """A <sensor> -> Camera, or an error text (raised only if an aligned camera uses it)."""
    stype = sensor.get("type", "frame")
    cals = sensor.findall("calibration")
    cal = next((c for c in cals if c.get("class") == "adjusted"), None) or (cals[0] if cals else None)
    if cal is None:
        return f"{where}: sensor {sensor.get('id')} ({sensor.get('label')!r}) has no <calibration>"
    res = cal.find("resolution")
    if res is None:
        res = sensor.find("resolution")
    if res is None:
        return f"{where}: sensor {sensor.get('id')} has no <resolution>"
    try:
        w, h = int(res.get("width", "0")), int(res.get("height", "0"))
    except ValueError:
        return f"{where}: sensor {sensor.get('id')}: resolution is not integer"

    def val(tag: str) -> float:
        el = cal.find(tag)
        if el is None:
            return 0.0
        return float(_floats(el.text, 1, f"{where}: sensor {sensor.get('id')} <{tag}>")[0])

    if cal.find("f") is None:
        return f"{where}: sensor {sensor.get('id')} ({sensor.get('label')!r}): calibration has no <f>"
    f, cx, cy, b1, b2 = val("f"), val("cx"), val("cy"), val("b1"), val("b2")
    d = [val(k) for k in _DIST]
    if stype == "frame":
        return Camera("METASHAPE", w, h, [f, w / 2.0 + cx, h / 2.0 + cy, b1, b2, *d])
    if stype == "fisheye":
        if any(d[4:]) or b2:
            return (f"{where}: fisheye sensor {sensor.get('id')} has tangential terms or skew, "
                    f"which the fisheye model here does not support")
        return Camera("OPENCV_FISHEYE", w, h, [f + b1, f, w / 2.0 + cx, h / 2.0 + cy, *d[:4]])
    return (f"{where}: sensor {sensor.get('id')} is of type {stype!r}; only frame and fisheye "
            f"cameras are supported")


def _zip_xml(zpath: Path, where: str) -> ET.Element:
    """``doc.xml`` of one of a project's zip files (size-checked before it is inflated)."""
    if not zpath.is_file():
        raise InputFormatError(f"{zpath}: missing ({where})")
    try:
        with zipfile.ZipFile(zpath) as z:
            info = z.getinfo("doc.xml")
            if info.file_size > MAX_XML_BYTES:
                raise InputFormatError(f"{zpath}: doc.xml inflates to {info.file_size} bytes "
                                       f"(limit {MAX_XML_BYTES})")
            data = z.read(info)
    except (zipfile.BadZipFile, KeyError, OSError) as e:
        raise InputFormatError(f"{zpath}: not a Metashape project zip with doc.xml ({e})") from None
    try:
        return ET.fromstring(data)
    except ET.ParseError as e:
        raise InputFormatError(f"{zpath}: doc.xml is not valid XML ({e})") from None


def _read_psx(path: Path) -> tuple[ET.Element, dict[str, Path], list[str]]:
    """A ``.psx`` project -> (its first chunk's <chunk>, {camera id: photo path}, notes).

    Layout: ``<name>.files/project.zip`` lists the chunks (``<chunk id path="0/chunk.zip">``);
    each ``chunk.zip`` holds the chunk's doc.xml; its ``<frames><frame path="0/frame.zip">``
    (relative to the chunk's folder) hold ``<camera camera_id><photo path>`` (relative to the
    frame's folder unless absolute).
    """
    files = path.with_name(path.stem + ".files")
    proj = _zip_xml(files / "project.zip", f"the project zip of {path.name}")
    entries = [c for c in proj.iter("chunk") if c.get("path")]
    if not entries:
        raise InputFormatError(f"{files / 'project.zip'}: the project lists no chunk")
    notes = []
    if len(entries) > 1:
        notes.append(f"{path.name}: {len(entries)} chunks; used the first ({entries[0].get('path')})")
    chunk_zip = files / entries[0].get("path")
    chunk = _zip_xml(chunk_zip, f"chunk {entries[0].get('id')} of {path.name}")
    photos: dict[str, Path] = {}
    frames = chunk.find("frames")
    for fr in (frames.findall("frame") if frames is not None else [])[:1]:
        fz = chunk_zip.parent / fr.get("path", "")
        if not fz.is_file():
            notes.append(f"{fz}: frame zip missing; photos matched by camera label")
            break
        for cam in _zip_xml(fz, "the chunk's frame").iter("camera"):
            ph = cam.find("photo")
            if ph is not None and ph.get("path") and cam.get("camera_id") is not None:
                p = Path(ph.get("path").replace("{projectfolder}", str(path.parent)))
                photos[cam.get("camera_id")] = p if p.is_absolute() else (fz.parent / p)
    return chunk, photos, notes


def read_metashape(path: str | Path) -> SparseModel:
    path = Path(path)
    if not path.is_file():
        raise InputFormatError(f"{path}: Metashape XML not found")
    if path.stat().st_size > MAX_XML_BYTES:
        raise InputFormatError(f"{path}: larger than {MAX_XML_BYTES} bytes")
    photos: dict[str, Path] = {}
    psx_notes: list[str] = []
    if path.suffix.lower() == ".psx":
        root, photos, psx_notes = _read_psx(path)
    else:
        try:
            root = ET.parse(path).getroot()
        except ET.ParseError as e:
            raise InputFormatError(f"{path}: not valid XML ({e})") from None
    if root.tag == "document":
        chunks = root.findall("chunk")
        if not chunks:
            raise InputFormatError(f"{path}: <document> has no <chunk>")
        chunk = chunks[0]
    elif root.tag == "chunk":
        chunks, chunk = [root], root
    else:
        raise InputFormatError(f"{path}: root element <{root.tag}> is not a Metashape "
                               f"<document> or <chunk>")
    notes: list[str] = list(psx_notes)
    if len(chunks) > 1:
        notes.append(f"{path.name}: {len(chunks)} chunks; used the first ({chunk.get('label')!r})")

    sensors: dict[str, Camera | str] = {}
    for s in chunk.iter("sensor"):
        sensors[s.get("id", "")] = _sensor_camera(s, str(path))
    chunk_T = _similarity(chunk.find("transform"), f"{path}: chunk <transform>")
    comps: dict[str, np.ndarray] = {}
    comp_root = chunk.find("components")
    if comp_root is not None:
        for c in comp_root.findall("component"):
            T = _similarity(c.find("transform"), f"{path}: component {c.get('id')} <transform>")
            if T is not None:
                comps[c.get("id", "")] = T
    ref_el = chunk.find("reference")
    ref_text = ref_el.text if ref_el is not None and ref_el.text else None
    ref_crs = crsmod.parse_crs(ref_text, f"{path}: <reference>") if ref_text else None
    local = ref_crs is None

    cam_root = chunk.find("cameras")
    cams = list(cam_root.iter("camera")) if cam_root is not None else []
    images: list[SparseImage] = []
    unaligned, disabled = [], []
    ref_pos = {}
    for c in cams:
        label = c.get("label") or f"camera {c.get('id')}"
        if c.get("enabled", "true").lower() in ("false", "0"):
            disabled.append(label)
            continue
        tr = c.find("transform")
        if tr is None or not (tr.text or "").strip():
            unaligned.append(label)
            continue
        sensor = sensors.get(c.get("sensor_id", ""))
        if sensor is None:
            raise InputFormatError(f"{path}: camera {label!r} refers to unknown sensor "
                                   f"{c.get('sensor_id')!r}")
        if isinstance(sensor, str):
            raise InputFormatError(f"{sensor} (used by camera {label!r})")
        M = _floats(tr.text, 16, f"{path}: camera {label!r} <transform>").reshape(4, 4)
        W = comps.get(c.get("component_id", ""), chunk_T)
        M_world = M if W is None else W @ M  # camera -> world (similarity)
        A = M_world[:3, :3]
        s = np.cbrt(abs(np.linalg.det(A)))
        if s <= 0:
            raise InputFormatError(f"{path}: camera {label!r}: degenerate transform")
        R_wc = A / s
        if not np.allclose(R_wc @ R_wc.T, np.eye(3), atol=1e-5):
            raise InputFormatError(f"{path}: camera {label!r}: transform is not a rotation")
        T = np.eye(4)
        T[:3, :3] = R_wc.T
        T[:3, 3] = -R_wc.T @ M_world[:3, 3]
        photo = photos.get(c.get("id", ""))
        images.append(SparseImage(len(images) + 1, photo.name if photo is not None else label,
                                  sensor, T, np.zeros(0, np.int64), np.zeros((0, 2))))
        r = c.find("reference")
        if r is not None and r.get("x") is not None:
            ref_pos[label] = [float(r.get(k, "nan")) for k in ("x", "y", "z")]
    if unaligned:
        notes.append(f"{path.name}: {len(unaligned)} camera(s) not aligned, skipped: "
                     f"{', '.join(unaligned[:20])}{' ...' if len(unaligned) > 20 else ''}")
    if disabled:
        notes.append(f"{path.name}: {len(disabled)} camera(s) disabled, skipped: "
                     f"{', '.join(disabled[:20])}{' ...' if len(disabled) > 20 else ''}")
    for n in notes:
        log.warning(n)
    if not images:
        raise InputFormatError(f"{path}: no aligned, enabled camera (cameras: {len(cams)})")
    georef = not local and (chunk_T is not None or comps)
    model = SparseModel(
        images, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), path,
        kind="metashape", crs=crsmod.ecef_crs() if georef else None,
        output_crs=ref_crs, local_frame=local, has_tracks=False, notes=notes,
        meta={"reference": crsmod.crs_label(ref_crs), "unaligned": unaligned,
              "disabled": disabled, "reference_positions": ref_pos,
              "chunk_transform": chunk_T.tolist() if chunk_T is not None else None},
    )
    dirs = {photos[c].parent for c in photos}
    if len(dirs) == 1 and next(iter(dirs)).is_dir():
        model.default_images = next(iter(dirs)).resolve()  # where the project's photos are
    if not local and not georef:
        notes.append(f"{path.name}: <reference> is {crsmod.crs_label(ref_crs)} but the chunk has "
                     f"no <transform>: cameras are taken to be in that CRS")
        model.crs = ref_crs
    return model
