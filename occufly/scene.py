"""The scene model and its on-disk workspace.

A :class:`Scene` holds the frames (camera, world-to-camera pose, image), the dense point cloud
in float32 *scene-local* coordinates plus a float64 origin offset (``xyz_world = origin +
xyz``), and the 2D-3D visibility as CSR-like arrays: for frame ``f`` the slice
``offsets[f]:offsets[f + 1]`` of ``point_ids`` / ``uv`` / ``depth`` lists the points it sees,
where they project and at what camera depth.

Workspace layout (all arrays ``.npy``, memory-mapped on load)::

    WS/scene.json                 format, version, origin, frames, meta, counts
    WS/taxonomy.json              the scene's class table
    WS/points/xyz.npy             (N, 3) float32 scene-local metres
    WS/points/rgb.npy             (N, 3) uint8
    WS/visibility/offsets.npy     (F + 1,) int64
    WS/visibility/point_ids.npy   (M,) int32
    WS/visibility/uv.npy          (M, 2) float32 pixels (COLMAP convention)  [optional]
    WS/visibility/depth.npy       (M,) float32 camera z in metres            [optional]

``uv.npy`` / ``depth.npy`` are written only for a visibility that carries them (version-1
workspaces always did); without them they are recomputed by projecting each frame's points
(:class:`Visibility`), which is what an import computed them with in the first place.

Later pipeline steps add their own sub-folders (labels, grids, exports) next to these.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from occufly.camera import Camera, camera_center, viewing_direction
from occufly.errors import WorkspaceError
from occufly.fsutil import atomic_directory
from occufly.taxonomy import Taxonomy, default_taxonomy
from occufly.workspace import Workspace

WORKSPACE_FORMAT = "occufly-workspace"
WORKSPACE_VERSION = 2  # 2: visibility uv/depth optional (projected on demand)


@dataclass
class Frame:
    """One registered image.

    T_cam_world: (4, 4) float64 world-to-camera in *scene-local* coordinates.
    """

    name: str
    camera: Camera
    T_cam_world: np.ndarray
    image_path: str | None = None
    altitude: float = math.nan
    nominal_altitude: int | None = None

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 camera centre, scene-local metres."""
        return camera_center(self.T_cam_world)

    @property
    def direction(self) -> np.ndarray:
        """(3,) float64 unit optical axis, scene-local frame."""
        return viewing_direction(self.T_cam_world)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "camera": self.camera.to_dict(),
            "T_cam_world": np.asarray(self.T_cam_world, dtype=np.float64).tolist(),
            "image_path": self.image_path,
            "altitude": None if math.isnan(self.altitude) else float(self.altitude),
            "nominal_altitude": self.nominal_altitude,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Frame:
        alt = d.get("altitude")
        return cls(
            name=d["name"],
            camera=Camera.from_dict(d["camera"]),
            T_cam_world=np.asarray(d["T_cam_world"], dtype=np.float64),
            image_path=d.get("image_path"),
            altitude=math.nan if alt is None else float(alt),
            nominal_altitude=d.get("nominal_altitude"),
        )


