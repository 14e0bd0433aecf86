"""``export_dataset``: per-frame ground truth for a scene workspace, written in the OccuFly or
SSCBench layout through the executor interface.

Guarantees
- Everything that can be checked is checked before anything is written: the target (it must
  be empty / absent, an export root of the same layout, or an earlier export of *this* scene
  -- same scene fingerprint), every selected frame's pose, altitude and image.
- Each frame's files are all written to hidden temporary names first, then renamed into
  place together, then a done marker (in ``<root>/.occufly_export/<layout>/<scene_id>/done/``)
  recording the config hash and file sizes is written last
  (:func:`occufly.export.common.write_frame_files`). A rerun sweeps leftover temporaries,
  skips frames whose marker matches and whose files have the recorded sizes, and rewrites
  the rest, so an interrupted export resumes where it stopped.
- Disk full raises :class:`ExportError` with a clear message; completed frames are kept.
- The manifest (taxonomy, provenance, sampling parameters, frames) is written before the
  frames with ``complete: false`` and rewritten with ``complete: true`` at the end.

Grids per altitude: ``grid`` may be a :class:`SceneGrid` (used for every frame) or a dict
``{altitude: SceneGrid}``; when None, ``WS/grid/scene_grid_<alt>.npz`` files are used if
present, else ``WS/grid/scene_grid.npz``. ``grid_for_altitude`` maps a frame's altitude to
the altitude whose grid it samples; by default every frame samples the grid of the highest
altitude available ("frames at 40/30 m sample the grid built from the 50 m data").
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.export import occufly as occufly_layout
from occufly.export import splits as split_rules
from occufly.export import sscbench as sscbench_layout
from occufly.export.axes import frame_axes
from occufly.export.common import (
    DOWNSAMPLE_RULES,
    EXPORT_FORMAT_VERSION,
    ExportDiskFull,
    ExportError,
    cached,
    clean_stray_temporaries,
    frame_done,
    grid_digest,
    image_as_png,
    is_disk_full,
    scene_fingerprint,
    sha256_bytes,
    write_frame_files,
)
from occufly.fsutil import atomic_write_bytes, fsync_dir, ordinary_mode, pid_alive
from occufly.grid import SceneGrid
from occufly.progress import ProgressFn
from occufly.sampling import (
    FrameGridSpec,
    check_pose,
    frame_depth_map,
    quarter_shape,
    resample_depth,
    sample_frame,
)
from occufly.workspace import Workspace

LAYOUTS = {"occufly": occufly_layout, "sscbench": sscbench_layout}
SCENE_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
SPLITS = ("train", "val", "test")
MAX_CAMERAS = 8


def camera_groups(scene, idx: list[int]) -> list[list[int]]:
    """Frame indices grouped by identical camera (model, size, parameters): the largest group
    first, then by first frame."""
    by: dict[str, list[int]] = {}
    for i in idx:
        by.setdefault(json.dumps(scene.frames[i].camera.to_dict(), sort_keys=True), []).append(i)
    return sorted(by.values(), key=lambda g: (-len(g), g[0]))


def group_scene_ids(scene_id: str, n: int) -> list[str]:
    return [scene_id] + [f"{scene_id}_cam{k}" for k in range(2, n + 1)]


def default_split(scene_id: str) -> str:
    """The release's split rule: scenes 1-5 train, 6-7 val, 8-9 test; anything else train."""
    m = re.match(r"^scene_?0*(\d+)", scene_id)
    if m:
        k = int(m.group(1))
        if k in (6, 7):
            return "val"
        if k in (8, 9):
            return "test"
    return "train"


def frame_id_of(index: int) -> str:
    return f"{index:06d}"


def frame_altitude(frame, where: str) -> int:
    if frame.nominal_altitude is not None:
        return int(frame.nominal_altitude)
    if frame.altitude is not None and math.isfinite(frame.altitude):
        return int(round(frame.altitude))
    raise ExportError(f"{where}: frame {frame.name!r} has no altitude (run import / altitudes first)")


