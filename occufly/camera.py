"""Camera models (COLMAP conventions), projection, poses and frusta.

Pixel coordinates follow COLMAP: the top-left corner of the top-left pixel is (0, 0), so the
centre of pixel (row r, column c) is (c + 0.5, r + 0.5) and ``floor(uv)`` gives its index.
Camera frame: x right, y down, z forward (viewing direction). Poses are world-to-camera,
``xyz_cam = R_cam_world @ xyz_world + t_cam_world``, stored as a (4, 4) float64 matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from occufly.errors import InputFormatError

# model name -> parameter names in COLMAP order (the COLMAP names are COLMAP's own models)
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    # Brown-Conrady with OpenCV's tangential order (OpenSfM/ODM "brown", Pix4D R1-R3/T1-T2)
    # and a skew on the distorted coordinates: u = fx x' + skew y' + cx, v = fy y' + cy
    "BROWN": ("fx", "fy", "cx", "cy", "skew", "k1", "k2", "k3", "k4", "p1", "p2"),
    # Agisoft Metashape "frame": p1/p2 in Metashape's order (swapped relative to OpenCV),
    # p3/p4 scale the tangential term, b1 affinity, b2 skew; cx/cy are ABSOLUTE pixels here
    # (the reader adds Metashape's offsets to W/2, H/2): u = cx + x'(f + b1) + y' b2, v = cy + y' f
    "METASHAPE": ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2", "p3", "p4"),
}

# number of leading parameters in pixels (they scale with the image); the rest is distortion
_N_LINEAR = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 3, "RADIAL": 3, "OPENCV": 4,
             "FULL_OPENCV": 4, "OPENCV_FISHEYE": 4, "BROWN": 5, "METASHAPE": 5}
_FISHEYE = frozenset({"OPENCV_FISHEYE"})


# Camera.valid_radius and Camera.view_bounds per intrinsic model (and margin): the frames of
# a survey share a few models
_DERIVED: dict[tuple, object] = {}


def _derived(key: tuple, compute):  # noqa: ANN001, ANN202
    """``compute()`` once per ``key`` (a bounded cache: cleared past 4096 entries)."""
    if key in _DERIVED:
        return _DERIVED[key]
    if len(_DERIVED) > 4096:
        _DERIVED.clear()
    got = _DERIVED[key] = compute()
    return got


@dataclass(frozen=True)
class Camera:
    """An intrinsic camera model.

    model: one of :data:`CAMERA_MODELS`; params: (P,) float64 in COLMAP's order for that model
    (the models COLMAP lacks use the order listed in :data:`CAMERA_MODELS`).
    Projection: normalised ``xy = (X/Z, Y/Z)`` -> distorted ``xy'`` (model's distortion) ->
    pixels ``u = fx x' + skew y' + cx``, ``v = fy y' + cy`` (COLMAP pixel convention).
    """

    model: str
    width: int
    height: int
    params: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise InputFormatError(
                f"camera model {self.model!r} is not supported; expected one of "
                f"{', '.join(CAMERA_MODELS)}"
            )
        params = np.asarray(self.params, dtype=np.float64).reshape(-1)
        expected = len(CAMERA_MODELS[self.model])
        if params.shape != (expected,):
            raise InputFormatError(
                f"camera model {self.model} takes {expected} parameters "
                f"({', '.join(CAMERA_MODELS[self.model])}), got {params.size}"
            )
        if not np.all(np.isfinite(params)):
            raise InputFormatError(f"camera {self.model} has non-finite parameters {params}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputFormatError(f"camera size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        fx, fy = self.focal
        if fx <= 0 or fy <= 0:
            raise InputFormatError(f"camera {self.model}: focal length must be positive, got "
                                   f"fx={fx}, fy={fy}")

    # ---- intrinsics ----------------------------------------------------------------------
    @property
    def focal(self) -> tuple[float, float]:
        p = self.params
        if self.model == "METASHAPE":
            return float(p[0] + p[3]), float(p[0])
        if _N_LINEAR[self.model] >= 4:
            return float(p[0]), float(p[1])
        return float(p[0]), float(p[0])

    @property
    def principal_point(self) -> tuple[float, float]:
        p = self.params
        if self.model == "METASHAPE" or _N_LINEAR[self.model] == 3:
            return float(p[1]), float(p[2])
        return float(p[2]), float(p[3])

    @property
    def skew(self) -> float:
        """Pixels of u per unit of distorted y (0 for every COLMAP model)."""
        if self.model == "BROWN":
            return float(self.params[4])
        if self.model == "METASHAPE":
            return float(self.params[4])
        return 0.0

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 calibration matrix (distortion not included)."""
        fx, fy = self.focal
        cx, cy = self.principal_point
        return np.array([[fx, self.skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        """True when projection is not ``K @ [x, y, 1]`` (distortion, skew or fisheye)."""
        return (self.model in _FISHEYE or self.skew != 0.0
                or bool(np.any(self._dist_params() != 0)))

    @property
    def _n_dist(self) -> int:
        return len(self.params) - _N_LINEAR[self.model]

    def _dist_params(self) -> np.ndarray:
        return self.params[_N_LINEAR[self.model]:]

    # ---- distortion on normalised coordinates -------------------------------------------
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """xy: (N, 2) float64 undistorted normalised coords -> (N, 2) distorted normalised."""
        xy = np.asarray(xy, dtype=np.float64)
        if not self._n_dist:
            return xy.copy()
        return xy + self._distortion_delta(xy)

    def _distortion_delta(self, xy: np.ndarray) -> np.ndarray:
        u, v = xy[:, 0], xy[:, 1]
        d = self._dist_params()
        r2 = u * u + v * v
        m = self.model
        if m == "SIMPLE_RADIAL":
            radial = d[0] * r2
            return np.stack([u * radial, v * radial], axis=1)
        if m == "OPENCV_FISHEYE":
            r = np.sqrt(r2)
            theta = np.arctan(r)
            t2 = theta * theta
            theta_d = theta * (1.0 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(r > 1e-12, theta_d / np.where(r > 1e-12, r, 1.0), 1.0) - 1.0
            return np.stack([u * scale, v * scale], axis=1)
        uv = u * v
        if m == "RADIAL":
            radial = d[0] * r2 + d[1] * r2 * r2
            return np.stack([u * radial, v * radial], axis=1)
        if m == "OPENCV":
            k1, k2, p1, p2 = d
            radial = k1 * r2 + k2 * r2 * r2
        elif m == "FULL_OPENCV":
            k1, k2, p1, p2, k3, k4, k5, k6 = d
            num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
            radial = num / den - 1.0
        elif m == "BROWN":
            k1, k2, k3, k4, p1, p2 = d
            radial = r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
        else:  # METASHAPE: P1 on (r^2 + 2x^2) in x, P2 in y (OpenCV has them the other way)
            k1, k2, k3, k4, p1, p2, p3, p4 = d
            radial = r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
            tscale = 1.0 + r2 * (p3 + r2 * p4)
            du = u * radial + (p1 * (r2 + 2.0 * u * u) + 2.0 * p2 * uv) * tscale
            dv = v * radial + (p2 * (r2 + 2.0 * v * v) + 2.0 * p1 * uv) * tscale
            return np.stack([du, dv], axis=1)
        du = u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u * u)
        dv = v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v * v)
        return np.stack([du, dv], axis=1)

    def undistort(self, xy_d: np.ndarray, *, iterations: int = 50, tol: float = 1e-12) -> np.ndarray:
        """Invert :meth:`distort` by vectorised Newton iterations (numeric 2x2 Jacobian).

        xy_d: (N, 2) float64 distorted normalised coords -> (N, 2) undistorted.
        """
        xy_d = np.asarray(xy_d, dtype=np.float64)
        if not self._n_dist and self.model not in _FISHEYE:
            return xy_d.copy()
        x = xy_d.copy()
        if self.model in _FISHEYE:  # start from the equidistant inverse: r = tan(r_d)
            r_d = np.linalg.norm(xy_d, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(r_d > 1e-12, np.tan(np.minimum(r_d, 1.5)) / np.where(r_d > 1e-12, r_d, 1.0), 1.0)
            x = xy_d * s[:, None]
        eps = 1e-9
        active = np.isfinite(x).all(axis=1)
        for _ in range(iterations):
            xa = x[active]
            f = xa + self._distortion_delta(xa) - xy_d[active]
            # numeric Jacobian of distort at xa
            ex = np.array([eps, 0.0])
            ey = np.array([0.0, eps])
            jx = (self.distort(xa + ex) - self.distort(xa - ex)) / (2 * eps)
            jy = (self.distort(xa + ey) - self.distort(xa - ey)) / (2 * eps)
            a, c = jx[:, 0], jx[:, 1]
            b, d = jy[:, 0], jy[:, 1]
            det = a * d - b * c
            det = np.where(np.abs(det) < 1e-15, 1e-15, det)
            step = np.stack([(d * f[:, 0] - b * f[:, 1]) / det, (-c * f[:, 0] + a * f[:, 1]) / det], 1)
            x[active] = xa - step
            done = np.abs(step).max(axis=1) < tol
            idx = np.flatnonzero(active)
            active[idx[done]] = False
            if not active.any():
                break
        return x

    @property
    def valid_radius(self) -> float:
        """The largest normalised radius ``|(X/Z, Y/Z)|`` that :meth:`project` maps to pixels
        (inf: every one). A lens polynomial is only a model of the calibrated field: beyond it
        the distorted radius stops growing and turns back, so a point far outside the view
        (a drone lens's k3 < 0: ~68 degrees off the axis) would land in the middle of the
        image, at the depth of the ground there. The radius is 1.25 x the largest radius of
        the image border's undistorted points, or less where the model stops increasing
        before that (along 32 directions). Computed once per camera."""
        return _derived(("valid_radius", self), self._valid_radius_uncached)

    def _valid_radius_uncached(self) -> float:
        if self.model in _FISHEYE or not np.any(self._dist_params() != 0):
            return float("inf")
        xy = self._border_undistorted(0.0)
        if xy is None:  # the inverse did not converge: no limit
            return float("inf")
        r_border = float(np.linalg.norm(xy, axis=1).max())
        limit = 1.25 * r_border
        # where the distorted radius stops increasing along a direction, points beyond it
        # fold back: the limit is the first such radius (if it comes before 1.25 x border)
        a = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)
        r = np.linspace(0.0, limit, 801)[1:]
        d = np.stack([np.cos(a), np.sin(a)], axis=1)  # (32, 2)
        pts = (r[None, :, None] * d[:, None, :]).reshape(-1, 2)
        rd = np.linalg.norm(self.distort(pts), axis=1).reshape(len(a), len(r))
        bad = np.diff(rd, axis=1) <= 0  # (32, 799): between r[j] and r[j + 1]
        if bad.any():
            first = int(np.flatnonzero(bad.any(axis=0))[0])
            limit = min(limit, float(r[first]))
        return limit

    def _border_undistorted(self, margin: float) -> np.ndarray | None:
        """(260, 2) normalised undistorted points of the image border widened by ``margin``
        pixels (65 per side), or None where the inverse of the lens model does not give them
        back (non-finite, or re-projected more than 1e-3 px off)."""
        t = np.linspace(0.0, 1.0, 65)
        w, h, m = float(self.width), float(self.height), float(margin)
        us, vs = -m + t * (w + 2 * m), -m + t * (h + 2 * m)
        border = np.concatenate([np.c_[us, 0 * t - m], np.c_[us, 0 * t + h + m],
                                 np.c_[0 * t - m, vs], np.c_[0 * t + w + m, vs]])
        xy = self.unproject(border, 1.0)[:, :2]
        if not np.isfinite(xy).all():
            return None
        back, _ = self._project_within(np.c_[xy, np.ones(len(xy))])
        return xy if np.allclose(back, border, atol=1e-3) else None

    def view_bounds(self, margin: float = 0.0) -> tuple[float, float, float, float] | None:
        """(x0, x1, y0, y1): bounds of the normalised ``X/Z``, ``Y/Z`` of every point that
        :meth:`project` puts within ``margin`` pixels of the image, or None where they cannot
        be bounded (a lens model without a :attr:`valid_radius`). Without distortion the
        pinhole's; with it, the box of the widened image border's undistorted points (65 per
        side, padded by 2 % of the box for the border's bulge between them), within the valid
        radius's square. Computed once per camera and margin."""
        m = float(margin)
        return _derived(("view_bounds", self, m), lambda: self._view_bounds_uncached(m))

    def _view_bounds_uncached(self, m: float) -> tuple[float, float, float, float] | None:
        fx, fy = self.focal
        cx, cy = self.principal_point
        w, h = float(self.width), float(self.height)
        if not self.has_distortion:
            return (-(cx + m) / fx, (w + m - cx) / fx, -(cy + m) / fy, (h + m - cy) / fy)
        R = self.valid_radius
        if not np.isfinite(R):
            return None
        xy = self._border_undistorted(m)
        if xy is None:
            return (-R, R, -R, R)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        pad = 0.02 * (hi - lo)
        lo, hi = lo - pad, hi + pad
        return (max(-R, lo[0]), min(R, hi[0]), max(-R, lo[1]), min(R, hi[1]))

    # ---- projection ----------------------------------------------------------------------
    def project(self, xyz_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """xyz_cam: (N, 3) camera metres -> (uv (N, 2) float64 pixels, z (N,) float64 depth).

        Points with z <= 0, and points beyond the lens model's :attr:`valid_radius` (which it
        would fold back into the image), get uv = NaN; callers test ``z > 0`` and the image
        bounds.
        """
        return self._project_within(xyz_cam, self.valid_radius)

    def _project_within(self, xyz_cam: np.ndarray, lim: float = float("inf")
                           ) -> tuple[np.ndarray, np.ndarray]:
        xyz = np.asarray(xyz_cam, dtype=np.float64).reshape(-1, 3)
        z = xyz[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = xyz[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        if lim != float("inf"):
            with np.errstate(invalid="ignore"):
                xy[(xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1]) > lim * lim] = np.nan
        xy = self.distort(xy)
        fx, fy = self.focal
        cx, cy = self.principal_point
        uv = np.empty_like(xy)
        uv[:, 0] = fx * xy[:, 0] + self.skew * xy[:, 1] + cx
        uv[:, 1] = fy * xy[:, 1] + cy
        return uv, z

    def unproject(self, uv: np.ndarray, depth: np.ndarray | float = 1.0) -> np.ndarray:
        """uv: (N, 2) pixels, depth: (N,) or scalar z-depth in metres -> (N, 3) camera metres."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        fx, fy = self.focal
        cx, cy = self.principal_point
        y_d = (uv[:, 1] - cy) / fy
        xy_d = np.stack([(uv[:, 0] - cx - self.skew * y_d) / fx, y_d], axis=1)
        xy = self.undistort(xy_d)
        depth = np.broadcast_to(np.asarray(depth, dtype=np.float64), (len(uv),))
        return np.column_stack([xy * depth[:, None], depth])

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """(N,) bool: uv inside [0, width) x [0, height)."""
        return (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)

    def scaled(self, factor: float) -> Camera:
        """The camera for the image resized by ``factor`` (e.g. 0.25 for 1/4 resolution)."""
        p = self.params.copy()
        p[: _N_LINEAR[self.model]] *= factor
        return Camera(
            self.model,
            max(1, int(round(self.width * factor))),
            max(1, int(round(self.height * factor))),
            p,
        )

    def pixel_rays(self, step: int = 1) -> np.ndarray:
        """(H/step * W/step, 3) float64 unit-z rays through pixel centres, row-major."""
        cols = np.arange(0, self.width, step) + 0.5 * step
        rows = np.arange(0, self.height, step) + 0.5 * step
        uu, vv = np.meshgrid(cols, rows)
        return self.unproject(np.column_stack([uu.ravel(), vv.ravel()]), 1.0)

    # ---- (de)serialisation ---------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": [float(v) for v in self.params],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(d["model"], int(d["width"]), int(d["height"]), np.asarray(d["params"], float))

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, Camera)
            and self.model == other.model
            and self.width == other.width
            and self.height == other.height
            and np.array_equal(self.params, other.params)
        )

    def __hash__(self) -> int:
        return hash((self.model, self.width, self.height, self.params.tobytes()))


# ---- poses ---------------------------------------------------------------------------------
def make_pose(R_cam_world: np.ndarray, t_cam_world: np.ndarray) -> np.ndarray:
    """(3, 3) rotation and (3,) translation -> (4, 4) float64 world-to-camera matrix."""
    T = np.eye(4)
    T[:3, :3] = R_cam_world
    T[:3, 3] = np.asarray(t_cam_world, dtype=np.float64).reshape(3)
    return T


def camera_center(T_cam_world: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera -> (3,) float64 camera centre in world coordinates."""
    R = T_cam_world[:3, :3]
    return -R.T @ T_cam_world[:3, 3]


def pose_in_world(T_cam_local: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera in scene-local coordinates (world = origin + local) -> the same
    pose in world (e.g. UTM) coordinates: t_world = t - R @ origin."""
    T = np.array(T_cam_local, dtype=np.float64)
    T[:3, 3] -= T[:3, :3] @ np.asarray(origin, dtype=np.float64)
    return T


def viewing_direction(T_cam_world: np.ndarray) -> np.ndarray:
    """(4, 4) world-to-camera -> (3,) unit vector of the optical axis in world coordinates."""
    return T_cam_world[2, :3].copy()


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera pose of a camera at ``center`` looking at ``target`` (x right, y down).

    ``up`` is the world direction that should appear upwards in the image; for a nadir view
    pass a horizontal vector (the image's "up" on the ground).
    """
    center = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - center
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return make_pose(R, -R @ center)


def transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) rigid transform to (N, 3) points; returns float64."""
    xyz = np.asarray(xyz, dtype=np.float64)
    return xyz @ T[:3, :3].T + T[:3, 3]


def project_world(
    camera: Camera, T_cam_world: np.ndarray, xyz_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points into an image.

    Returns uv (N, 2) float64 pixels, z (N,) float64 camera depth, and visible (N,) bool:
    in front of the camera and inside the image.
    """
    xyz_cam = transform(T_cam_world, xyz_world)
    uv, z = camera.project(xyz_cam)
    with np.errstate(invalid="ignore"):
        visible = (z > 0) & camera.in_image(uv)
    return uv, z, visible


def frustum_corners(camera: Camera, T_cam_world: np.ndarray, depth: float) -> np.ndarray:
    """(5, 3) float64 world points: camera centre then image corners at z = ``depth``."""
    corners = np.array(
        [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]], float
    )
    xyz_cam = camera.unproject(corners, depth)
    T_world_cam = np.linalg.inv(T_cam_world)
    return np.vstack([camera_center(T_cam_world), transform(T_world_cam, xyz_cam)])


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) quaternion (w, x, y, z), w >= 0 (COLMAP text order)."""
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def quaternion_to_rotation(q_wxyz: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) -> (3, 3) rotation matrix."""
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat([x, y, z, w]).as_matrix()
