"""2D-3D correspondences: every frame that sees a point.

A point is visible in a frame when it projects inside the image, in front of the camera, and
passes the depth test against that frame's depth: the MVS depth map where one exists
(``|z - d| <= rel_tol * d``), otherwise a depth map *rendered from the cloud* by z-buffer
splatting at a raster resolution that resolves the cloud's spacing (``render_rel_tol``).
The reconstruction's own lists (``fused.ply.vis``, COLMAP tracks) are united with that
(:data:`VISIBILITY_MODES`: ``union`` default, ``vis`` lists only, ``depth`` depth test only):
a fusion's ``.vis`` names only the images whose depth maps were fused into a point (about 7
per point on the ``bench`` preset), not every image that sees it (about 60 there).

Everything is vectorised and chunked by frame: candidate points per frame come from a
coarse spatial binning (:class:`PointBins`, robust to far outliers), memory is one frame's
raster and candidates plus the output, which holds 4 bytes per correspondence (point ids;
uv and depth are recomputed on demand, see :class:`occufly.scene.Visibility`).

Bad input is reported, never silently empty: a depth map that is not a (scaled) copy of its
frame's image is ignored for that frame with a warning naming the file (its depth is
rendered from the cloud instead); a frame that sees no point (pose behind the cloud, wrong
frame) is warned about by name; non-finite points are never visible (callers reject them).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from occufly.camera import Camera
from occufly.errors import OccuflyError
from occufly.parallel import LocalExecutor
from occufly.pointbins import PointBins  # noqa: F401 - re-exported (the binning lives below render)
from occufly.progress import ProgressFn, noop
from occufly.scene import Frame, Visibility, project_points, views_summary  # noqa: F401 - re-exported
from occufly.workspace import NpyStreamWriter

log = logging.getLogger(__name__)


def project_ids(
    frame: Frame, xyz: np.ndarray, ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project points ``ids`` into ``frame``; keep those in the image and in front.

    Returns (ids (m,) int64, uv (m, 2) float64 pixels, z (m,) float64 camera depth).
    """
    cam = frame.camera
    if cam.has_distortion:
        uv, z = project_points(frame, xyz, ids)
        with np.errstate(invalid="ignore"):
            ok = (z > 0) & cam.in_image(uv)
        return ids[ok], uv[ok], z[ok]
    # pinhole: the same arithmetic as project_points + Camera.project (bit-identical), but
    # the image test runs before the (m, 2) arrays are built, on the points in front only
    pts = np.asarray(xyz[ids])
    T = np.asarray(frame.T_cam_world, dtype=np.float64)
    x, y, w = (pts[:, i].astype(np.float64) for i in range(3))
    z = x * T[2, 0] + y * T[2, 1] + w * T[2, 2] + T[2, 3]
    with np.errstate(invalid="ignore"):
        front = np.flatnonzero(z > 0)
    x, y, w, z = x[front], y[front], w[front], z[front]
    xn = (x * T[0, 0] + y * T[0, 1] + w * T[0, 2] + T[0, 3]) / z
    yn = (x * T[1, 0] + y * T[1, 1] + w * T[1, 2] + T[1, 3]) / z
    del x, y, w
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    u = fx * xn + cam.skew * yn + cx
    v = fy * yn + cy
    ok = np.flatnonzero((u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height))
    uv = np.empty((len(ok), 2), np.float64)
    uv[:, 0] = u[ok]
    uv[:, 1] = v[ok]
    return ids[front[ok]], uv, z[ok]


def depth_test(
    uv: np.ndarray, z: np.ndarray, depth_map: np.ndarray, image_size: tuple[int, int],
    rel_tol: float,
) -> np.ndarray:
    """(m,) bool: camera depth ``z`` agrees with ``depth_map`` (h, w) at pixel ``uv``.

    The depth map may be a downscaled version of the (width, height) image.
    """
    h, w = depth_map.shape
    sx = w / image_size[0]
    sy = h / image_size[1]
    col = np.clip((uv[:, 0] * sx).astype(np.int64), 0, w - 1)
    row = np.clip((uv[:, 1] * sy).astype(np.int64), 0, h - 1)
    d = depth_map[row, col]
    return (d > 0) & (np.abs(z - d) <= rel_tol * d)