def _resolve_grids(ws: Path, grid, altitudes: set[int], grid_for_altitude: dict[int, int] | None
                   ) -> tuple[dict[int, SceneGrid], dict[int, int], dict[int, str]]:
    """-> (grids by source altitude or -1 for the single grid, frame altitude -> grid key,
    grid key -> provenance string)."""
    grids: dict[int, SceneGrid] = {}
    source: dict[int, str] = {}
    if isinstance(grid, SceneGrid):
        grids[-1], source[-1] = grid, "given"
    elif isinstance(grid, dict):
        for k, g in grid.items():
            if not isinstance(g, SceneGrid):
                raise TypeError("grid dict values must be SceneGrid")
            grids[int(k)], source[int(k)] = g, "given"
    elif grid is None:
        for p in sorted(Workspace(ws).grid_dir.glob("scene_grid_*.npz")):
            m = re.match(r"scene_grid_(\d+)\.npz$", p.name)
            if m:
                grids[int(m.group(1))], source[int(m.group(1))] = SceneGrid.load(p), str(p)
        if not grids:
            p = Workspace(ws).grid_path()
            if not p.is_file():
                raise ExportError(
                    f"{p}: no scene grid in the workspace; run `occufly voxelize` first "
                    "(or pass a grid)")
            grids[-1], source[-1] = SceneGrid.load(p), str(p)
    else:
        raise TypeError(f"grid must be a SceneGrid, a dict or None, got {type(grid).__name__}")
    mapping: dict[int, int] = {}
    keys = sorted(k for k in grids if k >= 0)
    for alt in altitudes:
        want = (grid_for_altitude or {}).get(alt)
        if want is not None:
            if want in grids:
                mapping[alt] = want
            elif -1 in grids:
                mapping[alt] = -1
            else:
                raise ExportError(f"grid_for_altitude asks for the {want} m grid; available: {keys}")
        elif -1 in grids:
            mapping[alt] = -1
        else:
            mapping[alt] = max(keys)  # the highest flight's grid
    return grids, mapping, source


def _image_png(path: str | None, where: str) -> bytes:
    if not path or not Path(path).is_file():
        raise ExportError(f"{where}: image file {path!r} not found")
    p = Path(path)
    if p.suffix.lower() == ".png":
        return p.read_bytes()
    from PIL import Image

    try:
        with Image.open(p) as im:
            return image_as_png(im)
    except OSError as e:
        raise InputFormatError(f"{p}: cannot read image ({e})") from None


def frame_points(scene, f: int) -> np.ndarray:
    """(N, 4) float32 "velodyne" points of frame ``f``: the fused points it sees (its
    visibility list, else every point projecting into the image in front of it) in the camera
    frame, 4th column the grey value of the point colour in [0, 1]."""
    from occufly.camera import project_world, transform

    frame = scene.frames[f]
    vis = scene.visibility
    if vis is not None and vis.n_frames > f and vis.offsets[f + 1] > vis.offsets[f]:
        ids = np.asarray(vis.point_ids[vis.offsets[f]:vis.offsets[f + 1]], dtype=np.int64)
    else:
        _uv, _z, visible = project_world(frame.camera, frame.T_cam_world, np.asarray(scene.xyz))
        ids = np.flatnonzero(visible)
    xyz = transform(frame.T_cam_world, np.asarray(scene.xyz)[ids].astype(np.float64))
    keep = xyz[:, 2] > 0
    rgb = np.asarray(scene.rgb)[ids][keep].astype(np.float32)
    grey = (0.299 * rgb[:, 0] + 0.587 * rgb[:, 1] + 0.114 * rgb[:, 2]) / 255.0
    return np.column_stack([xyz[keep], grey]).astype(np.float32)


# ---- the per-frame task (runs in a worker process or on a Dask worker) ---------------------
def export_frame_task(task: dict) -> dict:
    """Compute and write one frame. ``task`` holds only paths and small values."""
    from occufly.scene import Scene

    t0, c0 = time.perf_counter(), time.process_time()
    ws, root = Path(task["ws"]), Path(task["out"])
    scene = cached(("scene", task["ws"], task["scene_mtime"]), lambda: Scene.load(ws))
    grid = cached(("grid", task["grid_path"], task["grid_digest"]),
                  lambda: SceneGrid.load(task["grid_path"]))
    f = task["frame_index"]
    frame = scene.frames[f]
    spec = FrameGridSpec(**task["spec"])
    gt = sample_frame(grid, frame.camera, frame.T_cam_world, scene.origin, spec)
    t_sample = time.perf_counter() - t0
    depth, depth_src = frame_depth_map(scene, f)
    image = _image_png(frame.image_path, f"frame {frame.name}")
    layout = LAYOUTS[task["layout"]]
    pose = np.linalg.inv(frame.T_cam_world).astype(np.float32)
    prio = scene.taxonomy.priority_lut()
    rule = task.get("downsample_rule", "occufly")
    kw: dict = {"downsample_rule": rule}
    extra: dict = {}
    if task["layout"] == "sscbench":
        kw["taxonomy"] = scene.taxonomy
        kw["depth_full"] = resample_depth(depth, (frame.camera.height, frame.camera.width))
        if task.get("velodyne"):
            kw["points"] = frame_points(scene, f)
        extra["class_counts"] = sscbench_layout.class_counts(gt, scene.taxonomy)
    files = layout.frame_files(root, task["scene_id"], task["altitude"], task["frame_id"], gt,
                               pose, image, depth, prio, **kw)
    t_compute = time.perf_counter() - t0
    marker = layout.marker(root, task["scene_id"], task["altitude"], task["frame_id"])
    nbytes = write_frame_files(files, marker, {
        "config": task["config"], "frame": frame.name, **extra,
        "files": {str(p.relative_to(root)): len(b) for p, b in files.items()}})
    return {
        "frame_id": task["frame_id"], "altitude": task["altitude"], "name": frame.name,
        "occupied": gt.stats["occupied"], "valid": gt.stats["valid"],
        "surface": int(np.count_nonzero(gt.surface)), "occluded": int(np.count_nonzero(gt.occluded)),
        "depth_source": depth_src, "depth_pixels": int(np.count_nonzero(depth)),
        "bytes": nbytes, "seconds_sample": round(t_sample, 4),
        "seconds_compute": round(t_compute, 4), "seconds": round(time.perf_counter() - t0, 4),
        "cpu_seconds": round(time.process_time() - c0, 4),
    }


