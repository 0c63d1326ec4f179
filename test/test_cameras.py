import cv2
import numpy as np
import pytest

from cusfm_ros.core.cameras import (FisheyeCamera, FThetaCamera, OpenCVCamera, PinholeCamera,
                                    camera_from_dict)
from cusfm_ros.core.cameras.undistort import (default_pinhole_target, undistort_image,
                                              undistort_points)
from cusfm_ros.core.cameras.windshield import PolynomialWindshield
from cusfm_ros.errors import CalibrationError

WINDSHIELD = PolynomialWindshield([1e-3, 0.01, 0.002, 0.003, 0.001, -0.002],
                                  [-2e-3, 0.001, 0.015, -0.001, 0.002, 0.001])

CAMERAS = {
    "pinhole": PinholeCamera(640, 480, fx=500, fy=505, cx=319.5, cy=239.5),
    "opencv": OpenCVCamera(640, 480, fx=500, fy=505, cx=320.2, cy=241.7, k1=-0.28, k2=0.07,
                           p1=1e-3, p2=-5e-4, k3=0.01),
    "opencv_rational": OpenCVCamera(640, 480, fx=400, fy=401, cx=320.2, cy=241.7, k1=2.0,
                                    k2=0.5, p1=1e-3, p2=-5e-4, k3=0.01, k4=2.3, k5=1.0,
                                    k6=0.1),
    "fisheye": FisheyeCamera(640, 480, fx=200, fy=201, cx=320, cy=240, k1=0.05, k2=-0.01,
                             k3=0.002, k4=-0.0003),
    "ftheta": FThetaCamera(1280, 720, cx=640, cy=360, p1=500, p2=-10, p3=-20, p4=2),
    "ftheta_windshield": FThetaCamera(1280, 720, cx=641.5, cy=359, p1=500, p2=-10, p3=-20,
                                      p4=2, windshield=WINDSHIELD),
}


@pytest.fixture(params=sorted(CAMERAS))
def camera(request):
    return CAMERAS[request.param]


def test_round_trip_over_the_full_image(camera):
    pixels = camera.pixel_grid()
    rays = camera.unproject(pixels)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    uv, valid = camera.project(rays * 7.5)  # depth does not matter
    assert valid.all()
    assert np.max(np.abs(uv - pixels)) < 1e-6


def test_project_then_unproject_recovers_directions(camera, rng):
    uv = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(500, 2))
    rays = camera.unproject(uv)
    points = rays * rng.uniform(1, 50, size=(500, 1))
    uv2, valid = camera.project(points)
    assert valid.all()
    np.testing.assert_allclose(camera.unproject(uv2), rays, atol=1e-9)


def test_points_outside_the_view_are_invalid(camera):
    behind = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    _, valid = camera.project(behind)
    assert not valid.any()
    far_side = np.array([[100.0, 0.0, 1.0]])  # outside the image for all of these models
    _, valid = camera.project(far_side)
    assert not valid.any()


def test_dict_round_trip(camera):
    again = camera_from_dict(camera.to_dict())
    assert again == camera
    assert again.to_dict() == camera.to_dict()


@pytest.mark.parametrize("name", ["opencv", "opencv_rational"])
def test_opencv_matches_cv2_project_points(rng, name):
    cam = CAMERAS[name]
    points = np.c_[rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)] * rng.uniform(1, 9, (200, 1))
    dist = cam.coefficients
    expected, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, dist)
    uv, _ = cam.project(points)
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-9)
    undist = cv2.undistortPoints(expected, cam.K, dist, P=cam.K,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100,
                                           1e-14)).reshape(-1, 2)
    target = PinholeCamera(640, 480, fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy)
    ours, valid = undistort_points(cam, uv, target)
    assert cam.is_rational == (len(dist) == 8)
    assert valid.all()
    np.testing.assert_allclose(ours, undist, atol=1e-4)


def test_fisheye_matches_cv2_fisheye(rng):
    cam = CAMERAS["fisheye"]
    points = np.c_[rng.uniform(-1.5, 1.5, (200, 2)), np.ones(200)]
    dist = np.array([cam.k1, cam.k2, cam.k3, cam.k4])
    expected, _ = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                            cam.K, dist)
    uv, _ = cam.project(points)
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-9)


