"""The COLMAP sparse model of the synthetic flight, written with pycolmap."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occufly.camera import Camera
from occufly.io.colmap import import_pycolmap


def write_sparse_model(
    out_dir: Path,
    camera: Camera | list[Camera],
    names: list[str],
    poses_world: list[np.ndarray],
    points_world: np.ndarray,
    colors: np.ndarray,
    tracks: list[tuple[np.ndarray, np.ndarray]],
) -> dict:
    """Write ``cameras/images/points3D.bin`` into ``out_dir``.

    camera: one camera for every image, or one per image (distinct ones get camera ids 1, 2, ...
    in order of first use); names: F image names, image ids are 1..F in this order; poses_world: F (4, 4) float64
    world-to-camera in WORLD (georeferenced) coordinates; points_world: (P, 3) float64;
    colors: (P, 3) uint8; tracks: per point (frame indices (k,) int, uv (k, 2) float64 pixels).
    """
    pycolmap = import_pycolmap()
    rec = pycolmap.Reconstruction()
    # the camera's own COLMAP model (PINHOLE for the default scene, FULL_OPENCV with lens
    # distortion for synthetic/formats.py)
    per_frame = camera if isinstance(camera, list) else [camera] * len(names)
    cam_ids: dict[Camera, int] = {}
    for c in per_frame:
        if c not in cam_ids:
            cam_ids[c] = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(
                model=c.model, width=c.width, height=c.height,
                params=[float(v) for v in c.params], camera_id=cam_ids[c]))
    # keypoints per image: every observation of every track, in track order
    per_image: list[list[np.ndarray]] = [[] for _ in names]
    obs_index: list[list[tuple[int, int]]] = []
    counts = np.zeros(len(names), np.int64)
    for frames, uv in tracks:
        elems = []
        for f, p in zip(frames.tolist(), uv, strict=False):
            per_image[f].append(p)
            elems.append((f, int(counts[f])))
            counts[f] += 1
        obs_index.append(elems)
    for f, (name, T) in enumerate(zip(names, poses_world, strict=False)):
        kp = np.array(per_image[f], dtype=np.float64).reshape(-1, 2)
        img = pycolmap.Image(name=name, keypoints=kp, camera_id=cam_ids[per_frame[f]], image_id=f + 1)
        pose = pycolmap.Rigid3d(np.asarray(T[:3, :4], dtype=np.float64))
        rec.add_image_with_trivial_frame(img, pose)
    for xyz, col, elems in zip(points_world, colors, obs_index, strict=False):
        track = pycolmap.Track([pycolmap.TrackElement(f + 1, k) for f, k in elems])
        rec.add_point3D(np.asarray(xyz, np.float64), track, np.asarray(col, np.uint8))
    rec.update_point_3d_errors()
    out_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(out_dir))
    return {"images": rec.num_images(), "points3D": rec.num_points3D(),
            "observations": int(counts.sum())}