# ---- target checks ---------------------------------------------------------------------------
def _check_target(out: Path, layout, scene_id: str, fingerprint: str, layout_name: str) -> dict | None:
    """Raise unless ``out`` may receive this export; return the earlier manifest if any."""
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: export target exists and is not a directory")
    if not out.exists() or not any(out.iterdir()):
        return None
    mpath = layout.manifest_path(out, scene_id)
    if mpath.is_file():
        try:
            old = json.loads(mpath.read_text())
        except ValueError:
            raise ExportError(f"{mpath}: unreadable manifest; refusing to write into {out}") from None
        if old.get("layout") != layout_name or old.get("scene_fingerprint") != fingerprint:
            raise ExportError(
                f"{out}: holds an export of a different scene or layout under {scene_id!r} "
                f"(manifest {mpath}); choose another target or scene id")
        return old
    if layout.is_export_root(out):
        if layout_name == "occufly" and layout.scene_dir(out, scene_id).exists():
            raise ExportError(f"{layout.scene_dir(out, scene_id)}: exists without a manifest; "
                              "it is not an earlier export of this scene")
        return None
    raise ExportError(
        f"{out}: export target exists and is not an earlier {layout_name} export of this scene "
        "(no matching manifest); choose an empty or new folder")


def quality_path(out: Path, layout: str, scene_id: str) -> Path:
    """Where an export keeps its scene's quality report: ``quality.json`` beside the manifest
    (OccuFly layout), ``manifests/<scene_id>.quality.json`` (SSCBench layout)."""
    mpath = LAYOUTS[layout].manifest_path(out, scene_id)
    return mpath.with_name("quality.json" if layout == "occufly" else f"{scene_id}.quality.json")


def _dataset_files(out: Path, layout: str, taxonomy, spec) -> dict[Path, bytes]:
    """Root-level files rebuilt from every manifest: splits (both layouts), the YAML (SSCBench)."""
    if layout == "sscbench":
        return sscbench_layout.dataset_files(out, taxonomy, spec)
    splits: dict[str, list[str]] = {s: [] for s in SPLITS}
    for mp in sorted((out / "OccuFly_Dataset").glob("*/manifest.json")):
        try:
            m = json.loads(mp.read_text())
        except ValueError:
            continue
        if m.get("layout") == "occufly":
            scene_split = m.get("split") or default_split(m["scene_id"])
            # --split-by: the scene is in every split one of its frames is in
            for s in sorted({fr.get("split") or scene_split for fr in m.get("frames", {}).values()}
                            or {scene_split}):
                splits.setdefault(s, []).append(m["scene_id"])
    return occufly_layout.split_files(out, splits)


def _atomic_write(path: Path, data: bytes) -> None:
    try:
        atomic_write_bytes(path, data)
    except OSError as e:
        if is_disk_full(e):
            raise ExportDiskFull(f"disk full while writing {path}; nothing of this export was "
                              "changed beyond completed frames -- free space and rerun") from None
        raise


# ---- memory: up-front estimate -----------------------------------------------------------------
# Peak memory of one export worker, measured on one 5472 x 3648 frame of a survey cut with the
# default 192 x 128 x 128 frame grid (308 MB peak RSS in-process, scene and grid loaded), with
# some margin: interpreter + memory-mapped scene, the scene grid(s) it loads, the decoded
# image and its PNG encoding, the frame grid's sampling and pooling arrays.
EXPORT_WORKER_FIXED_BYTES = 200 * 2**20
EXPORT_BYTES_PER_IMAGE_PIXEL = 8
EXPORT_BYTES_PER_FRAME_VOXEL = 32


def _local_workers(executor, workers: int | None, n_frames: int) -> int | None:
    """Worker processes on this machine for the export (None: remote, e.g. Dask)."""
    import os

    from occufly.parallel import DaskExecutor, LocalExecutor, SerialExecutor

    if executor is None:
        if os.environ.get("OCCUFLY_DASK"):
            return None
        n = workers if workers is not None else min(n_frames, 2)
        return 0 if n <= 1 else int(n)  # 0: in this process
    if isinstance(executor, DaskExecutor):
        return None
    if isinstance(executor, LocalExecutor):
        return int(executor.workers)
    return 0 if isinstance(executor, SerialExecutor) else None


