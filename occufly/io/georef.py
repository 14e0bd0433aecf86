"""Make a non-georeferenced model metric from its photos' GPS (like COLMAP's model_aligner
and ODM): camera centres -> GPS positions in UTM by a robust similarity.

- GPS (WGS 84) -> UTM: zone from the mean longitude and hemisphere (EPSG:326zz / 327zz), or
  the CRS given with ``--crs``; heights are EXIF GPSAltitude as recorded.
- Similarity (Umeyama 1991, x_gps = s R x_sfm + t): RANSAC over random camera triplets
  (fitted as one batched SVD), inliers within ``inlier_m`` of the hypothesis, refitted on the
  best inlier set. Residuals per image are reported for every camera.
- Checks (warnings, never silent): SfM focal against the EXIF 35 mm equivalent (> 20 %),
  the ground against the flight height (DJI RelativeAltitude where present; points above
  the cameras always), residuals beyond ``residual_warn_m``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyproj

from occufly.errors import InputFormatError

MIN_GPS_CAMERAS = 3
FOCAL_TOLERANCE = 0.20


@dataclass
class GeorefParams:
    inlier_m: float = 5.0
    residual_warn_m: float = 3.0
    iterations: int = 256
    seed: int = 0
    ground_tolerance: float = 0.25  # relative disagreement of ground depth vs RelativeAltitude


@dataclass
class Alignment:
    scale: float
    R: np.ndarray  # (3, 3) float64
    t: np.ndarray  # (3,) float64, target CRS metres
    crs: object
    residuals: np.ndarray  # (M,) float64 metres, every camera with GPS
    names: list[str]
    inliers: np.ndarray  # (M,) bool
    warnings: list[str] = field(default_factory=list)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals[self.inliers] ** 2)))

    def apply_points(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) SfM -> (N, 3) float64 target CRS."""
        return self.scale * (np.asarray(xyz, np.float64) @ self.R.T) + self.t

    def apply_pose(self, T_cam_world: np.ndarray) -> np.ndarray:
        """World-to-camera pose in SfM units -> the same camera in metres of the target CRS."""
        Rc, tc = T_cam_world[:3, :3], T_cam_world[:3, 3]
        out = np.eye(4)
        out[:3, :3] = Rc @ self.R.T
        out[:3, 3] = self.scale * tc - Rc @ self.R.T @ self.t
        return out

    def report(self) -> dict:
        r = self.residuals
        return {
            "method": "similarity to EXIF GPS (Umeyama + RANSAC)",
            "crs": self.crs.to_string() if self.crs is not None else None,
            "scale": round(float(self.scale), 6), "rms_m": round(self.rms, 4),
            "median_m": round(float(np.median(r)), 4), "max_m": round(float(r.max()), 4),
            "cameras": len(r), "inliers": int(self.inliers.sum()),
            "residuals_m": {n: round(float(v), 4) for n, v in zip(self.names, r, strict=True)},
            "outliers": [n for n, ok in zip(self.names, self.inliers, strict=True) if not ok],
        }


def utm_crs_for(lat: np.ndarray, lon: np.ndarray):
    """The WGS 84 UTM zone of the positions' mean (pyproj CRS)."""
    lon0, lat0 = float(np.mean(lon)), float(np.mean(lat))
    zone = int(np.floor((lon0 + 180.0) / 6.0)) % 60 + 1
    return pyproj.CRS.from_epsg((32600 if lat0 >= 0 else 32700) + zone)


