"""Render the semantic point cloud into a frame; 2D agreement with painted masks.

Rendering is a z-buffered splat of every point (labelled or not: unlabelled points still
occlude and render as 0). A point at depth z covers the ``s x s`` pixels whose centres lie within
``s / 2`` of its projection, ``s = clip(ceil(1.5 * f * spacing / z), 1, 8)`` (``f`` focal
length in pixels at the render scale, ``spacing`` the typical point spacing), so surfaces stay
closed while far points stay sharp.  Two passes
of ``np.minimum.at`` over the splat fragments: the nearest depth per pixel, then, among the
fragments of that front surface (depth within ``surface_tol * spacing + 0.5 %`` of it), the
label of the point that projects closest to the pixel centre (a Voronoi split of the front
surface, so class borders on one surface are not decided by depth noise).

Agreement (the paper's validation metric, FORMATS.md section 5): the share of pixels where a
mask and the rendering both have a label (mask not 0/255, rendering not 0) and agree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from occufly.camera import Camera
from occufly.confusion import Confusion
from occufly.density import point_spacing as estimate_point_spacing  # noqa: F401 (re-export)
from occufly.pointbins import PointBins
from occufly.scene import Scene
from occufly.splat import project_splat_pass, splat_label_pass_multi, splat_pass
from occufly.taxonomy import Taxonomy

MAX_SPLAT = 8  # largest splat side in pixels (radius 4)
SPLAT_FACTOR = 1.5
_SPACING_CACHE: dict[tuple[int, int], float] = {}
_BINS_CACHE: dict[tuple[int, int], object] = {}
_CULL_MIN_POINTS = 200_000  # below this a full pass over the cloud is as fast as culling
# the compiled projection's depth pass records the points it keeps for the label pass
# (splat.project_depth_pass / splat_labels_recorded); False: both passes project the cloud
# (splat.project_splat_pass; tests compare the two)
RECORD_PROJECTION = True
# render_many's class images and depth finished by one compiled sweep (splat.finish_keys);
# False: the numpy masks and casts (tests compare the two)
COMPILED_FINISH = True
# undistorted cameras project and splat in one compiled pass (occufly.splat.project_splat_pass);
# False takes the numpy projection it replaced (tests compare the two images bit for bit)
COMPILED_PROJECTION = True


def scene_point_spacing(scene: Scene) -> float:
    """Cached :func:`estimate_point_spacing` of a scene (``scene.meta['point_spacing']`` wins)."""
    if "point_spacing" in scene.meta:
        return float(scene.meta["point_spacing"])
    key = (id(scene.xyz), scene.n_points)
    if key not in _SPACING_CACHE:
        _SPACING_CACHE[key] = estimate_point_spacing(scene.xyz)
    return _SPACING_CACHE[key]


def _to_camera(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(N, 3) float64 camera coordinates of world points, as :func:`occufly.camera.transform`
    computes them, but as 9 multiply-adds per point instead of a BLAS matrix product: the
    product of an (N, 3) by a (3, 3) matrix spends ~15 x more CPU in OpenBLAS' threads (0.48 s
    vs 0.03 s for 2 M points on this machine). Equal to ``transform`` within 1e-13 relative."""
    xyz = np.asarray(xyz)
    R, t = np.asarray(T, dtype=np.float64)[:3, :3], np.asarray(T, dtype=np.float64)[:3, 3]
    cols = [xyz[:, i].astype(np.float64) for i in range(3)]
    out = np.empty((len(xyz), 3), dtype=np.float64)
    for i in range(3):
        r = out[:, i]
        np.multiply(cols[0], R[i, 0], out=r)
        r += R[i, 1] * cols[1]
        r += R[i, 2] * cols[2]
        r += t[i]
    return out