def export_memory_estimate(grids: list[SceneGrid], spec: FrameGridSpec, image_pixels: int,
                           workers: int) -> int:
    """Estimated peak bytes of an export on this machine: ``workers`` processes (0 = in this
    process) each holding the grids, one frame's image of ``image_pixels`` and its grid, plus
    the caller's copy of the grids."""
    grid_bytes = sum(int(g.labels.nbytes) for g in grids)
    per = (EXPORT_WORKER_FIXED_BYTES + grid_bytes + EXPORT_BYTES_PER_IMAGE_PIXEL * int(image_pixels)
           + EXPORT_BYTES_PER_FRAME_VOXEL * int(np.prod(spec.shape)))
    return int(per if workers == 0 else grid_bytes + workers * per)


def check_export_memory(grids: list[SceneGrid], spec: FrameGridSpec, image_pixels: int,
                        workers: int | None, *, where: str) -> dict:
    """:class:`ExportError` (CLI exit 2) before anything is written when the local export
    cannot fit in the memory available now (Linux ``MemAvailable``; remote workers and
    systems without it are not checked)."""
    from occufly.fsutil import require_memory

    if workers is None:
        return {}
    return require_memory(
        export_memory_estimate(grids, spec, image_pixels, workers),
        f"{where}: exporting with {max(workers, 1)} local worker(s) (grids of "
        f"{sum(g.labels.nbytes for g in grids) / 1e6:.0f} MB, frames up to "
        f"{image_pixels / 1e6:.1f} MP)", error=ExportError,
        hint="nothing was written (use --workers 1, or export on a Dask cluster with --dask)")


# ---- entry point -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExportOptions:
    """What to export and how (every field but the workspace, the target, the executor and the
    progress callback of :func:`export_dataset`).

    frames: frame indices (default all); grid: a :class:`SceneGrid` for every frame or
    ``{altitude: SceneGrid}`` (default: the workspace's grids); workers: local pool size when
    no executor is given; split: ``train`` / ``val`` / ``test`` for the splits files (default:
    the release's rule on the scene number, see :mod:`occufly.export.occufly`);
    downsample_rule: ``occufly`` or ``lmscnet`` for the coarser grids; split_by: ``altitude``
    / ``region`` / ``ratio`` split this scene's frames into train / val / test
    (:mod:`occufly.export.splits`; ``split_ratios`` for the last two); velodyne: also write
    ``velodyne_points`` (SSCBench layout); provenance: more entries of the manifest's
    ``provenance`` (the web app's ``policy``, ``labels`` and the per-frame ``masks`` whose
    votes made the labels); quality: the quality report
    (:func:`occufly.lifting.quality.quality_report`) written as ``quality.json`` beside the
    manifest (:func:`quality_path`).
    """

    scene_id: str = "scene_01"
    layout: str = "occufly"
    grid: SceneGrid | dict[int, SceneGrid] | None = None
    frames: list[int] | None = None
    spec: FrameGridSpec | None = None
    grid_for_altitude: dict[int, int] | None = None
    workers: int | None = None
    split: str | None = None
    downsample_rule: str = "occufly"
    velodyne: bool = False
    provenance: dict | None = None
    quality: dict | None = None
    split_by: str | None = None
    split_ratios: tuple[float, float, float] | None = None

    def check(self) -> None:
        """:class:`ExportError` naming the option that is wrong."""
        if self.layout not in LAYOUTS:
            raise ExportError(f"unknown layout {self.layout!r}; expected one of {', '.join(LAYOUTS)}")
        if not SCENE_ID_RE.match(self.scene_id):
            raise ExportError(f"scene id {self.scene_id!r}: expected letters, digits, '_', '-' (e.g. scene_01)")
        if self.split is not None and self.split not in SPLITS:
            raise ExportError(f"split {self.split!r}: expected one of {', '.join(SPLITS)}")
        if self.split_by is not None and self.split_by not in split_rules.RULES:
            raise ExportError(f"split_by {self.split_by!r}: expected one of {', '.join(split_rules.RULES)}")
        if self.split_by is not None and self.split is not None:
            raise ExportError("--split names the whole scene's split and --split-by splits its frames: give one")
        if self.velodyne and self.layout != "sscbench":
            raise ExportError("--velodyne writes velodyne_points/ of the SSCBench layout; use --layout sscbench")
        if self.downsample_rule not in DOWNSAMPLE_RULES:
            raise ExportError(f"downsample rule {self.downsample_rule!r}: expected one of "
                              f"{', '.join(DOWNSAMPLE_RULES)}")

    @property
    def writes_velodyne(self) -> bool:
        return bool(self.velodyne) and self.layout == "sscbench"


