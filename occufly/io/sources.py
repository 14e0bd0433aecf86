"""What ``occufly import SOURCE`` reads: the project kind, its reader, and the CRS rules.

Kinds (``--format`` forces one; otherwise detected in this order):

- ``metashape``: SOURCE is a Metashape camera XML (``<document>`` / ``<chunk>`` root), or a
  folder holding exactly one;
- ``odm``: SOURCE has ``opensfm/reconstruction.json``, or ``cameras.json`` +
  ``odm_report/shots.geojson`` (WebODM all-assets download);
- ``pix4d``: SOURCE is, or has under ``params/`` / ``1_initial/params/``, a
  ``*_calibrated_camera_parameters.txt``;
- ``colmap``: a COLMAP model in SOURCE, ``SOURCE/sparse`` or ``SOURCE/sparse/0``.

CRS. The scene's CRS is the cloud's: the LAS/LAZ CRS record (WKT or GeoTIFF keys), a side-car
``.prj`` of a PLY, else ``--crs``, else the CRS the tool exports its clouds in (ODM's UTM zone,
Metashape's ``<reference>``, Pix4D's ``_wkt.prj``). The cameras are brought from the
project's frame into that CRS exactly (:mod:`occufly.io.crs`). A COLMAP model, or a Pix4D
project without ``.prj``, is taken to be in the cloud's frame already. Cameras in a local
frame (Metashape ``LOCAL_CS``) and a cloud with a real CRS cannot be related: an error
naming both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.io import crs as crsmod
from occufly.io.colmap import SparseModel, find_sparse_dir, read_sparse_model
from occufly.io.metashape import find_metashape_xml
from occufly.io.odm import is_odm_project
from occufly.io.pix4d import find_pix4d_params

FORMATS = ("colmap", "odm", "metashape", "pix4d")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


def detect_format(source: str | Path) -> str:
    """The kind of project at ``source`` (see the module docstring) or a clear error."""
    source = Path(source)
    if not source.exists():
        raise InputFormatError(f"{source}: reconstruction folder not found")
    if find_metashape_xml(source) is not None:
        return "metashape"
    if is_odm_project(source):
        return "odm"
    if find_pix4d_params(source) is not None:
        return "pix4d"
    if source.is_dir():
        try:
            find_sparse_dir(source)
            return "colmap"
        except InputFormatError as e:
            raise InputFormatError(
                f"{e}; nor is it an OpenDroneMap project (opensfm/reconstruction.json, or "
                f"cameras.json + odm_report/shots.geojson), a Metashape camera XML or a Pix4D "
                f"project (1_initial/params/*_calibrated_camera_parameters.txt); --format "
                f"{'|'.join(FORMATS)} forces one") from None
    raise InputFormatError(
        f"{source}: not a project OccuFly recognises: a file must be a Metashape camera XML or "
        f"a Pix4D *_calibrated_camera_parameters.txt; --format {'|'.join(FORMATS)} forces one")


def read_source(source: str | Path, fmt: str | None = None, *,
                images: Path | None = None) -> SparseModel:
    """Read the project at ``source`` as ``fmt`` (detected when None) -> SparseModel."""
    source = Path(source)
    if fmt is not None and fmt not in FORMATS:
        raise InputFormatError(f"--format {fmt!r}: expected one of {', '.join(FORMATS)}")
    kind = fmt or detect_format(source)
    if kind == "colmap":
        model = read_sparse_model(source)
    elif kind == "odm":
        from occufly.io.odm import read_odm

        model = read_odm(source, images=images)
    elif kind == "metashape":
        from occufly.io.metashape import find_metashape_xml, read_metashape

        xml = find_metashape_xml(source)
        if xml is None:
            raise InputFormatError(f"{source}: not a Metashape camera XML (expected a <document> "
                                   f"or <chunk> root, or a folder holding one .xml)")
        model = read_metashape(xml)
        if model.default_images is None and (xml.parent / "images").is_dir():
            model.default_images = xml.parent / "images"
        if model.default_cloud is None:
            model.default_cloud = find_cloud_beside(xml)
    else:
        from occufly.io.pix4d import read_pix4d

        model = read_pix4d(source)
        root = model.path.parent.parent
        root = root.parent if root.name == "1_initial" else root
        if (root / "images").is_dir():
            model.default_images = root / "images"
    check_image_names(model)
    return model


CLOUD_SUFFIXES = (".las", ".laz", ".ply")


def find_cloud_beside(xml: Path) -> Path | None:
    """The dense cloud exported beside a camera XML (Metashape "Export Cameras" + "Export
    Point Cloud" into one folder): the one ``.las``/``.laz``/``.ply`` file in the XML's
    folder, None when there is none, an error listing them when there are several."""
    folder = xml.parent
    found = sorted(p for p in folder.iterdir()
                   if p.is_file() and p.suffix.lower() in CLOUD_SUFFIXES) if folder.is_dir() else []
    if len(found) > 1:
        raise InputFormatError(
            f"{folder}: several point clouds beside {xml.name} ({', '.join(p.name for p in found)}); "
            f"pass the dense cloud with --cloud")
    return found[0] if found else None


def check_image_names(model: SparseModel) -> None:
    """Image names come from the project files: they must stay inside the image folder
    (relative, no '..', no NUL) and name each frame once."""
    seen: dict[str, int] = {}
    for im in model.images:
        n = im.name
        parts = Path(n).parts
        if (not n or "\x00" in n or Path(n).is_absolute() or ".." in parts
                or n.startswith(("/", "\\")) or "\\" in n):
            raise InputFormatError(
                f"{model.path}: image name {n!r} is not a relative path inside the image folder")
        seen[n] = seen.get(n, 0) + 1
    dup = [n for n, c in seen.items() if c > 1]
    if dup:
        raise InputFormatError(
            f"{model.path}: {len(dup)} image name(s) used by several cameras "
            f"({', '.join(dup[:5])}); each frame needs its own image")


def resolve_image_names(image_dir: Path, model: SparseModel) -> None:
    """Metashape labels images without their extension: map ``label`` to ``label.JPG`` etc.

    Names that are files already are kept; the importer reports the ones still missing.
    """
    try:
        by_stem: dict[str, str] = {}
        for p in image_dir.iterdir():
            if p.suffix.lower() in IMAGE_SUFFIXES:
                by_stem.setdefault(p.stem, p.name)
    except OSError:
        return
    for im in model.images:
        if not (image_dir / im.name).is_file() and im.name in by_stem:
            im.name = by_stem[im.name]


def into_cloud_crs(model: SparseModel, cloud_path: Path | None, crs_override: str | None
                   ) -> tuple[object | None, dict]:
    """Bring the model's cameras (and sparse points) into the cloud's CRS, in place.

    Returns (the scene's CRS or None, a dict describing what was done for scene.meta).
    """
    given = crsmod.parse_crs(crs_override, "--crs") if crs_override else None
    info: dict = {"cameras_crs": crsmod.crs_label(model.crs) if model.crs is not None else
                  ("local" if model.local_frame else "as the cloud")}
    if cloud_path is not None:
        declared, where = crsmod.cloud_crs(cloud_path)
        if declared is not None and given is not None and not crsmod.same_crs(declared, given):
            raise InputFormatError(
                f"{cloud_path}: declares {crsmod.crs_label(declared)} ({where}) but --crs says "
                f"{crsmod.crs_label(given)}")
        target = declared or given or model.output_crs
        info["cloud_crs_from"] = (where if declared is not None else "--crs" if given is not None
                                  else f"{model.kind} project" if target is not None else None)
        cloud_name = str(cloud_path)
    else:  # the sparse points are the cloud: they are in the model's frame
        target = given or (model.output_crs if model.output_crs is not None else model.crs)
        info["cloud_crs_from"] = f"{model.kind} project" if target is not None else None
        cloud_name = f"the sparse points of {model.path}"
    if target is not None and target.is_geographic and cloud_path is None and model.kind != "colmap":
        looked = (f"no {'/'.join(CLOUD_SUFFIXES)} file beside {model.path.name} in "
                  f"{model.path.parent}" if model.kind == "metashape"
                  else f"no dense cloud in the {model.kind} project")
        raise InputFormatError(
            f"{model.path}: {looked}, so the sparse points would be the cloud, and they are in "
            f"the project's CRS {crsmod.crs_label(target)}, which is geographic (degrees): export "
            f"the dense cloud in a projected CRS (e.g. UTM) next to the XML or pass it with --cloud")
    if target is not None and target.is_geographic:
        raise InputFormatError(
            f"{cloud_name}: its CRS {crsmod.crs_label(target)} is geographic (degrees); the "
            f"scene needs metres: export the cloud in a projected CRS (e.g. UTM) or pass --crs")
    if model.crs is None:
        if model.local_frame and target is not None and cloud_path is not None:
            raise InputFormatError(
                f"{model.path}: the cameras are in a local frame (no CRS) but {cloud_name} is in "
                f"{crsmod.crs_label(target)}: there is no way to relate the two; export the "
                f"cloud in the project's local coordinates or georeference the project")
        info["cameras_transformed"] = False
        return target, info
    if target is None:
        raise InputFormatError(
            f"{cloud_name}: declares no CRS but the cameras of {model.path} are in "
            f"{crsmod.crs_label(model.crs)}: pass the cloud's CRS with --crs (e.g. EPSG:32633)")
    if crsmod.same_crs(model.crs, target):
        info["cameras_transformed"] = False
        return target, info
    fn = crsmod.crs_mapping(model.crs, target)
    Ts, scale = crsmod.map_poses([im.T_cam_world for im in model.images], fn)
    for im, T in zip(model.images, Ts, strict=True):
        im.T_cam_world = T
    if len(model.xyz):
        model.xyz = fn(np.asarray(model.xyz, np.float64))
    info["cameras_transformed"] = True
    info["mapping_scale"] = [float(scale.min()), float(scale.max())]
    model.crs = target
    return target, info