def frustum_candidates(scene: Scene, cam: Camera, T_cam_world: np.ndarray,
                       margin: float = MAX_SPLAT) -> np.ndarray | None:
    """Sorted (K,) int64 ids of the points whose splat can reach the image of ``cam`` (a
    conservative cull: every point whose bin sphere is not entirely outside one of the frustum's
    side planes, widened by ``margin`` pixels, or behind the camera), or None for "all points"
    (small clouds, a lens model without a :attr:`~occufly.camera.Camera.valid_radius`). The cull
    drops only points that cannot touch the image, so renderings are identical with and without
    it. A distorted camera: the cone of its :meth:`~occufly.camera.Camera.view_bounds` (the
    widened image's border undistorted, within the lens model's valid radius; it projects
    nothing beyond that). The bins are built once per cloud."""
    if scene.n_points < _CULL_MIN_POINTS:
        return None
    vb = cam.view_bounds(margin) if cam.has_distortion else None
    if cam.has_distortion and vb is None:
        return None
    key = (id(scene.xyz), scene.n_points)
    bins = _BINS_CACHE.get(key)
    if bins is None:
        _BINS_CACHE.clear()  # one cloud at a time: a long-lived process switches scenes
        bins = _BINS_CACHE[key] = PointBins(scene.xyz)
    if not len(bins.centers):
        return None
    c = _to_camera(T_cam_world, bins.centers)
    r = bins.cell * 0.8661  # bin half diagonal
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    w, h, m = cam.width, cam.height, float(margin)
    ok = c[:, 2] > -r
    # u = fx x / z + cx in [-m, w + m] and v likewise, as half-spaces through the camera centre;
    # a distorted camera: x / z and y / z within its view bounds (Camera.view_bounds)
    sides = (((fx, 0.0, cx + m), (-fx, 0.0, w + m - cx), (0.0, fy, cy + m), (0.0, -fy, h + m - cy))
             if vb is None else ((1.0, 0.0, -vb[0]), (-1.0, 0.0, vb[1]), (0.0, 1.0, -vb[2]),
                                 (0.0, -1.0, vb[3])))
    for a, b, d in sides:
        ok &= (a * c[:, 0] + b * c[:, 1] + d * c[:, 2]) >= -r * float(np.sqrt(a * a + b * b + d * d))
    sel = np.flatnonzero(ok)
    lens = bins.starts[sel + 1] - bins.starts[sel]
    idx = np.repeat(bins.starts[sel] - np.r_[0, np.cumsum(lens)[:-1]], lens) + np.arange(lens.sum())
    ids = np.concatenate([bins.order[idx], bins.loose])  # distinct ids
    if len(ids) * 16 > scene.n_points:  # a large share of the cloud: a mask beats the sort
        keep = np.zeros(scene.n_points, dtype=bool)
        keep[ids] = True
        return np.flatnonzero(keep)
    return np.sort(ids)