def export_dataset(ws: Path, out: Path, options: ExportOptions | None = None, *, executor=None,
                   progress: ProgressFn | None = None, **fields) -> dict:
    """Export per-frame ground truth of workspace ``ws`` into ``out``; returns a summary.

    ``options`` (:class:`ExportOptions`) says what and how; keyword ``fields`` of
    :class:`ExportOptions` given here override it (``export_dataset(ws, out, frames=[3])``).
    executor: from :func:`occufly.parallel.get_executor` (default: a local pool with
    ``options.workers`` processes, closed afterwards).

    Frames that use different cameras are exported as one scene per camera (the camera with
    the most frames keeps ``scene_id``, the others get ``_cam2``, ``_cam3``, ...): both layouts
    hold one calibration per scene / sequence. The summary then has ``scenes`` (one summary
    each) and the totals.
    """
    t_start = time.perf_counter()
    opts = replace(options or ExportOptions(), **fields)
    opts.check()
    ws, out = Path(ws).absolute(), Path(out).absolute()
    if out.exists():
        if not out.is_dir() or any(out.iterdir()):
            # adding to / resuming an earlier export: each frame is written atomically, the
            # frames already complete are kept whatever happens (rerun to resume)
            return _export_scene(ws, out, opts, executor=executor, progress=progress,
                                 t_start=t_start)
        # an empty folder (maybe a mount point: never swapped for a sibling): written in
        # place and emptied again if the export fails
        try:
            return _export_scene(ws, out, opts, executor=executor, progress=progress,
                                 t_start=t_start)
        except BaseException as e:
            _empty_folder(out)
            if is_disk_full(e):
                raise _disk_full_error(out) from None
            raise
    # a new export: built under a temporary sibling (.NAME.<pid>-XXXX.partial) and renamed
    # into place once complete. A failure removes the sibling (disk full included: nothing is
    # left); an interrupted run (Ctrl-C, SIGTERM, a kill) leaves it, and the next run for the
    # same target takes it over with its completed frames (the export resumes)
    tmp = _partial_dir(out)
    try:
        summary = _export_scene(ws, tmp, opts, executor=executor, progress=progress,
                                t_start=t_start)
        os.replace(tmp, out)
        fsync_dir(out.parent)
    except KeyboardInterrupt:
        raise
    except BaseException as e:
        shutil.rmtree(tmp, ignore_errors=True)
        if is_disk_full(e):
            raise _disk_full_error(out) from None
        if isinstance(e, ExportError):
            raise type(e)(str(e).replace(str(tmp), str(out))) from None
        raise
    summary["out"] = str(out)
    for part in summary.get("scenes") or []:
        part["out"] = str(out)
    return summary


def _partial_dir(out: Path) -> Path:
    """The hidden sibling a new export of ``out`` is built in: the partial folder an
    interrupted run left (its process gone) is taken over, so its completed frames count;
    else a new one."""
    out.parent.mkdir(parents=True, exist_ok=True)
    pat = re.compile(rf"^\.{re.escape(out.name)}\.(\d+)-.*\.partial$")
    for p in sorted(out.parent.iterdir()):
        m = pat.match(p.name)
        if not (m and p.is_dir() and not pid_alive(int(m.group(1)))):
            continue
        mine = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}-", suffix=".partial",
                                     dir=out.parent))
        try:
            os.replace(p, mine)  # an empty folder is replaced atomically
        except OSError:  # another run took it first
            mine.rmdir()
            continue
        return mine
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.{os.getpid()}-", suffix=".partial",
                                dir=out.parent))
    os.chmod(tmp, ordinary_mode(directory=True))  # mkdtemp's 0700 would be the export's
    return tmp


def _disk_full_error(out: Path) -> ExportDiskFull:
    return ExportDiskFull(
        f"disk full while exporting to {out}: the export was not written (the partial output "
        "was removed) -- free space and run it again")


def _empty_folder(out: Path) -> None:
    """Remove what a failed export wrote into ``out``, which was empty before it."""
    for p in list(out.iterdir()) if out.is_dir() else []:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _export_scene(ws: Path, out: Path, opts: ExportOptions, *, executor, progress,
                  t_start: float) -> dict:
    """:func:`export_dataset` into ``out`` as it stands (checked by ``_check_target``)."""
    from occufly.scene import Scene

    scene = Scene.load(ws)
    idx = _frame_indices(len(scene.frames), opts.frames)
    groups = camera_groups(scene, idx)
    if len(groups) > 1:
        return _export_per_camera(ws, out, opts, groups, executor=executor, progress=progress,
                                  t_start=t_start)
    return _export_one_camera(ws, out, opts, scene, idx, executor=executor, progress=progress,
                              t_start=t_start)


def _frame_indices(n: int, frames: list[int] | None) -> list[int]:
    """The frame indices to export, checked against the scene's ``n`` frames."""
    idx = list(range(n)) if frames is None else [int(i) for i in frames]
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        raise ExportError(f"frame index {bad[0]} out of range: the scene has {n} frames")
    if len(set(idx)) != len(idx):
        raise ExportError("frame list has duplicates")
    if not idx:
        raise ExportError("no frames to export (the frame list is empty)")
    return idx


