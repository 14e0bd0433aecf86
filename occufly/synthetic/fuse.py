"""The dense cloud as MVS fusion would produce it: back-projected noisy depth, voxel-hash fusion.

Samples from every image (a pixel grid of the noisy depth maps) are fused one point per hash
cell (mean position, colour and normal); each point's true label is the majority of the true
classes of its contributing pixels, and its visibility is the set of contributing images plus,
optionally, every image whose depth map agrees with the fused point.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occufly.camera import Camera


@dataclass
class Samples:
    """Back-projected depth samples of all images.

    xyz: (S, 3) float32 scene-local metres; rgb: (S, 3) uint8; cls: (S,) uint8 true class of
    the pixel; normal: (S, 3) float16 or float32 world; frame: (S,) int32 image index (0-based).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    cls: np.ndarray
    normal: np.ndarray
    frame: np.ndarray


@dataclass
class FusedCloud:
    """xyz: (N, 3) float64 scene-local; rgb (N, 3) uint8; normal (N, 3) float32 unit;
    label (N,) uint8 majority true class; n_samples (N,) int32; vis_offsets (N + 1,) int64
    and vis_frames (M,) uint32: CSR list of the images that see each point (0-based indices)."""

    xyz: np.ndarray
    rgb: np.ndarray
    normal: np.ndarray
    label: np.ndarray
    n_samples: np.ndarray
    vis_offsets: np.ndarray
    vis_frames: np.ndarray


