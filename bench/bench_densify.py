"""Benchmark: densify + voxelize the synthetic ``bench`` scene (~5 M points) end to end.

Prints one JSON object: per-stage seconds, end-to-end seconds, peak RSS of this process,
quality against the exact truth grid, and the direct-binning step compared with Open3D's
``VoxelGrid.create_from_point_cloud`` on the same points in the same run (ratio + a check that
both give the same occupied voxels on Open3D's lattice).

The scene is generated and imported once by the CLI in *subprocesses* (cached under
``--root``), so the peak memory reported is that of loading the workspace and densifying.

    .venv/bin/python bench/bench_densify.py [--root /tmp/occufly_bench] [--preset bench]
        [--labels truth|lifting] [--min-points-scale auto|1]
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _scene import ensure_scene  # noqa: E402


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # kB on Linux


def _binning_vs_open3d(xyz: np.ndarray, labels: np.ndarray, prio: np.ndarray, voxel: float) -> dict:
    """Our direct binning + majority vote vs Open3D VoxelGrid on the same points."""
    import open3d as o3d

    from occufly.densify.voxelize import SceneGridSpec, majority_vote

    pts64 = np.asarray(xyz, dtype=np.float64)
    t = time.perf_counter()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts64))
    vg = o3d.geometry.VoxelGrid.create_from_point_cloud(pcd, voxel_size=voxel)
    n_o3d = len(vg.get_voxels())
    t_o3d = time.perf_counter() - t
    # same lattice as Open3D: origin = min bound - voxel/2
    lo = pts64.min(axis=0) - voxel / 2
    hi = pts64.max(axis=0) + voxel / 2
    shape = tuple(int(s) for s in np.floor((hi - lo) / voxel).astype(np.int64) + 1)
    spec = SceneGridSpec(origin=lo, local_origin=lo, shape=shape, voxel_size=voxel)
    t = time.perf_counter()
    keys, inside = spec.keys_of_local(xyz)
    k, _, _ = majority_vote(keys[inside], labels[inside], prio)
    t_ours = time.perf_counter() - t
    t = time.perf_counter()
    keys, inside = spec.keys_of_local(xyz)
    n_occ = len(np.unique(keys[inside]))
    t_occ = time.perf_counter() - t
    return {
        "points": int(len(xyz)),
        "open3d_voxelgrid_s": round(t_o3d, 3),
        "ours_binning_majority_s": round(t_ours, 3),
        "ratio_ours_over_open3d": round(t_ours / max(t_o3d, 1e-9), 3),
        "ours_occupancy_only_s": round(t_occ, 3),
        "ratio_occupancy_only_over_open3d": round(t_occ / max(t_o3d, 1e-9), 3),
        "voxels_ours_occupancy_only": int(n_occ),
        "voxels_open3d": n_o3d,
        "voxels_ours": int(len(k)),
        "same_voxel_count": n_o3d == int(len(k)),
        "note": "Open3D builds occupancy only (colour average); ours also votes the majority class",
    }


def _dbscan_scale(n: int) -> dict:
    """DBSCAN on n points spread over 400 flat 20 x 20 m roofs 6 m apart (eps 1 m, minPts 100).

    At n = 10 M that is 62 points/m^2, ~196 neighbours per eps-ball: Open3D would store ~2 G
    neighbour indices (8+ GB); the expected result is 400 clusters and no noise.
    """
    from occufly.densify.dbscan import dbscan

    rng = np.random.default_rng(0)
    roof = rng.integers(0, 400, n)
    xy = rng.uniform(0, 20, (n, 2)).astype(np.float32) + np.stack([(roof % 20) * 26.0, (roof // 20) * 26.0], 1)
    xyz = np.concatenate([xy, (roof[:, None] % 3).astype(np.float32) * 3.0], axis=1).astype(np.float32)
    del xy, roof
    rss0 = _peak_rss_gb()
    t = time.perf_counter()
    lab = dbscan(xyz, 1.0, 100)
    dt = time.perf_counter() - t
    return {"bench": "dbscan-scale", "points": n, "eps": 1.0, "min_points": 100, "seconds": round(dt, 2),
            "clusters": int(lab.max()) + 1, "noise": int((lab < 0).sum()),
            "peak_rss_gb": round(_peak_rss_gb(), 3), "rss_before_gb": round(rss0, 3),
            "open3d_estimate_gb": "every neighbourhood stored: ~n * pi * eps^2 * density * 4 B"}


def _dbscan_compare(ws: Path, labels_path: Path, scale: float | None) -> dict:
    """Our DBSCAN (default cells, and exact point mode) vs Open3D's exact cluster_dbscan."""
    import open3d as o3d

    from occufly.densify.dbscan import dbscan, partition_agreement
    from occufly.densify.pipeline import (
        REFERENCE_SURFACE_DENSITY,
        load_point_labels,
        surface_density,
    )
    from occufly.scene import Scene

    scene = Scene.load(ws)
    labels = load_point_labels(labels_path, scene.n_points)
    if scale is None:
        scale = min(1.0, surface_density(scene.xyz) / REFERENCE_SURFACE_DENSITY)
    out = {}
    for c in scene.taxonomy.classes:
        if c.group != "instance":
            continue
        p = np.asarray(scene.xyz[labels == c.id])
        if len(p) == 0 or len(p) > 200_000:
            continue
        mp = max(2, round(c.dbscan_min_points * scale))
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.astype(np.float64)))
        t = time.perf_counter()
        ref = np.asarray(pc.cluster_dbscan(c.dbscan_eps, mp))
        t_ref = time.perf_counter() - t
        t = time.perf_counter()
        lab = dbscan(p, c.dbscan_eps, mp)
        t_ours = time.perf_counter() - t
        exact = dbscan(p, c.dbscan_eps, mp, cell=0)
        out[c.name] = {
            "points": int(len(p)), "eps": c.dbscan_eps, "min_points": mp,
            "open3d": {"clusters": int(ref.max()) + 1, "noise": int((ref < 0).sum()), "s": round(t_ref, 2)},
            "ours": {"clusters": int(lab.max()) + 1, "noise": int((lab < 0).sum()), "s": round(t_ours, 2)},
            "agreement_cells": round(partition_agreement(lab, ref), 5),
            "agreement_exact_mode": round(partition_agreement(exact, ref), 5),
        }
    return {"bench": "dbscan-vs-open3d", "min_points_scale": scale, "classes": out}


