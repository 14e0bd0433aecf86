"""Per-frame ground truth: the camera-centric voxel grid of FORMATS.md section 2, its masks and
a metric depth map.

Grid. Shape (X, Y, Z) (default 192 x 128 x 128) with edge ``r`` (default 0.5 m), axes = the
camera's (x right, y down, z forward), origin at the camera centre. Voxel (i, j, k) spans
``x in [(i - X/2) r, (i - X/2 + 1) r]``, ``y in [(j - Y/2) r, ...]``, ``z in [k r, (k + 1) r]``;
its centre is ``((i - X/2 + .5) r, (j - Y/2 + .5) r, (k + .5) r)``.

Sampling. Every voxel centre is moved to world coordinates with the frame pose
(``xyz_world = scene.origin + T_world_cam @ centre``; frame poses are scene-local) and takes
the label of the scene-grid voxel that contains it (nearest-neighbour resampling). When the
scene grid is finer than the frame grid (``s = round(r / scene voxel) >= 2``), a voxel whose
centre sample is empty or unknown also looks at ``s^3`` sub-voxel centres and takes their most
common occupied label (ties: the first in x-major order): a surface thinner than a frame
voxel is otherwise missed whenever no centre falls inside it (a 0.25 m grid sampled into
0.5 m voxels lost most of the thin ground layer, docs/ssc-porting.md).

Masks (all (X, Y, Z) bool):

- **invalid**: the centre is outside the truncated frustum -- it does not project inside the
  image (``0 <= u < W``, ``0 <= v < H`` with the camera's distortion) or its camera depth
  ``z`` is not in ``[near, far]`` -- *or* the reconstruction has no data there, which we take
  as: the centre lies outside the scene grid's bounding box, or in a scene-grid voxel marked
  255 (unknown; the synthetic truth grid marks the columns outside the survey so). Such
  voxels are empty for the surface and occlusion tests. Invalid voxels have label 0 in
  :attr:`FrameGT.labels` (255 in the exported ``.label``, see :meth:`FrameGT.label_with_invalid`).
- **surface**: valid, occupied, and at least one of its 6 neighbours is empty. Neighbours are
  looked up in the *sampled* grid before the frustum crop (so a voxel is not "surface" just
  because its neighbour is outside the image); a neighbour outside the frame grid counts as
  not empty. (Only a widened frustum, dilated by one slice, is sampled -- see
  :func:`region_rects` -- which always contains every valid voxel's 6 neighbours.)
- **occluded**: valid, occupied, and its pixel's ray hits an occupied voxel in an earlier
  depth slice first. Rays: an angular raster over undistorted normalised image coordinates
  (a = x/z, b = y/z) with cell size ``voxel_size / (oversample * far)`` (default
  oversample 2: a voxel at the far plane spans >= 2 cells), covering the image; a voxel's
  "pixel" is the raster cell containing its centre, and the ray is the one through that
  cell's centre. The first hit per ray is exact, not marched: every occupied *surface*
  voxel (the first occupied voxel along any ray entering from empty space is always a
  surface voxel) is splatted into the raster cells whose centre rays intersect its box -- a
  conservative angular bounding box followed by an exact ray/box slab test -- and a z-buffer
  keeps the smallest entry depth per cell. So no occluder is missed however thin. A voxel is
  occluded when the z-buffer at its cell is smaller than its own front face ``k r`` (hits in
  the same depth slice do not count). Occupied voxels with front face closer than ``near``
  are not occluders.

Depth maps. At 1/4 image resolution (``round(W/4) x round(H/4)``), metres along the optical
axis, 0 = no depth: nearest sample of the reconstruction's MVS depth map when the workspace
has one for the frame (``scene.meta["depth_maps"]``, COLMAP ``.geometric.bin``), else a
z-buffer of the dense points the frame sees (its visibility entries, or all points if it has
none) splatted one pixel each.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occufly.camera import Camera, project_world
from occufly.errors import InputFormatError, WorkspaceError
from occufly.grid import SceneGrid
from occufly.io.colmap_dense import depth_map_layout, no_depth_where_invalid
from occufly.taxonomy import INVALID


@dataclass(frozen=True)
class FrameGridSpec:
    """Camera-centric grid and frustum parameters.

    shape: (X, Y, Z) voxels; voxel_size: metres; near/far: clip distances along the optical
    axis in metres (far defaults to the grid depth Z * voxel_size); oversample: occlusion rays
    per voxel width at the far plane.
    """

    shape: tuple[int, int, int] = (192, 128, 128)
    voxel_size: float = 0.5
    near: float = 1.0
    far: float | None = None
    oversample: float = 2.0
    max_raster: int = 2048

    def __post_init__(self) -> None:
        shape = tuple(int(s) for s in self.shape)
        if len(shape) != 3 or min(shape) <= 0:
            raise ValueError(f"FrameGridSpec.shape must be 3 positive ints, got {self.shape!r}")
        object.__setattr__(self, "shape", shape)
        if not self.voxel_size > 0:
            raise ValueError(f"FrameGridSpec.voxel_size must be > 0, got {self.voxel_size}")
        if not (self.near >= 0 and self.far_m > self.near):
            raise ValueError(f"FrameGridSpec needs 0 <= near < far, got near={self.near} far={self.far_m}")

    @property
    def far_m(self) -> float:
        return float(self.far) if self.far is not None else self.shape[2] * self.voxel_size

    @property
    def n_voxels(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]

    def axis_centers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(X,), (Y,), (Z,) float64 voxel-centre coordinates along camera x, y, z in metres."""
        X, Y, Z = self.shape
        r = self.voxel_size
        return (
            (np.arange(X) - X / 2 + 0.5) * r,
            (np.arange(Y) - Y / 2 + 0.5) * r,
            (np.arange(Z) + 0.5) * r,
        )

    def to_dict(self) -> dict:
        return {"shape": list(self.shape), "voxel_size": self.voxel_size, "near": self.near,
                "far": self.far_m, "oversample": self.oversample}