def render_depth(
    camera: Camera, uv: np.ndarray, z: np.ndarray, radius_px: np.ndarray | float,
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """Z-buffer splatting of projected points -> (h, w) float32 depth, 0 where empty.

    uv: (m, 2) full-resolution pixels, z: (m,) depth, radius_px: splat half-size per point
    (or scalar) in raster pixels; shape: (h, w) of the raster (default the image's), uv are
    scaled to it. Each point covers the square of pixels within ``radius_px`` of its pixel.
    """
    h, w = (camera.height, camera.width) if shape is None else shape
    zbuf = np.full(h * w, np.inf, dtype=np.float32)
    uv = np.asarray(uv)
    col = np.floor(uv[:, 0] * (w / camera.width)).astype(np.int64)
    row = np.floor(uv[:, 1] * (h / camera.height)).astype(np.int64)
    rad = np.broadcast_to(np.asarray(np.round(radius_px), dtype=np.int64), z.shape)
    rmax = int(rad.max(initial=0))
    zf = np.asarray(z).astype(np.float32)
    for dr in range(-rmax, rmax + 1):
        for dc in range(-rmax, rmax + 1):
            sel = (abs(dr) <= rad) & (abs(dc) <= rad) if rmax else slice(None)
            r = row[sel] + dr
            c = col[sel] + dc
            ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            np.minimum.at(zbuf, (r[ok] * w + c[ok]), zf[sel][ok])
    zbuf[~np.isfinite(zbuf)] = 0.0
    return zbuf.reshape(h, w)


VISIBILITY_MODES = ("union", "vis", "depth")
MAX_RASTER_SIDE = 4096  # longest side of a rendered depth raster
MAX_WARNINGS = 20  # listed in the stats (all are logged)


def render_shape(camera: Camera, spacing: float, z_typical: float) -> tuple[int, int]:
    """(h, w) of a rendered depth raster that resolves the cloud's spacing: the points'
    projected spacing at the typical depth is at most 2 raster pixels (so 3x3 splats close
    the surface), never finer than the image, never longer than MAX_RASTER_SIDE."""
    px = camera.focal[0] * spacing / max(z_typical, 1e-6)  # projected spacing, image pixels
    k = max(1.0, px / 2.0, max(camera.width, camera.height) / MAX_RASTER_SIDE)
    return max(1, int(round(camera.height / k))), max(1, int(round(camera.width / k)))


def _depth_map_ok(dm: np.ndarray, camera: Camera) -> bool:
    """A depth map is usable when it is the image or a uniformly scaled copy (1 % slack)."""
    if dm.ndim != 2 or dm.size == 0:
        return False
    h, w = dm.shape
    sx, sy = w / camera.width, h / camera.height
    return abs(sx - sy) <= 0.01 * max(sx, sy) + 1.0 / min(camera.width, camera.height)


class FrameLists:
    """The reconstruction's visibility lists grouped by frame (CSR over frames).

    point_ids: (L,) int32, for each frame the points its list names, in list order (ascending
    point id for CSR-by-point input); bounds: (F + 1,) int64. 4 bytes per list entry.
    """

    def __init__(self, point_ids: np.ndarray, bounds: np.ndarray) -> None:
        self.point_ids = point_ids
        self.bounds = bounds

    def __len__(self) -> int:
        return int(self.bounds[-1])

    def frame(self, f: int) -> np.ndarray:
        return self.point_ids[self.bounds[f]:self.bounds[f + 1]]

    @classmethod
    def from_point_lists(cls, n_frames: int, offsets: np.ndarray, frame_indices: np.ndarray,
                         *, chunk: int = 1 << 23) -> FrameLists:
        """Per-point lists (offsets (N + 1,), frame indices (M,)) -> grouped by frame.

        Entries naming a frame outside [0, n_frames) are dropped. A counting sort in chunks
        of ``chunk`` entries: memory is the output (4 bytes per entry) plus one chunk, not
        the int64 argsort of all entries (the same order as a stable sort by frame).
        """
        offsets = np.asarray(offsets, dtype=np.int64)
        fidx = np.asarray(frame_indices)
        m = len(fidx)
        n = len(offsets) - 1
        per_frame = np.zeros(n_frames, np.int64)
        for a in range(0, m, chunk):
            f = fidx[a:a + chunk]
            f = f[(f >= 0) & (f < n_frames)] if _may_be_outside(f, n_frames) else f
            per_frame += np.bincount(f, minlength=n_frames)[:n_frames]
        bounds = np.zeros(n_frames + 1, np.int64)
        np.cumsum(per_frame, out=bounds[1:])
        out = np.empty(int(bounds[-1]), np.int32)
        cursor = bounds[:-1].copy()
        # chunks aligned to points, so each point's entries are in one chunk
        cuts = np.unique(np.r_[np.searchsorted(offsets, np.arange(0, m, chunk), side="left"), n])
        for p0, p1 in zip(cuts[:-1], cuts[1:], strict=True):
            e0, e1 = int(offsets[p0]), int(offsets[p1])
            if e1 <= e0:
                continue
            f = fidx[e0:e1]
            pts = np.repeat(np.arange(p0, p1, dtype=np.int32), np.diff(offsets[p0:p1 + 1]))
            if _may_be_outside(f, n_frames):
                keep = (f >= 0) & (f < n_frames)
                f, pts = f[keep], pts[keep]
            # a stable sort by frame; 16-bit keys sort by radix (linear time)
            key = f.astype(np.uint16) if n_frames <= 1 << 16 else f
            order = np.argsort(key, kind="stable")
            fs = f[order].astype(np.int64)
            c = np.bincount(fs, minlength=n_frames)
            first = np.zeros(n_frames, np.int64)
            np.cumsum(c[:-1], out=first[1:])
            pos = cursor[fs] + (np.arange(len(fs), dtype=np.int64) - first[fs])
            out[pos] = pts[order]
            cursor += c
        return cls(out, bounds)


def _may_be_outside(f: np.ndarray, n_frames: int) -> bool:
    return bool(len(f)) and (int(f.max()) >= n_frames or int(f.min()) < 0)


class _FrameVisibility:
    """The visibility of one frame at a time: its lists projected, its depth test, their
    union. ``run(f)`` -> (ids (m,) int64 ascending, stat increments, warnings, spacing or
    None). Holds an (N,) uint8 scratch of flags (1 = in the lists, 2 = passes the test)."""

    def __init__(self, frames: Sequence[Frame], xyz: np.ndarray, lists: FrameLists | None,
                 bins: PointBins | None, depth_for, params: dict) -> None:
        self.frames, self.xyz, self.lists, self.depth_for = frames, xyz, lists, depth_for
        self.use_lists = bool(params["use_lists"])
        self.use_depth = bool(params["use_depth"])
        self.rel_tol, self.render_rel_tol = params["rel_tol"], params["render_rel_tol"]
        self.bins = bins if bins is not None or not self.use_depth else PointBins(xyz)
        self.flags = np.zeros(len(xyz), np.uint8)
        self.spacing: float | None = None

    def run(self, f: int) -> tuple[np.ndarray, dict, list[str], float | None]:
        frame, xyz, flags = self.frames[f], self.xyz, self.flags
        cam = frame.camera
        inc = dict.fromkeys(("list_entries_outside_image", "frames_with_depth_maps",
                             "frames_rendered", "depth_test_entries", "entries_only_in_lists",
                             "entries_only_in_depth_test", "frames_seeing_nothing"), 0)
        warnings: list[str] = []
        spacing_now = None
        ids_l = ids_d = None
        if self.use_lists:
            cand = self.lists.frame(f).astype(np.int64)
            ids_l, _, _ = project_ids(frame, xyz, cand)
            inc["list_entries_outside_image"] += int(len(cand) - len(ids_l))
            flags[ids_l] |= 1
        if self.use_depth:
            ids, uv, z = project_ids(frame, xyz, self.bins.candidates(cam, frame.T_cam_world))
            got = self.depth_for(f) if self.depth_for is not None and len(ids) else None
            dm, dname = (got if isinstance(got, tuple) else (got, f"depth map of {frame.name}"))
            if dm is not None and not _depth_map_ok(np.asarray(dm), cam):
                warnings.append(
                    f"{dname}: {np.asarray(dm).shape[1] if np.ndim(dm) == 2 else '?'}x"
                    f"{np.asarray(dm).shape[0] if np.ndim(dm) == 2 else '?'} is not a scaled "
                    f"copy of frame {frame.name}'s {cam.width}x{cam.height} image; its depth "
                    "is rendered from the cloud instead")
                dm = None
            if dm is not None:
                inc["frames_with_depth_maps"] += 1
                dm = np.nan_to_num(np.asarray(dm, dtype=np.float32), nan=0.0, posinf=0.0,
                                   neginf=0.0)
                ok = depth_test(uv, z, dm, (cam.width, cam.height), self.rel_tol)
            elif len(ids):
                if self.spacing is None:
                    from occufly.render import estimate_point_spacing

                    self.spacing = estimate_point_spacing(xyz[np.isfinite(xyz).all(axis=1)])
                spacing_now = spacing = self.spacing
                inc["frames_rendered"] += 1
                shape = render_shape(cam, spacing, float(np.median(z)))
                fx = cam.focal[0] * shape[1] / cam.width
                radius = np.clip(0.5 * fx * spacing / np.maximum(z, 1e-6), 0, 3)
                dm = render_depth(cam, uv, z, radius, shape)
                ok = depth_test(uv, z, dm, (cam.width, cam.height), self.render_rel_tol)
            else:
                ok = np.zeros(0, bool)
            ids_d = ids[ok]
            flags[ids_d] |= 2
        # the union, ascending, without a sort: a pass over the flags between the smallest
        # and the largest id touched (not all N: a frame's ids span a part of the cloud)
        touched = [a for a in (ids_l, ids_d) if a is not None and len(a)]
        if touched:
            lo = min(int(a.min()) for a in touched)
            hi = max(int(a.max()) for a in touched) + 1
            both = np.flatnonzero(flags[lo:hi])
            if lo:
                both += lo
        else:
            both = np.zeros(0, np.int64)
        fl = flags[both]
        flags[both] = 0
        if self.use_depth:
            inc["depth_test_entries"] += int(np.count_nonzero(fl & 2))
        if ids_l is not None and ids_d is not None:
            inc["entries_only_in_lists"] += int(np.count_nonzero(fl == 1))
            inc["entries_only_in_depth_test"] += int(np.count_nonzero(fl == 2))
        if not len(both):
            inc["frames_seeing_nothing"] += 1
            warnings.append(
                f"frame {frame.name} sees no point of the cloud (none is in front of the "
                "camera and inside the image, or none passes the depth test): check its pose")
        return both, inc, warnings, spacing_now


# ---- frames in parallel ----------------------------------------------------------------------
BLOCK_FRAMES = 4  # consecutive frames per task
_WORKER: dict = {}


def _init_worker(frames, xyz_path: str, lists_path: str | None, bounds, depth_for,
                 params: dict) -> None:
    xyz = np.load(xyz_path, mmap_mode="r")
    lists = (FrameLists(np.load(lists_path, mmap_mode="r"), bounds)
             if lists_path is not None else None)
    _WORKER["fv"] = _FrameVisibility(frames, xyz, lists, None, depth_for, params)


def _run_block(fs: list[int]) -> list[tuple[np.ndarray, dict, list[str], float | None]]:
    fv: _FrameVisibility = _WORKER["fv"]
    out = []
    for f in fs:
        both, inc, w, sp = fv.run(f)
        out.append((both.astype(np.int32), inc, w, sp))
    return out


def _parallel_frames(frames, xyz, lists: FrameLists | None, depth_for, params: dict,
                     workers: int, scratch_dir: Path | None):
    """Yield each frame's result in frame order, computed by ``workers`` processes; at most
    2 x workers blocks are in flight (bounded memory)."""
    tmp = Path(tempfile.mkdtemp(prefix=".visibility-", dir=scratch_dir))
    try:
        xyz_path = str(tmp / "xyz.npy")  # 12 bytes per point, memory-mapped by the workers
        np.save(xyz_path, np.ascontiguousarray(xyz))
        lists_path = None
        if lists is not None:
            lists_path = str(tmp / "lists.npy")
            np.save(lists_path, np.asarray(lists.point_ids, np.int32))
        blocks = [list(range(a, min(a + BLOCK_FRAMES, len(frames))))
                  for a in range(0, len(frames), BLOCK_FRAMES)]
        with LocalExecutor(workers, initializer=_init_worker,
                           initargs=(list(frames), xyz_path, lists_path,
                                     None if lists is None else np.asarray(lists.bounds),
                                     depth_for, params)) as ex:
            pending: deque = deque()
            nxt = 0
            while nxt < len(blocks) or pending:
                while nxt < len(blocks) and len(pending) < 2 * workers:
                    pending.append(ex.submit(_run_block, blocks[nxt]))
                    nxt += 1
                yield from pending.popleft().result()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


DISK_SAMPLE_FRAMES = 64  # frames whose candidates are counted for the disk estimate


def estimate_correspondences(frames: Sequence[Frame], bins: PointBins | None,
                             list_entries: int = 0) -> int:
    """Upper estimate of the correspondences an import will write: every candidate of the
    depth test (points in bins that may project into the frame, counted on an even sample of
    up to :data:`DISK_SAMPLE_FRAMES` frames and scaled) plus every list entry."""
    F = len(frames)
    if bins is None or not F:
        return int(list_entries)
    pick = np.unique(np.linspace(0, F - 1, min(F, DISK_SAMPLE_FRAMES)).round().astype(int))
    got = sum(bins.candidate_count(frames[f].camera, frames[f].T_cam_world) for f in pick)
    return int(got * F / len(pick)) + int(list_entries)


def check_output_disk(ids_out: Path, frames: Sequence[Frame], bins: PointBins | None,
                      list_entries: int) -> int:
    """Refuse, before the frame loop, an output that cannot fit on the disk holding
    ``ids_out`` (4 bytes per correspondence, upper estimate): an
    :class:`~occufly.errors.OccuflyError` naming the needed and the free space. Returns the
    estimated correspondences."""
    est = estimate_correspondences(frames, bins, list_entries)
    need = 4 * est + 8 * (len(frames) + 1) + (1 << 20)
    free = shutil.disk_usage(ids_out.parent).free
    if need > free:
        gb = 2.0 ** 30
        raise OccuflyError(
            f"{ids_out.parent}: the visibility of {len(frames)} frames needs up to "
            f"{need / gb:.1f} GB of disk (about {est / 1e6:.0f} M correspondences at 4 bytes), "
            f"{free / gb:.1f} GB are free there")
    return est


def compute_visibility(
    frames: Sequence[Frame],
    xyz: np.ndarray,
    *,
    mode: str = "union",
    lists: tuple[np.ndarray, np.ndarray] | FrameLists | None = None,
    lists_name: str = "visibility lists",
    depth_for: Callable[[int], np.ndarray | tuple[np.ndarray, str] | None] | None = None,
    rel_tol: float = 0.02,
    render_rel_tol: float = 0.05,
    progress: ProgressFn | None = None,
    ids_out: str | Path | None = None,
    workers: int = 1,
) -> tuple[Visibility, dict]:
    """Every frame that sees each point, one frame at a time.

    lists: the reconstruction's per-point frame lists as (offsets (N + 1,), frame indices
    (M,)), e.g. ``fused.ply.vis`` or tracks; entries that do not project into their frame
    are dropped (counted). depth_for(f): frame f's MVS depth map (or (map, file name)), or
    None to render one from the cloud. mode: ``union`` (lists + depth test), ``vis`` (lists
    only), ``depth`` (depth test only). Returns (visibility without stored uv/depth, stats).

    lists may also be given grouped by frame (:class:`FrameLists`), so a caller can free
    the per-point arrays first. ids_out: a ``.npy`` path the point ids are streamed to, one
    frame at a time (:class:`~occufly.workspace.NpyStreamWriter`, byte-identical to
    ``np.save`` of the in-memory result); the returned visibility memory-maps it. Without
    it the ids are assembled in memory (4 bytes per correspondence).

    workers > 1: frames are computed by a local process pool (:mod:`occufly.parallel`), in
    blocks of consecutive frames, and written in frame order -- the same output. Each worker
    memory-maps the points and the lists (scratch copies beside ``ids_out`` when they are not
    files already) and builds its own spatial bins; ``depth_for`` must then pickle.
    """
    if mode not in VISIBILITY_MODES:
        raise ValueError(f"visibility mode {mode!r}: expected one of {', '.join(VISIBILITY_MODES)}")
    if mode == "vis" and lists is None:
        raise ValueError("visibility mode 'vis' needs the reconstruction's visibility lists "
                         "(fused.ply.vis or tracks), and there are none")
    report = progress or noop
    t0 = time.perf_counter()
    xyz = np.asarray(xyz)
    n, F = len(xyz), len(frames)
    use_lists = lists is not None and mode in ("union", "vis")
    use_depth = mode in ("union", "depth")
    stats: dict = {"mode": mode, "frames_with_depth_maps": 0, "frames_rendered": 0,
                   "list_entries": 0, "list_entries_outside_image": 0,
                   "depth_test_entries": 0, "entries_only_in_lists": 0,
                   "entries_only_in_depth_test": 0, "frames_seeing_nothing": 0, "warnings": []}
    warnings: list[str] = []

    def warn(msg: str) -> None:
        log.warning("%s", msg)
        warnings.append(msg)

    if use_lists:
        if not isinstance(lists, FrameLists):
            lists = FrameLists.from_point_lists(F, lists[0], lists[1])
        stats["list_entries"] = len(lists)
    bins = PointBins(xyz) if use_depth else None
    if bins is not None and len(bins.loose):
        stats["far_outlier_points"] = int(len(bins.loose))
    if ids_out is not None:
        stats["estimated_correspondences_max"] = check_output_disk(
            Path(ids_out), frames, bins, len(lists) if use_lists else 0)
    out: list[np.ndarray] = []
    writer = NpyStreamWriter(ids_out, np.int32) if ids_out is not None else None
    counts = np.zeros(F, np.int64)
    views = np.zeros(n, np.int32)  # frames seeing each point (a bincount of the output would
    # cast all of it to int64: 8 bytes per correspondence)
    params = {"use_lists": use_lists, "use_depth": use_depth, "rel_tol": rel_tol,
              "render_rel_tol": render_rel_tol}
    if workers > 1 and F > 1:
        bins = None  # each worker builds its own
        results = _parallel_frames(frames, xyz, lists if use_lists else None, depth_for, params,
                                   workers, Path(ids_out).parent if ids_out is not None else None)
    else:
        one = _FrameVisibility(frames, xyz, lists if use_lists else None, bins, depth_for, params)
        results = (one.run(f) for f in range(F))
    for f, (both, inc, frame_warnings, spacing) in enumerate(results):
        report(f / max(F, 1), "visibility")
        for k, v in inc.items():
            stats[k] += v
        if spacing is not None and "point_spacing" not in stats:
            stats["point_spacing"] = spacing
        for w in frame_warnings:
            warn(w)
        views[both] += 1  # ids are unique within a frame
        if writer is not None:
            writer.append(both)
        else:
            out.append(both.astype(np.int32, copy=False))
        counts[f] = len(both)
    offsets = np.zeros(F + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    if writer is not None:
        writer.close()
        ids = np.load(ids_out, mmap_mode="r")
    else:
        # copy the parts into one array, freeing each as it is copied: np.empty's pages
        # become resident only when written, so the peak stays about one copy of the output
        ids = np.empty(int(offsets[-1]), np.int32)
        for f in range(F):
            ids[offsets[f]:offsets[f + 1]] = out[f]
            out[f] = None
    del out
    vis = Visibility(offsets, ids)
    stats["correspondences"] = int(offsets[-1])
    stats["views_per_point"] = views_summary(views)
    stats["warnings"] = warnings[:MAX_WARNINGS]
    stats["warning_count"] = len(warnings)
    stats["seconds"] = round(time.perf_counter() - t0, 3)
    report(1.0, "visibility")
    return vis, stats

