"""``generate``: render the synthetic flight and write it as a COLMAP dense workspace + truth.

Output layout (world coordinates = scene-local + ``meta.json`` ``world_offset``)::

    OUT/images/frame_000000.png|jpg        RGB 8-bit
    OUT/sparse/{cameras,images,points3D}.bin   COLMAP model: 1 PINHOLE camera (2 with full-size
                                           frames: camera 2 is the full sensor), image ids 1..F
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
import shutil
import time
from pathlib import Path

import numpy as np
from PIL import Image

from occufly.camera import Camera, project_world
from occufly.errors import OccuflyError, WorkspaceError
from occufly.fsutil import atomic_directory, require_memory
from occufly.io.colmap_dense import (
    read_depth_map,
    write_depth_map,
    write_fused_ply,
    write_fused_vis,
)
from occufly.progress import ProgressFn, noop
from occufly.synthetic.flight import make_camera, plan_flight
from occufly.synthetic.fuse import (
    SampleSpill,
    TileIndex,
    back_project,
    build_visibility,
    depth_agreement,
    sample_grid,
)
from occufly.synthetic.presets import Preset, get_preset
from occufly.synthetic.render import Renderer, noisy_depth, render_banded
from occufly.synthetic.sparse import write_sparse_model
from occufly.synthetic.truth import truth_grid
from occufly.synthetic.world import build_world
from occufly.taxonomy import default_taxonomy

FORMAT = "occufly-synthetic"
VERSION = 1


def full_size_frames(P: Preset, n_frames: int) -> set[int]:
    """Indices of the frames rendered at the full sensor size: ``P.full_frames`` of them,
    spread evenly over the flight (every altitude, pass and pitch gets some)."""
    n = min(P.full_frames, n_frames)
    return {int((k + 0.5) * n_frames / n) for k in range(n)} if n else set()


def _render_frames(job: dict, renderer: Renderer | None = None, report=None) -> dict:
    """Render frames ``job["frames"]`` (indices, ascending): write image, truth mask and noisy
    depth map of each, stream its depth samples into a :class:`SampleSpill` of its own. Runs
    in-process or in a worker process (then it builds the world itself: it is deterministic)."""
    P, seed, tmp = job["preset"], job["seed"], Path(job["tmp"])
    if renderer is None:
        renderer = Renderer(build_world(P, seed), seed)
    cams = job["cams"]
    base = cams[0] if not P.full_frames else min(cams, key=lambda c: c.width)
    grids = {c: sample_grid(c, P.pixel_stride * (c.width // base.width)) for c in set(cams)}
    spill = SampleSpill(job["spill"], job["edges"])
    depth_dir = tmp / "dense" / "stereo" / "depth_maps"
    bboxes: list[tuple[float, float, float, float]] = []
    mask_classes = np.zeros(256, bool)
    for k, f in enumerate(job["frames"]):
        cam_f, name, T = cams[f], job["names"][f], job["poses"][f]
        rr, cc, rays = grids[cam_f]
        rng = np.random.default_rng([seed, 1, f])
        res = render_banded(renderer, cam_f, T, rng)
        dn = noisy_depth(res.depth, res.cls, rng, sigma=P.depth_noise)
        stem = Path(name).stem
        img = Image.fromarray(res.rgb)
        if P.image_ext == ".png":
            img.save(tmp / "images" / name, compress_level=1)
        else:
            img.save(tmp / "images" / name, quality=92)
        Image.fromarray(res.cls, mode="L").save(tmp / "truth" / "masks" / f"{stem}.png", compress_level=1)
        write_depth_map(depth_dir / f"{name}.geometric.bin", dn)
        mask_classes[np.bincount(res.cls.ravel(), minlength=256) > 0] = True
        xyz, keep = back_project(dn, rays, rr, cc, T)
        r_, c_ = rr[keep], cc[keep]
        spill.add(xyz, res.rgb[r_, c_], res.cls[r_, c_], res.normal[r_, c_].astype(np.float16), int(f),
                  np.flatnonzero(keep))
        hit = res.depth > 0
        if hit.any():
            hx, hy = res.xyz[..., 0][hit], res.xyz[..., 1][hit]
            bboxes.append((float(hx.min()) - 1, float(hx.max()) + 1, float(hy.min()) - 1, float(hy.max()) + 1))
        else:
            bboxes.append((0.0, -1.0, 0.0, -1.0))
        del res, dn, xyz
        if report is not None:
            report(k + 1)
    return {"spill": spill, "bboxes": bboxes, "mask_classes": mask_classes}


def estimate_resources(P: Preset, n_frames: int, *, workers: int = 1) -> dict:
    """Up-front estimate of what generating ``P`` needs: peak memory and disk (bytes).

    Measured on this generator (2 cores): a frame costs about 110 B per pixel while it is
    rendered (20 MP frames are cast in bands, their full-size fields ~40 B per pixel), fusion
    ~110 B per sample of one strip, then ~330 B per fused point (the cloud, its visibility, the
sparse model and the truth grid; survey, 32 M points: 10.7 GB peak measured); on
    disk the sample spill takes 30 B per sample until fusion, depth maps 4 B per pixel, JPEGs
    ~0.4 B and masks ~0.1 B per pixel, the fused cloud + .vis ~60 B per point. Points are
    taken as 1/10 of the samples (the survey presets fuse 9-12 samples per point).
    """
    n_full = min(P.full_frames, n_frames)
    px_small = P.width * P.height
    px_full = P.full_width * P.full_height if n_full else 0
    pixels = (n_frames - n_full) * px_small + n_full * px_full
    samples = (n_frames * px_small) // (P.pixel_stride ** 2)
    points = samples // 10
    frame_mem = max(px_small * 110, min(px_full, 1 << 21) * 110 + px_full * 40)
    render = workers * (frame_mem + (300 << 20))
    after = min(samples, 6_000_000) * 110 + points * 330  # fusion, visibility, sparse, truth grid
    memory = (400 << 20) + max(render, after)
    disk = samples * 30 + pixels * 4.5 + points * 60 + (50 << 20)
    return {"memory_bytes": int(memory), "disk_bytes": int(disk), "frames": n_frames,
            "full_size_frames": n_full, "depth_samples": int(samples), "points_estimate": int(points)}


def check_resources(P: Preset, n_frames: int, out: Path, *, workers: int = 1) -> dict:
    """:func:`estimate_resources` against free disk under ``out``'s parent and available memory;
    an :class:`~occufly.errors.OccuflyError` naming both figures when they do not fit (before
    anything is written: never a full disk or an out-of-memory kill halfway)."""
    est = estimate_resources(P, n_frames, workers=workers)
    parent = Path(out).absolute().parent
    while not parent.exists():
        parent = parent.parent
    free = shutil.disk_usage(parent).free
    gb = 2.0 ** 30
    if est["disk_bytes"] > free:
        raise OccuflyError(
            f"{out}: preset {P.name} needs about {est['disk_bytes'] / gb:.1f} GB of disk "
            f"({n_frames} frames, ~{est['depth_samples'] / 1e6:.0f} M depth samples), "
            f"{parent} has {free / gb:.1f} GB free")
    require_memory(est["memory_bytes"], f"preset {P.name}", detail=f" with --workers {workers}",
                   hint="try --workers 1" if workers > 1 else "")
    return est


def _is_nonempty_dir(p: Path) -> bool:
    return p.exists() and (not p.is_dir() or any(p.iterdir()))


def generate(out: str | Path, *, preset: str = "small", seed: int = 0,
             progress: ProgressFn | None = None, overwrite: bool = False,
             camera: Camera | None = None, strip_samples: int = 6_000_000, workers: int = 1) -> dict:
    """Generate the synthetic scene ``preset`` for ``seed`` into ``out``.

    The folder is built under a temporary sibling name and renamed into place at the end, so an
    interrupted run leaves nothing half-written. An existing non-empty ``out`` is replaced only
    with ``overwrite``. Returns a summary dict (frames, points, classes present, timings).

    Memory is bounded by one frame's render plus one x strip of about ``strip_samples`` depth
    samples (frames stream their samples to disk; fusion runs strip by strip, with the same
    result as fusing everything at once) plus the fused cloud itself. ``workers`` > 1 renders
    contiguous frame ranges in that many processes (same files, byte for byte).
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
    full = full_size_frames(P, len(frames))
    camera_full = camera.scaled(P.full_scale) if len(full) else None
    cams = [camera_full if f in full else camera for f in range(len(frames))]
    renderer = Renderer(world, seed)
    timings["world"] = time.perf_counter() - t0
    F = len(frames)
    names = [f.name for f in frames]
    check_resources(P, F, out, workers=max(1, min(workers, F)))

    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "images").mkdir()
        (tmp / "truth" / "masks").mkdir(parents=True)
        depth_dir = tmp / "dense" / "stereo" / "depth_maps"
        depth_dir.mkdir(parents=True)

        # ---- render every frame; stream its depth samples to disk strips ---------------
        t0 = time.perf_counter()
        grids = {c: sample_grid(c, P.pixel_stride * (c.width // camera.width)) for c in set(cams)}
        expected = sum(len(grids[c][0]) for c in cams)
        n_strips = max(1, min(int(np.ceil(expected / strip_samples)),
                              int(world.size / (4 * P.fuse_voxel))))
        edges = np.linspace(world.x0, world.x0 + world.size, n_strips + 1)
        jobs = [{"preset": P, "seed": seed, "frames": list(r), "names": names, "cams": cams,
                 "poses": [fr.T_cam_world for fr in frames], "tmp": tmp, "edges": edges,
                 "spill": tmp / ".samples" / f"part{k:02d}"}
                for k, r in enumerate(np.array_split(np.arange(F), max(1, min(workers, F)))) if len(r)]
        parts = _render_jobs(jobs, renderer, report, F)
        spill = SampleSpill.union([p_["spill"] for p_ in parts])
        bboxes = [b_ for p_ in parts for b_ in p_["bboxes"]]
        mask_classes = np.logical_or.reduce([p_["mask_classes"] for p_ in parts])
        timings["render"] = time.perf_counter() - t0

        # ---- fuse the dense cloud, strip by strip ------------------------------------------
        t0 = time.perf_counter()
        n_samples = spill.n_samples
        try:
            cloud, contrib = spill.fuse(P.fuse_voxel, F, priority, min_views=P.min_views,
                                        progress=lambda x, m="": report(0.7 + 0.08 * x, m))
        finally:
            spill.close()
        timings["fuse"] = time.perf_counter() - t0
        report(0.78, "visibility")

        # ---- visibility: contributing images (+ images whose depth map agrees) ----------
        t0 = time.perf_counter()
        N = len(cloud.xyz)
        _fused_visibility(cloud, contrib, P, frames, cams, bboxes, depth_dir)
        del contrib
        timings["visibility"] = time.perf_counter() - t0
        report(0.85, "writing dense cloud")

        offset = world.offset
        xyz_world = cloud.xyz + offset
        write_fused_ply(tmp / "dense" / "fused.ply", xyz_world, cloud.normal, cloud.rgb, double=True)
        write_fused_vis(tmp / "dense" / "fused.ply.vis", cloud.vis_offsets, cloud.vis_frames)
        np.save(tmp / "truth" / "point_labels.npy", cloud.label)

        # ---- sparse model: a subset of the points with their tracks ---------------------
        t0 = time.perf_counter()
        sparse_info = _sparse_model(tmp / "sparse", cloud, xyz_world, P, seed, frames, cams,
                                    cams if len(full) else camera, names, offset)
        timings["sparse"] = time.perf_counter() - t0
        report(0.9, "truth grid")

        # ---- truth grid ---------------------------------------------------------------------
        t0 = time.perf_counter()
        grid = truth_grid(world, tax, P.grid_voxel, seed, camera=camera,
                          poses=[fr.T_cam_world for fr in frames], min_views=P.min_views,
                          observed_xy=cloud.xyz[:, :2])
        grid.save(tmp / "truth" / "scene_grid.npz")
        timings["truth_grid"] = time.perf_counter() - t0

        summary = _summary(out, P, seed, world, cloud, grid, mask_classes, camera, camera_full,
                           full, n_frames=F, n_samples=n_samples,
                           sparse_points=int(sparse_info["points3D"]))
        meta = _meta(summary, P, world, frames, full, camera, camera_full, grid, F, N)
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


def _summary(out: Path, P, seed: int, world, cloud, grid, mask_classes: np.ndarray, camera,  # noqa: ANN001
             camera_full, full, *, n_frames: int, n_samples: int, sparse_points: int) -> dict:  # noqa: ANN001
    """What :func:`generate` returns (and ``meta.json`` starts with): sizes and the classes
    present in the world, the masks, the points and the truth grid."""
    N = len(cloud.xyz)
    n_vis = np.diff(cloud.vis_offsets)
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
        "frames": n_frames,
        "points": int(N),
        "image_size": [camera.width, camera.height],
        "altitudes": list(P.altitudes),
        "depth_samples": int(n_samples),
        "mean_views_per_point": float(n_vis.mean()) if N else 0.0,
        "sparse_points": sparse_points,
        "grid_shape": list(grid.shape),
        "classes_present": classes,
        "n_classes_present": len(classes["world"]),
    }
    if len(full):
        summary["full_size_frames"] = len(full)
        summary["full_image_size"] = [camera_full.width, camera_full.height]
    return summary


def _render_jobs(jobs: list[dict], renderer: Renderer, report: ProgressFn, F: int) -> list[dict]:
    """Render every job's frames (one job: in this process; more: one spawned process each,
    contiguous frame ranges, so the spills concatenate in frame order)."""
    if len(jobs) == 1:
        return [_render_frames(jobs[0], renderer=renderer,
                               report=lambda k: report(0.7 * k / F, f"rendering {k}/{F}"))]
    import multiprocessing as mp  # only for a multi-process render
    from concurrent.futures import ProcessPoolExecutor

    ex = ProcessPoolExecutor(len(jobs), mp_context=mp.get_context("spawn"))
    try:
        futs = [ex.submit(_render_frames, j) for j in jobs]
        parts, done = [], 0
        for j, fu in zip(jobs, futs, strict=True):
            parts.append(fu.result())
            done += len(j["frames"])
            report(0.7 * done / F, f"rendering {done}/{F}")
    except BaseException:  # Ctrl-C / SIGTERM / a worker's error: stop the others now
        for proc in list(getattr(ex, "_processes", {}).values()):
            proc.terminate()
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    ex.shutdown()
    return parts


def _fused_visibility(cloud, contrib: tuple[np.ndarray, np.ndarray], P, frames, cams,  # noqa: ANN001
                      bboxes, depth_dir: Path) -> None:  # noqa: ANN001
    """``cloud.vis_offsets`` / ``vis_frames``: the images that contributed to each fused point
    (``contrib``: (point ids, frame ids)), plus, with ``P.vis_depth_check``, the images whose
    depth map agrees with it."""
    N, F = len(cloud.xyz), len(frames)
    if not P.vis_depth_check:  # the contributing pairs are already unique and sorted by (point, frame)
        cloud.vis_offsets = np.zeros(N + 1, np.int64)
        np.cumsum(np.bincount(contrib[0], minlength=N), out=cloud.vis_offsets[1:])
        cloud.vis_frames = contrib[1].astype(np.uint32)
        return
    pts_l, frm_l = [contrib[0]], [contrib[1]]
    index = TileIndex(cloud.xyz)
    for f, fr in enumerate(frames):  # the depth maps as written (one in memory at a time)
        dn = read_depth_map(depth_dir / f"{fr.name}.geometric.bin")
        pts = depth_agreement(cloud.xyz, index, cams[f], fr.T_cam_world, dn,
                              bboxes[f], P.vis_tolerance)
        pts_l.append(pts)
        frm_l.append(np.full(len(pts), f, np.int32))
    del index
    cloud.vis_offsets, cloud.vis_frames = build_visibility(N, F, pts_l, frm_l)


def _sparse_model(path: Path, cloud, xyz_world: np.ndarray, P, seed: int, frames, cams,  # noqa: ANN001
                  model_cameras, names: list[str], offset: np.ndarray) -> dict:  # noqa: ANN001
    """The COLMAP sparse model: a random subset of the multi-view points with their tracks
    (observations projected frame by frame, vectorised)."""
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
        uv, _, vis = project_world(cams[f], frames[f].T_cam_world, cloud.xyz[obs_pt[m]])
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
    return write_sparse_model(path, model_cameras, names, poses_world,
                              xyz_world[kept_idx], cloud.rgb[kept_idx], tracks)


def _meta(summary: dict, P, world, frames, full, camera, camera_full, grid, F: int, N: int) -> dict:  # noqa: ANN001
    """``truth/meta.json``: the summary, the preset, the cameras, the noise model, the fusion
    and truth-grid rules and every frame's flight record."""
    offset = world.offset
    return {
        "format": FORMAT,
        "version": VERSION,
        **summary,
        "n_frames": F,
        "n_points": int(N),
        "preset_params": P.to_dict(),
        "world_offset": [float(v) for v in offset],
        "sun_direction": [float(v) for v in world.sun],
        "camera": camera.to_dict(),
        **({"camera_full_size": camera_full.to_dict(),
            "full_size_frames": [frames[f].name for f in sorted(full)]} if len(full) else {}),
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
             "center_world": [float(v) for v in fr.center + offset],
             **({"camera_id": 2 if i in full else 1} if len(full) else {})}
            for i, fr in enumerate(frames)
        ],
    }