def _export_per_camera(ws: Path, out: Path, opts: ExportOptions, groups: list[list[int]], *,
                       executor, progress, t_start: float) -> dict:
    """One scene per camera group (``scene_id``, ``scene_id_cam2``, ...) and the totals."""
    if len(groups) > MAX_CAMERAS:
        raise ExportError(
            f"{ws}: the frames use {len(groups)} different cameras; both layouts hold one "
            f"calibration per scene, so each camera becomes its own scene (at most "
            f"{MAX_CAMERAS}). Re-import with a shared camera model, or export subsets with --frames")
    parts = [_export_scene(ws, out, replace(opts, scene_id=sid, frames=g), executor=executor,
                           progress=progress, t_start=time.perf_counter())
             for sid, g in zip(group_scene_ids(opts.scene_id, len(groups)), groups, strict=True)]
    return {
        "out": str(out), "layout": opts.layout, "scene_id": opts.scene_id,
        "scenes": [{k: v for k, v in p.items() if k != "results"} for p in parts],
        "frames": sum(p["frames"] for p in parts), "written": sum(p["written"] for p in parts),
        "skipped_done": sum(p["skipped_done"] for p in parts),
        "complete": all(p["complete"] for p in parts), "bytes": sum(p["bytes"] for p in parts),
        "seconds": round(time.perf_counter() - t_start, 3),
        "results": [r for p in parts for r in p["results"]],
    }


def _frame_altitudes(ws: Path, scene, idx: list[int]) -> dict[int, int]:
    """Every selected frame's altitude, after checking its pose and image (nothing is written
    before every frame passes)."""
    alts: dict[int, int] = {}
    for i in idx:
        fr = scene.frames[i]
        check_pose(fr.T_cam_world, f"{ws}: frame {i} ({fr.name})")
        alts[i] = frame_altitude(fr, f"{ws}: frame {i}")
        if not fr.image_path or not Path(fr.image_path).is_file():
            raise ExportError(f"{ws}: frame {i} ({fr.name}): image file {fr.image_path!r} not found")
    return alts


def _stage_grids(sdir: Path, grids: dict[int, SceneGrid], used: set[int]
                 ) -> tuple[dict[int, tuple[str, str]], dict[int, str]]:
    """The grids used, stored next to the export state so workers (local or remote) load them:
    ``({key: (path, digest)}, {key: digest})``."""
    grid_paths: dict[int, tuple[str, str]] = {}
    digests = {}
    for key, g in grids.items():
        if key not in used:
            continue
        dg = grid_digest(g)
        p = sdir / f"grid_{'all' if key < 0 else key}_{dg[:12]}.npz"
        if not p.is_file():
            _atomic_write(p, g.to_bytes(compress=False))  # a working copy: speed over size
        grid_paths[key] = (str(p), dg)
        digests[key] = dg
    return grid_paths, digests


