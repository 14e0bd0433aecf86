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
    "FULL_OPENCV": [800.0, 790.0, 320.0, 240.0, -0.1, 0.02, 0.001, -0.0015, 0.003, 0.01,
                    -0.002, 0.0005],
    "OPENCV_FISHEYE": [400.0, 402.0, 321.0, 241.0, 0.05, -0.01, 0.002, -0.0003],
    "BROWN": [800.0, 790.0, 320.0, 240.0, 0.4, -0.1, 0.02, -0.003, 0.0004, 0.001, -0.0015],
    "METASHAPE": [800.0, 322.5, 238.0, 1.3, -0.4, -0.1, 0.02, -0.003, 0.0004, 0.001, -0.0015,
                  0.02, -0.01],
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


def _metashape_formula(params, x, y):
    """Agisoft's 'frame' model written out as the Metashape manual (Appendix C) states it."""
    f, cx, cy, b1, b2, k1, k2, k3, k4, p1, p2, p3, p4 = params
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3 + k4 * r2**4
    t = 1 + p3 * r2 + p4 * r2**2
    xd = x * rad + (p1 * (r2 + 2 * x * x) + 2 * p2 * x * y) * t
    yd = y * rad + (p2 * (r2 + 2 * y * y) + 2 * p1 * x * y) * t
    return cx + xd * f + xd * b1 + yd * b2, cy + yd * f


def test_metashape_distortion_matches_manual():
    cam = Camera("METASHAPE", 640, 480, PARAMS["METASHAPE"])
    pts = np.array([[0.3, -0.2], [-0.25, 0.31], [0.0, 0.0], [0.1, 0.05]])
    uv, _ = cam.project(np.column_stack([pts * 7.0, np.full(len(pts), 7.0)]))
    for (x, y), got in zip(pts, uv, strict=True):
        np.testing.assert_allclose(got, _metashape_formula(PARAMS["METASHAPE"], x, y), atol=1e-9)


def test_metashape_p1_p2_are_swapped_relative_to_opencv():
    """Metashape (p1, p2) == OpenCV/Brown (p2, p1): the same image point with swapped values."""
    f, cx, cy = 800.0, 320.0, 240.0
    ms = Camera("METASHAPE", 640, 480, [f, cx, cy, 0, 0, -0.1, 0.02, 0, 0, 0.001, -0.0015, 0, 0])
    br = Camera("BROWN", 640, 480, [f, f, cx, cy, 0, -0.1, 0.02, 0, 0, -0.0015, 0.001])
    cv = Camera("OPENCV", 640, 480, [f, f, cx, cy, -0.1, 0.02, -0.0015, 0.001])
    xyz = np.random.default_rng(2).uniform([-3, -2, 5], [3, 2, 9], (200, 3))
    np.testing.assert_allclose(ms.project(xyz)[0], br.project(xyz)[0], atol=1e-9)
    np.testing.assert_allclose(ms.project(xyz)[0], cv.project(xyz)[0], atol=1e-9)
    # and not the same without the swap: the tangential terms move points by > 0.05 px
    ms_unswapped = Camera("METASHAPE", 640, 480, [f, cx, cy, 0, 0, -0.1, 0.02, 0, 0, -0.0015, 0.001, 0, 0])
    assert np.abs(ms_unswapped.project(xyz)[0] - cv.project(xyz)[0]).max() > 0.05


def test_brown_skew_and_k3_k4():
    fx, fy, cx, cy, skew, k1, k2, k3, k4, p1, p2 = PARAMS["BROWN"]
    cam = Camera("BROWN", 640, 480, PARAMS["BROWN"])
    x, y = 0.3, -0.2
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3 + k4 * r2**4
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    uv, _ = cam.project(np.array([[x * 4, y * 4, 4.0]]))
    np.testing.assert_allclose(uv[0], [fx * xd + skew * yd + cx, fy * yd + cy], atol=1e-9)
    assert cam.K[0, 1] == skew and cam.has_distortion


def test_fisheye_matches_opencv_formula():
    fx, fy, cx, cy, k1, k2, k3, k4 = PARAMS["OPENCV_FISHEYE"]
    cam = Camera("OPENCV_FISHEYE", 640, 480, PARAMS["OPENCV_FISHEYE"])
    x, y = 0.9, -0.6  # ~47 degrees off axis
    r = np.hypot(x, y)
    th = np.arctan(r)
    thd = th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
    uv, _ = cam.project(np.array([[x, y, 1.0]]))
    np.testing.assert_allclose(uv[0], [fx * x * thd / r + cx, fy * y * thd / r + cy], atol=1e-9)
    # the optical axis maps to the principal point (no 0/0)
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 2.0]]))[0][0], [cx, cy])
    assert Camera("OPENCV_FISHEYE", 640, 480, [400, 400, 320, 240, 0, 0, 0, 0]).has_distortion


@pytest.mark.parametrize("model", ["BROWN", "METASHAPE", "OPENCV_FISHEYE", "FULL_OPENCV"])
def test_scaled_camera_projects_to_scaled_pixels(model):
    cam = Camera(model, 640, 480, PARAMS[model])
    half = cam.scaled(0.5)
    xyz = np.random.default_rng(3).uniform([-2, -2, 5], [2, 2, 9], (100, 3))
    np.testing.assert_allclose(half.project(xyz)[0], cam.project(xyz)[0] * 0.5, atol=1e-9)