def sample_grid(camera: Camera, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel grid every ``stride`` pixels -> rows (K,), cols (K,) int64 and unit-z rays (K, 3) float32."""
    rows = np.arange(stride // 2, camera.height, stride)
    cols = np.arange(stride // 2, camera.width, stride)
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    rr, cc = rr.ravel(), cc.ravel()
    rays = camera.unproject(np.column_stack([cc + 0.5, rr + 0.5]), 1.0).astype(np.float32)
    return rr, cc, rays


def back_project(depth: np.ndarray, rays: np.ndarray, rr: np.ndarray, cc: np.ndarray,
                 T_cam_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """depth (H, W) float32 z-depth; rays (K, 3) unit-z camera rays of pixels (rr, cc).
    -> (xyz (K', 3) float32 local, keep (K,) bool: pixels with depth > 0)."""
    d = depth[rr, cc]
    keep = d > 0
    R = T_cam_world[:3, :3]
    c = -R.T @ T_cam_world[:3, 3]
    ray = rays[keep] * d[keep, None]
    xyz = ray[:, 0:1] * R[0].astype(np.float32) + ray[:, 1:2] * R[1].astype(np.float32) \
        + ray[:, 2:3] * R[2].astype(np.float32) + c.astype(np.float32)
    return xyz.astype(np.float32), keep


def unique_sorted(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique values of a 1-D integer array and their counts (sort based; numpy's
    hash-based ``np.unique`` is far slower on millions of distinct values)."""
    a = np.sort(x)
    if not len(a):
        return a, np.zeros(0, np.int64)
    flag = np.empty(len(a), bool)
    flag[0] = True
    np.not_equal(a[1:], a[:-1], out=flag[1:])
    starts = np.flatnonzero(flag)
    return a[starts], np.diff(np.append(starts, len(a)))


def unique_inverse(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sorted unique values, inverse (N,) int64, counts) of a 1-D integer array."""
    order = np.argsort(x)
    a = x[order]
    flag = np.empty(len(a), bool)
    flag[:1] = True
    np.not_equal(a[1:], a[:-1], out=flag[1:])
    ids = np.cumsum(flag) - 1
    inv = np.empty(len(x), np.int64)
    inv[order] = ids
    starts = np.flatnonzero(flag)
    return a[starts], inv, np.diff(np.append(starts, len(a)))


def _majority(cell: np.ndarray, cls: np.ndarray, n_cells: int, priority: np.ndarray) -> np.ndarray:
    """Most frequent class per cell; ties go to the lower ``priority`` rank (taxonomy tie order).

    cell: (S,) int64 in [0, n_cells); cls: (S,) uint8; priority: (256,) int16 rank per id.
    """
    pair = cell.astype(np.int64) * 256 + cls
    u, counts = unique_sorted(pair)
    pc = u // 256
    pcls = (u % 256).astype(np.uint8)
    order = np.lexsort((priority[pcls], -counts, pc))
    pc, pcls = pc[order], pcls[order]
    first = np.ones(len(pc), bool)
    first[1:] = pc[1:] != pc[:-1]
    out = np.zeros(n_cells, np.uint8)
    out[pc[first]] = pcls[first]
    return out


def fuse(samples: Samples, voxel: float, n_frames: int, priority: np.ndarray,
         min_views: int = 1) -> tuple[FusedCloud, tuple[np.ndarray, np.ndarray]]:
    """Fuse samples one point per ``voxel`` cell. Cells with samples from fewer than
    ``min_views`` distinct images are dropped (as COLMAP's fusion drops points with too few
    consistent pixels: the rarely seen periphery and isolated outliers). Returns the cloud and
    the (point ids (P,) int64, frame ids (P,) int32) pairs of the contributing images."""
    xyz = samples.xyz
    lo = xyz.min(axis=0).astype(np.float64) - voxel
    dims = np.floor((xyz.max(axis=0) - lo) / voxel).astype(np.int64) + 2
    parts = _fuse_cells(samples, lo, dims, voxel, n_frames, priority, min_views)
    return _cloud(parts[:5], np.zeros(len(parts[0]) + 1, np.int64)), (parts[5], parts[6])


def _cloud(fields: tuple[np.ndarray, ...], vis_offsets: np.ndarray,
           vis_frames: np.ndarray | None = None) -> FusedCloud:
    xyz, rgb, nrm, label, cnt = fields
    return FusedCloud(xyz, rgb, nrm, label, cnt, vis_offsets,
                      np.zeros(0, np.uint32) if vis_frames is None else vis_frames)


def _fuse_cells(samples: Samples, lo: np.ndarray, dims: np.ndarray, voxel: float, n_frames: int,
                priority: np.ndarray, min_views: int, ix_stop: int | None = None):
    """Fusion on the lattice ``lo`` (3,) float64, ``dims`` (3,) int64. With ``ix_stop``, only the
    cells with x index < ix_stop are fused; the samples of the others are returned (in their
    input order) as the last element. Sums run over each cell's samples in input order.
    Returns (xyz, rgb, normal, label, n_samples, contrib point ids, contrib frames[, held])."""
    xyz = samples.xyz
    key = np.zeros(len(xyz), np.int64)  # built column by column (no (S, 3) int64 temporary)
    for k in range(3):
        key *= dims[k]
        key += np.floor((xyz[:, k] - lo[k]) / voxel).astype(np.int64)
    held = None
    if ix_stop is not None:
        late = key >= ix_stop * dims[1] * dims[2]  # x index >= ix_stop
        if late.any():
            held = np.flatnonzero(late)
            now = np.flatnonzero(~late)
            samples = Samples(*(getattr(samples, f)[now] for f in ("xyz", "rgb", "cls", "normal", "frame")))
            xyz, key = samples.xyz, key[now]
        else:
            held = np.zeros(0, np.int64)
    _, inv, cnt = unique_inverse(key)
    del key
    n = len(cnt)
    out_xyz = np.empty((n, 3), np.float64)
    for k in range(3):
        out_xyz[:, k] = np.bincount(inv, weights=xyz[:, k], minlength=n) / cnt
    rgb = np.empty((n, 3), np.uint8)
    for k in range(3):
        rgb[:, k] = np.round(np.bincount(inv, weights=samples.rgb[:, k], minlength=n) / cnt).astype(np.uint8)
    nrm = np.empty((n, 3), np.float64)
    for k in range(3):
        nrm[:, k] = np.bincount(inv, weights=samples.normal[:, k], minlength=n)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    label = _majority(inv, samples.cls, n, priority)
    pairs, _ = unique_sorted(inv * n_frames + samples.frame)
    del inv
    pc = pairs // n_frames
    pf = (pairs - pc * n_frames).astype(np.int32)
    keep = np.bincount(pc, minlength=n) >= min_views
    new_id = np.cumsum(keep) - 1
    m = keep[pc]
    out = (out_xyz[keep], rgb[keep], nrm[keep].astype(np.float32), label[keep],
           cnt[keep].astype(np.int32), new_id[pc[m]], pf[m])
    return out if ix_stop is None else (*out, held)


_SPILL_FIELDS = (("xyz", np.float32, 3), ("rgb", np.uint8, 3), ("cls", np.uint8, 1),
                 ("normal", np.float16, 3), ("frame", np.int32, 1), ("pix", np.int32, 1))


class SampleSpill:
    """Depth samples streamed to disk in x strips, then fused strip by strip.

    The generator renders one frame at a time and appends its samples here, so memory holds one
    frame's samples, not the whole flight's; :meth:`fuse` then holds one strip's samples (plus
    the one-voxel-wide seam carried to the next strip). The result is identical, bit for bit
    and point for point, to :func:`fuse` on all samples at once: the lattice comes from the
    global bounds, each cell's samples are summed in the same (frame, pixel) order, and strips
    in x order concatenate to the global key order.

    folder: where the strip files go (removed by :meth:`close`); x_edges: (S + 1,) float64
    increasing strip boundaries in scene-local x (samples outside go to the first/last strip).
    """

    def __init__(self, folder: Path, x_edges: np.ndarray) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.edges = np.asarray(x_edges, np.float64)
        self.n_strips = len(self.edges) - 1
        if self.n_strips < 1 or np.any(np.diff(self.edges) <= 0):
            raise ValueError("x_edges must be increasing with at least two values")
        self.counts = np.zeros(self.n_strips, np.int64)
        self.lo = np.full(3, np.inf, np.float32)
        self.hi = np.full(3, -np.inf, np.float32)

        self.parts: list[Path] = [self.folder]  # more than one after :meth:`union`

    @classmethod
    def union(cls, spills: list[SampleSpill]) -> SampleSpill:
        """The spills of consecutive frame ranges (in frame order) as one: strip ``s`` is the
        concatenation of every part's strip ``s``. They must share their strip edges."""
        out = spills[0]
        if len(spills) == 1:
            return out
        for sp in spills[1:]:
            if not np.array_equal(sp.edges, out.edges):
                raise ValueError("spills with different strip edges cannot be joined")
        joined = object.__new__(cls)
        joined.folder, joined.edges, joined.n_strips = out.folder, out.edges, out.n_strips
        joined.counts = np.sum([sp.counts for sp in spills], axis=0)
        joined.lo = np.min([sp.lo for sp in spills], axis=0)
        joined.hi = np.max([sp.hi for sp in spills], axis=0)
        joined.parts = [p for sp in spills for p in sp.parts]
        return joined

    def _path(self, s: int, field: str, part: Path | None = None) -> Path:
        return (part or self.folder) / f"strip{s:04d}.{field}"

    @property
    def n_samples(self) -> int:
        return int(self.counts.sum())

    def add(self, xyz: np.ndarray, rgb: np.ndarray, cls: np.ndarray, normal: np.ndarray,
            frame: int, pix: np.ndarray) -> None:
        """One frame's samples, in pixel order. xyz (K, 3) float32 local; rgb (K, 3) uint8;
        cls (K,) uint8; normal (K, 3) float16; pix (K,) int32 increasing sample index."""
        if not len(xyz):
            return
        self.lo = np.minimum(self.lo, xyz.min(axis=0))
        self.hi = np.maximum(self.hi, xyz.max(axis=0))
        strip = np.clip(np.searchsorted(self.edges, xyz[:, 0].astype(np.float64), side="right") - 1,
                        0, self.n_strips - 1)
        order = np.argsort(strip, kind="stable")
        bounds = np.searchsorted(strip[order], np.arange(self.n_strips + 1))
        cols = {"xyz": xyz, "rgb": rgb, "cls": cls, "normal": normal,
                "frame": np.full(len(xyz), frame, np.int32), "pix": pix.astype(np.int32)}
        for s in np.flatnonzero(np.diff(bounds)):
            sel = order[bounds[s] : bounds[s + 1]]
            for name, dtype, _ in _SPILL_FIELDS:
                with open(self._path(s, name), "ab") as fh:
                    np.ascontiguousarray(cols[name][sel], dtype=dtype).tofile(fh)
            self.counts[s] += len(sel)

    def _load(self, s: int) -> dict[str, np.ndarray]:
        out = {}
        for name, dtype, width in _SPILL_FIELDS:
            chunks = [np.fromfile(p, dtype=dtype) for p in (self._path(s, name, part) for part in self.parts)
                      if p.exists()]
            a = np.concatenate(chunks) if chunks else np.zeros(0, dtype)
            out[name] = a.reshape(-1, width) if width > 1 else a
        return out

    def fuse(self, voxel: float, n_frames: int, priority: np.ndarray, min_views: int = 1,
             progress=None) -> tuple[FusedCloud, tuple[np.ndarray, np.ndarray]]:
        """Same result as :func:`fuse` on every sample added, strip by strip."""
        if not self.n_samples:
            raise ValueError("no depth samples to fuse")
        lo = self.lo.astype(np.float64) - voxel
        dims = np.floor((self.hi - lo) / voxel).astype(np.int64) + 2
        parts: list[tuple] = []
        carry: dict[str, np.ndarray] | None = None
        offset = 0
        for s in range(self.n_strips):
            cur = self._load(s)
            if carry is not None and len(carry["frame"]):  # seam cells: restore (frame, pixel) order
                cur = {k: np.concatenate([carry[k], cur[k]]) for k in cur}
                order = np.lexsort((cur["pix"], cur["frame"]))
                cur = {k: v[order] for k, v in cur.items()}
            if not len(cur["frame"]):
                carry = None
                continue
            last = s == self.n_strips - 1
            # cells with x index >= ix_stop may also hold samples of the next strips
            ix_stop = None if last else int(np.floor((self.edges[s + 1] - lo[0]) / voxel))
            smp = Samples(cur["xyz"], cur["rgb"], cur["cls"], cur["normal"], cur["frame"])
            res = _fuse_cells(smp, lo, dims, voxel, n_frames, priority, min_views, ix_stop)
            if last:
                carry = None
            else:
                held = res[7]
                carry = {k: v[held] for k, v in cur.items()}
                res = res[:7]
            del cur, smp
            xyz_, rgb_, nrm_, lab_, cnt_, cp, cf = res
            parts.append((xyz_, rgb_, nrm_, lab_, cnt_, cp + offset, cf))
            offset += len(xyz_)
            if progress is not None:
                progress((s + 1) / self.n_strips, f"fusing strip {s + 1}/{self.n_strips}")
        fields = tuple(np.concatenate([p[k] for p in parts]) for k in range(7))
        return _cloud(fields[:5], np.zeros(offset + 1, np.int64)), (fields[5], fields[6])

    def close(self) -> None:
        for part in self.parts:
            for s in range(self.n_strips):
                for name, _, _ in _SPILL_FIELDS:
                    self._path(s, name, part).unlink(missing_ok=True)
            for d in (part, part.parent):
                try:
                    d.rmdir()
                except OSError:
                    pass


class TileIndex:
    """Points bucketed into square xy tiles, for cheap "points inside this xy box" queries.

    xyz: (N, 3) float64 scene-local metres.
    """

    def __init__(self, xyz: np.ndarray, tile: float = 8.0) -> None:
        self.tile = tile
        self.lo = xyz[:, :2].min(axis=0)
        ij = np.floor((xyz[:, :2] - self.lo) / tile).astype(np.int64)
        self.shape = ij.max(axis=0) + 1
        tid = ij[:, 0] * self.shape[1] + ij[:, 1]
        self.order = np.argsort(tid, kind="stable").astype(np.int64)
        self.starts = np.searchsorted(tid[self.order], np.arange(int(np.prod(self.shape)) + 1))

    def query(self, x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
        """(K,) int64 indices of the points in the tiles overlapping [x0, x1] x [y0, y1]."""
        i0, j0 = np.floor((np.array([x0, y0]) - self.lo) / self.tile).astype(np.int64)
        i1, j1 = np.floor((np.array([x1, y1]) - self.lo) / self.tile).astype(np.int64)
        i0, i1 = max(i0, 0), min(i1, self.shape[0] - 1)
        j0, j1 = max(j0, 0), min(j1, self.shape[1] - 1)
        if i1 < i0 or j1 < j0:
            return np.zeros(0, np.int64)
        parts = [self.order[self.starts[i * self.shape[1] + j0] : self.starts[i * self.shape[1] + j1 + 1]]
                 for i in range(i0, i1 + 1)]
        return np.concatenate(parts)


def depth_agreement(xyz: np.ndarray, index: TileIndex, camera: Camera, T_cam_world: np.ndarray,
                    depth: np.ndarray, bbox: tuple[float, float, float, float], tol: float) -> np.ndarray:
    """(K,) int64 indices of the points whose projection into the image lands on a depth within
    ``tol`` (relative) of the point's own camera depth.

    xyz: (N, 3) float64 local points; index: a :class:`TileIndex` of them; depth: (H, W)
    float32 the image's (noisy) depth map; bbox: local (x0, x1, y0, y1) of the surface the
    image sees (a superset filter).
    """
    cand = index.query(*bbox)
    p = xyz[cand]
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    xc = p[:, 0:1] * R[:, 0] + p[:, 1:2] * R[:, 1] + p[:, 2:3] * R[:, 2] + t
    z = xc[:, 2]
    front = z > 1e-6
    fx, fy = camera.focal
    cx, cy = camera.principal_point
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * xc[:, 0] / z + cx
        v = fy * xc[:, 1] / z + cy
    inside = front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    cand, z, u, v = cand[inside], z[inside], u[inside], v[inside]
    d = depth[v.astype(np.int64), u.astype(np.int64)]
    ok = (d > 0) & (np.abs(d - z) <= tol * z)
    return cand[ok]


def build_visibility(n_points: int, n_frames: int, point_ids: list[np.ndarray],
                     frame_ids: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Union of (point, frame) pairs -> CSR (offsets (N + 1,) int64, frames (M,) uint32),
    each point's frames sorted ascending and unique."""
    keys = np.concatenate([p.astype(np.int64) * n_frames + f for p, f in zip(point_ids, frame_ids, strict=False)])
    keys, _ = unique_sorted(keys)
    pts = keys // n_frames
    frames = (keys - pts * n_frames).astype(np.uint32)
    offsets = np.zeros(n_points + 1, np.int64)
    np.cumsum(np.bincount(pts, minlength=n_points), out=offsets[1:])
    return offsets, frames