def test_fisheye_sees_beyond_ninety_degrees():
    cam = FisheyeCamera(1000, 1000, fx=250, fy=250, cx=499.5, cy=499.5)
    ray = np.array([[np.sin(np.radians(100)), 0.0, np.cos(np.radians(100))]])
    uv, valid = cam.project(ray)
    assert valid[0]
    assert uv[0, 0] == pytest.approx(499.5 + 250 * np.radians(100))


def test_windshield_bends_and_unbends_rays(rng):
    rays = rng.normal(size=(100, 3))
    rays[:, 2] = np.abs(rays[:, 2]) + 1.0
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    bent = WINDSHIELD.apply(rays)
    assert np.max(np.linalg.norm(bent - rays, axis=1)) > 1e-3
    np.testing.assert_allclose(WINDSHIELD.remove(bent), rays, atol=1e-12)


def test_undistort_image_matches_opencv():
    cam = CAMERAS["opencv"]
    yy, xx = np.mgrid[0:cam.height, 0:cam.width]
    image = ((np.sin(xx / 7.0) + np.cos(yy / 5.0)) * 60 + 128).astype(np.uint8)
    target = default_pinhole_target(cam)
    ours, _ = undistort_image(image, cam, target)
    dist = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3])
    map_x, map_y = cv2.initUndistortRectifyMap(cam.K, dist, None, target.K,
                                               (cam.width, cam.height), cv2.CV_32FC1)
    reference = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)
    inner = (slice(40, -40), slice(40, -40))
    assert np.max(np.abs(ours[inner].astype(int) - reference[inner].astype(int))) <= 1


def test_undistort_image_checks_size():
    with pytest.raises(CalibrationError, match="image is 10x10"):
        undistort_image(np.zeros((10, 10), np.uint8), CAMERAS["pinhole"])


@pytest.mark.parametrize("data, message", [
    ({"model": "KANNALA", "width": 1, "height": 1}, "unknown camera model 'KANNALA'"),
    ({"model": "PINHOLE", "width": 640, "height": 480, "fx": 1, "fy": 1, "cx": 1},
     "missing parameter 'cy'"),
    ({"model": "PINHOLE", "width": 640, "height": 480, "fx": 1, "fy": 1, "cx": 1, "cy": 1,
      "k9": 0}, "unknown parameter"),
    ({"model": "OPENCV", "height": 480}, "missing field 'width'"),
    ({"model": "PINHOLE", "width": 640, "height": 480, "fx": -1, "fy": 1, "cx": 1, "cy": 1},
     "focal lengths must be positive"),
    ({"model": "PINHOLE", "width": 640, "height": 480, "fx": "nan", "fy": 1, "cx": 1, "cy": 1},
     "'fx' is nan"),
    ({"model": "FTHETA", "width": 64, "height": 48, "cx": 1, "cy": 1, "p1": 5,
      "windshield": {"horizontal": [0, 1]}}, "missing field 'vertical'"),
])
def test_bad_camera_dicts_raise_named_errors(data, message):
    with pytest.raises(CalibrationError, match=message):
        camera_from_dict(data)


def test_pixel_size_in_normalized_units_matches_the_focal_length_at_the_centre(camera):
    centre = np.array([[(camera.width - 1) / 2.0, (camera.height - 1) / 2.0]])
    scale = camera.normalized_per_px(centre)[0]
    fy_over_fx = getattr(camera, "fy", camera.focal_px) / camera.focal_px
    assert scale == pytest.approx(1.0 / (camera.focal_px * np.sqrt(fy_over_fx)), rel=0.05)
    off_axis = centre + [0.3 * camera.height, 0.0]  # ~25-60 degrees off the axis
    # no lens here shrinks normalized coordinates (tan of the angle) off the axis
    assert camera.normalized_per_px(off_axis)[0] >= scale * (1 - 1e-9)


def test_pinhole_unprojection_is_the_newton_iterations_result_exactly():
    """The pinhole's closed form gives the bits the base class's Newton iteration gives for
    no distortion (the verification threads use the closed form)."""
    from cusfm_ros.core.cameras.base import PerspectiveCamera
    from cusfm_ros.core.cameras.pinhole import PinholeCamera

    camera = PinholeCamera(1241, 376, fx=620.5, fy=610.25, cx=620.0, cy=187.5)
    uv = np.random.default_rng(0).random((500, 2)) * [1241, 376]
    closed = camera.undistort_normalized(uv)
    assert closed.shape == (500, 2)
    np.testing.assert_array_equal(closed, PerspectiveCamera.undistort_normalized(camera, uv))
    np.testing.assert_array_equal(camera.undistort_normalized(uv[0]), closed[:1])