def test_non_positive_focal_is_an_error():
    with pytest.raises(InputFormatError, match="focal length must be positive"):
        Camera("METASHAPE", 640, 480, [800.0, 320, 240, -900.0, 0, 0, 0, 0, 0, 0, 0, 0, 0])


def test_a_lens_model_does_not_fold_far_points_back_into_the_image():
    """A drone lens's polynomial (the synthetic formats' LENS: k3 < 0) turns back beyond its
    calibrated field: a ground point ~68 degrees off the axis has a distorted radius near 0,
    and projected into the middle of the image, at the depth of the ground there. Such points
    are not projected (uv NaN); everything the image shows still is, exactly as before."""
    from occufly.synthetic.formats import LENS

    cam = Camera("FULL_OPENCV", 5472, 3648, [3648.0, 3648.0, 2736.0, 1824.0, LENS["k1"],
                                             LENS["k2"], LENS["p1"], LENS["p2"], LENS["k3"],
                                             0.0, 0.0, 0.0])
    far = np.array([[2.5, 0.0, 1.0], [0.0, 2.5, 1.0], [1.8, 1.8, 1.0]]) * 50.0
    xy = far[:, :2] / far[:, 2:]
    uv_model = cam.distort(xy) * 3648.0 + [2736.0, 1824.0]
    assert cam.in_image(uv_model[:1]).all()  # what the polynomial alone gives: in the image
    uv, z = cam.project(far)
    assert np.isnan(uv).all() and (z > 0).all()
    # the image's own points: unchanged, and the round trip holds at the border and corners
    px = np.array([[0.0, 0.0], [5471.0, 3647.0], [2736.0, 1824.0], [100.0, 3600.0],
                   [5400.0, 10.0]])
    xyz = cam.unproject(px, 30.0)
    back, _ = cam.project(xyz)
    assert np.allclose(back, px, atol=1e-6)
    r_border = np.linalg.norm(cam.unproject(np.array([[0.0, 0.0]]), 1.0)[0, :2])
    assert r_border < cam.valid_radius <= 1.25 * np.linalg.norm(
        cam.unproject(np.array([[0.0, 0.0], [5472.0, 3648.0], [0.0, 3648.0], [5472.0, 0.0]]),
                      1.0)[:, :2], axis=1).max() + 1e-9
    # no distortion, or fisheye: every point in front is projected, as before
    assert Camera("PINHOLE", 100, 80, [50.0, 50.0, 50.0, 40.0]).valid_radius == np.inf
    pin, _ = Camera("PINHOLE", 100, 80, [50.0, 50.0, 50.0, 40.0]).project(far)
    assert np.isfinite(pin).all()
    # a lens that keeps growing (k1 < 0 < k2, no k3): limited at 1.25 x the border radius only
    mono = Camera("OPENCV", 5472, 3648, [3648.0, 3648.0, 2736.0, 1824.0, -0.045, 0.032, 0.0, 0.0])
    rb = np.linalg.norm(mono.unproject(np.array([[0.0, 0.0], [5472.0, 3648.0]]), 1.0)[:, :2],
                        axis=1).max()
    assert mono.valid_radius == pytest.approx(1.25 * rb, rel=1e-3)


@pytest.mark.parametrize("margin", [0.0, 8.0, 128.0])
def test_view_bounds_hold_every_point_projected_near_the_image(margin):
    """The distorted render's cull (``render.frustum_candidates``) keeps the cone of
    ``view_bounds``: every point that ``project`` puts within ``margin`` pixels of the image
    must lie in it; and it is tighter than the valid radius's square."""
    from occufly.synthetic.formats import LENS

    for cam in (Camera("FULL_OPENCV", 5472, 3648, [3648.0, 3648.0, 2736.0, 1824.0, LENS["k1"],
                                                   LENS["k2"], LENS["p1"], LENS["p2"], LENS["k3"],
                                                   0.0, 0.0, 0.0]),
                Camera("SIMPLE_RADIAL", 4000, 3000, [3000.0, 2000.0, 1500.0, -0.2]),
                Camera("OPENCV", 4000, 3000, [2900.0, 2950.0, 2010.0, 1490.0, -0.1, 0.05,
                                              0.002, -0.001])):
        x0, x1, y0, y1 = cam.view_bounds(margin)
        R = cam.valid_radius
        assert -R <= x0 < x1 <= R and -R <= y0 < y1 <= R  # (the square where the border
        # widened by the margin lies beyond what the lens reaches: SIMPLE_RADIAL k = -0.2)
        xy = np.random.default_rng(0).uniform(-3, 3, (400_000, 2))
        uv, _ = cam.project(np.c_[xy, np.ones(len(xy))])
        with np.errstate(invalid="ignore"):
            near = ((uv[:, 0] >= -margin) & (uv[:, 0] < cam.width + margin)
                    & (uv[:, 1] >= -margin) & (uv[:, 1] < cam.height + margin))
        assert near.sum() > 1000
        p = xy[near]
        assert ((p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)).all()
    pin = Camera("PINHOLE", 100, 80, [50.0, 50.0, 50.0, 40.0])
    assert pin.view_bounds(0.0) == pytest.approx((-1.0, 1.0, -0.8, 0.8))