def gps_to_crs(lat, lon, alt, crs) -> np.ndarray:
    """(M,) WGS 84 degrees + heights -> (M, 3) float64 easting, northing, height in ``crs``."""
    tr = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    e, n = tr.transform(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
    return np.column_stack([e, n, np.asarray(alt, np.float64)])


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched Umeyama: src, dst (B, K, 3) -> scale (B,), R (B, 3, 3), t (B, 3), with
    dst ~ s R src + t (least squares, proper rotations)."""
    mu_s, mu_d = src.mean(axis=1), dst.mean(axis=1)
    a, b = src - mu_s[:, None], dst - mu_d[:, None]
    var_s = (a ** 2).sum(axis=(1, 2)) / src.shape[1]
    cov = np.einsum("bki,bkj->bij", b, a) / src.shape[1]
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.ones((len(src), 3))
    D[:, 2] = np.where(d == 0, 1.0, d)
    R = np.einsum("bij,bj,bjk->bik", U, D, Vt)
    s = (S * D).sum(axis=1) / np.maximum(var_s, 1e-300)
    t = mu_d - s[:, None] * np.einsum("bij,bj->bi", R, mu_s)
    return s, R, t


def robust_similarity(src: np.ndarray, dst: np.ndarray, params: GeorefParams
                      ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """src, dst (M, 3) -> (scale, R, t, inliers (M,) bool): RANSAC over triplets, refit."""
    M = len(src)
    rng = np.random.default_rng(params.seed)
    idx = np.array([rng.choice(M, 3, replace=False) for _ in range(params.iterations)])
    s, R, t = umeyama(src[idx], dst[idx])
    ok = np.isfinite(s) & (s > 0)
    pred = s[:, None, None] * np.einsum("bij,mj->bmi", R, src) + t[:, None]
    err = np.linalg.norm(pred - dst[None], axis=2)
    count = np.where(ok, (err < params.inlier_m).sum(axis=1), -1)
    best = int(np.argmax(count))
    inl = err[best] < params.inlier_m
    if inl.sum() < MIN_GPS_CAMERAS:
        inl = np.ones(M, bool)
    for _ in range(3):  # refit on the inliers until the set is stable
        s1, R1, t1 = (v[0] for v in umeyama(src[inl][None], dst[inl][None]))
        r = np.linalg.norm(s1 * src @ R1.T + t1 - dst, axis=1)
        new = r < params.inlier_m
        if new.sum() < MIN_GPS_CAMERAS or np.array_equal(new, inl):
            break
        inl = new
    return float(s1), R1, t1, inl


def align_to_gps(model, geotags, *, crs=None, params: GeorefParams | None = None) -> Alignment:
    """The similarity taking ``model`` (a SparseModel in SfM units) to its photos' GPS, with
    the checks of the module docstring. Does not change ``model``."""
    params = params or GeorefParams()
    by_name = {g.name: g for g in geotags}
    rows = [(im, by_name.get(im.name)) for im in model.images]
    rows = [(im, g) for im, g in rows if g is not None and g.has_gps and g.altitude is not None]
    if len(rows) < MIN_GPS_CAMERAS:
        raise InputFormatError(
            f"{model.path}: only {len(rows)} of {len(model.images)} images carry EXIF GPS; "
            f"{MIN_GPS_CAMERAS} are needed to georeference the model")
    lat = np.array([g.lat for _, g in rows])
    lon = np.array([g.lon for _, g in rows])
    alt = np.array([g.altitude for _, g in rows])
    if crs is None:
        crs = utm_crs_for(lat, lon)
    elif crs.is_geographic:
        raise InputFormatError(f"--crs {crs.name}: geographic (degrees); georeferencing from "
                               "GPS needs a projected CRS in metres (e.g. EPSG:32617)")
    dst = gps_to_crs(lat, lon, alt, crs)
    src = np.array([-im.T_cam_world[:3, :3].T @ im.T_cam_world[:3, 3] for im, _ in rows])
    if np.linalg.matrix_rank(src - src.mean(axis=0), tol=1e-9) < 2:
        raise InputFormatError(f"{model.path}: the camera centres are (nearly) collinear: "
                               "the GPS cannot fix the model's rotation; pass --scale")
    s, R, t, inl = robust_similarity(src, dst, params)
    res = np.linalg.norm(s * src @ R.T + t - dst, axis=1)
    al = Alignment(s, R, t, crs, res, [im.name for im, _ in rows], inl)
    al.warnings.extend(_checks(model, rows, al, params))
    return al


def _checks(model, rows, al: Alignment, params: GeorefParams) -> list[str]:
    out = []
    if not al.inliers.all():
        bad = [n for n, ok in zip(al.names, al.inliers, strict=True) if not ok]
        out.append(f"{len(bad)} camera(s) disagree with their GPS by more than "
                   f"{params.inlier_m:g} m and were left out of the fit: {', '.join(bad[:10])}")
    if al.rms > params.residual_warn_m or al.residuals[al.inliers].max() > 2 * params.residual_warn_m:
        out.append(f"GPS residuals RMS {al.rms:.2f} m, max {al.residuals.max():.2f} m: beyond "
                   f"{params.residual_warn_m:g} m -- the scene's metric scale is uncertain")
    # focal: SfM vs EXIF 35 mm equivalent (36 mm film width along the long side)
    for cam in {id(im.camera): im.camera for im, _ in rows}.values():
        f35 = [g.focal_35mm for im, g in rows if im.camera is cam and g.focal_35mm]
        if not f35:
            continue
        f_exif = float(np.median(f35)) / 36.0 * max(cam.width, cam.height)
        f_sfm = float(np.mean(cam.focal))
        ratio = f_exif / f_sfm
        if abs(ratio - 1.0) > FOCAL_TOLERANCE:
            out.append(
                f"SfM focal {f_sfm:.1f} px differs from the EXIF 35 mm equivalent "
                f"({float(np.median(f35)):g} mm -> {f_exif:.1f} px at {cam.width}x{cam.height}) "
                f"by a factor {ratio:.2f}: the reconstruction's depth (ground height) inherits "
                "this error; re-run SfM with the EXIF focal as prior or fixed")
    # ground against the flight height
    if len(model.xyz):
        cam_z = float(np.median([al.apply_points(
            (-im.T_cam_world[:3, :3].T @ im.T_cam_world[:3, 3])[None])[0, 2] for im, _ in rows]))
        ground_z = float(np.median(al.apply_points(model.xyz)[:, 2]))
        depth = cam_z - ground_z
        rel = [g.relative_altitude for _, g in rows if g.relative_altitude is not None]
        if depth <= 0:
            out.append(f"the points lie above the cameras after georeferencing (median point "
                       f"height {ground_z:.1f} m, cameras {cam_z:.1f} m): the model is inverted "
                       "or not a nadir survey")
        elif rel:
            h = float(np.median(rel))
            if h > 0 and abs(depth - h) > params.ground_tolerance * h:
                out.append(f"the ground lies {depth:.1f} m below the cameras but the drone "
                           f"recorded a flight height of {h:.1f} m (DJI RelativeAltitude)")
    return out
