"""Coordinate reference systems of imported projects, with pyproj.

A scene's CRS is the CRS of its dense cloud (the coordinates every export writes). Cameras of a
photogrammetry project are brought into it exactly:

- points: through pyproj (``Transformer``, always x = easting/longitude first, 3-D: heights
  are carried through as ellipsoidal heights; no geoid grids are used);
- poses: the camera centre is transformed like a point; the rotation by the local Jacobian of
  the mapping at the centre (central differences of +-1 m), reduced to its rotation part by
  polar decomposition. The Jacobian's scale (e.g. the UTM scale factor 0.9996) changes camera
  depths by that factor but not where a point projects, to first order in the distance.

``None`` stands for "no CRS": a local or arbitrary frame (COLMAP, Metashape ``LOCAL_CS``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError

ECEF_EPSG = 4978


def _pyproj():
    import pyproj

    return pyproj


def parse_crs(text: str, source: str | Path) -> object | None:
    """A CRS from WKT, ``EPSG:nnnn``, a bare EPSG number or a PROJ string -> pyproj.CRS.

    A local engineering frame (WKT ``LOCAL_CS`` / ``ENGCRS``) returns None: it has no relation
    to the Earth. Anything unreadable is an error naming ``source``.
    """
    pyproj = _pyproj()
    text = (text or "").strip()
    if not text:
        raise InputFormatError(f"{source}: empty coordinate reference system")
    if re.match(r"^\s*(LOCAL_CS|ENGCRS|ENGINEERING)", text, re.IGNORECASE):
        return None
    try:
        crs = pyproj.CRS.from_user_input(int(text) if text.isdigit() else text)
    except pyproj.exceptions.CRSError as e:
        raise InputFormatError(
            f"{source}: not a coordinate reference system pyproj understands "
            f"(expected WKT, EPSG:nnnn or a PROJ string; {str(e).splitlines()[0]})"
        ) from None
    if crs.type_name.startswith("Engineering"):
        return None
    if crs.is_bound and crs.source_crs is not None and re.search(
            r"TOWGS84\[\s*0(\.0*)?(\s*,\s*-?0(\.0*)?){6}\s*\]", text):
        crs = crs.source_crs  # a null TOWGS84 (Metashape writes one for WGS 84) adds nothing
    return crs


def crs_label(crs) -> str:
    """'WGS 84 / UTM zone 17N (EPSG:32617)', or 'local (no CRS)' for None."""
    if crs is None:
        return "local (no CRS)"
    code = crs.to_epsg(min_confidence=70)
    return f"{crs.name} (EPSG:{code})" if code else crs.name


def crs_record(crs) -> dict | None:
    """What the workspace stores: {'name', 'epsg', 'wkt'} (WKT2 2019), or None."""
    if crs is None:
        return None
    return {"name": crs.name, "epsg": crs.to_epsg(min_confidence=70),
            "wkt": crs.to_wkt(version="WKT2_2019")}


def crs_from_record(rec: dict | None):
    if not rec:
        return None
    return parse_crs(rec["wkt"], "workspace scene.json crs")


def same_crs(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a == b or (a.to_epsg(min_confidence=70) is not None
                      and a.to_epsg(min_confidence=70) == b.to_epsg(min_confidence=70))


def odm_utm_crs(line: str, source: str | Path):
    """ODM's ``coords.txt`` first line, e.g. 'WGS84 UTM 17N' -> EPSG:32617 (S: 327xx)."""
    m = re.match(r"^\s*WGS\s*84\s+UTM\s+(\d{1,2})\s*([NS])\s*$", line, re.IGNORECASE)
    if not m or not 1 <= int(m.group(1)) <= 60:
        raise InputFormatError(
            f"{source}: first line {line.strip()!r} is not a UTM zone like 'WGS84 UTM 17N'"
        )
    zone, hemi = int(m.group(1)), m.group(2).upper()
    return _pyproj().CRS.from_epsg((32600 if hemi == "N" else 32700) + zone)


def read_prj(path: Path) -> object | None:
    """The CRS of an ESRI/WKT ``.prj`` file."""
    try:
        text = path.read_text(errors="strict")
    except (OSError, UnicodeDecodeError) as e:
        raise InputFormatError(f"{path}: cannot read the .prj file ({e})") from None
    return parse_crs(text, path)


def sidecar_prj(cloud: Path) -> Path | None:
    """``cloud.ply.prj`` or ``cloud.prj`` next to a cloud, if present."""
    for cand in (Path(str(cloud) + ".prj"), cloud.with_suffix(".prj")):
        if cand.is_file():
            return cand
    return None