def _export_one_camera(ws: Path, out: Path, opts: ExportOptions, scene, idx: list[int], *,
                       executor, progress, t_start: float) -> dict:
    """Export frames ``idx`` (all of one camera) as scene ``opts.scene_id``."""
    lay = LAYOUTS[opts.layout]
    spec = opts.spec or FrameGridSpec()
    alts = _frame_altitudes(ws, scene, idx)
    all_alts = set(alts.values())
    for fr in scene.frames:  # map every altitude of the scene so earlier frames stay checkable
        if fr.nominal_altitude is not None:
            all_alts.add(int(fr.nominal_altitude))
    grids, mapping, grid_src = _resolve_grids(ws, opts.grid, all_alts, opts.grid_for_altitude)
    fingerprint = scene_fingerprint(scene)
    old = _check_target(out, lay, opts.scene_id, fingerprint, opts.layout)
    check_export_memory([grids[k] for k in set(mapping.values())], spec,
                        max(scene.frames[i].camera.width * scene.frames[i].camera.height for i in idx),
                        _local_workers(executor, opts.workers, len(idx)), where=str(out))
    grid_paths, digests = _stage_grids(lay.state_dir(out, opts.scene_id), grids,
                                       set(mapping.values()))
    # per-altitude config hash: what a frame's files depend on (not the frame selection)
    configs = {
        a: sha256_bytes(json.dumps({
            "v": EXPORT_FORMAT_VERSION, "layout": opts.layout, "spec": spec.to_dict(),
            "scene": fingerprint, "grid": digests[mapping[a]], "downsample": opts.downsample_rule,
            "velodyne": opts.writes_velodyne}, sort_keys=True).encode())[:32]
        for a in mapping
    }
    grid_record = {("all" if k < 0 else str(k)): {
        "source": grid_src[k], "digest": digests[k], "shape": list(grids[k].shape),
        "origin": grids[k].origin.tolist(), "voxel_size": grids[k].voxel_size} for k in digests}
    manifest = _manifest(ws, out, opts, scene, idx, alts, spec, old, grid_record, mapping,
                         fingerprint=fingerprint, config=sha256_bytes(json.dumps(configs, sort_keys=True).encode())[:32])
    mpath = lay.manifest_path(out, opts.scene_id)
    _write_scene_files(out, opts, lay, manifest, mpath, scene.frames[idx[0]].camera)

    # -- tasks for frames that are not done yet
    scene_mtime = Workspace(ws).scene_json.stat().st_mtime_ns
    tasks, skipped = [], 0
    for i in idx:
        fid = frame_id_of(i)
        if frame_done(lay.marker(out, opts.scene_id, alts[i], fid), configs[alts[i]], out):
            skipped += 1
            continue
        gp, gd = grid_paths[mapping[alts[i]]]
        tasks.append({
            "ws": str(ws), "out": str(out), "scene_mtime": scene_mtime, "scene_id": opts.scene_id,
            "layout": opts.layout, "frame_index": i, "frame_id": fid, "altitude": alts[i],
            "grid_path": gp, "grid_digest": gd, "spec": {
                "shape": spec.shape, "voxel_size": spec.voxel_size, "near": spec.near,
                "far": spec.far, "oversample": spec.oversample, "max_raster": spec.max_raster},
            "config": configs[alts[i]], "downsample_rule": opts.downsample_rule,
            "velodyne": opts.writes_velodyne,
        })
    results = _run_frame_tasks(tasks, out, executor=executor, workers=opts.workers,
                               progress=progress)
    manifest["complete"] = all(
        a["altitude"] in configs
        and frame_done(lay.marker(out, opts.scene_id, a["altitude"], fid), configs[a["altitude"]], out)
        for fid, a in manifest["frames"].items())
    manifest["updated"] = datetime.now(UTC).isoformat(timespec="seconds")
    _atomic_write(mpath, json.dumps(manifest, indent=1).encode())
    for p, data in _dataset_files(out, opts.layout, scene.taxonomy, spec).items():
        _atomic_write(p, data)
    secs = [r["seconds_sample"] for r in results]
    return {
        "out": str(out), "layout": opts.layout, "scene_id": opts.scene_id,
        "frames": len(idx), "written": len(results), "skipped_done": skipped,
        "complete": manifest["complete"], "bytes": sum(r["bytes"] for r in results),
        "seconds": round(time.perf_counter() - t_start, 3),
        "sample_seconds_mean": round(float(np.mean(secs)), 4) if secs else None,
        "grid_for_altitude": manifest["provenance"]["grid_for_altitude"],
        "results": results,
    }


def _conventions(downsample_rule: str) -> dict:
    """The manifest's ``conventions``: how to read every array of the export."""
    return {
        "frame_grid": "camera-centric, x right, y down, z forward; voxel (i,j,k) centre "
                      "((i-X/2+.5)r, (j-Y/2+.5)r, (k+.5)r); C order",
        "label": "raw class ids, 0 empty, 255 invalid",
        "masks": "numpy.packbits of the flattened bool array, MSB first",
        "pose": "pkl 'pose' (and frames[*].pose here) = (4,4) camera-to-world, scene-local metres",
        "depth": "float32 metres along the optical axis, 0 = none, (H/4)*(W/4) flattened "
                 "(shape: depth_map_shape, and per frame)",
        "pooling": ("most common non-empty valid class per block; ties by taxonomy tie order; "
                    "no non-empty valid voxel -> 0 if any valid voxel else 255")
        if downsample_rule == "occufly" else
        ("LMSCNet/MonoScene: block empty (0, or 255 if more invalid than empty) when > 95 % "
         "of it is empty or invalid, else its most common other id (ties: smallest id)"),
        "calibration": "scene-level calibration.txt: fx fy cx cy width height of the full "
                       "image (COLMAP convention); '# depth_maps: h w' comment line",
    }