def _ablation(out: Path, ws: Path, labels_path: Path, voxel: float, scale: float | None, args) -> dict:
    from occufly.densify.evaluate import evaluate_grids
    from occufly.densify.pipeline import DensifyOptions, densify, load_point_labels
    from occufly.grid import SceneGrid
    from occufly.scene import Scene

    scene = Scene.load(ws)
    labels = load_point_labels(labels_path, scene.n_points)
    truth = SceneGrid.load(out / "truth" / "scene_grid.npz")
    from occufly.densify.freespace import FrameDepths

    views = FrameDepths(scene.frames, scene.visibility, voxel)
    runs = {}
    for name, kw in (("points_only", dict(carve=False, poisson=False)),
                     ("plus_instances", dict(poisson=False, free_space=False)),
                     ("plus_poisson", dict(free_space=False)),
                     ("plus_free_space", {}),
                     ("without_point_smoothing", dict(smooth_radius=0.0))):
        t = time.perf_counter()
        res = densify(scene.xyz, labels, scene.taxonomy, scene_origin=scene.origin, views=views,
                      options=DensifyOptions(voxel_size=voxel, min_points_scale=scale, **kw))
        ev = evaluate_grids(res.grid, truth, scene.taxonomy)
        runs[name] = {
            "seconds": round(time.perf_counter() - t, 1),
            "completion_iou": round(ev["completion_iou"], 4),
            "precision": round(ev["precision"], 4),
            "recall": round(ev["recall"], 4),
            "miou": round(ev["miou"], 4),
            "per_class_iou": {k: (None if v is None else round(v, 3)) for k, v in ev["per_class_iou"].items()},
        }
    return {"bench": "densify-ablation", "preset": args.preset, "labels": args.labels,
            "labels_path": str(labels_path), "points": scene.n_points, "runs": runs}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="/tmp/occufly_bench")
    ap.add_argument("--preset", default="bench")
    ap.add_argument("--labels", choices=("truth", "lifting"), default="truth")
    ap.add_argument("--min-points-scale", default="auto")
    ap.add_argument("--voxel", type=float, default=0.5)
    ap.add_argument("--synth", help="use this existing synthetic output (OUT) instead of generating")
    ap.add_argument("--workspace", help="use this existing workspace (imported from --synth)")
    ap.add_argument("--dbscan-points", type=int, default=0,
                    help="instead: DBSCAN alone on this many synthetic roof points (eps 1 m), peak memory")
    ap.add_argument("--dbscan-compare", action="store_true",
                    help="instead: our DBSCAN (cells and exact mode) vs Open3D per instance class")
    ap.add_argument("--ablation", action="store_true",
                    help="instead: quality of points only / + instances / + Poisson (no timing budget)")
    args = ap.parse_args(argv)

    if args.dbscan_points:
        print(json.dumps(_dbscan_scale(args.dbscan_points)))
        return 0
    root = Path(args.root)
    root.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    if args.synth and args.workspace:
        out, ws = Path(args.synth), Path(args.workspace)
    else:
        out, ws = ensure_scene(root, args.preset)
    t_prepare = time.perf_counter() - t

    from occufly.densify.evaluate import evaluate_grids
    from occufly.densify.pipeline import DensifyOptions, voxelize_workspace
    from occufly.grid import SceneGrid
    from occufly.scene import Scene

    labels_path = out / "truth" / "point_labels.npy" if args.labels == "truth" else ws / "lifting" / "labels.npy"
    scale = None if args.min_points_scale == "auto" else float(args.min_points_scale)
    if args.ablation:
        print(json.dumps(_ablation(out, ws, labels_path, args.voxel, scale, args)))
        return 0
    if args.dbscan_compare:
        print(json.dumps(_dbscan_compare(ws, labels_path, scale)))
        return 0
    rss0 = _peak_rss_gb()
    t = time.perf_counter()
    report = voxelize_workspace(
        ws, labels_path=labels_path,
        options=DensifyOptions(voxel_size=args.voxel, min_points_scale=scale),
        out_path=root / f"grid_{args.preset}.npz",
    )
    t_e2e = time.perf_counter() - t
    peak = _peak_rss_gb()

    scene = Scene.load(ws)
    truth = SceneGrid.load(out / "truth" / "scene_grid.npz")
    pred = SceneGrid.load(root / f"grid_{args.preset}.npz")
    ev = evaluate_grids(pred, truth, scene.taxonomy)
    labels = np.load(labels_path)
    cmp = _binning_vs_open3d(np.asarray(scene.xyz), labels, scene.taxonomy.priority_lut(), args.voxel)

    result = {
        "bench": "densify",
        "preset": args.preset,
        "labels": args.labels,
        "points": report["points"],
        "grid_shape": report["grid_shape"],
        "end_to_end_s": round(t_e2e, 2),
        "budget_s": 300,
        "within_time_budget": t_e2e <= 300,
        "peak_rss_gb": round(peak, 3),
        "rss_before_densify_gb": round(rss0, 3),
        "within_memory_budget": peak <= 8.0,
        "stages_s": report["timings_s"],
        "min_points_scale": report["options"]["min_points_scale"],
        "instances": {k: v.get("instances") for k, v in report["instances"].items()},
        "occupied_voxels": report["occupied_voxels"],
        "quality": {k: ev[k] for k in ("completion_iou", "precision", "recall", "miou", "classes_evaluated")},
        "voxelization_vs_open3d": cmp,
        "prepare_s_not_counted": round(t_prepare, 1),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