def cloud_crs(path: Path) -> tuple[object | None, str]:
    """The CRS a point cloud file declares -> (pyproj.CRS or None, where it came from).

    LAS/LAZ: the WKT VLR or the GeoTIFF keys (laspy's parser); PLY: a side-car ``.prj``.
    """
    suffix = path.suffix.lower()
    if suffix in (".las", ".laz"):
        import laspy

        try:
            with laspy.open(path) as f:
                crs = f.header.parse_crs()
        except Exception as e:  # noqa: BLE001 - laspy/pyproj raise many kinds for bad VLRs
            raise InputFormatError(f"{path}: cannot read the CRS records of the LAS header ({e})") from None
        if crs is not None:
            return crs, f"{path.name} (LAS CRS record)"
    prj = sidecar_prj(path)
    if prj is not None:
        return read_prj(prj), prj.name
    return None, ""


# ---- transformations -----------------------------------------------------------------------
def _transformer(src, dst):
    pyproj = _pyproj()
    try:
        return pyproj.Transformer.from_crs(src.to_3d() if hasattr(src, "to_3d") else src,
                                           dst.to_3d() if hasattr(dst, "to_3d") else dst,
                                           always_xy=True)
    except pyproj.exceptions.ProjError as e:
        raise InputFormatError(
            f"no transformation from {crs_label(src)} to {crs_label(dst)} ({e})") from None


def transform_points(xyz: np.ndarray, src, dst) -> np.ndarray:
    """xyz: (N, 3) float64 in ``src`` -> (N, 3) float64 in ``dst`` (both pyproj CRSs)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if same_crs(src, dst):
        return xyz.copy()
    t = _transformer(src, dst)
    x, y, z = t.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    out = np.column_stack([x, y, z]).astype(np.float64)
    if not np.isfinite(out).all():
        raise InputFormatError(
            f"coordinates fall outside the area where {crs_label(dst)} is defined "
            f"(transforming from {crs_label(src)})")
    return out


def enu_to_ecef(enu: np.ndarray, lat_deg: float, lon_deg: float, h: float) -> np.ndarray:
    """Topocentric east-north-up metres around (lat, lon, h) on WGS 84 -> (N, 3) ECEF metres."""
    pyproj = _pyproj()
    enu = np.asarray(enu, dtype=np.float64).reshape(-1, 3)
    x0, y0, z0 = pyproj.Transformer.from_crs(4979, ECEF_EPSG, always_xy=True).transform(
        lon_deg, lat_deg, h)
    R = enu_rotation(lat_deg, lon_deg)
    return enu @ R + np.array([x0, y0, z0])


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3) rows = east, north, up unit vectors in ECEF (x_ecef - o = R^T enu)."""
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl, so, co = np.sin(la), np.cos(la), np.sin(lo), np.cos(lo)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def ecef_crs():
    return _pyproj().CRS.from_epsg(ECEF_EPSG)


def local_jacobians(fn, centers: np.ndarray, step: float = 1.0) -> np.ndarray:
    """(F, 3, 3) Jacobians d fn / d x at ``centers`` (F, 3) by central differences."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    cols = []
    for a in range(3):
        e = np.zeros(3)
        e[a] = step
        cols.append((fn(centers + e) - fn(centers - e)) / (2 * step))
    return np.stack(cols, axis=2)


def map_poses(T_cam_src: list[np.ndarray], fn) -> tuple[list[np.ndarray], np.ndarray]:
    """World-to-camera poses in a source frame -> poses in the frame ``fn`` maps points to.

    fn: vectorised (N, 3) -> (N, 3) point mapping (e.g. topocentric -> UTM). Returns the new
    (4, 4) poses and (F,) the local scale of the mapping at each camera (1 for rigid maps).
    """
    if not T_cam_src:
        return [], np.zeros(0)
    Ts = np.asarray(T_cam_src, dtype=np.float64)
    R = Ts[:, :3, :3]
    C = -np.einsum("fji,fj->fi", R, Ts[:, :3, 3])  # -R^T t
    C_dst = fn(C)
    J = local_jacobians(fn, C)
    U, S, Vt = np.linalg.svd(J)
    R_J = U @ Vt  # rotation part (polar decomposition)
    if (np.linalg.det(R_J) < 0).any():
        raise InputFormatError("the coordinate mapping of the cameras is not orientation-preserving")
    R_new = R @ np.transpose(R_J, (0, 2, 1))
    out = []
    for f in range(len(Ts)):
        T = np.eye(4)
        T[:3, :3] = R_new[f]
        T[:3, 3] = -R_new[f] @ C_dst[f]
        out.append(T)
    return out, S.mean(axis=1)


def crs_mapping(src, dst):
    """A vectorised point mapping src -> dst (pyproj CRSs, both metric for poses)."""
    for c in (src, dst):
        if c.is_geographic:
            raise InputFormatError(
                f"{crs_label(c)} is geographic (degrees): camera poses need a metric CRS; "
                f"give the cloud a projected CRS (e.g. UTM) or pass --crs")
    t = _transformer(src, dst)

    def fn(xyz: np.ndarray) -> np.ndarray:
        x, y, z = t.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
        return np.column_stack([x, y, z])

    return fn
