"""Point selection for the 3D viewer, vectorised with numpy (no per-point Python loops).

Every function takes scene-local float32 coordinates of the candidate points and returns a
boolean mask over them (or point ids), so the server can combine tools, filters and
add / subtract modes on the points it sent to the browser.

Screen coordinates follow viser: 0..1 from the top-left corner of the canvas; the camera's
``wxyz``/``position`` map camera to world with OpenCV axes (x right, y down, z forward) and
``fov_y`` is the vertical field of view.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from app.viewer.scene_builder import quat_to_matrix

TOOLS = ("rectangle", "lasso", "grow", "brush")
MODES = ("replace", "add", "subtract")


def project_to_screen(xyz: np.ndarray, cam_position: np.ndarray, cam_wxyz: np.ndarray,
                      fov_y: float, aspect: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, in_front): screen coordinates (0..1, top-left) of (N, 3) points and whether
    each is in front of the camera."""
    R = quat_to_matrix(np.asarray(cam_wxyz, np.float64))
    p = (np.asarray(xyz, np.float64) - np.asarray(cam_position, np.float64)) @ R
    z = p[:, 2]
    t = np.tan(float(fov_y) / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 0.5 + p[:, 0] / (z * t * float(aspect)) / 2.0
        v = 0.5 + p[:, 1] / (z * t) / 2.0
    return u, v, z > 0


def points_in_polygon(u: np.ndarray, v: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N,) bool: even-odd rule test of points (u, v) against a closed polygon ((M, 2),
    M >= 3). Loops over the M edges, vectorised over the N points."""
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    if len(poly) < 3:
        raise ValueError(f"a lasso needs at least 3 vertices, got {len(poly)}")
    inside = np.zeros(len(u), bool)
    x0, y0 = poly[-1]
    for x1, y1 in poly:
        crosses = (y1 > v) != (y0 > v)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = (x0 - x1) * (v - y1) / (y0 - y1) + x1
        inside ^= crosses & (u < xc)
        x0, y0 = x1, y1
    return inside


def lasso(xyz: np.ndarray, cam_position, cam_wxyz, fov_y: float, aspect: float,  # noqa: ANN001
          polygon: np.ndarray) -> np.ndarray:
    """(N,) bool: points in front of the camera whose projection falls in the polygon.

    Projected in float32 (scene-local metres: ~0.1 mm at 1 km), and only the points inside
    the polygon's bounding box are tested against its edges: a lasso over a survey-sized
    cloud touches a fraction of it, and a hand-drawn one has tens of edges."""
    poly = np.asarray(polygon, np.float64).reshape(-1, 2)
    if len(poly) < 3:
        raise ValueError(f"a lasso needs at least 3 vertices, got {len(poly)}")
    R = quat_to_matrix(np.asarray(cam_wxyz, np.float64)).astype(np.float32)
    p = np.asarray(xyz, np.float32) - np.asarray(cam_position, np.float64).astype(np.float32)
    p = p @ R  # = R^T (x - t) per point
    z = p[:, 2]
    t = np.float32(np.tan(float(fov_y) / 2.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.float32(0.5) + p[:, 0] / (z * (t * np.float32(aspect))) / np.float32(2.0)
        v = np.float32(0.5) + p[:, 1] / (z * t) / np.float32(2.0)
    (u0, v0), (u1, v1) = poly.min(axis=0), poly.max(axis=0)
    box = np.flatnonzero((z > 0) & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1))
    out = np.zeros(len(z), bool)
    out[box] = points_in_polygon(u[box].astype(np.float64), v[box].astype(np.float64), poly)
    return out


def rectangle(xyz: np.ndarray, cam_position, cam_wxyz, fov_y: float, aspect: float,  # noqa: ANN001
              screen_min, screen_max) -> np.ndarray:  # noqa: ANN001
    (u0, v0), (u1, v1) = screen_min, screen_max
    poly = np.array([[min(u0, u1), min(v0, v1)], [max(u0, u1), min(v0, v1)],
                     [max(u0, u1), max(v0, v1)], [min(u0, u1), max(v0, v1)]])
    return lasso(xyz, cam_position, cam_wxyz, fov_y, aspect, poly)


def ray_hit(xyz: np.ndarray, ray_origin, ray_direction, radius: float) -> int | None:  # noqa: ANN001
    """Index of the surface point the ray hits: the nearest point along the ray among those
    within ``radius`` of it (None when the ray passes no point)."""
    o = np.asarray(ray_origin, np.float64)
    d = np.asarray(ray_direction, np.float64)
    d = d / max(np.linalg.norm(d), 1e-12)
    rel = np.asarray(xyz, np.float64) - o
    t = rel @ d
    perp2 = np.einsum("ij,ij->i", rel, rel) - t * t
    ok = (t > 0) & (perp2 <= radius * radius)
    if not ok.any():
        return None
    cand = np.flatnonzero(ok)
    return int(cand[np.argmin(t[cand])])


def brush(xyz: np.ndarray, ray_origin, ray_direction, radius: float) -> np.ndarray:  # noqa: ANN001
    """(N,) bool: points within ``radius`` of the surface point the pointer ray hits."""
    hit = ray_hit(xyz, ray_origin, ray_direction, radius)
    out = np.zeros(len(xyz), bool)
    if hit is None:
        return out
    rel = np.asarray(xyz, np.float64) - np.asarray(xyz[hit], np.float64)
    return np.einsum("ij,ij->i", rel, rel) <= radius * radius


_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) > (0, 0, 0)], np.int64)  # 13: each neighbour pair once


def grow(xyz: np.ndarray, labels: np.ndarray, seed: int, voxel: float) -> np.ndarray:
    """(N,) bool: the connected region of the seed point's label -- points of that label whose
    ``voxel``-sized cells are 26-connected to the seed's cell (sparse: only occupied cells are
    hashed; connected components with scipy.sparse.csgraph)."""
    labels = np.asarray(labels)
    same = np.flatnonzero(labels == labels[seed])
    cells = np.floor(np.asarray(xyz, np.float64)[same] / float(voxel)).astype(np.int64)
    cells -= cells.min(axis=0) - 1
    dims = cells.max(axis=0) + 2
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    uniq, inv = np.unique(key, return_inverse=True)
    rows, cols = [], []
    for off in _OFFSETS:
        nk = key_of = uniq + (off[0] * dims[1] + off[1]) * dims[2] + off[2]
        pos = np.searchsorted(uniq, nk)
        ok = pos < len(uniq)
        ok[ok] = uniq[pos[ok]] == key_of[ok]
        rows.append(np.flatnonzero(ok))
        cols.append(pos[ok])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    g = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(len(uniq), len(uniq)))
    _n, comp = connected_components(g, directed=False)
    seed_cell = inv[np.searchsorted(same, seed)]
    out = np.zeros(len(labels), bool)
    out[same[comp[inv] == comp[seed_cell]]] = True
    return out


def height_above_ground(xyz: np.ndarray, cell: float = 2.0) -> np.ndarray:
    """(N,) metres above the lowest point of each ``cell`` x ``cell`` ground column."""
    xyz = np.asarray(xyz, np.float64)
    ij = np.floor(xyz[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    low = np.full(len(uniq), np.inf)
    np.minimum.at(low, inv, xyz[:, 2])
    return xyz[:, 2] - low[inv]


@dataclass
class Filters:
    """Which candidate points a tool may select. classes / origins: allowed raw class ids /
    origin codes (None = any); height band in metres above ground (None = unbounded)."""

    classes: set[int] | None = None
    origins: set[int] | None = None
    min_height: float | None = None
    max_height: float | None = None
    extra: dict = field(default_factory=dict)

    def mask(self, xyz: np.ndarray, labels: np.ndarray | None,
             origin: np.ndarray | None, height: np.ndarray | None = None) -> np.ndarray:
        ok = np.ones(len(xyz), bool)
        if self.classes is not None and labels is not None:
            ok &= np.isin(np.asarray(labels), list(self.classes))
        if self.origins is not None and origin is not None:
            ok &= np.isin(np.asarray(origin), list(self.origins))
        if self.min_height is not None or self.max_height is not None:
            h = height if height is not None else height_above_ground(xyz)
            if self.min_height is not None:
                ok &= h >= self.min_height
            if self.max_height is not None:
                ok &= h <= self.max_height
        return ok


def combine(current: np.ndarray, picked: np.ndarray, mode: str) -> np.ndarray:
    """Sorted unique point ids after applying ``picked`` to ``current`` in ``mode``."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    picked = np.asarray(picked, np.int64).reshape(-1)
    if len(picked) > 1 and not np.all(picked[1:] > picked[:-1]):  # (the tools' picks are
        picked = np.sort(picked)  # sorted already; np.unique hashes: 1.1 s on 1.4 M ids)
        picked = picked[np.concatenate(([True], picked[1:] != picked[:-1]))]
    if mode == "replace":
        return picked
    if mode == "add":
        return np.union1d(current, picked)
    return np.setdiff1d(current, picked, assume_unique=True)


def class_counts(labels: np.ndarray | None, ids: np.ndarray) -> dict[int, int]:
    """{raw class id: selected points}, largest first."""
    if labels is None or len(ids) == 0:
        return {}
    c = np.bincount(np.asarray(labels[np.asarray(ids, np.int64)]), minlength=256)
    nz = np.flatnonzero(c)
    return {int(i): int(c[i]) for i in nz[np.argsort(-c[nz], kind="stable")]}