@dataclass
class FrameGT:
    """Ground truth of one frame.

    labels: (X, Y, Z) uint8 raw ids, 0 = empty or invalid; invalid / surface / occluded:
    (X, Y, Z) bool; depth: (h, w) float32 metres at 1/4 resolution (0 = none) or None.
    """

    labels: np.ndarray
    invalid: np.ndarray
    surface: np.ndarray
    occluded: np.ndarray
    depth: np.ndarray | None = None
    stats: dict = field(default_factory=dict)

    def label_with_invalid(self) -> np.ndarray:
        """(X, Y, Z) uint8 labels with 255 where invalid (the exported ``.label``)."""
        out = self.labels.copy()
        out[self.invalid] = 255
        return out


def check_pose(T_cam_world: np.ndarray, where: str) -> np.ndarray:
    """Validate a (4, 4) world-to-camera pose; raise WorkspaceError naming ``where``."""
    T = np.asarray(T_cam_world, dtype=np.float64) if T_cam_world is not None else None
    if T is None or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise WorkspaceError(f"{where}: frame has no valid pose (expected a finite 4x4 world-to-camera matrix)")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise WorkspaceError(f"{where}: frame pose is not a rigid transform (rotation not orthonormal)")
    return T


# ---- sampling -------------------------------------------------------------------------------
def sample_labels(
    grid: SceneGrid, T_cam_world: np.ndarray, scene_origin: np.ndarray, spec: FrameGridSpec,
    rects: list[tuple[int, int, int, int, int]] | None = None, *, subvoxel: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample the scene grid at frame-grid voxel centres (``subvoxel``: and, for a finer scene
    grid, at sub-voxel centres where the centre is empty -- see the module docstring;
    ``subvoxel=False`` is the plain nearest-centre rule, kept for comparisons).

    T_cam_world: (4, 4) float64 world-to-camera, scene-local; scene_origin: (3,) float64;
    rects: optional [(k, i0, i1, j0, j1)] per-slice index rectangles to sample (default:
    everything); voxels outside them get label 0 and inside False.
    Returns (labels (X, Y, Z) uint8, inside (X, Y, Z) bool: centre inside the scene grid).
    """
    T_world_cam = np.linalg.inv(np.asarray(T_cam_world, dtype=np.float64))
    R = T_world_cam[:3, :3]
    # camera centre in scene-grid voxel units (float64 before anything gets small)
    p0 = (np.asarray(scene_origin, np.float64) + T_world_cam[:3, 3] - grid.origin) / grid.voxel_size
    cx, cy, cz = spec.axis_centers()
    X, Y, Z = spec.shape
    if rects is None:
        rects = [(k, 0, X, 0, Y) for k in range(Z)]
    # world axis d of every centre in scene-grid voxel units is separable in (i, j, k);
    # float32 is exact enough here: values are small (relative to the grid origin)
    A = [(p0[d] + R[d, 0] * cx / grid.voxel_size).astype(np.float32) for d in range(3)]
    B = [(R[d, 1] * cy / grid.voxel_size).astype(np.float32) for d in range(3)]
    C = [(R[d, 2] * cz / grid.voxel_size).astype(np.float32) for d in range(3)]
    sx, sy, sz = grid.shape
    itype = np.int32 if grid.labels.size < 2**31 else np.int64
    strides = (sy * sz, sz, 1)
    flat_labels = grid.labels.reshape(-1)
    labels = np.zeros(spec.shape, dtype=np.uint8)
    inside = np.zeros(spec.shape, dtype=bool)
    sub = int(round(spec.voxel_size / grid.voxel_size)) if subvoxel else 1
    # sub-voxel centre offsets (frame-voxel units) -> scene-grid units, per world axis d
    offs = [(a + 0.5) / sub - 0.5 for a in range(sub)] if sub >= 2 else []
    deltas = [np.array([sum(R[d, e] * o[e] * spec.voxel_size / grid.voxel_size for e in range(3))
                        for d in range(3)], np.float32)
              for o in ((ox, oy, oz) for ox in offs for oy in offs for oz in offs)]

    def lookup(i0, i1, j0, j1, k, delta):
        flat = np.zeros((i1 - i0, j1 - j0), dtype=itype)
        ins = np.ones((i1 - i0, j1 - j0), dtype=bool)
        for d, (n, stride) in enumerate(zip(grid.shape, strides, strict=True)):
            f = A[d][i0:i1, None] + B[d][None, j0:j1]
            f += C[d][k] + delta[d]
            ins &= f >= 0
            ins &= f < n
            np.clip(f, 0, n - 1, out=f)  # after clipping, truncation == floor
            flat += f.astype(itype) * itype(stride)
        lab = np.take(flat_labels, flat)
        lab[~ins] = 0
        return lab, ins

    zero = np.zeros(3, np.float32)
    for k, i0, i1, j0, j1 in rects:
        lab, ins = lookup(i0, i1, j0, j1, k, zero)
        if deltas:
            todo = (lab == 0) | (lab == INVALID)
            if todo.any():
                subs = np.stack([lookup(i0, i1, j0, j1, k, dl)[0][todo] for dl in deltas], axis=1)
                occ = (subs != 0) & (subs != INVALID)
                counts = (subs[:, :, None] == subs[:, None, :]).sum(axis=2) * occ
                best = counts.argmax(axis=1)
                hit = occ.any(axis=1)
                vals = lab[todo]
                vals[hit] = subs[np.flatnonzero(hit), best[hit]]
                lab[todo] = vals
        labels[i0:i1, j0:j1, k] = lab
        inside[i0:i1, j0:j1, k] = ins
    return labels, inside


def region_rects(camera: Camera, spec: FrameGridSpec) -> list[tuple[int, int, int, int, int]]:
    """Per-slice rectangles [(k, i0, i1, j0, j1)] covering every voxel that sampling needs:
    the widened frustum (:func:`frustum_mask` with ``margin``), dilated by one slice in z so
    that every valid voxel's 6 neighbours are sampled."""
    X, Y, Z = spec.shape
    aok, bok, zok = _margin_parts(camera, spec)
    iu = aok & zok[None, :]
    jv = bok & zok[None, :]
    out = []
    for k in range(Z):
        ks = slice(max(k - 1, 0), min(k + 2, Z))
        ii = np.flatnonzero(iu[:, ks].any(axis=1))
        jj = np.flatnonzero(jv[:, ks].any(axis=1))
        if len(ii) and len(jj):
            out.append((k, int(ii[0]), int(ii[-1]) + 1, int(jj[0]), int(jj[-1]) + 1))
    return out


def _border_normalised(camera: Camera, n: int = 65) -> np.ndarray:
    """(4n, 2) float64 undistorted normalised coords (x/z, y/z) of n samples per image edge."""
    W, H = camera.width, camera.height
    t = np.linspace(0, 1, n)
    border = np.concatenate([
        np.column_stack([t * W, np.zeros_like(t)]), np.column_stack([t * W, np.full_like(t, H)]),
        np.column_stack([np.zeros_like(t), t * H]), np.column_stack([np.full_like(t, W), t * H]),
    ])
    return camera.unproject(border, 1.0)[:, :2]


def normalized_bounds(camera: Camera) -> tuple[float, float, float, float]:
    """(a_lo, a_hi, b_lo, b_hi): bounds of the image in undistorted normalised coordinates
    (a = x/z, b = y/z). Exact for pinhole cameras; for distorted ones the extremes of the
    unprojected image border (65 samples per edge) widened by 1e-4, which bounds the image
    for the usual monotonic distortion."""
    if not camera.has_distortion:
        fx, fy = camera.focal
        px, py = camera.principal_point
        return -px / fx, (camera.width - px) / fx, -py / fy, (camera.height - py) / fy
    ab = _border_normalised(camera)
    lo, hi = ab.min(axis=0) - 1e-4, ab.max(axis=0) + 1e-4
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def _bounds_parts(camera: Camera, spec: FrameGridSpec, *, margin: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Separable test of voxel-centre directions against :func:`normalized_bounds`:
    (X, Z) and (Y, Z) bool. With ``margin`` each box's angular half-extent (+1 voxel of
    slack) is added so any box that may intersect the frustum passes."""
    cx, cy, cz = spec.axis_centers()
    a_lo, a_hi, b_lo, b_hi = normalized_bounds(camera)
    a = cx[:, None] / cz[None, :]  # (X, Z)
    b = cy[:, None] / cz[None, :]  # (Y, Z)
    if not margin:
        return (a >= a_lo) & (a <= a_hi), (b >= b_lo) & (b <= b_hi)
    r = spec.voxel_size
    zf = np.maximum(cz - r / 2, 1e-6)[None, :]
    ma = (np.abs(cx)[:, None] + r) / zf - np.abs(cx)[:, None] / cz[None, :]
    mb = (np.abs(cy)[:, None] + r) / zf - np.abs(cy)[:, None] / cz[None, :]
    return (a >= a_lo - ma) & (a <= a_hi + ma), (b >= b_lo - mb) & (b <= b_hi + mb)


def _margin_parts(camera: Camera, spec: FrameGridSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Separable widened frustum test: (X, Z), (Y, Z), (Z,) bool."""
    aok, bok = _bounds_parts(camera, spec, margin=True)
    _, _, cz = spec.axis_centers()
    zok = cz + 1.5 * spec.voxel_size >= spec.near
    return aok, bok, zok


def frustum_mask(camera: Camera, spec: FrameGridSpec, *, margin: bool = False) -> np.ndarray:
    """(X, Y, Z) bool: voxel centre inside the image and with near <= z <= far.

    With ``margin`` the test is widened (separably, in normalised coordinates) so that every
    voxel whose *box* may intersect the image frustum beyond the near plane is kept (used to
    select occluders and the region to sample).
    """
    cx, cy, cz = spec.axis_centers()
    if margin:
        aok, bok, zmk = _margin_parts(camera, spec)
        return aok[:, None, :] & bok[None, :, :] & zmk[None, None, :]
    zok = (cz >= spec.near) & (cz <= spec.far_m)
    if not camera.has_distortion:
        fx, fy = camera.focal
        px, py = camera.principal_point
        u = fx * cx[:, None] / cz[None, :] + px  # (X, Z)
        v = fy * cy[:, None] / cz[None, :] + py  # (Y, Z)
        uok = (u >= 0) & (u < camera.width)
        vok = (v >= 0) & (v < camera.height)
        return uok[:, None, :] & vok[None, :, :] & zok[None, None, :]
    # distorted: exact projection, but only of the centres inside the bounding directions
    aok, bok = _bounds_parts(camera, spec, margin=False)
    out = np.zeros(spec.shape, dtype=bool)
    for k in np.flatnonzero(zok):  # one slice at a time keeps memory small
        ii = np.flatnonzero(aok[:, k])
        jj = np.flatnonzero(bok[:, k])
        if not len(ii) or not len(jj):
            continue
        gi, gj = np.meshgrid(ii, jj, indexing="ij")
        xyz = np.column_stack([cx[gi.ravel()], cy[gj.ravel()], np.full(gi.size, cz[k])])
        uv, _z = camera.project(xyz)
        with np.errstate(invalid="ignore"):
            ok = camera.in_image(uv)
        out[gi.ravel()[ok], gj.ravel()[ok], k] = True
    return out


def surface_mask(occupied: np.ndarray) -> np.ndarray:
    """(X, Y, Z) bool: occupied with at least one empty 6-neighbour (outside = not empty)."""
    empty = ~occupied
    has_empty = np.zeros_like(occupied)
    has_empty[1:] |= empty[:-1]
    has_empty[:-1] |= empty[1:]
    has_empty[:, 1:] |= empty[:, :-1]
    has_empty[:, :-1] |= empty[:, 1:]
    has_empty[:, :, 1:] |= empty[:, :, :-1]
    has_empty[:, :, :-1] |= empty[:, :, 1:]
    return occupied & has_empty


@dataclass(frozen=True)
class Raster:
    """Angular ray raster over undistorted normalised coordinates (a = x/z, b = y/z)."""

    a0: float
    b0: float
    step: float
    na: int
    nb: int

    @classmethod
    def for_camera(cls, camera: Camera, spec: FrameGridSpec) -> Raster:
        ab = _border_normalised(camera)
        lo, hi = ab.min(axis=0), ab.max(axis=0)
        step = spec.voxel_size / (spec.oversample * spec.far_m)
        step = max(step, float((hi - lo).max()) / spec.max_raster)
        na = int(math.ceil((hi[0] - lo[0]) / step)) + 1
        nb = int(math.ceil((hi[1] - lo[1]) / step)) + 1
        return cls(float(lo[0]), float(lo[1]), float(step), na, nb)

    def cell_of(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer cell (ia, ib) containing normalised coords; clipped into the raster."""
        ia = np.clip(np.floor((a - self.a0) / self.step), 0, self.na - 1).astype(np.int64)
        ib = np.clip(np.floor((b - self.b0) / self.step), 0, self.nb - 1).astype(np.int64)
        return ia, ib

    def cell_center(self, ia: np.ndarray, ib: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.a0 + (ia + 0.5) * self.step, self.b0 + (ib + 0.5) * self.step


def first_hit_zbuffer(
    ijk: np.ndarray, spec: FrameGridSpec, raster: Raster, *, max_pairs: int = 20_000_000
) -> np.ndarray:
    """Z-buffer of box entry depths.

    ijk: (M, 3) int frame-grid indices of occluder voxels. Returns (na, nb) float64: per
    raster cell the smallest camera z at which its centre ray enters any of the boxes
    (inf where none).
    """
    X, Y, _ = spec.shape
    r = spec.voxel_size
    zbuf = np.full(raster.na * raster.nb, np.inf)
    if len(ijk) == 0:
        return zbuf.reshape(raster.na, raster.nb)
    x0 = (ijk[:, 0] - X / 2) * r
    y0 = (ijk[:, 1] - Y / 2) * r
    z0 = ijk[:, 2] * r
    x1, y1, z1 = x0 + r, y0 + r, z0 + r
    # conservative angular bounding box of each box (z0 > 0 guaranteed by the caller)
    amin = np.minimum(x0 / z0, x0 / z1)
    amax = np.maximum(x1 / z0, x1 / z1)
    bmin = np.minimum(y0 / z0, y0 / z1)
    bmax = np.maximum(y1 / z0, y1 / z1)
    s = raster.step
    ia_lo = np.clip(np.ceil((amin - raster.a0) / s - 0.5), 0, raster.na).astype(np.int64)
    ia_hi = np.clip(np.floor((amax - raster.a0) / s - 0.5), -1, raster.na - 1).astype(np.int64)
    ib_lo = np.clip(np.ceil((bmin - raster.b0) / s - 0.5), 0, raster.nb).astype(np.int64)
    ib_hi = np.clip(np.floor((bmax - raster.b0) / s - 0.5), -1, raster.nb - 1).astype(np.int64)
    na_ = np.maximum(ia_hi - ia_lo + 1, 0)
    nb_ = np.maximum(ib_hi - ib_lo + 1, 0)
    # fast path for the common small footprints: the slab test is separable in (a, b), so
    # per box compute the z-interval of each footprint column and row once, then combine
    small = (na_ <= _FAST_FOOTPRINT) & (nb_ <= _FAST_FOOTPRINT)
    fs = np.flatnonzero(small)
    if len(fs):
        _zbuffer_small(zbuf, raster, fs, ia_lo, ib_lo, na_, nb_, x0, x1, y0, y1, z0, z1)
    big = np.flatnonzero(~small)
    counts = np.zeros(len(ijk), dtype=np.int64)
    counts[big] = na_[big] * nb_[big]
    order = big[np.argsort(z0[big], kind="stable")]  # near boxes first
    cum = np.cumsum(counts[order])
    start = 0
    while start < len(order):
        stop = int(np.searchsorted(cum, (cum[start - 1] if start else 0) + max_pairs, side="right"))
        stop = max(stop, start + 1)
        sel = order[start:stop]
        start = stop
        cnt = counts[sel]
        total = int(cnt.sum())
        if total == 0:
            continue
        owner = np.repeat(sel, cnt)
        first = np.cumsum(cnt) - cnt
        local = np.arange(total) - np.repeat(first, cnt)
        nbo = nb_[owner]
        ia = ia_lo[owner] + local // nbo
        ib = ib_lo[owner] + local % nbo
        a, b = raster.cell_center(ia, ib)
        entry = _slab_entry(a, b, x0[owner], x1[owner], y0[owner], y1[owner], z0[owner], z1[owner])
        hit = np.isfinite(entry)
        np.minimum.at(zbuf, ia[hit] * raster.nb + ib[hit], entry[hit])
    return zbuf.reshape(raster.na, raster.nb)


_FAST_FOOTPRINT = 6


def _axis_interval(s: np.ndarray, c0: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z-interval where s * z lies in [c0, c1] (empty interval = (inf, -inf))."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = c0 / s
        t1 = c1 / s
    tl = np.minimum(t0, t1)
    th = np.maximum(t0, t1)
    zero = s == 0
    if zero.any():
        inside0 = (c0 <= 0) & (c1 >= 0)
        tl = np.where(zero, np.where(inside0, -np.inf, np.inf), tl)
        th = np.where(zero, np.where(inside0, np.inf, -np.inf), th)
    return tl, th


def _zbuffer_small(zbuf, raster, sel, ia_lo, ib_lo, na_, nb_, x0, x1, y0, y1, z0, z1) -> None:
    M = _FAST_FOOTPRINT
    ial, ibl, na_s, nb_s = ia_lo[sel], ib_lo[sel], na_[sel], nb_[sel]
    z0s, z1s = z0[sel], z1[sel]
    xs = [_axis_interval(raster.a0 + (ial + dx + 0.5) * raster.step, x0[sel], x1[sel])
          for dx in range(min(M, int(na_s.max(initial=0))))]
    ys = [_axis_interval(raster.b0 + (ibl + dy + 0.5) * raster.step, y0[sel], y1[sel])
          for dy in range(min(M, int(nb_s.max(initial=0))))]
    for dx, (xl, xh) in enumerate(xs):
        okx = na_s > dx
        lo_x = np.maximum(z0s, xl)
        hi_x = np.minimum(z1s, xh)
        for dy, (yl, yh) in enumerate(ys):
            lo = np.maximum(lo_x, yl)
            hit = okx & (nb_s > dy) & (lo <= np.minimum(hi_x, yh))
            if hit.any():
                cell = (ial[hit] + dx) * raster.nb + (ibl[hit] + dy)
                np.minimum.at(zbuf, cell, lo[hit])


def _slab_entry(a, b, x0, x1, y0, y1, z0, z1) -> np.ndarray:
    """Entry z of the ray (a z, b z, z) into boxes [x0,x1]x[y0,y1]x[z0,z1]; inf on a miss."""
    lo = z0.astype(np.float64).copy()
    hi = z1.astype(np.float64).copy()
    for s, c0, c1 in ((a, x0, x1), (b, y0, y1)):
        tl, th = _axis_interval(s, c0, c1)
        np.maximum(lo, tl, out=lo)
        np.minimum(hi, th, out=hi)
    return np.where(lo <= hi, lo, np.inf)


def _nonzero_ijk(mask: np.ndarray) -> np.ndarray:
    """(M, 3) int64 indices of True voxels (faster than np.argwhere on large grids)."""
    flat = np.flatnonzero(mask.reshape(-1))
    X, Y, Z = mask.shape
    i, rem = np.divmod(flat, Y * Z)
    j, k = np.divmod(rem, Z)
    return np.column_stack([i, j, k])


def occlusion_mask(
    occupied: np.ndarray, surface_all: np.ndarray, valid: np.ndarray, camera: Camera, spec: FrameGridSpec,
    near_frustum: np.ndarray | None = None,
) -> np.ndarray:
    """(X, Y, Z) bool occluded mask (see the module docstring)."""
    X, Y, Z = spec.shape
    r = spec.voxel_size
    raster = Raster.for_camera(camera, spec)
    kmin = int(math.ceil(spec.near / r - 1e-9))
    kmin = max(kmin, 1)  # slice 0 touches the camera centre
    if near_frustum is None:
        near_frustum = frustum_mask(camera, spec, margin=True)
    cand = surface_all & near_frustum
    cand[:, :, :kmin] = False
    occ_ijk = _nonzero_ijk(cand)
    zbuf = first_hit_zbuffer(occ_ijk, spec, raster)
    targets = _nonzero_ijk(occupied & valid)
    out = np.zeros(spec.shape, dtype=bool)
    if len(targets) == 0:
        return out
    cx, cy, cz = spec.axis_centers()
    a = cx[targets[:, 0]] / cz[targets[:, 2]]
    b = cy[targets[:, 1]] / cz[targets[:, 2]]
    ia, ib = raster.cell_of(a, b)
    front = targets[:, 2] * r
    occl = zbuf[ia, ib] < front - 1e-9 * max(r, 1.0)
    t = targets[occl]
    out[t[:, 0], t[:, 1], t[:, 2]] = True
    return out


def sample_frame(
    grid: SceneGrid,
    camera: Camera,
    T_cam_world: np.ndarray,
    scene_origin: np.ndarray,
    spec: FrameGridSpec | None = None,
    *,
    subvoxel: bool = True,
) -> FrameGT:
    """Labels and masks of one frame (no depth map; see :func:`frame_depth_map`).

    T_cam_world: (4, 4) float64 world-to-camera, scene-local; scene_origin: (3,) float64.
    """
    spec = spec or FrameGridSpec()
    rects = region_rects(camera, spec)
    labels_all, inside = sample_labels(grid, T_cam_world, scene_origin, spec, rects, subvoxel=subvoxel)
    nodata = labels_all == INVALID
    if nodata.any():
        labels_all[nodata] = 0
        inside = inside & ~nodata
    occupied_all = labels_all != 0
    surface_all = surface_mask(occupied_all)  # unsampled voxels count as empty: see docstring
    valid = frustum_mask(camera, spec) & inside
    near_frustum = frustum_mask(camera, spec, margin=True)
    occluded = occlusion_mask(occupied_all, surface_all, valid, camera, spec, near_frustum)
    labels = labels_all
    labels[~valid] = 0
    surface = surface_all & valid
    return FrameGT(labels=labels, invalid=~valid, surface=surface, occluded=occluded,
                   stats={"occupied": int(np.count_nonzero(labels)), "valid": int(np.count_nonzero(valid))})


# ---- depth maps ---------------------------------------------------------------------------------
def quarter_shape(camera: Camera) -> tuple[int, int]:
    """(h, w) of the 1/4-resolution depth map."""
    q = camera.scaled(0.25)
    return q.height, q.width


def _nearest_indices(n_out: int, n_in: int) -> np.ndarray:
    return np.minimum(((np.arange(n_out) + 0.5) * n_in / n_out).astype(np.int64), n_in - 1)


def resample_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-sample an (H', W') depth map at the pixel centres of an (h, w) map -> float32."""
    h, w = shape
    H, W = depth.shape
    rows, cols = _nearest_indices(h, H), _nearest_indices(w, W)
    return np.ascontiguousarray(depth[rows[:, None], cols[None, :]], dtype=np.float32)


def read_depth_map_resampled(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """``resample_depth(read_depth_map(path), shape)`` of a COLMAP ``.bin`` depth map, reading
    only the rows it keeps (a quarter of a 1/4-resolution export's file: for a 20 MP map 20 of
    80 MB, 0.07 -> ~0.02 s). Same values (non-finite and negative depths are 0) and the same
    errors as :func:`occufly.io.colmap_dense.read_depth_map` for a file that is not a
    well-formed map."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
            size = fh.seek(0, 2)
    except OSError as e:
        raise InputFormatError(f"{path}: cannot read depth map ({e.strerror})") from None
    width, height, offset = depth_map_layout(path, head, size)
    h, w = shape
    # the file holds the map row by row (COLMAP's column-major (W, H) array)
    mm = np.memmap(path, dtype="<f4", mode="r", offset=offset, shape=(height, width))
    try:
        d = np.ascontiguousarray(mm[_nearest_indices(h, height)][:, _nearest_indices(w, width)],
                                 dtype=np.float32)
    finally:
        del mm
    return no_depth_where_invalid(d)


def render_depth(camera: Camera, uv: np.ndarray, z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Z-buffer of points at full-resolution pixels ``uv`` (N, 2) with depth ``z`` (N,) into an
    (h, w) float32 map (smallest positive depth per pixel, 0 where none)."""
    h, w = shape
    uv = np.asarray(uv, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    col = np.floor(uv[:, 0] * w / camera.width)
    row = np.floor(uv[:, 1] * h / camera.height)
    ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    buf = np.full(h * w, np.inf)
    np.minimum.at(buf, (row[ok] * w + col[ok]).astype(np.int64), z[ok])
    buf[~np.isfinite(buf)] = 0.0
    return buf.reshape(h, w).astype(np.float32)


def frame_depth_map(scene, f: int, *, depth_dir: str | Path | None = None) -> tuple[np.ndarray, str]:
    """(h, w) float32 depth at 1/4 resolution for frame index ``f`` and its source
    ("mvs" or "rendered")."""
    frame = scene.frames[f]
    shape = quarter_shape(frame.camera)
    ddir = depth_dir if depth_dir is not None else scene.meta.get("depth_maps")
    if ddir:
        from occufly.io.colmap_dense import find_depth_map

        p = find_depth_map(Path(ddir), frame.name)
        if p is not None:
            return read_depth_map_resampled(p, shape), "mvs"
    vis = scene.visibility
    if vis is not None and vis.n_frames > f and vis.offsets[f + 1] > vis.offsets[f]:
        _ids, uv, z = vis.frame(f)
        return render_depth(frame.camera, uv, z, shape), "rendered"
    uv, z, visible = project_world(frame.camera, frame.T_cam_world, np.asarray(scene.xyz))
    return render_depth(frame.camera, uv[visible], z[visible], shape), "rendered"