def _manifest(ws: Path, out: Path, opts: ExportOptions, scene, idx: list[int],
              alts: dict[int, int], spec: FrameGridSpec, old: dict | None, grid_record: dict,
              mapping: dict[int, int], *, fingerprint: str, config: str) -> dict:
    """The scene's manifest with ``complete: false``: taxonomy, conventions, provenance and
    the frames of this export merged into those an earlier export of the scene wrote."""
    camera = scene.frames[idx[0]].camera  # one camera per exported scene (camera_groups)
    if old and old.get("camera") not in (None, camera.to_dict()):
        raise ExportError(
            f"{LAYOUTS[opts.layout].manifest_path(out, opts.scene_id)}: scene {opts.scene_id!r} "
            f"was exported with another camera ({old['camera']}); its calibration is one camera "
            "for every frame -- export these frames under another --scene-id")
    by_alt_cam: dict[int, object] = {}
    for i in idx:
        by_alt_cam.setdefault(alts[i], scene.frames[i].camera)
    split_rule = None if opts.split is not None else (
        {"rule": opts.split_by,
         "ratios": list(split_rules.check_ratios(opts.split_ratios or split_rules.DEFAULT_RATIOS))}
        if opts.split_by is not None else (old or {}).get("split_by"))
    now = datetime.now(UTC).isoformat(timespec="seconds")
    manifest = {
        "format": "occufly-export", "version": EXPORT_FORMAT_VERSION, "layout": opts.layout,
        "scene_id": opts.scene_id, "scene_fingerprint": fingerprint, "complete": False,
        "created": (old or {}).get("created") or now, "updated": now,
        "taxonomy": scene.taxonomy.to_dict(),
        "learning_map": {str(k): v for k, v in scene.taxonomy.learning_map().items()},
        "grid_spec": spec.to_dict(),
        "conventions": _conventions(opts.downsample_rule),
        "split": opts.split or (old or {}).get("split") or default_split(opts.scene_id),
        "split_by": split_rule,
        # which grid axis is what in the image: adapters mirror axis 0 for a left-right flip
        "axes": frame_axes(),
        "downsample_rule": opts.downsample_rule,
        "camera": camera.to_dict(),
        "image_shape": [camera.height, camera.width],
        "depth_map_shape": list(quarter_shape(camera)),
        "provenance": {
            "workspace": str(ws), "scene_origin": scene.origin.tolist(),
            # the CRS of scene_origin and the grids' origins ({name, epsg, wkt}; None: local)
            "crs": getattr(scene, "crs", None),
            "scene_meta": {k: scene.meta.get(k) for k in ("source", "cloud", "depth_maps",
                                                          "georeferenced", "synthetic")
                           if k in scene.meta},
            "grids": grid_record,
            "grid_for_altitude": {str(a): ("all" if k < 0 else k) for a, k in sorted(mapping.items())},
            "config_hash": config,
            **(opts.provenance or {}),
        },
        "cameras": {str(a): c.to_dict() for a, c in sorted(by_alt_cam.items())},
    }
    frames_index = dict((old or {}).get("frames", {}))
    for i in idx:
        fr = scene.frames[i]
        frames_index[frame_id_of(i)] = {"name": fr.name, "altitude": alts[i],
                                        "camera": fr.camera.to_dict(),
                                        "depth_shape": list(quarter_shape(fr.camera)),
                                        "pose": np.linalg.inv(fr.T_cam_world).round(9).tolist()}
    manifest["frames"] = dict(sorted(frames_index.items()))
    for rec in manifest["frames"].values():
        rec.pop("split", None)
    if split_rule is not None:
        for fid, s in split_rules.assign_splits(manifest["frames"], split_rule["rule"],
                                                split_rule["ratios"]).items():
            manifest["frames"][fid]["split"] = s
    return manifest


def _write_scene_files(out: Path, opts: ExportOptions, lay, manifest: dict, mpath: Path,
                       camera) -> None:
    """Before any frame: the manifest (``complete: false``), ``quality.json`` and the layout's
    per-scene files (calibration, links)."""
    clean_stray_temporaries(out)
    _atomic_write(mpath, json.dumps(manifest, indent=1).encode())
    if opts.quality is not None:
        _atomic_write(quality_path(out, opts.layout, opts.scene_id),
                      json.dumps(opts.quality, indent=1).encode())
    seq_alts = sorted({int(a["altitude"]) for a in manifest["frames"].values()})
    for p, data in lay.static_files(out, opts.scene_id, camera, quarter_shape(camera),
                                    altitudes=seq_alts).items():
        _atomic_write(p, data)
    if opts.layout == "occufly":
        for a in seq_alts:  # export format 1 wrote calibration.txt per altitude
            (occufly_layout.scene_dir(out, opts.scene_id) / str(a) / "calibration.txt").unlink(missing_ok=True)
    else:
        sscbench_layout.make_links(out, opts.scene_id, seq_alts)


def _run_frame_tasks(tasks: list[dict], out: Path, *, executor, workers: int | None,
                     progress: ProgressFn | None) -> list[dict]:
    """:func:`export_frame_task` over ``tasks`` on ``executor`` (default: a local pool of
    ``workers``, closed afterwards); disk full is an :class:`ExportError`."""
    own = executor is None
    if own:
        from occufly.parallel import get_executor

        executor = get_executor(None, workers if workers is not None else min(len(tasks), 2) or 1)
    try:
        return executor.map(export_frame_task, tasks, progress=progress) if tasks else []
    except OSError as e:
        if is_disk_full(e):
            raise ExportDiskFull(f"disk full while exporting into {out}; completed frames are kept, "
                              "free space and rerun to resume") from None
        raise
    finally:
        if own:
            executor.close()
