"""Class-aware densification and scene voxelisation (paper section 3.3.3).

Groups come from the taxonomy (``instance`` / ``ground`` / ``other``):

- instance classes: DBSCAN per class (the class's ε, minPts; :mod:`.dbscan`), each instance
  carved as a visual hull from 24 α-shape silhouettes (:mod:`.carve`); DBSCAN noise points and
  degenerate instances (fewer than 4 distinct points, or flat / collinear: thinner than
  ``degenerate_thickness`` voxel edges along a principal axis) are binned directly with a
  logged warning;
- ground classes: Poisson surface, scan-converted, majority ground class (:mod:`.ground`);
- other classes: direct binning with a majority vote.

Aggregation: ground, then other over it, then instance over both (instance ≻ other ≻ ground);
within the instance layer a voxel holding instance points takes their majority class, and a
voxel only carved takes the carving class ranked first in the taxonomy's tie order. 0 = empty.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occufly.densify.carve import CarveParams, carve_instance
from occufly.densify.dbscan import dbscan
from occufly.densify.freespace import FrameDepths, FreeSpaceParams
from occufly.densify.ground import PoissonParams, voxelize_ground
from occufly.densify.smooth import project_to_planes
from occufly.densify.voxelize import SceneGridSpec, bin_points, grid_spec_for, majority_vote
from occufly.density import surface_density
from occufly.errors import InputFormatError
from occufly.fsutil import atomic_write_text, require_memory
from occufly.grid import SceneGrid
from occufly.progress import ProgressFn, noop
from occufly.scene import Scene
from occufly.taxonomy import EMPTY, INVALID, Taxonomy
from occufly.workspace import Workspace

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DensifyOptions:
    """What to run and with which tolerances (``carve``/``poisson`` False = ablations)."""

    voxel_size: float = 0.5
    carve: bool = True
    poisson: bool = True
    dbscan_cell_fraction: float = 0.25  # DBSCAN reduction cell = fraction * eps (0 = exact)
    # minPts multiplier: 1.0 = the taxonomy's values as-is; None = "auto" (default), scaled by
    # the cloud's measured surface density relative to REFERENCE_SURFACE_DENSITY (see below):
    # 1.0 for clouds at least that dense, smaller for sparser ones
    min_points_scale: float | None = None
    degenerate_thickness: float = 0.05  # in voxel edges; thinner instances are binned directly
    carve_params: CarveParams = field(default_factory=CarveParams)
    poisson_params: PoissonParams = field(default_factory=PoissonParams)
    pad: int = 2  # voxels around the labelled points' bounding box
    # instance classes: points are projected onto the least-squares plane of their same-class
    # neighbours within this many voxel edges (capped at the class's DBSCAN eps, so persons
    # and bicycles keep their shape) before clustering and carving (:mod:`.smooth`; 0 = off).
    # Other classes use ``smooth_radius_other``; ground classes are smoothed in :mod:`.ground`.
    smooth_radius: float = 3.0
    smooth_radius_other: float = 0.0
    # remove carved voxels the survey's cameras saw through (:mod:`.freespace`); needs the
    # scene's frames and visibility (``views``), skipped without them
    free_space: bool = True
    free_space_params: FreeSpaceParams = field(default_factory=FreeSpaceParams)


@dataclass
class DensifyResult:
    grid: SceneGrid
    report: dict


class _Warnings:
    """Collects warnings for the report and logs each one."""

    def __init__(self) -> None:
        self.items: list[str] = []

    def __call__(self, msg: str) -> None:
        log.warning(msg)
        self.items.append(msg)


# Points per square metre of surface the taxonomy's minPts values are meant for. The default
# table asks e.g. 500 vehicle points within 1 m and 1000 roof points within 1 m, i.e. ~160-320
# points/m^2 inside an eps-disk on a surface; a 50 m-altitude MVS cloud fused at ~5 cm spacing
# has ~400/m^2. Clouds that are sparser (the synthetic scenes fuse at 0.1-0.4 m) make every
# instance DBSCAN noise with the table as-is; ``min_points_scale=None`` ("auto") multiplies
# minPts by min(1, measured density / this reference).
REFERENCE_SURFACE_DENSITY = 400.0

# The aggregation holds a few dense uint8 / bool copies of the grid: 1.5 G voxels stays well
# inside the 8 GB budget (e.g. 1.5 x 1.5 km x 160 m at 0.5 m is 0.29 G).
MAX_GRID_VOXELS = 1_500_000_000


# Peak memory of :func:`densify` beyond its inputs, measured with ``bench/bench_scale.py`` on
# a 4 M-point crop of the synthetic survey cloud (1.01 GB peak RSS with the inputs; the
# 2 M-point survey cut through ``occufly voxelize``: 0.89 GB): per point (group and label
# arrays, per-class point copies, the Poisson input) and per voxel of the scene grid (the
# aggregation's dense uint8 / bool layers and the saved grid), with some margin.
DENSIFY_BYTES_PER_POINT = 120
DENSIFY_BYTES_PER_VOXEL = 6
DENSIFY_FIXED_BYTES = 400 * 2**20
# the free-space check's nearest-depth raster per frame (at most 512 px on its long side)
DENSIFY_BYTES_PER_FRAME = 2**20


def densify_memory_estimate(n_points: int, n_voxels: int, frames: int = 0) -> int:
    """Estimated peak bytes :func:`densify` allocates for a cloud and a grid of these sizes
    (``frames``: depth rasters of the free-space check)."""
    return int(DENSIFY_FIXED_BYTES + DENSIFY_BYTES_PER_POINT * int(n_points)
               + DENSIFY_BYTES_PER_VOXEL * int(n_voxels) + DENSIFY_BYTES_PER_FRAME * int(frames))


def check_densify_memory(n_points: int, n_voxels: int, *, where: str = "voxelize",
                         frames: int = 0) -> dict:
    """:class:`InputFormatError` (CLI exit 2) before any heavy work when the densification
    cannot fit in the memory available now (Linux ``MemAvailable``; unchecked elsewhere)."""
    return require_memory(
        densify_memory_estimate(n_points, n_voxels, frames),
        f"{where}: densifying {n_points:,} points into a grid of {n_voxels / 1e6:.1f} M voxels",
        error=InputFormatError,
        hint="nothing was written (free memory, use a larger --voxel, or crop the cloud)")


def _smoothed(xyz: np.ndarray, sel: np.ndarray, radius: float) -> np.ndarray:
    """(len(sel), 3) float32 points of one class, projected onto local planes within
    ``radius`` metres (as they are for radius 0)."""
    pts = np.asarray(xyz[sel], dtype=np.float32)
    if radius > 0 and len(pts) >= 4:
        pts = project_to_planes(pts, radius)
    return pts


def _is_degenerate(pts: np.ndarray, thickness: float) -> str | None:
    """Why an instance cannot be carved (None when it can). pts: (n, 3) float64."""
    uniq = np.unique(pts, axis=0) if len(pts) < 64 else pts
    if len(uniq) < 4:
        return f"only {len(uniq)} distinct points"
    c = pts - pts.mean(axis=0)
    # principal axes from the 3x3 covariance (cheap for any n); extent along the thinnest one
    _, vecs = np.linalg.eigh(c.T @ c)
    proj = c @ vecs
    ext = proj.max(axis=0) - proj.min(axis=0)
    if ext[1] < thickness:
        return f"collinear (thinner than {thickness:.3g} m in two directions)"
    if ext[0] < thickness:
        return f"flat (thinner than {thickness:.3g} m)"
    return None


@dataclass
class _InstanceLayer:
    """What the instance stage leaves for the free-space check and the aggregation."""

    point_keys: list[np.ndarray] = field(default_factory=list)  # voxels holding instance points
    point_labels: list[np.ndarray] = field(default_factory=list)  # their classes
    direct_keys: list[np.ndarray] = field(default_factory=list)  # binned directly (fallbacks)
    carved: dict[int, np.ndarray] = field(default_factory=dict)  # class id -> carved voxels
    stats: dict[str, dict] = field(default_factory=dict)  # class name -> counts
    min_points_scale: float | None = None
    density: float | None = None
    t_dbscan: float = 0.0
    t_carve: float = 0.0


def densify(
    xyz: np.ndarray,
    labels: np.ndarray,
    taxonomy: Taxonomy,
    *,
    scene_origin: np.ndarray | None = None,
    options: DensifyOptions = DensifyOptions(),
    views: FrameDepths | None = None,
    progress: ProgressFn | None = None,
) -> DensifyResult:
    """Build the semantic scene grid from a labelled point cloud.

    xyz: (N, 3) float32, scene-local metres; labels: (N,) uint8 raw ids (0 / 255 / ids not
    in ``taxonomy`` are ignored); scene_origin: (3,) float64 world offset of the local frame;
    views: the survey's observed depths (:class:`.freespace.FrameDepths`) for the free-space
    check of carved voxels (skipped when None).
    Returns the grid (origin in WORLD coordinates, snapped to the voxel lattice) and a report
    with per-stage timings and voxel counts.
    """
    report_progress = progress or noop
    warn = _Warnings()
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    scene_origin = np.zeros(3) if scene_origin is None else np.asarray(scene_origin, np.float64)
    labels = np.asarray(labels)
    if labels.shape != (len(xyz),):
        raise InputFormatError(
            f"labels: expected shape ({len(xyz)},) (one raw class id per point), got {labels.shape}"
        )
    labels = labels.astype(np.uint8, copy=False)
    vs = float(options.voxel_size)
    if not vs > 0:
        raise InputFormatError(f"voxel size must be > 0, got {options.voxel_size}")
    prio = taxonomy.priority_lut()

    t = time.perf_counter()
    gl, spec, counts_per_class = _groups(xyz, labels, taxonomy, scene_origin, options, warn)
    timings["groups"] = time.perf_counter() - t
    report_progress(0.02, "groups")

    t = time.perf_counter()
    layer = _instances(xyz, labels, taxonomy, spec, options, counts_per_class, warn, report_progress)
    timings["instances"] = time.perf_counter() - t
    timings["instances_dbscan"] = layer.t_dbscan
    timings["instances_carve"] = layer.t_carve

    t = time.perf_counter()
    free_removed = _free_space(layer, taxonomy, spec, options, views, report_progress)
    timings["free_space"] = time.perf_counter() - t

    t = time.perf_counter()
    other_k, other_l = _other(xyz, labels, np.flatnonzero(gl == 3), spec, prio,
                              options.smooth_radius_other * vs)
    timings["other"] = time.perf_counter() - t
    report_progress(0.65, "other")

    t = time.perf_counter()
    sel = np.flatnonzero(gl == 2)
    ground = voxelize_ground(
        spec, np.asarray(xyz[sel], np.float32), labels[sel], prio,
        poisson=options.poisson, params=options.poisson_params,
    )
    if "fallback" in ground.stats:
        warn(f"ground: {ground.stats['fallback']}; binned directly")
    timings["ground"] = time.perf_counter() - t
    report_progress(0.9, "ground")

    t = time.perf_counter()
    grid = SceneGrid(_aggregate(spec, ground, other_k, other_l, layer, prio).reshape(spec.shape),
                     spec.origin, vs)
    timings["aggregate"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_all
    report_progress(1.0, "done")

    counts = grid.class_counts()
    occupied = int(sum(counts.values()))
    if occupied == 0:  # cannot happen with labelled points inside the grid; never hide it
        raise InputFormatError("labels: the densified grid is empty")
    report = {
        "voxel_size": vs,
        "grid_shape": list(spec.shape),
        "grid_origin_world": spec.origin.tolist(),
        "points": int(len(xyz)),
        "labelled_points": int((gl > 0).sum()),
        "options": {
            "carve": options.carve,
            "poisson": options.poisson,
            "min_points_scale": layer.min_points_scale if options.carve else None,
            "free_space": bool(options.free_space and views is not None and views.n_frames),
            "surface_density_per_m2": layer.density,
        },
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "occupied_voxels": occupied,
        "voxels_per_class": {taxonomy[c].name if c in taxonomy else str(c): n for c, n in sorted(counts.items())},
        "voxels_per_stage": {
            "instance_points": (int(len(np.unique(np.concatenate(layer.point_keys))))
                                if layer.point_keys else 0),
            "instance_direct": (int(len(np.unique(np.concatenate(layer.direct_keys))))
                                if layer.direct_keys else 0),
            "instance_carved": int(sum(len(v) for v in layer.carved.values())),
            "instance_free_space_removed": int(sum(free_removed.values())),
            "other": int(len(other_k)),
            "ground_points": int(ground.stats.get("voxels_from_points", 0)),
            "ground_total": int(len(ground.keys)),
        },
        "instances": layer.stats,
        "ground": ground.stats,
        "warnings": warn.items,
    }
    return DensifyResult(grid, report)


def _groups(xyz: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy, scene_origin: np.ndarray,
            options: DensifyOptions, warn: _Warnings
            ) -> tuple[np.ndarray, SceneGridSpec, np.ndarray]:
    """Each point's class group ((N,) uint8: 0 none, 1 instance, 2 ground, 3 other), the grid
    spanning the labelled points (checked against the voxel and memory limits) and the points
    per class ((256,) int64)."""
    vs = float(options.voxel_size)
    group_of = np.zeros(256, dtype=np.uint8)  # 0 none, 1 instance, 2 ground, 3 other
    for gi, g in enumerate(("instance", "ground", "other"), start=1):
        group_of[taxonomy.group_ids(g)] = gi
    gl = group_of[labels]
    unknown = (gl == 0) & (labels != EMPTY) & (labels != INVALID)
    if unknown.any():
        bad = np.unique(labels[unknown])
        warn(f"{int(unknown.sum())} points have ids {bad.tolist()} not in taxonomy {taxonomy.name!r}; ignored")
    labelled = gl > 0
    if not labelled.any():
        raise InputFormatError(
            "labels: no point carries a class of the taxonomy (all empty/unknown); nothing to voxelize"
        )
    sub = np.asarray(xyz[np.flatnonzero(labelled)], dtype=np.float32)
    lo, hi = sub.min(axis=0), sub.max(axis=0)
    del sub
    spec = grid_spec_for(lo, hi, scene_origin, vs, pad=options.pad)
    if spec.n_voxels > MAX_GRID_VOXELS:
        ext = (hi - lo).astype(float)
        raise InputFormatError(
            f"voxel size {vs:g} m: the labelled points span {ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} m, "
            f"a grid of {' x '.join(str(int(d)) for d in spec.shape)} = {spec.n_voxels / 1e9:.2f} G voxels; "
            f"the limit is {MAX_GRID_VOXELS / 1e9:.2f} G (memory): use a larger --voxel "
            f"(>= {vs * (spec.n_voxels / MAX_GRID_VOXELS) ** (1 / 3):.3g} m) or crop the cloud"
        )
    check_densify_memory(len(xyz), spec.n_voxels, where=f"voxel size {vs:g} m")
    counts_per_class = np.bincount(labels[labelled], minlength=256)
    for c in taxonomy.classes:
        if counts_per_class[c.id] == 0:
            log.info("class %s (%d) has no points", c.name, c.id)
    return gl, spec, counts_per_class


def _instances(xyz: np.ndarray, labels: np.ndarray, taxonomy: Taxonomy, spec: SceneGridSpec,
               options: DensifyOptions, counts_per_class: np.ndarray, warn: _Warnings,
               report_progress: ProgressFn) -> _InstanceLayer:
    """Instance classes: DBSCAN per class into instances, each carved as a visual hull; noise
    points and degenerate instances are binned directly."""
    vs = float(options.voxel_size)
    layer = _InstanceLayer(min_points_scale=options.min_points_scale)
    inst_ids = [int(c) for c in taxonomy.group_ids("instance") if counts_per_class[c] > 0]
    if layer.min_points_scale is None:
        layer.density = surface_density(xyz)
        layer.min_points_scale = min(1.0, layer.density / REFERENCE_SURFACE_DENSITY)
    for ci, cid in enumerate(inst_ids):
        cls = taxonomy[cid]
        sel = np.flatnonzero(labels == cid)
        pts = _smoothed(xyz, sel, min(options.smooth_radius * vs, float(cls.dbscan_eps)))
        k, ins = spec.keys_of_local(pts)
        layer.point_keys.append(k[ins])
        layer.point_labels.append(np.full(int(ins.sum()), cid, np.uint8))
        st = {"points": int(len(sel))}
        layer.stats[cls.name] = st
        if not options.carve:
            layer.direct_keys.append(k[ins])
            continue
        _carve_class(layer, cls, pts, k, ins, spec, options, st, warn)
        report_progress(0.02 + 0.6 * (ci + 1) / max(1, len(inst_ids)), f"instances: {cls.name}")
    return layer


def _carve_class(layer: _InstanceLayer, cls, pts: np.ndarray, k: np.ndarray, ins: np.ndarray,
                 spec: SceneGridSpec, options: DensifyOptions, st: dict, warn: _Warnings) -> None:
    """One instance class: DBSCAN its points ``pts`` ((n, 3) float32, voxel keys ``k``, inside
    the grid ``ins``) and carve each instance into ``layer``."""
    vs = float(options.voxel_size)
    t0 = time.perf_counter()
    eps = float(cls.dbscan_eps)
    minpts = max(2, int(round(int(cls.dbscan_min_points) * layer.min_points_scale)))
    st["eps"], st["min_points"] = eps, minpts
    cl = dbscan(pts, eps, minpts, cell=options.dbscan_cell_fraction * eps)
    layer.t_dbscan += time.perf_counter() - t0
    n_inst = int(cl.max()) + 1 if len(cl) else 0
    noise = int((cl < 0).sum())
    st.update({"instances": n_inst, "noise_points": noise, "fallback_instances": 0})
    if noise:
        msg = (
            f"{cls.name}: {noise} of {len(pts)} points are DBSCAN noise "
            f"(eps={eps}, minPts={minpts}); they are binned directly"
            + (
                "; for a sparse cloud try min_points_scale auto (--min-points-scale auto)"
                if n_inst == 0 and options.min_points_scale is not None
                else ""
            )
        )
        if n_inst == 0:
            warn(msg)
        else:
            log.info(msg)
        layer.direct_keys.append(k[(cl < 0) & ins])
    t0 = time.perf_counter()
    order = np.argsort(cl, kind="stable")
    bounds = np.searchsorted(cl[order], np.arange(n_inst + 1))
    keys_c: list[np.ndarray] = []
    for j in range(n_inst):
        members = order[bounds[j] : bounds[j + 1]]
        p = pts[members].astype(np.float64)
        why = _is_degenerate(p, options.degenerate_thickness * vs)
        if why is not None:
            warn(f"{cls.name} instance {j} ({len(p)} points) is degenerate: {why}; binned directly")
            st["fallback_instances"] += 1
            layer.direct_keys.append(k[members[ins[members]]])
            continue
        keys_c.append(carve_instance(p, spec, options.carve_params))
    if keys_c:
        layer.carved[cls.id] = np.unique(np.concatenate(keys_c))
    st["carved_voxels"] = int(len(layer.carved.get(cls.id, ())))
    layer.t_carve += time.perf_counter() - t0


def _free_space(layer: _InstanceLayer, taxonomy: Taxonomy, spec: SceneGridSpec,
                options: DensifyOptions, views: FrameDepths | None,
                report_progress: ProgressFn) -> dict[str, int]:
    """Remove carved voxels (without points) the cameras saw through; returns the voxels
    removed per class name."""
    free_removed: dict[str, int] = {}
    carved = layer.carved
    if carved and options.free_space and views is not None and views.n_frames:
        held = (np.unique(np.concatenate(layer.point_keys + layer.direct_keys))
                if layer.point_keys else np.zeros(0, np.int64))
        for cid in list(carved):
            keys = carved[cid]
            test = keys[~np.isin(keys, held)]
            if not len(test):
                continue
            free = views.free_mask(spec.centers_local(spec.unravel(test)))
            if free.any():
                carved[cid] = np.setdiff1d(keys, test[free], assume_unique=True)
                layer.stats[taxonomy[cid].name]["carved_voxels"] = int(len(carved[cid]))
            free_removed[taxonomy[cid].name] = int(free.sum())
        report_progress(0.64, "free space")
    elif carved and options.free_space:
        log.info("free-space check skipped: no frames with visibility given")
    return free_removed


def _other(xyz: np.ndarray, labels: np.ndarray, sel: np.ndarray, spec: SceneGridSpec,
           prio: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """'Other' classes (points ``sel``): smoothed per class within ``radius`` metres, binned
    directly by majority vote: ``(voxel keys, labels)``."""
    if radius > 0 and len(sel):  # smoothing is per class: go class by class
        sel = sel[np.argsort(labels[sel], kind="stable")]
        cuts = np.flatnonzero(np.diff(labels[sel].astype(np.int16))) + 1
        pts = np.concatenate([_smoothed(xyz, part, radius) for part in np.split(sel, cuts)])
    else:
        pts = np.asarray(xyz[sel], np.float32)
    return bin_points(spec, pts, labels[sel], prio)


def _aggregate(spec: SceneGridSpec, ground, other_k: np.ndarray, other_l: np.ndarray,
               layer: _InstanceLayer, prio: np.ndarray) -> np.ndarray:
    """The flat (n_voxels,) uint8 grid: ground < other < instance."""
    flat = np.zeros(spec.n_voxels, dtype=np.uint8)
    flat[ground.keys] = ground.labels
    flat[other_k] = other_l
    # instance layer = carved voxels + directly binned fallback voxels. Carved voxels: least
    # preferred class first, so the preferred one ends on top; then every layer voxel holding
    # instance points takes their majority class.
    inst = np.zeros(spec.n_voxels, dtype=np.uint8)
    for cid in sorted(layer.carved, key=lambda c: -int(prio[c])):
        inst[layer.carved[cid]] = cid
    if layer.point_keys:
        k, lab, _ = majority_vote(np.concatenate(layer.point_keys),
                                  np.concatenate(layer.point_labels), prio)
        in_layer = inst > 0
        if layer.direct_keys:
            in_layer[np.concatenate(layer.direct_keys)] = True
        m = in_layer[k]
        inst[k[m]] = lab[m]
        del in_layer
    occ = inst > 0
    flat[occ] = inst[occ]
    return flat


def load_point_labels(path: str | Path, n_points: int) -> np.ndarray:
    """(N,) uint8 labels from an ``.npy`` file, checked against the cloud size."""
    path = Path(path)
    if not path.is_file():
        raise InputFormatError(
            f"{path}: point labels not found (run the lifting step, or pass --labels PATH to an "
            f".npy with one raw class id per point)"
        )
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as e:  # noqa: BLE001
        raise InputFormatError(f"{path}: not a readable .npy array ({e})") from None
    if arr.shape != (n_points,):
        raise InputFormatError(f"{path}: expected shape ({n_points},) to match the cloud, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise InputFormatError(f"{path}: expected integer raw class ids, got dtype {arr.dtype}")
    if arr.dtype != np.uint8:
        a = np.asarray(arr)
        if len(a) and (a.min() < 0 or a.max() > 255):
            raise InputFormatError(f"{path}: class ids must be 0..255")
        return a.astype(np.uint8)
    return np.asarray(arr)


def voxelize_workspace(
    ws: str | Path,
    *,
    labels_path: str | Path | None = None,
    options: DensifyOptions = DensifyOptions(),
    out_path: str | Path | None = None,
    progress: ProgressFn | None = None,
) -> dict:
    """Densify a workspace's labelled cloud and save ``WS/grid/scene_grid.npz`` (atomic).

    Labels default to ``WS/lifting/labels.npy`` with the reviewers' corrections applied
    (:func:`occufly.lifting.corrections.apply_to_labels`). Returns the report (also written next to
    the grid as ``voxelize_report.json``).
    """
    wsp = Workspace(ws)
    t = time.perf_counter()
    scene = Scene.load(wsp.root)
    lp = Path(labels_path) if labels_path is not None else wsp.labels_path
    labels = load_point_labels(lp, scene.n_points)
    if labels_path is None:  # the workspace's labels: with reviewers' corrections, like every reader
        from occufly.lifting.corrections import apply_to_labels

        labels = apply_to_labels(labels, wsp)
    use_views = bool(options.carve and options.free_space)
    if scene.n_points:  # up front, before the frames' depth rasters: the whole cloud's box
        xyz = np.asarray(scene.xyz)
        spec0 = grid_spec_for(xyz.min(axis=0), xyz.max(axis=0), scene.origin, float(options.voxel_size),
                              pad=options.pad)
        check_densify_memory(scene.n_points, spec0.n_voxels, where=str(lp),
                             frames=len(scene.frames) if use_views else 0)
    t_load = time.perf_counter() - t
    views = None
    if use_views:
        t = time.perf_counter()
        views = FrameDepths(scene.frames, scene.visibility, options.voxel_size, options.free_space_params)
        t_load += time.perf_counter() - t
    res = densify(scene.xyz, labels, scene.taxonomy, scene_origin=scene.origin, options=options,
                  views=views, progress=progress)
    out = Path(out_path) if out_path is not None else wsp.grid_path()
    t = time.perf_counter()
    res.grid.crs = (scene.crs or {}).get("wkt")  # the grid's origin is in the scene's CRS
    res.report["crs"] = (scene.crs or {}).get("name")
    res.grid.save(out)
    res.report["timings_s"]["load"] = round(t_load, 3)
    res.report["timings_s"]["save"] = round(time.perf_counter() - t, 3)
    res.report["labels"] = str(lp)
    res.report["grid"] = str(out)
    atomic_write_text(Workspace.report_path_of(out), json.dumps(res.report, indent=1))
    return res.report


def spec_of_grid(grid: SceneGrid, scene_origin: np.ndarray) -> SceneGridSpec:
    """The :class:`SceneGridSpec` of an existing grid, for a scene with ``scene_origin`` (3,)."""
    return SceneGridSpec(
        origin=grid.origin.copy(),
        local_origin=grid.origin - np.asarray(scene_origin, np.float64),
        shape=grid.shape,
        voxel_size=grid.voxel_size,
    )
