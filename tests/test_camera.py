import numpy as np
import pytest

from occufly.camera import (
    CAMERA_MODELS,
    Camera,
    camera_center,
    frustum_corners,
    look_at,
    project_world,
    quaternion_to_rotation,
    rotation_to_quaternion,
    viewing_direction,
)
from occufly.errors import InputFormatError

PARAMS = {
    "SIMPLE_PINHOLE": [800.0, 320.0, 240.0],
    "PINHOLE": [800.0, 780.0, 321.0, 239.0],
    "SIMPLE_RADIAL": [800.0, 320.0, 240.0, -0.08],
    "RADIAL": [800.0, 320.0, 240.0, -0.1, 0.02],
    "OPENCV": [800.0, 790.0, 320.0, 240.0, -0.1, 0.02, 0.001, -0.0015],
}


@pytest.mark.parametrize("model", list(CAMERA_MODELS))
def test_project_unproject_roundtrip(model):
    cam = Camera(model, 640, 480, PARAMS[model])
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [640, 480], size=(5000, 2))
    depth = rng.uniform(1, 100, size=5000)
    xyz = cam.unproject(uv, depth)
    np.testing.assert_allclose(xyz[:, 2], depth)
    uv2, z = cam.project(xyz)
    np.testing.assert_allclose(uv2, uv, atol=1e-6)
    np.testing.assert_allclose(z, depth)


def test_pinhole_matches_k_matrix():
    cam = Camera("PINHOLE", 640, 480, PARAMS["PINHOLE"])
    xyz = np.array([[1.0, -2.0, 10.0]])
    uv, _ = cam.project(xyz)
    expected = cam.K @ xyz[0] / xyz[0, 2]
    np.testing.assert_allclose(uv[0], expected[:2])


def test_opencv_distortion_matches_formula():
    cam = Camera("OPENCV", 640, 480, PARAMS["OPENCV"])
    x, y = 0.3, -0.2
    fx, fy, cx, cy, k1, k2, p1, p2 = PARAMS["OPENCV"]
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2
    xd = x + x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y + y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    uv, _ = cam.project(np.array([[x * 5, y * 5, 5.0]]))
    np.testing.assert_allclose(uv[0], [fx * xd + cx, fy * yd + cy])


def test_points_behind_camera_are_nan():
    cam = Camera("PINHOLE", 640, 480, PARAMS["PINHOLE"])
    uv, z = cam.project(np.array([[0.0, 0.0, -1.0]]))
    assert np.isnan(uv).all() and z[0] == -1


def test_bad_parameters():
    with pytest.raises(InputFormatError, match="takes 4 parameters"):
        Camera("PINHOLE", 10, 10, [1.0, 2.0])
    with pytest.raises(InputFormatError, match="not supported"):
        Camera("FISHEYE", 10, 10, [1.0])


def test_pose_centre_direction_and_projection():
    center = np.array([10.0, 20.0, 50.0])
    T = look_at(center, [10.0, 20.0, 0.0], up=[0.0, 1.0, 0.0])  # nadir
    np.testing.assert_allclose(camera_center(T), center, atol=1e-12)
    np.testing.assert_allclose(viewing_direction(T), [0, 0, -1], atol=1e-12)
    cam = Camera("SIMPLE_PINHOLE", 640, 480, [500.0, 320.0, 240.0])
    uv, z, vis = project_world(cam, T, np.array([[10.0, 20.0, 0.0], [10.0, 20.0, 60.0]]))
    np.testing.assert_allclose(uv[0], [320.0, 240.0])
    assert z[0] == pytest.approx(50.0) and vis.tolist() == [True, False]
    corners = frustum_corners(cam, T, 50.0)
    np.testing.assert_allclose(corners[1:, 2], 0.0, atol=1e-9)


def test_quaternion_roundtrip():
    T = look_at([1.0, 2.0, 3.0], [4.0, -1.0, 0.0])
    q = rotation_to_quaternion(T[:3, :3])
    np.testing.assert_allclose(quaternion_to_rotation(q), T[:3, :3], atol=1e-12)


def test_scaled_camera_maps_pixels():
    cam = Camera("PINHOLE", 640, 480, PARAMS["PINHOLE"])
    small = cam.scaled(0.25)
    assert (small.width, small.height) == (160, 120)
    xyz = np.array([[0.5, 0.3, 4.0]])
    np.testing.assert_allclose(small.project(xyz)[0], cam.project(xyz)[0] * 0.25)
