"""CGFormer (pkqbajng/CGFormer 0331e11): a KITTI-360 dataset class over an SSCBench-layout
export, registered in mmdet's ``DATASETS`` registry when mmdet is importable.

CGFormer reads its config with mmcv's ``Config.fromfile`` (main.py:30), which imports the
modules listed in ``custom_imports``; the dataset is then built by registry name. So the port
is configuration only (configs/CGFormer-Efficient-Swin-KITTI360.py)::

    custom_imports = dict(imports=['occufly.datasets.compat.cgformer'], allow_failed_imports=False)
    dataset_type = 'OccuFlyKITTI360Dataset'
    data_root = '/path/to/export'
    ann_file = '/path/to/export/preprocess/labels'
    stereo_depth_root = '/path/to/export/depth_full'
    point_cloud_range = [x0, y0, z0, x1, y1, z1]   # occufly.yaml voxel_origin, + scene_size
    occ_size = [X, Y, Z]
    # ... and the model's literals that repeat them (see docs/ssc-porting.md)

CGFormer's ``CreateDepthFromLiDAR`` step reads ``velodyne_points/``: export with
``--velodyne``.

Input-dict contract (``mmdet3d_plugin/datasets/kitti360.py:98-148`` at 0331e11), the dict its
pipeline receives: ``occ_size`` (3,) and ``pc_range`` (6,) numpy, ``sequence``, ``frame_id``
(str), ``img_filename`` [path per camera], ``lidar2img`` [(4, 4) P @ Tr], ``cam_intrinsic``
[(4, 4) P], ``lidar2cam`` [(4, 4) Tr], ``focal_length`` (P[0, 0]), ``baseline`` (from P3 - P2;
0 here: one camera), ``stereo_depth_path`` (``<stereo_depth_root>/sequences/<seq>/<id>.npy``),
``gt_occ`` ((X, Y, Z) uint8 training ids, or None without labels). Constructor: the same
keywords as ``KITTI360Dataset``.

Flips: CGFormer's image flip (``data_config['flip']``) goes through ``post_rot`` and is right
for any grid. Its 3-D ``bda`` augmentation (``LoadAnnotationOcc`` with ``apply_bda=True``,
``mmdet3d_plugin/datasets/pipelines/loading_annotation_occ.py:35-124``) flips / rotates /
scales the label grid *and* returns the same transform as ``bda_rot``, about the centre of the
step's ``point_cloud_range``; the model applies it wherever it places image features in 3-D
(``img2bev/VoxelProposalLayer.py:64-69``, ``LSSViewTransformer.py:98-103``, and its inverse on
the reference points in ``transformer_utils/encoder.py:127-133``), so labels and features stay
consistent whatever the grid's axes mean. Here ``flip_dx`` mirrors image left-right and
``flip_dy`` image top-bottom (a camera-centric grid: axis 1 is y down in the image, not the
world's vertical) -- both are the scene seen by a camera rolled by 180 degrees about one image
axis, plausible for near-nadir drone views. What must hold is that the pipeline's
``point_cloud_range`` is the export's (its centre is the flip centre; the grid is flipped as an
array): a pipeline step with another range is refused at construction.
"""

from __future__ import annotations

import os

import numpy as np

from occufly.datasets.compat.common import export_root, list_scans, load_geometry


def _check_pipeline(pipeline, pc_range, where: str) -> None:
    """``LoadAnnotationOcc`` turns bda flips / rotations about the centre of its
    ``point_cloud_range`` and flips the label grid as an array: that range must be the export's,
    or the labels land beside the features."""
    for step in pipeline or ():
        if not isinstance(step, dict) or step.get("type") != "LoadAnnotationOcc":
            continue
        pcr = step.get("point_cloud_range")
        if pcr is None:  # their default is KITTI's [0, -25.6, -2, 51.2, 25.6, 4.4]
            raise ValueError(f"{where}: LoadAnnotationOcc has no point_cloud_range: its default is "
                             f"KITTI's; set point_cloud_range={list(pc_range)} (the export's)")
        if not np.allclose(np.asarray(pcr, np.float64), np.asarray(pc_range, np.float64), atol=1e-6):
            raise ValueError(f"{where}: LoadAnnotationOcc point_cloud_range {list(pcr)} is not the "
                             f"export's {list(pc_range)}: its bda flips would turn about the wrong centre")