def render_labels(scene: Scene, labels: np.ndarray, frame_index: int, *, scale: float = 1.0,
                  point_spacing: float | None = None, splat_factor: float = SPLAT_FACTOR,
                  surface_tol: float = 3.0,
                  chunk: int = 500_000
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Render per-point labels into frame ``frame_index``.

    labels: (N,) uint8 raw class ids (0 = unlabelled). scale: resolution factor (0.25 = quarter).
    Returns ((h, w) uint8 class image, 0 = nothing; (h, w) float32 depth in metres, 0 = none).
    Images of more than 4 MP whose points are spread wider than ~4 px (a 20 MP frame: ~10 px)
    are rendered at 1/k and each pixel repeated k x k, k chosen for <= 1.5 px splats: the cloud has
    no finer detail there, the surfaces close, and the work drops by k^2.
    """
    cls, depth, _ = _render_scaled(scene, labels, frame_index, scale=scale,
                                   point_spacing=point_spacing, splat_factor=splat_factor,
                                   surface_tol=surface_tol, chunk=chunk, hole_radius=0)
    return cls, depth


# the prefill closes holes of up to 2 x this many pixels (at the rendered resolution) between
# rendered points: sparse parts of the cloud (scene borders, steep walls, far points) leave
# gaps between splats sized for the typical spacing
PREFILL_HOLE_RADIUS = 6


def render_prefill(scene: Scene, labels: np.ndarray, frame_index: int, *, scale: float = 1.0,
                   hole_radius: int = PREFILL_HOLE_RADIUS, **kw
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`render_labels` for a prefill: pixels no point reaches, inside gaps of up to
    ``2 * hole_radius`` px between rendered pixels, take the label and depth of the nearest
    rendered pixel (:func:`close_holes`). Returns (class image, depth, (h, w) bool "filled":
    those pixels, to mark as low confidence). The agreement metric keeps the unfilled
    :func:`render_labels`."""
    return _render_scaled(scene, labels, frame_index, scale=scale, hole_radius=hole_radius, **kw)


def close_holes(cls: np.ndarray, depth: np.ndarray, radius: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the pixels without a point (depth 0) that a morphological closing of the rendered
    pixels with a (2r+1)^2 square covers, from the nearest rendered pixel (Euclidean). Open
    borders (where the cloud ends, sky) stay empty: the closing does not grow outwards.
    Returns (cls, depth, filled) as new arrays."""
    has = depth > 0
    filled = np.zeros(has.shape, bool)
    if radius < 1 or has.all() or not has.any():
        return cls, depth, filled
    size = 2 * int(radius) + 1
    closed = ndimage.minimum_filter(ndimage.maximum_filter(has, size=size, mode="constant", cval=0),
                                    size=size, mode="constant", cval=1)
    filled = closed & ~has
    if not filled.any():
        return cls, depth, filled
    rows, cols = np.nonzero(filled)
    r0, r1 = max(0, rows.min() - size), min(has.shape[0], rows.max() + size + 1)
    c0, c1 = max(0, cols.min() - size), min(has.shape[1], cols.max() + size + 1)
    win = ~has[r0:r1, c0:c1]  # the nearest rendered pixel lies within the bounding box + size
    _, (ir, ic) = ndimage.distance_transform_edt(win, return_indices=True)
    fr, fc = rows - r0, cols - c0
    sr, sc = ir[fr, fc] + r0, ic[fr, fc] + c0
    cls, depth = cls.copy(), depth.copy()
    cls[rows, cols] = cls[sr, sc]
    depth[rows, cols] = depth[sr, sc]
    return cls, depth, filled


def _render_scaled(scene: Scene, labels: np.ndarray, frame_index: int, *, scale: float = 1.0,
                   point_spacing: float | None = None, splat_factor: float = SPLAT_FACTOR,
                   surface_tol: float = 3.0, chunk: int = 500_000, hole_radius: int = 0
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`render_labels` / :func:`render_prefill` (``hole_radius`` 0: no hole closing)."""
    labels = np.asarray(labels)
    if labels.shape != (scene.n_points,):
        raise ValueError(f"labels must be ({scene.n_points},), got {labels.shape}")
    frame = scene.frames[frame_index]
    cam = frame.camera if scale == 1.0 else frame.camera.scaled(scale)
    h, w = cam.height, cam.width
    spacing = scene_point_spacing(scene) if point_spacing is None else float(point_spacing)
    cand, k = _cull_and_coarsening(scene, frame, cam, spacing, splat_factor)
    if k > 1:  # a large image finer than the cloud: render k x coarser, repeat each pixel k x k
        cls, depth = _render(scene, labels, frame, cam.scaled(1.0 / k), spacing, splat_factor,
                             surface_tol, chunk, cand)
        cls, depth, filled = close_holes(cls, depth, math.ceil(hole_radius / k))
        return (_upsample(cls, k, h, w), _upsample(depth, k, h, w),
                _upsample(filled, k, h, w) if hole_radius else np.zeros((h, w), bool))
    cls, depth = _render(scene, labels, frame, cam, spacing, splat_factor, surface_tol, chunk, cand)
    return close_holes(cls, depth, hole_radius)


# images above this many pixels whose typical splat is wider than COARSE_SPLAT px are rendered
# coarser: same information, closed surfaces, ~1/k^2 work. The survey preset's own 20 MP
# frames (50 m, a 32 M-point cloud) have 3.1 px splats: with the earlier 4 px threshold they
# rendered at full size (2.8 s CPU, the prefill with holes closed 5-7 s); at k = 3 the
# prefill takes 1.2-1.5 s and gets 0.2-1.3 points more pixels right (three full-size frames,
# bench/bench_survey.py's frame path)
COARSE_MIN_PIXELS = 4_000_000
COARSE_SPLAT = 2.0
MAX_COARSE = 16


def _coarsening(scene: Scene, cam: Camera, T_cam_world: np.ndarray, spacing: float,
                splat_factor: float, cand: np.ndarray | None) -> int:
    """Integer factor k >= 1: render at 1/k so that the typical splat is <= 1.5 px (only for
    images above COARSE_MIN_PIXELS whose typical splat exceeds COARSE_SPLAT px)."""
    if cam.width * cam.height <= COARSE_MIN_PIXELS or scene.n_points == 0:
        return 1
    ids = np.arange(0, scene.n_points, max(1, scene.n_points // 20_000)) if cand is None \
        else cand[:: max(1, len(cand) // 20_000)]
    z = _to_camera(T_cam_world, scene.xyz[ids])[:, 2]
    z = z[z > 1e-6]
    if not len(z):
        return 1
    s_typ = splat_factor * 0.5 * sum(cam.focal) * spacing / float(np.median(z))
    return int(min(MAX_COARSE, math.ceil(s_typ / 1.5))) if s_typ > COARSE_SPLAT else 1


def _upsample(img: np.ndarray, k: int, h: int, w: int) -> np.ndarray:
    """Repeat every pixel k x k and fit to (h, w) (edge pixels repeated where short)."""
    h0, w0 = img.shape
    # one copy through a broadcast view (two np.repeat passes copied twice)
    big = np.broadcast_to(img[:, None, :, None], (h0, k, w0, k)).reshape(h0 * k, w0 * k)[:h, :w]
    if big.shape != (h, w):
        big = np.pad(big, ((0, h - big.shape[0]), (0, w - big.shape[1])), mode="edge")
    return np.ascontiguousarray(big)


def _render(scene: Scene, labels: np.ndarray, frame, cam: Camera, spacing: float, splat_factor: float,
            surface_tol: float, chunk: int, cand: np.ndarray | None, at_cand: bool = False
            ) -> tuple[np.ndarray, np.ndarray]:
    """The splat renderer at ``cam``'s resolution (``cand``: the frustum cull of the points;
    ``at_cand``: ``labels`` holds the labels of the points ``cand`` only, row k point
    ``cand[k]``, instead of every point's)."""
    at_cand = at_cand and cand is not None
    h, w = cam.height, cam.width
    f = 0.5 * sum(cam.focal)
    n_cand = scene.n_points if cand is None else len(cand)

    def projected():
        """Per chunk of points: (uv, z, splat size, first column, first row, label)."""
        for a in range(0, n_cand, chunk):
            b = min(n_cand, a + chunk)
            sub = slice(a, b) if cand is None else cand[a:b]
            xyz_cam = _to_camera(frame.T_cam_world, scene.xyz[sub])
            idx = np.flatnonzero(xyz_cam[:, 2] > 1e-6)
            uv, z = cam.project(xyz_cam[idx])
            # keep points whose largest splat could touch the image
            ok = ((uv[:, 0] >= -MAX_SPLAT) & (uv[:, 0] < w + MAX_SPLAT)
                  & (uv[:, 1] >= -MAX_SPLAT) & (uv[:, 1] < h + MAX_SPLAT))
            idx, uv, z = idx[ok], uv[ok], z[ok].astype(np.float32)
            if not len(idx):
                continue
            size = np.clip(np.ceil(splat_factor * f * spacing / z), 1, MAX_SPLAT).astype(np.int64)
            # the s x s pixels whose centres lie within s/2 of the projected point
            col0 = np.ceil(uv[:, 0] - size / 2.0 - 0.5).astype(np.int64)
            row0 = np.ceil(uv[:, 1] - size / 2.0 - 0.5).astype(np.int64)
            lab = labels[a:b] if at_cand else labels[sub]
            yield uv, z, size, col0, row0, lab[idx]  # (n,) or (n, L)

    # pass 1: nearest depth per pixel; pass 2: among the fragments of the front surface
    # (depth within a tolerance of the nearest), the point projecting closest to the pixel
    # centre gives the label (compiled loops over each point's splat, occufly.splat)

    multi = labels.ndim == 2  # (N, L): L label sets over one geometry (render_many)
    depth = np.full(h * w, np.inf, dtype=np.float32)
    best = np.full((labels.shape[1], h * w) if multi else h * w, np.iinfo(np.uint64).max,
                   dtype=np.uint64)
    tol = np.float32(surface_tol * spacing)
    ksize = splat_factor * f * spacing
    if COMPILED_PROJECTION and not cam.has_distortion and type(ksize) is float:
        # one compiled pass per pass straight from the cloud (the same float64 operations as
        # projected() below; a Python float ksize divides the float32 depths in float32 there,
        # as np.float32(ksize) does here); no per-point arrays: 0.2-0.3 s of numpy temporaries
        # for the 2.15 M culled points of a 20 MP frame
        ids = np.arange(scene.n_points, dtype=np.int64) if cand is None \
            else np.ascontiguousarray(cand, dtype=np.int64)
        lab2 = np.ascontiguousarray(labels if multi else labels.reshape(-1, 1), dtype=np.uint8)
        best2 = best if multi else best.reshape(1, -1)
        T = np.ascontiguousarray(np.asarray(frame.T_cam_world, dtype=np.float64)[:3, :4])
        fx, fy = cam.focal
        cx, cy = cam.principal_point
        xyz = np.asarray(scene.xyz)
        if RECORD_PROJECTION:
            # the depth pass records each point it keeps (position, u, v, depth, side): the
            # label pass reads those instead of gathering and projecting the cloud again
            # (survey frame 52 at 1/3: 1.9 of 3.0 M culled points kept, label pass 0.12 ->
            # 0.08 s CPU)
            from occufly.splat import splat_labels_recorded

            rec = _depth_record(depth, xyz, ids, T, cam, ksize, h, w)
            splat_labels_recorded(depth, best2, *rec, ids, lab2, at_cand, tol, h, w)
            return _finish(depth, best, multi, h, w)
        for label_pass in (False, True):
            project_splat_pass(depth, best2, xyz, ids, T, float(fx), float(fy), float(cx),
                               float(cy), float(cam.skew), np.float32(ksize), MAX_SPLAT,
                               MAX_SPLAT, lab2, tol, h, w, label_pass, at_cand)
        return _finish(depth, best, multi, h, w)

    # the projections are kept for the second pass when they are small (culled frames)
    kept = list(projected()) if n_cand <= 4_000_000 else None
    for label_pass in (False, True):
        for uv, z, size, col0, row0, lab in (kept if kept is not None else projected()):
            if multi and label_pass:
                splat_label_pass_multi(depth, best, np.ascontiguousarray(uv), z, size, col0, row0,
                                       np.ascontiguousarray(lab, dtype=np.uint8), tol, h, w)
                continue
            splat_pass(depth, best if not multi else best[0], np.ascontiguousarray(uv), z, size,
                       col0, row0, np.ascontiguousarray(lab if not multi else lab[:, 0],
                                                        dtype=np.uint8), tol, h, w, label_pass)
    return _finish(depth, best, multi, h, w)


def _depth_record(depth: np.ndarray, xyz: np.ndarray, ids: np.ndarray, T: np.ndarray,
                  cam: Camera, ksize: float, h: int, w: int) -> tuple:
    """The compiled depth pass over the points ``ids`` into ``depth``, recording each point it
    keeps: (count kept, pixel keys, uv, depth, splat side) for the label pass."""
    from occufly.splat import project_depth_pass

    fx, fy = cam.focal
    cx, cy = cam.principal_point
    n = len(ids)
    rk, ruv = np.empty(n, np.int64), np.empty((n, 2), np.float64)
    rz, rs = np.empty(n, np.float32), np.empty(n, np.int8)
    m = project_depth_pass(depth, xyz, ids, T, float(fx), float(fy), float(cx), float(cy),
                           float(cam.skew), np.float32(ksize), MAX_SPLAT, MAX_SPLAT, h, w,
                           rk, ruv, rz, rs)
    return m, rk, ruv, rz, rs


@dataclass
class FrameGeometry:
    """The half of :func:`render_many_for_mask` that needs no labels, for one frame and mask
    size: the frustum cull, the coarsening and the depth pass with its record of the points
    it kept. Computed while the labels are still being decided (a review does it beside the
    leave-one-out labels) and handed to ``render_many_for_mask(..., geometry=)``, which then
    runs the label pass only; the images are the same bit for bit. Used once: the label pass
    finishes its depth buffer in place."""

    key: tuple  # (frame index, mask shape, point spacing, splat factor, surface tolerance)
    cand: np.ndarray | None
    k: int
    h: int
    w: int
    depth: np.ndarray
    record: tuple
    ids: np.ndarray
    tol: np.float32


def _mask_camera(scene: Scene, frame_index: int, mask_shape: tuple[int, int]) -> tuple:
    """(frame, its camera at the size of a (possibly downscaled) mask ``mask_shape``); a
    ValueError where the mask is not the frame at an integer downscale."""
    frame = scene.frames[frame_index]
    scale = 1.0 / (frame.camera.width // int(mask_shape[1]))
    cam = frame.camera if scale == 1.0 else frame.camera.scaled(scale)
    if (cam.height, cam.width) != tuple(mask_shape):
        raise ValueError(f"rendered {(cam.height, cam.width)} does not match mask "
                         f"{tuple(mask_shape)}")
    return frame, cam


def _cull_and_coarsening(scene: Scene, frame, cam: Camera, spacing: float,  # noqa: ANN001
                         splat_factor: float) -> tuple[np.ndarray | None, int]:
    """(the frustum cull of the points for ``cam``, the render's coarsening factor k). A
    large image may be rendered up to MAX_COARSE x coarser, whose splats reach that much
    farther in full-size pixels: one cull wide enough for any k (the cull is conservative,
    so the image is the same as with the narrowest cull; one cull instead of two)."""
    big = cam.width * cam.height > COARSE_MIN_PIXELS
    cand = frustum_candidates(scene, cam, frame.T_cam_world,
                              margin=MAX_SPLAT * (MAX_COARSE if big else 1))
    return cand, _coarsening(scene, cam, frame.T_cam_world, spacing, splat_factor, cand)


def _geometry_key(frame_index: int, mask_shape: tuple[int, int], spacing: float,
                  splat_factor: float, surface_tol: float) -> tuple:
    return (int(frame_index), tuple(int(v) for v in mask_shape), spacing, float(splat_factor),
            float(surface_tol))


def frame_geometry(scene: Scene, frame_index: int, mask_shape: tuple[int, int], *,
                   point_spacing: float | None = None, splat_factor: float = SPLAT_FACTOR,
                   surface_tol: float = 3.0) -> FrameGeometry | None:
    """:class:`FrameGeometry` of ``render_many_for_mask(scene, ..., frame_index, mask_shape)``
    with the same keywords, or None where that render does not take the compiled recorded
    path (a distorted camera: it projects in numpy and gains nothing from this)."""
    frame, cam = _mask_camera(scene, frame_index, mask_shape)
    spacing = scene_point_spacing(scene) if point_spacing is None else float(point_spacing)
    cand, k = _cull_and_coarsening(scene, frame, cam, spacing, splat_factor)
    rcam = cam.scaled(1.0 / k) if k > 1 else cam
    ksize = splat_factor * (0.5 * sum(rcam.focal)) * spacing
    if not (COMPILED_PROJECTION and RECORD_PROJECTION and not rcam.has_distortion
            and type(ksize) is float):
        return None
    h, w = rcam.height, rcam.width
    ids = np.arange(scene.n_points, dtype=np.int64) if cand is None \
        else np.ascontiguousarray(cand, dtype=np.int64)
    depth = np.full(h * w, np.inf, dtype=np.float32)
    T = np.ascontiguousarray(np.asarray(frame.T_cam_world, dtype=np.float64)[:3, :4])
    rec = _depth_record(depth, np.asarray(scene.xyz), ids, T, rcam, ksize, h, w)
    return FrameGeometry(_geometry_key(frame_index, mask_shape, spacing, splat_factor,
                                       surface_tol), cand, k, h, w, depth, rec, ids,
                         np.float32(surface_tol * spacing))


def _finish(depth: np.ndarray, best: np.ndarray, multi: bool, h: int, w: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """The class image(s) and the depth image from the two passes' per-pixel minima."""
    if multi and COMPILED_FINISH and best.ndim == 2 and depth.ndim == 1:
        from occufly.splat import finish_keys

        cls = np.empty(best.shape, np.uint8)  # one compiled sweep, no (L, P) temporaries
        finish_keys(depth, best, cls)
        return cls.reshape(-1, h, w), depth.reshape(h, w)
    depth[~np.isfinite(depth)] = 0.0
    if multi:  # no match is key max, whose low byte is 255: those pixels are 0
        cls = (best & np.uint64(255)).astype(np.uint8)
        cls[best == np.iinfo(np.uint64).max] = 0
        return cls.reshape(-1, h, w), depth.reshape(h, w)
    hit = best != np.iinfo(np.uint64).max
    cls = np.zeros(h * w, dtype=np.uint8)
    cls[hit] = (best[hit] & np.uint64(255)).astype(np.uint8)
    return cls.reshape(h, w), depth.reshape(h, w)


def render_for_mask(scene: Scene, labels: np.ndarray, frame_index: int, mask_shape: tuple[int, int],
                    **kw) -> tuple[np.ndarray, np.ndarray]:
    """Render at the resolution of a (possibly downscaled) mask of that frame."""
    W = scene.frames[frame_index].camera.width
    s = W // int(mask_shape[1])
    cls, depth = render_labels(scene, labels, frame_index, scale=1.0 / s, **kw)
    if cls.shape != tuple(mask_shape):
        raise ValueError(f"rendered {cls.shape} does not match mask {tuple(mask_shape)}")
    return cls, depth


def render_many_for_mask(scene: Scene, labels: list, frame_index: int,
                         mask_shape: tuple[int, int], *, point_spacing: float | None = None,
                         splat_factor: float = SPLAT_FACTOR, surface_tol: float = 3.0,
                         chunk: int = 500_000, geometry: FrameGeometry | None = None
                         ) -> list[np.ndarray]:
    """:func:`render_for_mask` of several (N,) uint8 label arrays over the same points, as
    (h, w) class images (no depth): the projection, the cull and the depth pass are shared
    and one label pass keeps a key per label set, so each image equals that label array's own
    :func:`render_for_mask` image (tests/test_render.py) at little more than one render's
    cost. The review renders a frame's leave-one-out and self labels this way.

    A label set may also be given sparse, as ``(ids, values)``: the points ``ids`` (strictly
    increasing) labelled ``values``, every other point 0 -- the image of the (N,) array that
    holds them, without building it. Only the culled points' labels are gathered (a 20 MP
    frame of a 32 M-point scene: 2.6 M rows instead of an (N, L) stack)."""
    sets = []
    for a in labels:
        if isinstance(a, tuple):
            ids, vals = (np.asarray(v) for v in a)
            if ids.ndim != 1 or ids.shape != vals.shape:
                raise ValueError(f"sparse labels need (K,) ids and values, got {ids.shape}, {vals.shape}")
            if len(ids) and (ids[0] < 0 or ids[-1] >= scene.n_points):
                raise ValueError(f"sparse label ids must lie in 0..{scene.n_points - 1}")
            sets.append((ids, vals))
        else:
            a = np.asarray(a)
            if a.shape != (scene.n_points,):
                raise ValueError(f"labels must be ({scene.n_points},), got {a.shape}")
            sets.append(a)
    if not sets:
        return []
    frame, cam = _mask_camera(scene, frame_index, mask_shape)
    h, w = cam.height, cam.width
    spacing = scene_point_spacing(scene) if point_spacing is None else float(point_spacing)
    from occufly.splat import upsample_u8

    if geometry is not None:
        want = _geometry_key(frame_index, mask_shape, spacing, splat_factor, surface_tol)
        if geometry.key != want:
            raise ValueError(f"geometry of {geometry.key}, not of {want}")
        from occufly.splat import splat_labels_recorded

        g = geometry
        stack = _labels_at(scene.n_points, sets, g.cand)
        best = np.full((stack.shape[1], g.h * g.w), np.iinfo(np.uint64).max, dtype=np.uint64)
        splat_labels_recorded(g.depth, best, *g.record, g.ids,
                              np.ascontiguousarray(stack, dtype=np.uint8), g.cand is not None,
                              g.tol, g.h, g.w)
        cls, _ = _finish(g.depth, best, True, g.h, g.w)
        return [upsample_u8(c, g.k, h, w) if g.k > 1 else c for c in cls]
    cand, k = _cull_and_coarsening(scene, frame, cam, spacing, splat_factor)
    stack = _labels_at(scene.n_points, sets, cand)  # (K, L): the labels of the culled points
    cls, _ = _render(scene, stack, frame, cam.scaled(1.0 / k) if k > 1 else cam, spacing,
                     splat_factor, surface_tol, chunk, cand, at_cand=cand is not None)
    return [upsample_u8(c, k, h, w) if k > 1 else c for c in cls]


def _labels_at(n_points: int, sets: list, cand: np.ndarray | None) -> np.ndarray:
    """(K, L) uint8: the labels of the points ``cand`` (every point where None) in each label
    set ((N,) array or sparse ``(ids, values)``, see :func:`render_many_for_mask`)."""
    from occufly.splat import sparse_at_columns

    n = n_points if cand is None else len(cand)
    out = np.empty((n, len(sets)), np.uint8)
    at = None if cand is None else np.ascontiguousarray(cand, np.int64)
    groups: dict[int, list[int]] = {}  # sparse sets over the same ids: one merge walk
    for j, s in enumerate(sets):
        if not isinstance(s, tuple):
            out[:, j] = s if at is None else s[at]
        else:
            groups.setdefault(id(s[0]), []).append(j)
    for js in groups.values():
        ids = sets[js[0]][0]
        vals = np.stack([np.asarray(sets[j][1], np.uint8) for j in js], axis=1)
        if at is not None and sparse_at_columns(np.ascontiguousarray(ids, np.int64), vals, at,
                                                out, np.asarray(js, np.int64)):
            continue
        for c, j in enumerate(js):  # not sorted, or no cull: through an (N,) array
            full = np.zeros(n_points, np.uint8)
            full[ids] = vals[:, c]
            out[:, j] = full if at is None else full[at]
    return out


def prefill_for_mask(scene: Scene, labels: np.ndarray, frame_index: int,
                     mask_shape: tuple[int, int], **kw
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`render_prefill` at the resolution of a (possibly downscaled) mask of that frame."""
    W = scene.frames[frame_index].camera.width
    s = W // int(mask_shape[1])
    out = render_prefill(scene, labels, frame_index, scale=1.0 / s, **kw)
    if out[0].shape != tuple(mask_shape):
        raise ValueError(f"rendered {out[0].shape} does not match mask {tuple(mask_shape)}")
    return out


def _check_pair(mask: np.ndarray, rendered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mask = np.asarray(mask)
    rendered = np.asarray(rendered)
    if mask.shape != rendered.shape or mask.ndim != 2:
        raise ValueError(f"mask {mask.shape} and rendering {rendered.shape} must be the same (h, w)")
    return mask.astype(np.uint8, copy=False), rendered.astype(np.uint8, copy=False)


def agreement(mask: np.ndarray, rendered: np.ndarray, taxonomy: Taxonomy) -> dict:
    """Pixel agreement of a mask and a rendering, both (h, w) uint8 raw ids.

    Counts pixels where the mask has a class (not 0 / 255) and the rendering has one (not 0).
    Returns {"agreement", "pixels", "agree", "mask_pixels", "coverage" (share of mask-labelled
    pixels the rendering covers), "miou", "per_class": {name: {mask_pixels (painted pixels the
    rendering labels), painted_pixels (all painted pixels of the class), rendered_pixels,
    agree, recall, precision, iou}}, "confusion": {"ids": [...], "matrix": C x C list, rows =
    mask}}. Counted by :class:`occufly.confusion.Confusion` (mask = reference); classes absent
    from both are left out of the mIoU (its absent-class rule) and of ``per_class``, unless
    painted where the rendering has no label: then listed with recall and iou None.
    """
    mask, rendered = _check_pair(mask, rendered)
    conf = Confusion(taxonomy.ids)
    # every pixel pair counted once (compiled); rows / columns 1..C are the taxonomy classes,
    # 0 empty and C + 1 "other" (255 included): only class x class pixels are evaluated
    return agreement_from_counts(conf.add_all_pairs(mask, rendered), taxonomy)


def agreement_from_counts(full: np.ndarray, taxonomy: Taxonomy) -> dict:
    """:func:`agreement` from the (C + 2) x (C + 2) count of every (mask, rendering) pixel
    pair over compact columns (:meth:`occufly.confusion.Confusion.add_all_pairs`; several
    renderings of one mask are counted in one pass by
    :func:`occufly.confusion.count_pairs_many`)."""
    conf = Confusion(taxonomy.ids)
    # every painted pixel of each class, labelled in the rendering or not: a class painted
    # where the rendering has no label is listed too (its figures None: nothing to compare)
    painted_rows = np.asarray(full, np.int64)[1:conf.C + 1, :].sum(axis=1)
    mask_px = int(painted_rows.sum())
    both = np.zeros_like(full)
    both[1:conf.C + 1, 1:conf.C + 1] = full[1:conf.C + 1, 1:conf.C + 1]
    conf.merge_counts(both)
    cm = conf.class_matrix()
    agree = conf.correct()
    pixels = conf.total()
    per_class = {}
    rows, cols_ = conf.truth_counts(), conf.pred_counts()
    ious = conf.class_iou()
    for i, c in enumerate(taxonomy.classes):
        if painted_rows[i] == 0 and cols_[i] == 0:  # rows[i] <= painted_rows[i]
            continue
        tp = int(cm[i, i])
        compared = rows[i] > 0 or cols_[i] > 0
        per_class[c.name] = {
            "id": c.id,
            "mask_pixels": int(rows[i]),  # painted pixels with a rendered label (compared)
            "painted_pixels": int(painted_rows[i]),  # all painted pixels of the class
            "rendered_pixels": int(cols_[i]),
            "agree": tp,
            "recall": tp / int(rows[i]) if rows[i] else None,
            "precision": tp / int(cols_[i]) if cols_[i] else None,
            "iou": float(ious[i]) if compared else None,
        }
    return {
        "agreement": agree / pixels if pixels else None,
        "pixels": pixels,
        "agree": agree,
        "mask_pixels": mask_px,
        "coverage": pixels / mask_px if mask_px else None,
        "miou": conf.miou(),
        "per_class": per_class,
        "confusion": {"ids": [int(i) for i in taxonomy.ids], "matrix": cm.tolist()},
    }


def merge_agreements(results: list[dict]) -> dict:
    """Pixel-weighted total over several :func:`agreement` results."""
    pixels = sum(r["pixels"] for r in results)
    agree = sum(r["agree"] for r in results)
    mask_px = sum(r["mask_pixels"] for r in results)
    out = {"agreement": agree / pixels if pixels else None, "pixels": pixels, "agree": agree,
           "mask_pixels": mask_px, "coverage": pixels / mask_px if mask_px else None}
    if results:
        ids = results[0]["confusion"]["ids"]
        conf = Confusion(ids)
        for r in results:
            if r["confusion"]["ids"] != ids:
                raise ValueError("cannot merge agreements over different taxonomies")
            conf.merge(Confusion.from_class_matrix(ids, r["confusion"]["matrix"]))
        ious = conf.class_iou()
        out["per_class_iou"] = {int(i): float(ious[k]) for k, i in enumerate(ids) if not np.isnan(ious[k])}
        out["miou"] = conf.miou()
        out["confusion"] = {"ids": ids, "matrix": conf.class_matrix().tolist()}
    return out


# palette indices of the disagreement overlay: a disagreeing pixel's index is its rendered
# class id (1..254); these two are never a class's colour (0 empty, 255 ignore)
DISAGREE_CLEAR = 0
DISAGREE_GAP = 255


def disagreement_palette(taxonomy: Taxonomy) -> np.ndarray:
    """(256, 4) uint8 RGBA palette of :func:`disagreement_indices`: a class id's colour at
    alpha 230, ``DISAGREE_GAP`` grey at alpha 96, everything else transparent."""
    pal = np.zeros((256, 4), np.uint8)
    valid = taxonomy.valid_lut()
    pal[valid, :3] = taxonomy.colour_lut()[valid]
    pal[valid, 3] = 230
    pal[DISAGREE_GAP] = (128, 128, 128, 96)
    pal[DISAGREE_CLEAR] = 0
    return pal


def disagreement_indices(mask: np.ndarray, rendered: np.ndarray, taxonomy: Taxonomy) -> np.ndarray:
    """(h, w) uint8 palette indices of the overlay (:func:`disagreement_palette`): the rendered
    class id where both have a label and disagree, ``DISAGREE_GAP`` where the mask has a label
    the rendering does not cover, ``DISAGREE_CLEAR`` elsewhere. One table lookup per pixel
    pair (a 20 MP frame: one byte per pixel to encode instead of four)."""
    mask, rendered = _check_pair(mask, rendered)
    valid = taxonomy.valid_lut()
    ids = np.arange(256, dtype=np.uint8)
    table = np.where(valid[:, None] & valid[None, :] & (ids[:, None] != ids[None, :]),
                     ids[None, :], DISAGREE_CLEAR).astype(np.uint8)
    table[valid[:, None] & ~valid[None, :]] = DISAGREE_GAP
    if COMPILED_FINISH:
        from occufly.splat import pair_lookup

        out = np.empty(mask.shape, np.uint8)
        pair_lookup(table, np.ascontiguousarray(mask).reshape(-1),
                    np.ascontiguousarray(rendered).reshape(-1), out.reshape(-1))
        return out
    key = mask.astype(np.uint16)
    key <<= 8
    key |= rendered
    return table.reshape(-1)[key]


def disagreement_image(mask: np.ndarray, rendered: np.ndarray, taxonomy: Taxonomy) -> np.ndarray:
    """(h, w, 4) uint8 RGBA overlay for reviewers.

    Where both have a label and disagree: the *rendered* class colour, opaque (alpha 230).
    Where the mask has a label the rendering does not cover: grey, alpha 96. Elsewhere
    (agreement, unpainted, ignore): fully transparent. (The palette image of
    :func:`disagreement_indices` expanded.)
    """
    return disagreement_palette(taxonomy)[disagreement_indices(mask, rendered, taxonomy)]
