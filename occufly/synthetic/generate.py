"""``generate``: render the synthetic flight and write it as a COLMAP dense workspace + truth.

Output layout (world coordinates = scene-local + ``meta.json`` ``world_offset``)::

    OUT/images/frame_000000.png|jpg        RGB 8-bit
    OUT/sparse/{cameras,images,points3D}.bin   COLMAP model: 1 PINHOLE camera, image ids 1..F
    OUT/dense/fused.ply (+ .vis)           fused cloud (x, y, z double), visibility per point
    OUT/dense/stereo/depth_maps/<image name>.geometric.bin   noisy MVS-like z-depth, 0 = none
    OUT/truth/masks/<image stem>.png       uint8 raw class ids (0 = nothing / sky)
    OUT/truth/point_labels.npy             (N,) uint8 raw ids aligned with fused.ply
    OUT/truth/scene_grid.npz               labels (X, Y, Z) uint8, origin (WORLD), voxel_size
    OUT/truth/objects.json                 the analytic primitives (scene-local) + offset
    OUT/truth/meta.json                    preset, seed, frames (altitudes, pitch, ...), counts
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from occufly.camera import Camera, project_world
from occufly.errors import WorkspaceError
from occufly.fsutil import atomic_directory
from occufly.io.colmap_dense import write_depth_map, write_fused_ply, write_fused_vis
from occufly.progress import ProgressFn, noop
from occufly.synthetic.flight import make_camera, plan_flight
from occufly.synthetic.fuse import (
    Samples,
    TileIndex,
    back_project,
    build_visibility,
    depth_agreement,
    fuse,
    sample_grid,
)
from occufly.synthetic.presets import get_preset
from occufly.synthetic.render import Renderer, noisy_depth
from occufly.synthetic.sparse import write_sparse_model
from occufly.synthetic.truth import truth_grid
from occufly.synthetic.world import build_world
from occufly.taxonomy import default_taxonomy

FORMAT = "occufly-synthetic"
VERSION = 1


def _is_nonempty_dir(p: Path) -> bool:
    return p.exists() and (not p.is_dir() or any(p.iterdir()))


def generate(out: str | Path, *, preset: str = "small", seed: int = 0,
             progress: ProgressFn | None = None, overwrite: bool = False,
             camera: Camera | None = None) -> dict:
    """Generate the synthetic scene ``preset`` for ``seed`` into ``out``.

    The folder is built under a temporary sibling name and renamed into place at the end, so an
    interrupted run leaves nothing half-written. An existing non-empty ``out`` is replaced only
    with ``overwrite``. Returns a summary dict (frames, points, classes present, timings).
    """
    out = Path(out)
    if _is_nonempty_dir(out) and not overwrite:
        raise WorkspaceError(f"{out}: exists and is not empty (use --force to replace it)")
    P = get_preset(preset)
    report = progress or noop
    tax = default_taxonomy()
    priority = tax.priority_lut()
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    cpu_all = time.process_time()

    t0 = time.perf_counter()
    world = build_world(P, seed)
    camera = make_camera(P) if camera is None else camera  # a lens-distorted one: synthetic/formats.py
    frames = plan_flight(P, world, camera)
    renderer = Renderer(world, seed)
    timings["world"] = time.perf_counter() - t0
    F = len(frames)
    names = [f.name for f in frames]

    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "images").mkdir()
        (tmp / "truth" / "masks").mkdir(parents=True)
        depth_dir = tmp / "dense" / "stereo" / "depth_maps"
        depth_dir.mkdir(parents=True)

        # ---- render every frame; keep depth samples for fusion -------------------------
        t0 = time.perf_counter()
        rr, cc, rays = sample_grid(camera, P.pixel_stride)
        chunks: dict[str, list[np.ndarray]] = {k: [] for k in ("xyz", "rgb", "cls", "normal", "frame")}
        keep_depth: list[np.ndarray] = []
        bboxes: list[tuple[float, float, float, float]] = []
        mask_classes = np.zeros(256, bool)
        for f, fr in enumerate(frames):
            rng = np.random.default_rng([seed, 1, f])
            res = renderer.render(camera, fr.T_cam_world, rng)
            dn = noisy_depth(res.depth, res.cls, rng, sigma=P.depth_noise)
            stem = Path(fr.name).stem
            img = Image.fromarray(res.rgb)
            if P.image_ext == ".png":
                img.save(tmp / "images" / fr.name, compress_level=1)
            else:
                img.save(tmp / "images" / fr.name, quality=92)
            Image.fromarray(res.cls, mode="L").save(tmp / "truth" / "masks" / f"{stem}.png", compress_level=1)
            write_depth_map(depth_dir / f"{fr.name}.geometric.bin", dn)
            mask_classes[np.bincount(res.cls.ravel(), minlength=256) > 0] = True
            xyz, keep = back_project(dn, rays, rr, cc, fr.T_cam_world)
            r_, c_ = rr[keep], cc[keep]
            chunks["xyz"].append(xyz)
            chunks["rgb"].append(res.rgb[r_, c_])
            chunks["cls"].append(res.cls[r_, c_])
            chunks["normal"].append(res.normal[r_, c_].astype(np.float16))
            chunks["frame"].append(np.full(len(xyz), f, np.int32))
            hit = res.depth > 0
            if hit.any():
                hx, hy = res.xyz[..., 0][hit], res.xyz[..., 1][hit]
                bboxes.append((float(hx.min()) - 1, float(hx.max()) + 1, float(hy.min()) - 1, float(hy.max()) + 1))
            else:
                bboxes.append((0.0, -1.0, 0.0, -1.0))
            if P.vis_depth_check:
                keep_depth.append(dn)
            report(0.7 * (f + 1) / F, f"rendering {f + 1}/{F}")
        timings["render"] = time.perf_counter() - t0

        # ---- fuse the dense cloud --------------------------------------------------------
        t0 = time.perf_counter()
        fields = {}
        for k in ("xyz", "rgb", "cls", "normal", "frame"):  # one field at a time: lower peak memory
            fields[k] = np.concatenate(chunks[k])
            chunks[k] = []
        samples = Samples(**fields)
        del fields
        n_samples = len(samples.xyz)
        del chunks
        cloud, contrib = fuse(samples, P.fuse_voxel, F, priority, min_views=P.min_views)
        del samples
        timings["fuse"] = time.perf_counter() - t0
        report(0.78, "visibility")

        # ---- visibility: contributing images (+ images whose depth map agrees) ----------
        t0 = time.perf_counter()
        pts_l, frm_l = [contrib[0]], [contrib[1]]
        if P.vis_depth_check:
            index = TileIndex(cloud.xyz)
            for f, fr in enumerate(frames):
                pts = depth_agreement(cloud.xyz, index, camera, fr.T_cam_world, keep_depth[f],
                                      bboxes[f], P.vis_tolerance)
                pts_l.append(pts)
                frm_l.append(np.full(len(pts), f, np.int32))
            del keep_depth, index
        N = len(cloud.xyz)
        cloud.vis_offsets, cloud.vis_frames = build_visibility(N, F, pts_l, frm_l)
        del pts_l, frm_l, contrib
        timings["visibility"] = time.perf_counter() - t0
        report(0.85, "writing dense cloud")

        offset = world.offset
        xyz_world = cloud.xyz + offset
        write_fused_ply(tmp / "dense" / "fused.ply", xyz_world, cloud.normal, cloud.rgb, double=True)
        write_fused_vis(tmp / "dense" / "fused.ply.vis", cloud.vis_offsets, cloud.vis_frames)
        np.save(tmp / "truth" / "point_labels.npy", cloud.label)

        # ---- sparse model: a subset of the points with their tracks ---------------------
        t0 = time.perf_counter()
        rng = np.random.default_rng([seed, 2])
        n_vis = np.diff(cloud.vis_offsets)
        cand = np.flatnonzero(n_vis >= 2)
        pick = np.sort(rng.choice(cand, size=min(P.sparse_points, len(cand)), replace=False))
        # every observation of the picked points, projected frame by frame (vectorised)
        lens = n_vis[pick]
        obs_pt = np.repeat(pick, lens)
        obs_f = np.concatenate([cloud.vis_frames[cloud.vis_offsets[p] : cloud.vis_offsets[p + 1]]
                                for p in pick]).astype(np.int64) if len(pick) else np.zeros(0, np.int64)
        obs_uv = np.zeros((len(obs_pt), 2))
        obs_ok = np.zeros(len(obs_pt), bool)
        for f in np.unique(obs_f):
            m = np.flatnonzero(obs_f == f)
            uv, _, vis = project_world(camera, frames[f].T_cam_world, cloud.xyz[obs_pt[m]])
            obs_uv[m] = uv
            obs_ok[m] = vis
        tracks = []
        kept = []
        starts = np.concatenate([[0], np.cumsum(lens)])
        for k, p in enumerate(pick):
            sl = slice(starts[k], starts[k + 1])
            ok = obs_ok[sl]
            if ok.sum() >= 2:
                tracks.append((obs_f[sl][ok], obs_uv[sl][ok]))
                kept.append(p)
        kept_idx = np.array(kept, np.int64)
        poses_world = []
        for fr in frames:
            T = fr.T_cam_world.copy()
            T[:3, 3] = T[:3, 3] - T[:3, :3] @ offset
            poses_world.append(T)
        sparse_info = write_sparse_model(tmp / "sparse", camera, names, poses_world,
                                         xyz_world[kept_idx], cloud.rgb[kept_idx], tracks)
        timings["sparse"] = time.perf_counter() - t0
        report(0.9, "truth grid")

        # ---- truth grid ---------------------------------------------------------------------
        t0 = time.perf_counter()
        grid = truth_grid(world, tax, P.grid_voxel, seed, camera=camera,
                          poses=[fr.T_cam_world for fr in frames], min_views=P.min_views,
                          observed_xy=cloud.xyz[:, :2])
        grid.save(tmp / "truth" / "scene_grid.npz")
        timings["truth_grid"] = time.perf_counter() - t0

        classes = {
            "world": world.classes_present(),
            "masks": [int(i) for i in np.flatnonzero(mask_classes) if i != 0],
            "points": [int(i) for i in np.flatnonzero(np.bincount(cloud.label, minlength=256))],
            "grid": [int(i) for i in np.flatnonzero(np.bincount(grid.labels.ravel(), minlength=256)) if i not in (0, 255)],
        }
        summary = {
            "out": str(out),
            "preset": P.name,
            "seed": int(seed),
            "frames": F,
            "points": int(N),
            "image_size": [camera.width, camera.height],
            "altitudes": list(P.altitudes),
            "depth_samples": int(n_samples),
            "mean_views_per_point": float(n_vis.mean()) if N else 0.0,
            "sparse_points": int(sparse_info["points3D"]),
            "grid_shape": list(grid.shape),
            "classes_present": classes,
            "n_classes_present": len(classes["world"]),
        }
        meta = {
            "format": FORMAT,
            "version": VERSION,
            **summary,
            "n_frames": F,
            "n_points": int(N),
            "preset_params": P.to_dict(),
            "world_offset": [float(v) for v in offset],
            "sun_direction": [float(v) for v in world.sun],
            "camera": camera.to_dict(),
            "up_axis": "z",
            "depth_noise": {"relative_sigma": P.depth_noise, "invalid_near_discontinuities": 0.5,
                            "invalid_random": 0.005, "invalid_water": 0.3},
            "fusion": {"voxel": P.fuse_voxel, "pixel_stride": P.pixel_stride, "min_views": P.min_views,
                       "visibility": "contributing images" + (
                           f" + depth agreement (relative tolerance {P.vis_tolerance})" if P.vis_depth_check else "")},
            "grid_voxel": P.grid_voxel,
            "truth_grid": {
                "above_terrain_only": True,
                "invalid_255": f"columns whose terrain point is inside fewer than {P.min_views} images, "
                               "or with no fused point within 2 m (plan view)",
                "invalid_columns": int((grid.labels[:, :, 0] == 255).sum()),
                "columns": int(grid.shape[0] * grid.shape[1]),
            },
            "frames_detail": [
                {"name": fr.name, "image_id": i + 1, "nominal_altitude": fr.nominal_altitude,
                 "altitude_above_ground": round(fr.altitude_above_ground, 3), "pitch_deg": fr.pitch_deg,
                 "heading_deg": fr.heading_deg, "pass": fr.pass_index, "line": fr.line, "station": fr.station,
                 "center_world": [float(v) for v in fr.center + offset]}
                for i, fr in enumerate(frames)
            ],
        }
        objects = {"world_offset": [float(v) for v in offset], "coordinates": "scene-local metres",
                   "primitives": [p.to_dict() for p in world.prims]}
        (tmp / "truth" / "objects.json").write_text(json.dumps(objects))
        timings["total"] = time.perf_counter() - t_all
        timings["total_cpu"] = time.process_time() - cpu_all  # all threads of this process
        summary["timings"] = {k: round(v, 3) for k, v in timings.items()}
        meta["timings"] = summary["timings"]
        (tmp / "truth" / "meta.json").write_text(json.dumps(meta, indent=1))
        report(1.0, "done")
    return summary