class OccuFlyKITTI360Dataset:
    """CGFormer's ``KITTI360Dataset`` interface over an export (see the module docstring)."""

    def __init__(self, data_root, stereo_depth_root, ann_file, pipeline, split, camera_used,
                 occ_size, pc_range, test_mode=False, load_continuous=False):
        self.root = export_root(data_root)
        self.data_root = str(data_root)
        self.stereo_depth_root = str(stereo_depth_root)
        self.ann_file = str(ann_file)
        self.split = split
        self.test_mode = test_mode
        self.load_continuous = load_continuous
        self.geometry = g = load_geometry(self.root)
        want = list(g.grid_shape)
        if [int(v) for v in occ_size] != want:
            raise ValueError(f"occ_size {list(occ_size)} does not match the export's grid_shape "
                             f"{want} ({self.root}/occufly.yaml)")
        rng = [*g.voxel_origin.tolist(), *(g.voxel_origin + np.asarray(g.scene_size)).tolist()]
        if not np.allclose(np.asarray(pc_range, np.float64), rng, atol=1e-6):
            raise ValueError(f"pc_range {list(pc_range)} does not match the export's geometry "
                             f"{rng} (voxel_origin, + scene_size)")
        self.occ_size = occ_size
        self.pc_range = pc_range
        self.camera_map = {"left": "2", "right": "3"}
        bad = [c for c in camera_used if c not in self.camera_map]
        if bad:
            raise ValueError(f"camera_used {bad}: expected 'left' / 'right'")
        if "right" in camera_used:
            raise ValueError("camera_used 'right': an OccuFly export has one camera (image_00)")
        self.camera_used = [self.camera_map[c] for c in camera_used]
        _check_pipeline(pipeline, rng, str(self.root))
        self.data_infos = self.load_annotations(self.ann_file)
        self.pipeline = None
        if pipeline is not None:
            from mmdet.datasets.pipelines import Compose  # mmdet: CGFormer's own dependency

            self.pipeline = Compose(pipeline)
        self.flag = np.zeros(len(self), dtype=np.uint8)

    def __len__(self) -> int:
        return len(self.data_infos)

    def load_annotations(self, ann_file=None) -> list[dict]:
        scans = []
        for s in list_scans(self.root, self.split):
            P2 = np.eye(4)
            P2[:3, :4] = s.P2
            T = np.asarray(s.Tr, np.float64)
            img = os.path.join(self.data_root, "data_2d_raw", s.sequence, "image_00", "data_rect",
                               s.frame_id + ".png")
            vox = os.path.join(self.ann_file, s.sequence, s.frame_id + "_1_1.npy")
            scans.append({
                "img_2_path": img, "img_3_path": img, "sequence": s.sequence,
                "frame_id": s.frame_id, "P2": P2, "P3": P2.copy(), "T_velo_2_cam": T,
                "proj_matrix_2": P2 @ T, "proj_matrix_3": P2 @ T,
                "voxel_path": vox if os.path.exists(vox) else None,
                "stereo_depth_path": os.path.join(self.stereo_depth_root, "sequences", s.sequence,
                                                  s.frame_id + ".npy")})
        return scans

    def get_data_info(self, index: int) -> dict:
        info = self.data_infos[index]
        d = {"occ_size": np.array(self.occ_size), "pc_range": np.array(self.pc_range),
             "sequence": info["sequence"], "frame_id": info["frame_id"]}
        cams = self.camera_used
        d.update(
            img_filename=[info[f"img_{int(c)}_path"] for c in cams],
            lidar2img=[info[f"proj_matrix_{int(c)}"] for c in cams],
            cam_intrinsic=[info[f"P{int(c)}"] for c in cams],
            lidar2cam=[info["T_velo_2_cam"] for _ in cams],
            focal_length=info["P2"][0, 0],
            baseline=float(info["P3"][0, 3] / (-info["P3"][0, 0]) - info["P2"][0, 3] / (-info["P2"][0, 0])),
        )
        d["stereo_depth_path"] = info["stereo_depth_path"]
        d["gt_occ"] = None if info["voxel_path"] is None else np.load(info["voxel_path"])
        return d

    def __getitem__(self, idx: int):
        d = self.get_data_info(idx)
        if self.pipeline is None:
            return d
        while True:
            out = self.pipeline(d)
            if out is not None or self.test_mode:
                return out
            idx = int(np.random.choice(np.flatnonzero(self.flag == self.flag[idx])))
            d = self.get_data_info(idx)


try:  # registered where CGFormer's registry exists; importable (and testable) without it
    from mmdet.datasets import DATASETS as _DATASETS
except ImportError:  # pragma: no cover - depends on the environment
    _DATASETS = None
if _DATASETS is not None:  # pragma: no cover - needs mmdet
    _DATASETS.register_module()(OccuFlyKITTI360Dataset)


def point_cloud_range(root) -> list[float]:
    """``point_cloud_range`` for the config: voxel_origin and voxel_origin + scene_size."""
    g = load_geometry(export_root(root))
    return [*g.voxel_origin.tolist(), *(g.voxel_origin + np.asarray(g.scene_size)).tolist()]

