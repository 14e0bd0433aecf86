"""Frame grids and masks: analytic boxes, far plane, conventions, Open3D reference, depth."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.camera import Camera, look_at, transform
from occufly.errors import WorkspaceError
from occufly.grid import SceneGrid
from occufly.sampling import (
    FrameGridSpec,
    Raster,
    check_pose,
    frustum_mask,
    render_depth,
    resample_depth,
    sample_frame,
)

SPEC = FrameGridSpec(shape=(64, 48, 64), voxel_size=0.5, near=1.0)
CAM = Camera("PINHOLE", 320, 240, [200.0, 200.0, 160.0, 120.0])


def aligned_grid(labels: np.ndarray, spec: FrameGridSpec = SPEC, origin=(0.0, 0.0, 0.0)) -> SceneGrid:
    """A scene grid whose voxels coincide with the frame grid of a camera at the origin with
    identity pose (camera axes = world axes)."""
    X, Y, _ = spec.shape
    r = spec.voxel_size
    return SceneGrid(labels, np.asarray(origin) + [-X / 2 * r, -Y / 2 * r, 0.0], r)


def box_labels(i0, i1, j0, j1, k0, k1, cls=16, spec=SPEC) -> np.ndarray:
    lab = np.zeros(spec.shape, np.uint8)
    lab[i0:i1, j0:j1, k0:k1] = cls
    return lab


def test_box_in_front_exact_counts():
    # 8 x 6 x 10 box straight ahead, 10..15 m away: fully inside the image
    lab = box_labels(28, 36, 21, 27, 20, 30)
    gt = sample_frame(aligned_grid(lab), CAM, np.eye(4), np.zeros(3), SPEC)
    assert gt.labels.dtype == np.uint8 and gt.labels.shape == SPEC.shape
    assert np.array_equal(gt.labels, lab)  # every box voxel is valid, nothing else occupied
    assert int(gt.surface.sum()) == 8 * 6 * 10 - 6 * 4 * 8  # the shell
    interior = np.zeros(SPEC.shape, bool)
    interior[29:35, 22:26, 21:29] = True
    assert not (gt.surface & interior).any()
    # everything behind the front face is occluded (the box contains the optical axis, and
    # the ray to any box voxel crosses the front slab); the front face is not
    expected_occ = np.zeros(SPEC.shape, bool)
    expected_occ[28:36, 21:27, 21:30] = True
    assert np.array_equal(gt.occluded, expected_occ)
    assert not (gt.occluded & gt.invalid).any()


def test_thin_plate_occludes_and_side_box_does_not():
    lab = np.zeros(SPEC.shape, np.uint8)
    lab[20:44, 14:34, 20] = 9  # a one-voxel-thin plate at z in [10, 10.5]
    lab[30:34, 22:26, 40:44] = 16  # a box behind its middle: hidden
    lab[2:6, 22:26, 40:44] = 8  # a box far to the left: not behind the plate
    gt = sample_frame(aligned_grid(lab), CAM, np.eye(4), np.zeros(3), SPEC)
    assert gt.occluded[30:34, 22:26, 40:44].all()
    assert not gt.occluded[lab == 9].any()
    left = gt.occluded[2:6, 22:26, 40:44]
    assert not left[:, :, 0].any() and left[:, :, 1:].all()  # only its own front face shows


def test_point_behind_far_plane_is_invalid_and_exported_as_255():
    spec = FrameGridSpec(shape=(64, 48, 64), voxel_size=0.5, near=1.0, far=20.0)
    lab = np.zeros(spec.shape, np.uint8)
    lab[32, 24, 30] = 16  # centre z = 15.25 m: inside
    lab[32, 24, 50] = 16  # centre z = 25.25 m: behind the far plane
    gt = sample_frame(aligned_grid(lab, spec), CAM, np.eye(4), np.zeros(3), spec)
    assert gt.labels[32, 24, 30] == 16 and not gt.invalid[32, 24, 30]
    assert gt.labels[32, 24, 50] == 0 and gt.invalid[32, 24, 50]
    assert gt.label_with_invalid()[32, 24, 50] == 255
    assert gt.invalid[:, :, 1].all()  # in front of the near plane
    cz = (np.arange(64) + 0.5) * 0.5
    assert gt.invalid[32, 24, cz > 20].all() and not gt.invalid[32, 24, (cz >= 1) & (cz <= 20)].any()


def test_outside_scene_grid_is_invalid():
    lab = np.zeros((64, 48, 20), np.uint8)  # the scene grid ends at z = 10 m
    lab[:, :, 19] = 6
    gt = sample_frame(aligned_grid(lab), CAM, np.eye(4), np.zeros(3), SPEC)
    assert gt.invalid[:, :, 20:].all()
    assert gt.labels[32, 24, 19] == 6


def test_unknown_scene_grid_voxels_are_invalid_and_never_occlude():
    """A scene grid may mark voxels 255 (no data, e.g. the synthetic truth outside the survey)."""
    lab = box_labels(28, 36, 21, 27, 30, 34)  # a box 15..17 m ahead
    lab[20:44, 14:34, 20] = 255  # an unknown slab in front of it
    lab[2:6, 22:26, 40:44] = 255  # an unknown block elsewhere
    gt = sample_frame(aligned_grid(lab), CAM, np.eye(4), np.zeros(3), SPEC)
    unknown = lab == 255
    assert gt.invalid[unknown].all() and not gt.labels[unknown].any()
    assert gt.label_with_invalid()[unknown].tolist() == [255] * int(unknown.sum())
    assert not gt.surface[unknown].any()
    # the box behind the unknown slab is valid and its front face is not occluded by it
    assert gt.labels[28:36, 21:27, 30:34].min() == 16 and not gt.invalid[28:36, 21:27, 30:34].any()
    assert not gt.occluded[28:36, 21:27, 30].any()
    assert gt.stats["occupied"] == 8 * 6 * 4


def test_sampling_follows_pose_and_utm_origin():
    """Labels equal an independent lookup: frame centre -> world via the inverse pose."""
    rng = np.random.default_rng(1)
    origin = np.array([612_345.0, 5_432_100.0, 250.0])
    lab = rng.integers(0, 4, (90, 80, 50)).astype(np.uint8) * 5
    grid = SceneGrid(lab, origin + [-22.3, -19.1, -3.7], 0.5)
    T = look_at([1.0, 2.0, 20.0], [4.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    gt = sample_frame(grid, CAM, T, origin, SPEC)
    ijk = np.argwhere(~gt.invalid)
    pick = ijk[rng.choice(len(ijk), 500, replace=False)]
    X, Y, _ = SPEC.shape
    c_cam = np.column_stack([(pick[:, 0] - X / 2 + 0.5) * 0.5, (pick[:, 1] - Y / 2 + 0.5) * 0.5,
                             (pick[:, 2] + 0.5) * 0.5])
    world = transform(np.linalg.inv(T), c_cam) + origin
    expected = grid.lookup(world)
    assert np.array_equal(gt.labels[pick[:, 0], pick[:, 1], pick[:, 2]], expected)
    assert expected.any()


def test_frustum_with_distortion_matches_projection():
    cam = Camera("OPENCV", 160, 120, [100, 100, 80, 60, -0.2, 0.05, 0.001, -0.002])
    spec = FrameGridSpec(shape=(32, 24, 32), voxel_size=1.0, near=2.0)
    m = frustum_mask(cam, spec)
    cx, cy, cz = spec.axis_centers()
    xx, yy, zz = np.meshgrid(cx, cy, cz, indexing="ij")
    uv, z = cam.project(np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]))
    with np.errstate(invalid="ignore"):
        ref = cam.in_image(uv) & (z >= 2.0) & (z <= 32.0)
    assert np.array_equal(m.ravel(), ref)


def test_occlusion_matches_open3d_raycasting():
    import open3d as o3d
    rng = np.random.default_rng(3)
    lab = np.zeros(SPEC.shape, np.uint8)
    for _ in range(25):
        i, j, k = rng.integers([0, 0, 8], [58, 42, 58])
        a, b, c = rng.integers(1, 6, 3)
        lab[i:i + a, j:j + b, k:k + c] = 8
    T = look_at([0.3, -0.2, 0.0], [1.0, 0.5, 20.0], up=(0.0, -1.0, 0.0))
    grid = aligned_grid(lab)
    gt = sample_frame(grid, CAM, T, np.zeros(3), SPEC)
    # reference: rays through each target's raster cell centre against voxel-box meshes
    occ_all = np.zeros(SPEC.shape, bool)
    from occufly.sampling import sample_labels, surface_mask

    sampled, _ = sample_labels(grid, T, np.zeros(3), SPEC)
    occ_all = surface_mask(sampled != 0)
    occ_all[:, :, :2] = False  # front faces closer than near are not occluders
    boxes = o3d.geometry.TriangleMesh()
    X, Y, _ = SPEC.shape
    r = SPEC.voxel_size
    for i, j, k in np.argwhere(occ_all):
        b = o3d.geometry.TriangleMesh.create_box(r, r, r)
        b.translate(((i - X / 2) * r, (j - Y / 2) * r, k * r))
        boxes += b
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(boxes))
    targets = np.argwhere((sampled != 0) & ~gt.invalid)
    raster = Raster.for_camera(CAM, SPEC)
    cx, cy, cz = SPEC.axis_centers()
    ia, ib = raster.cell_of(cx[targets[:, 0]] / cz[targets[:, 2]], cy[targets[:, 1]] / cz[targets[:, 2]])
    a, b = raster.cell_center(ia, ib)
    rays = np.column_stack([np.zeros((len(a), 3)), a, b, np.ones(len(a))]).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()  # direction has z = 1
    ref = t < targets[:, 2] * r - 1e-4
    got = gt.occluded[targets[:, 0], targets[:, 1], targets[:, 2]]
    assert ref.sum() > 100 and (~ref).sum() > 100
    agree = np.mean(ref == got)
    print("agreement", agree, ref.sum(), len(ref))
    assert agree >= 0.999, agree


def test_depth_resample_and_render():
    d = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert np.array_equal(resample_depth(d, (3, 4)), d)
    big = np.kron(d, np.ones((4, 4), np.float32))
    assert np.array_equal(resample_depth(big, (3, 4)), d)
    cam = Camera("PINHOLE", 16, 12, [10, 10, 8, 6])
    uv = np.array([[0.5, 0.5], [1.0, 1.0], [15.5, 11.5], [20.0, 3.0]])
    z = np.array([5.0, 3.0, 7.0, 1.0])
    out = render_depth(cam, uv, z, (3, 4))
    assert out[0, 0] == 3.0 and out[2, 3] == 7.0 and np.count_nonzero(out) == 2


def test_bad_pose_is_a_clear_error():
    with pytest.raises(WorkspaceError, match="frame 7.*no valid pose"):
        check_pose(np.full((4, 4), np.nan), "frame 7")
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(WorkspaceError, match="not a rigid"):
        check_pose(T, "frame 8")


def test_depth_map_prefers_mvs_then_renders(tmp_path):
    from occufly.io.colmap_dense import write_depth_map
    from occufly.sampling import frame_depth_map
    from occufly.scene import Frame, Scene

    cam = Camera("PINHOLE", 16, 12, [10, 10, 8, 6])
    frames = [Frame(name=f"im{i}.jpg", camera=cam, T_cam_world=np.eye(4)) for i in range(2)]
    xyz = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 9.0]], np.float32)  # both on the optical axis
    scene = Scene(frames=frames, xyz=xyz, rgb=np.zeros((2, 3), np.uint8),
                  meta={"depth_maps": str(tmp_path)})
    mvs = np.arange(16 * 12, dtype=np.float32).reshape(12, 16)  # COLMAP map at full resolution
    write_depth_map(tmp_path / "im0.jpg.geometric.bin", mvs)
    d0, src0 = frame_depth_map(scene, 0)
    assert src0 == "mvs" and d0.shape == (3, 4)
    assert np.array_equal(d0, mvs[2::4, 2::4])  # nearest sample at the 1/4-res pixel centres
    d1, src1 = frame_depth_map(scene, 1)  # no depth map: rendered from the points (z-buffer)
    assert src1 == "rendered" and d1[1, 2] == 5.0 and np.count_nonzero(d1) == 1


def test_distorted_camera_region_loses_nothing():
    """Sampling only the widened frustum gives the same labels and surface as sampling the
    whole frame grid, for a distorted camera too."""
    from occufly.sampling import sample_labels, surface_mask

    cam = Camera("OPENCV", 160, 120, [100, 100, 80, 60, -0.2, 0.05, 0.001, -0.002])
    spec = FrameGridSpec(shape=(64, 48, 64), voxel_size=0.5, near=1.0)
    rng = np.random.default_rng(7)
    lab = (rng.random((80, 80, 70)) < 0.95).astype(np.uint8) * 8  # dense: surface hinges on each neighbour
    grid = SceneGrid(lab, [-20.0, -20.0, -2.0], 0.5)
    T = look_at([0.2, 0.1, 0.0], [1.0, -0.5, 20.0], up=(0.0, -1.0, 0.0))
    gt = sample_frame(grid, cam, T, np.zeros(3), spec)
    full, inside = sample_labels(grid, T, np.zeros(3), spec)  # every voxel, no region
    valid = frustum_mask(cam, spec) & inside
    assert np.array_equal(gt.invalid, ~valid)
    assert np.array_equal(gt.labels, np.where(valid, full, 0))
    assert np.array_equal(gt.surface, surface_mask(full != 0) & valid)
    assert 1000 < gt.surface.sum() < 0.5 * np.count_nonzero(gt.labels)