class Visibility:
    """2D-3D correspondences, CSR by frame.

    offsets: (F + 1,) int64; point_ids: (M,) int32, ascending within a frame; uv: (M, 2)
    float32 pixels; depth: (M,) float32 camera z in metres.

    ``uv`` and ``depth`` may be stored (workspaces before version 2, the synthetic
    generator) or, when omitted, recomputed on demand by projecting the points with the
    frame's camera (:meth:`bind` gives the frames and points; :class:`Scene` does it): both
    are a pure function of the point, the pose and the camera, so a workspace only stores
    4 bytes per correspondence instead of 16. :meth:`frame` projects one frame at a time.
    """

    def __init__(self, offsets: np.ndarray, point_ids: np.ndarray,
                 uv: np.ndarray | None = None, depth: np.ndarray | None = None) -> None:
        self.offsets = offsets
        self.point_ids = point_ids
        if (uv is None) != (depth is None):
            raise ValueError("visibility: give both uv and depth, or neither")
        self._uv = uv
        self._depth = depth
        self._frames = None
        self._xyz = None

    @classmethod
    def empty(cls, n_frames: int) -> Visibility:
        return cls(
            np.zeros(n_frames + 1, np.int64),
            np.zeros(0, np.int32),
            np.zeros((0, 2), np.float32),
            np.zeros(0, np.float32),
        )

    @classmethod
    def from_parts(
        cls, parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    ) -> Visibility:
        """parts[f] = (point_ids (m,), uv (m, 2), depth (m,)) for each frame in order."""
        counts = np.array([len(p[0]) for p in parts], dtype=np.int64)
        offsets = np.zeros(len(parts) + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        if len(parts) and offsets[-1]:
            ids = np.concatenate([p[0] for p in parts]).astype(np.int32, copy=False)
            uv = np.concatenate([np.asarray(p[1]).reshape(-1, 2) for p in parts]).astype(np.float32)
            depth = np.concatenate([p[2] for p in parts]).astype(np.float32, copy=False)
        else:
            return cls.empty(len(parts))
        return cls(offsets, ids, uv, depth)

    @property
    def stores_projections(self) -> bool:
        """True when uv/depth are stored arrays, False when they are projected on demand."""
        return self._uv is not None

    def bind(self, frames: list[Frame], xyz: np.ndarray) -> None:
        """Frames and points to project with when uv/depth are not stored."""
        self._frames = frames
        self._xyz = xyz

    def project(self, f: int, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(uv (m, 2), depth (m,)) float32 of points ``ids`` in frame ``f``, projected from the
        bound cloud (:meth:`bind`) as :meth:`frame` does when uv/depth are not stored: a caller
        that needs only some of a frame's points projects those."""
        if self._frames is None:
            raise ValueError("visibility without stored uv/depth needs bind(frames, xyz) first")
        uv, z = project_points(self._frames[f], self._xyz, np.asarray(ids, np.int64))
        return uv.astype(np.float32), z.astype(np.float32)

    @property
    def uv(self) -> np.ndarray:
        """(M, 2) float32 pixels of every correspondence (projected for all frames if not
        stored: O(M) memory -- prefer :meth:`frame`)."""
        if self._uv is None:
            return self._all()[0]
        return self._uv

    @property
    def depth(self) -> np.ndarray:
        """(M,) float32 camera depth of every correspondence (see :attr:`uv`)."""
        if self._depth is None:
            return self._all()[1]
        return self._depth

    def _all(self) -> tuple[np.ndarray, np.ndarray]:
        m = int(self.offsets[-1])
        uv = np.zeros((m, 2), np.float32)
        depth = np.zeros(m, np.float32)
        for f in range(self.n_frames):
            a, b = int(self.offsets[f]), int(self.offsets[f + 1])
            if b > a:
                uv[a:b], depth[a:b] = self.project(f, self.point_ids[a:b])
        return uv, depth

    @property
    def n_frames(self) -> int:
        return len(self.offsets) - 1

    def frame_ids(self, f: int) -> np.ndarray:
        """(m,) int32 ids of the points frame ``f`` sees (no projection)."""
        a, b = int(self.offsets[f]), int(self.offsets[f + 1])
        return self.point_ids[a:b]

    def projected_on_demand(self) -> np.ndarray | None:
        """The (N, 3) cloud :meth:`frame` projects from when uv/depth are not stored (bound by
        :meth:`bind`), else None: a caller may then project :meth:`frame_ids` itself."""
        return self._xyz if self._uv is None and self._frames is not None else None

    def frame(self, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point_ids (m,) int32, uv (m, 2) float32, depth (m,) float32) seen by frame ``f``."""
        a, b = int(self.offsets[f]), int(self.offsets[f + 1])
        ids = self.point_ids[a:b]
        if self._uv is None:
            uv, depth = self.project(f, ids)
            return ids, uv, depth
        return ids, self._uv[a:b], self._depth[a:b]

    def counts_per_frame(self) -> np.ndarray:
        return np.diff(self.offsets)

    def views_per_point(self, n_points: int) -> np.ndarray:
        """(N,) int64 number of frames that see each point (chunked: bincount casts its input
        to int64, which on 266 M correspondences alone is 2 GB)."""
        out = np.zeros(n_points, np.int64)
        for _a, ids in self.point_id_chunks():
            out += np.bincount(ids, minlength=n_points)
        return out

    def point_id_chunks(self, step: int = 1 << 24) -> Iterator[tuple[int, np.ndarray]]:
        """(position of the first, point ids) of the correspondences, ``step`` at a time, in
        order. A memory-mapped file is read once: its resident pages are released after each
        chunk, so the RSS stays at one chunk (2 B correspondences are 8.6 GB on a survey)."""
        ids = self.point_ids
        for a in range(0, len(ids), step):
            yield a, np.asarray(ids[a:a + step])
            _drop_resident(ids)

    def frames_of_entries(self) -> np.ndarray:
        """(M,) int32 frame index of each correspondence."""
        return np.repeat(np.arange(self.n_frames, dtype=np.int32), self.counts_per_frame())


@dataclass
class Scene:
    """Frames, dense points and visibility, in scene-local coordinates."""

    frames: list[Frame]
    xyz: np.ndarray  # (N, 3) float32 scene-local metres
    rgb: np.ndarray  # (N, 3) uint8
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) float64 world offset
    visibility: Visibility | None = None
    taxonomy: Taxonomy = field(default_factory=default_taxonomy)
    meta: dict = field(default_factory=dict)
    # the cloud's coordinate reference system {"name", "epsg", "wkt"} (occufly.io.crs), or None
    # for a local frame; world coordinates = origin + xyz are in it
    crs: dict | None = None

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise ValueError(f"xyz must be (N, 3), got {self.xyz.shape}")
        if self.rgb.shape != self.xyz.shape:
            raise ValueError(f"rgb must be {self.xyz.shape}, got {self.rgb.shape}")
        if self.visibility is None:
            self.visibility = Visibility.empty(len(self.frames))
        self.visibility.bind(self.frames, self.xyz)
        if self.visibility.n_frames != len(self.frames):
            raise ValueError(
                f"visibility has {self.visibility.n_frames} frames, scene has {len(self.frames)}"
            )

    # ---- convenience ---------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return int(self.xyz.shape[0])

    def frame_index(self, name_or_stem: str) -> int:
        for i, f in enumerate(self.frames):
            if f.name == name_or_stem or f.stem == name_or_stem:
                return i
        raise KeyError(name_or_stem)

    def centers(self) -> np.ndarray:
        """(F, 3) float64 camera centres, scene-local."""
        return np.array([f.center for f in self.frames]).reshape(-1, 3)

    def xyz_world(self, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        """(N, 3) float64 points in the original (e.g. UTM) coordinates."""
        return np.asarray(self.xyz[idx], dtype=np.float64) + self.origin

    def summary(self) -> dict:
        vis = self.visibility
        views = vis.views_per_point(self.n_points) if self.n_points else np.zeros(0, int)
        per_frame = vis.counts_per_frame()
        alts: dict[str, int] = {}
        for f in self.frames:
            key = "unknown" if f.nominal_altitude is None else str(f.nominal_altitude)
            alts[key] = alts.get(key, 0) + 1
        lo = self.xyz.min(axis=0).tolist() if self.n_points else [0, 0, 0]
        hi = self.xyz.max(axis=0).tolist() if self.n_points else [0, 0, 0]
        return {
            "frames": len(self.frames),
            "points": self.n_points,
            "origin": self.origin.tolist(),
            "bounds_local": {"min": lo, "max": hi},
            "visibility": {
                "correspondences": int(vis.offsets[-1]),
                "points_seen": int((views > 0).sum()),
                "points_unseen": int((views == 0).sum()),
                "frames_without_points": int((per_frame == 0).sum()),
                "points_per_frame_min": int(per_frame.min()) if len(per_frame) else 0,
                "points_per_frame_mean": float(per_frame.mean()) if len(per_frame) else 0.0,
                "views_per_point_mean": float(views.mean()) if len(views) else 0.0,
                "views_per_point": views_summary(views),
                "stores_uv": bool(vis.stores_projections),
            },
            "altitudes": alts,
            "taxonomy": {"name": self.taxonomy.name, "classes": len(self.taxonomy)},
            "crs": ({"name": self.crs.get("name"), "epsg": self.crs.get("epsg")}
                    if self.crs else None),
            "meta": self.meta,
        }

    # ---- workspace -----------------------------------------------------------------------
    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the workspace atomically: all of it appears, or nothing changes."""
        path = Path(path)
        if path.exists() and not overwrite:
            raise WorkspaceError(f"{path}: workspace already exists (use --force to replace it)")
        with atomic_directory(path, overwrite=overwrite) as tmp:
            self._write_into(tmp)
        return path

    def write_into(self, root: Path) -> None:
        """Write the workspace's files into the (new, e.g. atomic temporary) folder ``root``;
        point ids memory-mapped from ``root/visibility/point_ids.npy`` stay where they are."""
        self._write_into(Path(root))

    def _write_into(self, root: Path) -> None:
        ws = Workspace(root)
        ws.points_dir.mkdir()
        ws.visibility_dir.mkdir(exist_ok=True)  # the import may have streamed its ids there
        np.save(ws.points_xyz, np.ascontiguousarray(self.xyz, dtype=np.float32))
        np.save(ws.points_rgb, np.ascontiguousarray(self.rgb, dtype=np.uint8))
        v = self.visibility
        np.save(ws.visibility_array("offsets"), np.asarray(v.offsets, np.int64))
        ids_path = ws.visibility_array("point_ids")
        if not _mapped_from(v.point_ids, ids_path):  # else already written there (streamed)
            np.save(ids_path, np.asarray(v.point_ids, np.int32))
        if v.stores_projections:  # else they are recomputed on load (workspace version 2)
            np.save(ws.visibility_array("uv"), np.asarray(v.uv, np.float32))
            np.save(ws.visibility_array("depth"), np.asarray(v.depth, np.float32))
        ws.taxonomy_json.write_text(json.dumps(self.taxonomy.to_dict(), indent=1))
        ws.scene_json.write_text(json.dumps(self._header(), indent=1))

    def _header(self) -> dict:
        return {
            "format": WORKSPACE_FORMAT,
            "version": WORKSPACE_VERSION,
            "origin": self.origin.tolist(),
            "n_points": self.n_points,
            "frames": [f.to_dict() for f in self.frames],
            "meta": self.meta,
            "crs": self.crs,
        }

    @classmethod
    def load(cls, path: str | Path, *, mmap: bool = True) -> Scene:
        path = Path(path)
        ws = Workspace(path)
        header_path = ws.scene_json
        if not header_path.is_file():
            raise WorkspaceError(f"{path}: not a scene workspace (no scene.json)")
        try:
            header = json.loads(header_path.read_text())
        except json.JSONDecodeError as e:
            raise WorkspaceError(f"{header_path}: not valid JSON ({e})") from None
        if header.get("format") != WORKSPACE_FORMAT:
            raise WorkspaceError(f"{header_path}: not an OccuFly workspace header")
        if header.get("version", 0) > WORKSPACE_VERSION:
            raise WorkspaceError(
                f"{header_path}: workspace version {header['version']} is newer than this "
                f"OccuFly ({WORKSPACE_VERSION})"
            )
        def arr(p: Path) -> np.ndarray:
            return ws.array(p, mmap=mmap)

        tax_path = ws.taxonomy_json
        taxonomy = Taxonomy.load(tax_path) if tax_path.is_file() else default_taxonomy()
        frames = [Frame.from_dict(d) for d in header["frames"]]
        stored = ws.visibility_array("uv").is_file() or ws.visibility_array("depth").is_file()
        vis = Visibility(
            arr(ws.visibility_array("offsets")),
            arr(ws.visibility_array("point_ids")),
            arr(ws.visibility_array("uv")) if stored else None,
            arr(ws.visibility_array("depth")) if stored else None,
        )
        return cls(
            frames=frames,
            xyz=arr(ws.points_xyz),
            rgb=arr(ws.points_rgb),
            origin=np.asarray(header["origin"], dtype=np.float64),
            visibility=vis,
            taxonomy=taxonomy,
            meta=header.get("meta", {}),
            crs=header.get("crs"),
        )


def _drop_resident(a: np.ndarray) -> None:
    """Release the resident pages of a memory-mapped array (read-only use: the file keeps
    them; the page cache may too). A no-op for arrays in memory."""
    mm = getattr(a, "_mmap", None)
    if mm is None or not hasattr(mm, "madvise"):
        return
    try:
        import mmap

        mm.madvise(mmap.MADV_DONTNEED)
    except (OSError, ValueError, AttributeError):
        pass


def _mapped_from(a: np.ndarray, path: Path) -> bool:
    """True when ``a`` is the whole of the int32 ``.npy`` file ``path``, memory-mapped."""
    fn = getattr(a, "filename", None)
    if not isinstance(a, np.memmap) or fn is None or not path.is_file():
        return False
    try:
        return (os.path.samefile(fn, path) and a.dtype == np.int32
                and a.size * 4 + int(a.offset) == path.stat().st_size)
    except OSError:
        return False


# ---- altitudes ---------------------------------------------------------------------------------
def ground_height_under(
    xyz: np.ndarray, centers_xy: np.ndarray, *, radius: float = 20.0, percentile: float = 5.0
) -> np.ndarray:
    """Ground height below each camera: a low percentile of point z within ``radius`` in XY.

    xyz: (N, 3) float32 scene-local, z up; centers_xy: (F, 2) float64.
    Cameras with no point nearby fall back to the global percentile. Returns (F,) float64.
    """
    xyz = np.asarray(xyz)
    if len(xyz) == 0:
        return np.zeros(len(centers_xy))
    step = max(1, len(xyz) // 500_000)  # a subsample is plenty for a percentile
    sub = np.asarray(xyz[::step], dtype=np.float64)
    tree = cKDTree(sub[:, :2])
    global_h = float(np.percentile(sub[:, 2], percentile))
    out = np.full(len(centers_xy), global_h)
    for i, nbrs in enumerate(tree.query_ball_point(centers_xy, r=radius)):
        if len(nbrs) >= 10:
            out[i] = np.percentile(sub[nbrs, 2], percentile)
    return out


def bin_altitudes(
    altitudes: np.ndarray, nominal: list[float] | None = None, *, gap: float = 4.0,
    round_to: float = 5.0,
) -> np.ndarray:
    """Assign each altitude (F,) to a nominal flight altitude; returns (F,) int.

    With ``nominal`` given, the nearest one. Otherwise altitudes are clustered (a sorted gap
    larger than ``gap`` metres starts a new cluster) and each cluster's median is rounded to
    a multiple of ``round_to`` metres (flights are planned in round numbers), so a survey
    flown at 50/40/30 m bins to exactly those values despite +-2 m of terrain error.
    """
    alt = np.asarray(altitudes, dtype=np.float64)
    if len(alt) == 0:
        return np.zeros(0, dtype=int)
    if nominal:
        nom = np.asarray(sorted(nominal), dtype=np.float64)
        return nom[np.abs(alt[:, None] - nom[None, :]).argmin(axis=1)].round().astype(int)
    order = np.argsort(alt)
    cluster = np.zeros(len(alt), dtype=int)
    cluster[order[1:]] = np.cumsum(np.diff(alt[order]) > gap)
    out = np.empty(len(alt), dtype=int)
    for c in np.unique(cluster):
        sel = cluster == c
        out[sel] = int(round(float(np.median(alt[sel])) / round_to) * round_to)
    return out


def assign_altitudes(scene: Scene, nominal: list[float] | None = None) -> None:
    """Fill ``altitude`` (above ground) and ``nominal_altitude`` of every frame (z up)."""
    if not scene.frames:
        return
    centers = scene.centers()
    ground = ground_height_under(scene.xyz, centers[:, :2])
    alts = centers[:, 2] - ground
    bins = bin_altitudes(alts, nominal)
    for f, a, b in zip(scene.frames, alts, bins, strict=True):
        f.altitude = float(a)
        f.nominal_altitude = int(b)


def project_points(frame: Frame, xyz: np.ndarray, ids: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(uv (m, 2) float64 pixels, z (m,) float64 camera depth) of points ``ids`` in ``frame``
    (no culling). The one projection both the import and on-demand uv/depth use."""
    pts = np.asarray(xyz[ids])
    T = np.asarray(frame.T_cam_world, dtype=np.float64)
    x, y, z = (pts[:, i].astype(np.float64) for i in range(3))
    cam = np.empty((len(pts), 3), np.float64)
    # element-wise, not a (m, 3) @ (3, 3) matmul: BLAS threads on a 3-wide product are
    # several times slower on a busy machine (measured 3.5x)
    for i in range(3):
        cam[:, i] = x * T[i, 0] + y * T[i, 1] + z * T[i, 2] + T[i, 3]
    return frame.camera.project(cam)


def views_summary(views: np.ndarray) -> dict:
    """Mean / median / percentiles of views per point (``views``: (N,) counts)."""
    views = np.asarray(views)
    if not len(views):
        return {"mean": 0.0, "median": 0.0, "p10": 0.0, "p90": 0.0, "unseen": 0}
    p10, p50, p90 = np.percentile(views, [10, 50, 90])
    return {"mean": round(float(views.mean()), 3), "median": float(p50), "p10": float(p10),
            "p90": float(p90), "unseen": int((views == 0).sum())}
