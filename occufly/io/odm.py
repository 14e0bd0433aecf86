"""OpenDroneMap / WebODM projects (OpenSfM reconstruction) -> :class:`SparseModel`.

Files read (``SOURCE`` = the ODM project folder):

- ``opensfm/reconstruction.json``: a list of partial reconstructions; the one with the most
  shots is used and the others are reported. Cameras: intrinsics normalised by
  max(width, height), OpenSfM pixel ``u = max(w, h) x + (w - 1) / 2`` (pixel-centre
  convention; COLMAP's is half a pixel further: ``cx = w / 2 + max(w, h) c_x``). Shots:
  axis-angle ``rotation`` and ``translation``, world-to-camera, x right / y down / z forward.
- ``opensfm/reference_lla.json``: the origin of OpenSfM's topocentric (ENU) frame.
- ``odm_georeferencing/coords.txt``: line 1 the UTM zone ('WGS84 UTM 17N'), line 2 the
  offset (easting northing); then the images' GPS positions, UTM minus that offset.
- ``odm_report/shots.geojson``: per shot the UTM camera centre (``translation``) and rotation.
- ``odm_georeferencing/odm_georeferenced_model.laz``: the georeferenced dense cloud (UTM).

Frames. OpenSfM writes topocentric ENU; ODM's georeferencing step then rewrites
``reconstruction.json`` into UTM minus the coords.txt offset (keeping the topocentric one as
``reconstruction.topocentric.json``) but leaves ``gps_position`` topocentric. Which frame the
shots are in is decided from the files, in this order: the shots' centres + offset agree with
``shots.geojson`` to 1 cm; ``reconstruction.topocentric.json`` exists; the shots' centres are
closer to the GPS positions taken as UTM-offset than as topocentric (or the other way round).
Topocentric poses are mapped exactly to ECEF (a rigid transform) and from there by pyproj into
the cloud's CRS; UTM-offset poses get the offset back (UTM, EPSG:326xx/327xx).

A WebODM "all assets" download has no ``opensfm/``: then ``cameras.json`` (intrinsics; its
width/height may be those of downscaled images -- the normalised intrinsics are rescaled to
the real image size: the image file's if present, else the size ``shots.geojson`` records)
and ``odm_report/shots.geojson`` (UTM centres + rotations) are read instead.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from occufly.camera import Camera, make_pose
from occufly.errors import InputFormatError
from occufly.io import crs as crsmod
from occufly.io.colmap import SparseImage, SparseModel

log = logging.getLogger(__name__)

SUPPORTED_PROJECTIONS = ("perspective", "brown", "fisheye", "fisheye_opencv", "simple_radial",
                         "radial")
MAX_JSON_BYTES = 2 * 1024**3


def is_odm_project(source: Path) -> bool:
    return source.is_dir() and (
        (source / "opensfm" / "reconstruction.json").is_file()
        or ((source / "cameras.json").is_file() and (source / "odm_report" / "shots.geojson").is_file())
    )


def _load_json(path: Path):
    if path.stat().st_size > MAX_JSON_BYTES:
        raise InputFormatError(f"{path}: larger than {MAX_JSON_BYTES} bytes; not an ODM file")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputFormatError(f"{path}: not valid JSON ({e})") from None


def _num(d: dict, key: str, where: str, default: float | None = None) -> float:
    v = d.get(key, default)
    if v is None:
        raise InputFormatError(f"{where}: missing {key!r}")
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise InputFormatError(f"{where}: {key!r} is {v!r}, expected a number") from None
    if not np.isfinite(v):
        raise InputFormatError(f"{where}: {key!r} is not finite")
    return v


def opensfm_camera(c: dict, where: str, size: tuple[int, int] | None = None) -> Camera:
    """An OpenSfM camera dict -> :class:`Camera` in COLMAP pixel conventions.

    size: the real (width, height) when the dict's are those of downscaled images.
    """
    if not isinstance(c, dict):
        raise InputFormatError(f"{where}: expected a camera object")
    proj = str(c.get("projection_type", "perspective"))
    if proj not in SUPPORTED_PROJECTIONS:
        raise InputFormatError(
            f"{where}: projection type {proj!r} is not supported (a frame camera is needed: "
            f"{', '.join(SUPPORTED_PROJECTIONS)}); spherical/equirectangular images cannot be "
            f"annotated as frames")
    w, h = int(_num(c, "width", where)), int(_num(c, "height", where))
    if size is not None:
        w, h = int(size[0]), int(size[1])
    if w <= 0 or h <= 0:
        raise InputFormatError(f"{where}: image size {w}x{h} is not positive")
    s = float(max(w, h))
    g = lambda k, d=None: _num(c, k, where, d)  # noqa: E731
    if proj in ("perspective", "fisheye"):
        f = g("focal") * s
        k1, k2 = g("k1", 0.0), g("k2", 0.0)
        if proj == "perspective":
            return Camera("RADIAL", w, h, [f, w / 2.0, h / 2.0, k1, k2])
        return Camera("OPENCV_FISHEYE", w, h, [f, f, w / 2.0, h / 2.0, k1, k2, 0.0, 0.0])
    fx, fy = g("focal_x") * s, g("focal_y") * s
    cx, cy = w / 2.0 + g("c_x", 0.0) * s, h / 2.0 + g("c_y", 0.0) * s
    if proj == "fisheye_opencv":
        return Camera("OPENCV_FISHEYE", w, h, [fx, fy, cx, cy, g("k1", 0.0), g("k2", 0.0),
                                               g("k3", 0.0), g("k4", 0.0)])
    k1, k2 = g("k1", 0.0), g("k2", 0.0) if proj != "simple_radial" else 0.0
    k3, p1, p2 = (g("k3", 0.0), g("p1", 0.0), g("p2", 0.0)) if proj == "brown" else (0.0, 0.0, 0.0)
    return Camera("BROWN", w, h, [fx, fy, cx, cy, 0.0, k1, k2, k3, 0.0, p1, p2])


def _vec3(v, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InputFormatError(f"{where}: expected 3 numbers, got {v!r}") from None
    if not np.isfinite(a).all():
        raise InputFormatError(f"{where}: not finite")
    return a


def _rotvec(v, where: str) -> np.ndarray:
    """Axis-angle (3,) -> (3, 3) rotation matrix."""
    return Rotation.from_rotvec(_vec3(v, where)).as_matrix()


def read_coords(path: Path) -> tuple[object, np.ndarray, np.ndarray]:
    """coords.txt -> (UTM CRS, (3,) offset (e, n, 0), (K, 3) GPS positions minus offset)."""
    lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    if len(lines) < 2:
        raise InputFormatError(f"{path}: expected a UTM zone line and an offset line")
    crs = crsmod.odm_utm_crs(lines[0], path)
    try:
        e, n = (float(v) for v in lines[1].split()[:2])
        gps = np.array([[float(v) for v in ln.split()[:3]] for ln in lines[2:]]).reshape(-1, 3)
    except ValueError:
        raise InputFormatError(f"{path}: offset/GPS lines must hold numbers") from None
    return crs, np.array([e, n, 0.0]), gps


def _reference_lla(source: Path, rec: dict | None) -> dict | None:
    p = source / "opensfm" / "reference_lla.json"
    ref = _load_json(p) if p.is_file() else (rec or {}).get("reference_lla")
    if ref is None:
        return None
    where = str(p) if p.is_file() else "reconstruction.json reference_lla"
    return {k: _num(ref, k, where, 0.0 if k == "altitude" else None)
            for k in ("latitude", "longitude", "altitude")}


def _topo_to_ecef(ref: dict):
    return lambda xyz: crsmod.enu_to_ecef(xyz, ref["latitude"], ref["longitude"], ref["altitude"])


def _image_size(image_dir: Path | None, name: str) -> tuple[int, int] | None:
    if image_dir is None or not (image_dir / name).is_file():
        return None

    try:
        with Image.open(image_dir / name) as im:
            return im.size
    except Exception:  # noqa: BLE001 - PIL raises many types; the importer reports broken images
        return None


def read_odm(source: str | Path, *, images: Path | None = None) -> SparseModel:
    """Read an ODM/WebODM project folder. Poses come out in UTM (ECEF for a topocentric
    reconstruction; the importer maps them into the cloud's CRS)."""
    source = Path(source)
    if not source.is_dir():
        raise InputFormatError(f"{source}: ODM project folder not found")
    image_dir = images or (source / "images")
    coords_p = source / "odm_georeferencing" / "coords.txt"
    utm, offset, gps_coords = read_coords(coords_p) if coords_p.is_file() else (None, None, None)
    recon_p = source / "opensfm" / "reconstruction.json"
    geo_p = source / "odm_report" / "shots.geojson"
    geo = _read_shots_geojson(geo_p) if geo_p.is_file() else None
    notes: list[str] = []
    meta: dict = {}
    if recon_p.is_file():
        model = _from_reconstruction(source, recon_p, utm, offset, geo, notes, meta)
    elif geo is not None and (source / "cameras.json").is_file():
        model = _from_webodm_assets(source, image_dir, utm, geo, notes, meta)
    else:
        raise InputFormatError(
            f"{source}: not an ODM project: expected opensfm/reconstruction.json, or "
            f"cameras.json + odm_report/shots.geojson (WebODM all-assets download)")
    if gps_coords is not None:
        meta["gps_utm"] = _gps_by_image(source, gps_coords, offset)
    for cand in ("odm_georeferenced_model.laz", "odm_georeferenced_model.las"):
        if (source / "odm_georeferencing" / cand).is_file():
            model.default_cloud = source / "odm_georeferencing" / cand
            break
    model.default_images = image_dir if image_dir.is_dir() else None
    return model


def _gps_by_image(source: Path, gps: np.ndarray, offset: np.ndarray) -> dict[str, list[float]]:
    """coords.txt GPS lines are in img_list.txt order; -> {image: UTM [e, n, z]}."""
    lst = source / "img_list.txt"
    if not lst.is_file():
        return {}
    names = [ln.strip() for ln in lst.read_text(errors="replace").splitlines() if ln.strip()]
    if len(names) != len(gps):
        return {}
    return {n: (g + offset).tolist() for n, g in zip(names, gps, strict=True)}


def _read_shots_geojson(path: Path) -> dict[str, dict]:
    d = _load_json(path)
    feats = d.get("features") if isinstance(d, dict) else None
    if not isinstance(feats, list):
        raise InputFormatError(f"{path}: expected a GeoJSON FeatureCollection")
    out = {}
    for i, f in enumerate(feats):
        p = (f or {}).get("properties") or {}
        name = p.get("filename")
        if not name:
            raise InputFormatError(f"{path}: feature {i} has no properties.filename")
        where = f"{path}: shot {name}"
        out[str(name)] = {
            "translation": _vec3(p.get("translation"), f"{where} translation"),
            "rotation": _rotvec(p.get("rotation"), f"{where} rotation"),
            "camera": str(p.get("camera", "")),
            "size": (int(p["width"]), int(p["height"])) if "width" in p and "height" in p else None,
        }
    return out


def _from_reconstruction(source, recon_p, utm, offset, geo, notes, meta) -> SparseModel:
    recs = _load_json(recon_p)
    if isinstance(recs, dict):
        recs = [recs]
    if not isinstance(recs, list) or not recs:
        raise InputFormatError(f"{recon_p}: expected a list of reconstructions")
    sizes = [len((r or {}).get("shots") or {}) for r in recs]
    best = int(np.argmax(sizes))
    if sizes[best] == 0:
        raise InputFormatError(f"{recon_p}: no reconstruction has any shot")
    if len(recs) > 1:
        others = [f"#{i}: {n} shots" for i, n in enumerate(sizes) if i != best]
        notes.append(f"{recon_p.name}: {len(recs)} partial reconstructions; used #{best} "
                     f"({sizes[best]} shots), ignored {', '.join(others)}")
        log.warning(notes[-1])
    rec = recs[best]
    meta["reconstructions"] = sizes
    cams_raw = rec.get("cameras") or {}
    cameras = {k: opensfm_camera(v, f"{recon_p}: camera {k!r}") for k, v in cams_raw.items()}
    names, Ts = [], []
    for name in sorted(rec["shots"]):
        s = rec["shots"][name]
        where = f"{recon_p}: shot {name}"
        if s.get("camera") not in cameras:
            raise InputFormatError(f"{where} refers to unknown camera {s.get('camera')!r}")
        R = _rotvec(s.get("rotation"), f"{where} rotation")
        t = _vec3(s.get("translation"), f"{where} translation")
        names.append(name)
        Ts.append(make_pose(R, t))
    xyz, rgb = _points(rec.get("points") or {}, recon_p)
    frame, why = _decide_frame(source, rec, names, Ts, utm, offset, geo)
    meta["pose_frame"] = frame
    meta["pose_frame_decided_by"] = why
    ref = _reference_lla(source, rec)
    if frame == "utm_offset":
        if utm is None:
            raise InputFormatError(f"{source}: the poses are in UTM minus an offset but "
                                   f"odm_georeferencing/coords.txt is missing")
        shift = np.eye(4)
        shift[:3, 3] = -offset  # x_cam = R (x_utm - offset) + t
        Ts = [T @ shift for T in Ts]
        xyz = xyz + offset
        crs = utm
    elif ref is not None:
        fn = _topo_to_ecef(ref)
        Ts, _ = crsmod.map_poses(Ts, fn)
        xyz = fn(xyz) if len(xyz) else xyz
        crs = crsmod.ecef_crs()
    else:
        crs = None
        notes.append(f"{source}: no reference_lla.json and no coords.txt: the reconstruction "
                     f"is in a local frame")
    output_crs = utm if utm is not None else (_utm_for(ref) if ref else None)
    images = [SparseImage(i + 1, n, cameras[rec["shots"][n]["camera"]], T,
                          np.zeros(0, np.int64), np.zeros((0, 2)))
              for i, (n, T) in enumerate(zip(names, Ts, strict=True))]
    gps_topo = {n: rec["shots"][n]["gps_position"] for n in names if "gps_position" in rec["shots"][n]}
    meta["gps_position_topocentric"] = gps_topo
    meta["reference_lla"] = ref
    return SparseModel(images, np.arange(len(xyz), dtype=np.int64), xyz, rgb, recon_p,
                       kind="odm", crs=crs, output_crs=output_crs, local_frame=crs is None,
                       has_tracks=False, notes=notes, meta=meta)


def _points(pts: dict, where: Path) -> tuple[np.ndarray, np.ndarray]:
    """OpenSfM ``points`` -> (P, 3) float64, (P, 3) uint8, checked in one pass (no per-point
    Python validation)."""
    if not isinstance(pts, dict):
        raise InputFormatError(f"{where}: 'points' must be an object")
    try:
        xyz = np.array([p["coordinates"] for p in pts.values()], dtype=np.float64).reshape(-1, 3)
        rgb = np.array([p.get("color", (128, 128, 128)) for p in pts.values()],
                       dtype=np.float64).reshape(-1, 3)
    except (KeyError, TypeError, ValueError):
        raise InputFormatError(f"{where}: every point needs 3 'coordinates' (and 3 'color' "
                               f"values)") from None
    if len(xyz) != len(pts) or len(rgb) != len(pts):
        raise InputFormatError(f"{where}: every point needs 3 'coordinates' and 3 'color' values")
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputFormatError(f"{where}: point {list(pts)[int(np.flatnonzero(bad)[0])]} has "
                               f"non-finite coordinates")
    return xyz, np.nan_to_num(rgb).clip(0, 255).astype(np.uint8)


def _utm_for(ref: dict):
    zone = int((ref["longitude"] + 180.0) // 6.0) % 60 + 1
    return crsmod._pyproj().CRS.from_epsg((32600 if ref["latitude"] >= 0 else 32700) + zone)


def _decide_frame(source, rec, names, Ts, utm, offset, geo) -> tuple[str, str]:
    """('utm_offset' or 'topocentric', what decided it) -- see the module docstring.

    The GPS rule is the last resort: where it cannot tell the frames apart (a small survey near
    the zone's central meridian) they differ by less than the GPS noise, e.g. 5 cm over 100 m.
    """
    if utm is None:
        return "topocentric", "no coords.txt"
    C = np.array([-T[:3, :3].T @ T[:3, 3] for T in Ts])
    if geo:
        common = [i for i, n in enumerate(names) if n in geo]
        if common:
            d = np.linalg.norm(C[common] + offset - np.array([geo[names[i]]["translation"]
                                                             for i in common]), axis=1)
            if np.median(d) < 0.01:
                return "utm_offset", "centres + offset equal shots.geojson"
    if (source / "opensfm" / "reconstruction.topocentric.json").is_file():
        return "utm_offset", "reconstruction.topocentric.json exists"
    ref = _reference_lla(source, rec)
    gps = [(i, rec["shots"][n]["gps_position"]) for i, n in enumerate(names)
           if "gps_position" in rec["shots"][n]]
    if ref is None or not gps:
        return "topocentric", "no GPS positions to compare"
    idx = [i for i, _ in gps]
    g = np.array([v for _, v in gps], dtype=np.float64)
    g_utm = crsmod.transform_points(_topo_to_ecef(ref)(g), crsmod.ecef_crs(), utm) - offset
    r_topo = np.median(np.linalg.norm(C[idx] - g, axis=1))
    r_utm = np.median(np.linalg.norm(C[idx] - g_utm, axis=1))
    why = (f"GPS: median |C - gps| {r_utm:.3f} m as UTM-offset, {r_topo:.3f} m as topocentric")
    return ("utm_offset" if r_utm < r_topo else "topocentric"), why


def _from_webodm_assets(source, image_dir, utm, geo, notes, meta) -> SparseModel:
    cam_p = source / "cameras.json"
    cams = _load_json(cam_p)
    if not isinstance(cams, dict) or not cams:
        raise InputFormatError(f"{cam_p}: expected an object of cameras")
    if utm is None:
        raise InputFormatError(f"{source}: shots.geojson centres are UTM but "
                               f"odm_georeferencing/coords.txt (the UTM zone) is missing")

    def cam_key(k: str) -> str:
        return k[3:] if k.startswith("v2 ") else k

    by_key = {cam_key(k): v for k, v in cams.items()}
    images = []
    for i, name in enumerate(sorted(geo)):
        s = geo[name]
        key = cam_key(s["camera"]) if s["camera"] else (next(iter(by_key)) if len(by_key) == 1 else "")
        if key not in by_key:
            raise InputFormatError(f"{source / 'odm_report' / 'shots.geojson'}: shot {name} refers "
                                   f"to camera {s['camera']!r}, not in {cam_p}")
        size = _image_size(image_dir, name) or s["size"]
        raw = by_key[key]
        if size is not None and tuple(size) != (int(raw.get("width", 0)), int(raw.get("height", 0))):
            notes.append(f"{cam_p}: camera {key!r} is {raw.get('width')}x{raw.get('height')}; "
                         f"intrinsics rescaled to the real image size {size[0]}x{size[1]}")
        cam = opensfm_camera(raw, f"{cam_p}: camera {key!r}", size)
        R = s["rotation"]
        C = s["translation"]
        images.append(SparseImage(i + 1, name, cam, make_pose(R, -R @ C),
                                  np.zeros(0, np.int64), np.zeros((0, 2))))
    meta["pose_frame"] = "utm (shots.geojson)"
    notes[:] = list(dict.fromkeys(notes))
    return SparseModel(images, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                       source / "odm_report" / "shots.geojson", kind="odm", crs=utm,
                       output_crs=utm, has_tracks=False, notes=notes, meta=meta)
