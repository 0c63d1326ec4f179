"""Message conversions: exact round trips through CDR bytes, every encoding, every model."""

import cv2
import numpy as np
import pytest

from cusfm_ros.core.cameras import FisheyeCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import BagError, CalibrationError
from cusfm_ros.io.bags import messages as m


def through_cdr(message, msgtype):
    ts = m.typestore()
    return ts.deserialize_cdr(ts.serialize_cdr(message, msgtype), msgtype)


@pytest.mark.parametrize("camera", [
    PinholeCamera(640, 480, fx=500, fy=501, cx=319.5, cy=239.5),
    OpenCVCamera(640, 480, fx=500, fy=501, cx=320, cy=240, k1=-0.1, k2=0.01, p1=1e-4, p2=2e-4,
                 k3=0.001),
    OpenCVCamera(640, 480, fx=500, fy=501, cx=320, cy=240, k1=2.0, k2=0.5, p1=1e-4, p2=2e-4,
                 k3=0.01, k4=2.3, k5=1.0, k6=0.1),
    FisheyeCamera(640, 480, fx=200, fy=200, cx=320, cy=240, k1=0.02, k2=-0.004, k3=5e-4,
                  k4=0.0),
], ids=["pinhole", "plumb_bob", "rational_polynomial", "equidistant"])
def test_camera_info_round_trip(camera):
    info = through_cdr(m.camera_info_msg(camera, 123, "cam_optical"), m.CAMERA_INFO)
    assert m.camera_from_camera_info(info, "/cam/camera_info") == camera
    assert info.header.frame_id == "cam_optical" and m.stamp_ns_of(info.header) == 123


def test_bad_camera_info_is_named():
    info = m.camera_info_msg(PinholeCamera(64, 48, fx=1, fy=1, cx=1, cy=1), 0, "c")
    info.distortion_model = "double_sphere"
    info.d = np.array([0.1, 0.2])
    with pytest.raises(CalibrationError, match="/c/camera_info: unsupported distortion model "
                                               "'double_sphere'"):
        m.camera_from_camera_info(info, "/c/camera_info")
    info.k = np.zeros(9)
    with pytest.raises(CalibrationError, match="uncalibrated"):
        m.camera_from_camera_info(info, "/c/camera_info")


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16",
                                      "rgb16"])
def test_image_encodings_round_trip(rng, encoding):
    rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    if encoding == "bgr8":
        pixels, expected = rgb[..., ::-1], rgb
    elif encoding == "rgba8":
        pixels, expected = np.dstack([rgb, np.full((48, 64), 255, np.uint8)]), rgb
    elif encoding == "bgra8":
        pixels, expected = np.dstack([rgb[..., ::-1], np.zeros((48, 64), np.uint8)]), rgb
    elif encoding == "mono8":
        pixels = expected = rgb[..., 0]
    elif encoding == "mono16":
        pixels = expected = rng.integers(0, 65535, (48, 64), dtype=np.uint16)
    elif encoding == "rgb16":
        pixels = expected = rng.integers(0, 65535, (48, 64, 3), dtype=np.uint16)
    else:
        pixels = expected = rgb
    message = through_cdr(m.image_msg(pixels, 5, "f", encoding), m.IMAGE)
    np.testing.assert_array_equal(m.decode_image(message, m.IMAGE, "/t"), expected)


def test_mono16_big_endian_and_row_padding(rng):
    pixels = rng.integers(0, 65535, (4, 5), dtype=np.uint16)
    padded = np.zeros((4, 16), np.uint8)  # step 16 > 10 bytes of pixels per row
    padded[:, :10] = pixels.astype(">u2").view(np.uint8).reshape(4, 10)
    message = m.msg(m.IMAGE, header=m.header_msg(0, "f"), height=4, width=5, encoding="mono16",
                    is_bigendian=1, step=16, data=padded.ravel())
    np.testing.assert_array_equal(m.decode_image(message, m.IMAGE, "/t"), pixels)


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_demosaicing_recovers_colour(pattern):
    colour = np.array([200, 120, 40], np.uint8)  # a flat orange
    offsets = {"r": 0, "g": 1, "b": 2}
    mosaic = np.zeros((16, 16), np.uint8)
    for i, channel in enumerate(pattern):
        mosaic[i // 2::2, i % 2::2] = colour[offsets[channel]]
    message = m.image_msg(mosaic, 0, "f", f"bayer_{pattern}8")
    rgb = m.decode_image(message, m.IMAGE, "/t")
    np.testing.assert_allclose(rgb[4:-4, 4:-4].reshape(-1, 3).mean(0), colour, atol=2)


def test_compressed_jpeg_round_trip(rng):
    rgb = cv2.GaussianBlur(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), (7, 7), 2)
    message = through_cdr(m.compressed_image_msg(rgb, 0, "f", quality=98), m.COMPRESSED_IMAGE)
    decoded = m.decode_image(message, m.COMPRESSED_IMAGE, "/t")
    assert decoded.shape == rgb.shape and np.abs(decoded.astype(int) - rgb).mean() < 2.0


def test_unsupported_encoding_names_topic_and_fix():
    message = m.image_msg(np.zeros((4, 4, 2), np.uint8), 0, "f", "yuv422")
    with pytest.raises(BagError, match="/cam/image_raw: unsupported image encoding 'yuv422'.*"
                                       "image_proc"):
        m.decode_image(message, m.IMAGE, "/cam/image_raw")


def test_truncated_image_data():
    message = m.image_msg(np.zeros((4, 4, 3), np.uint8), 0, "f", "rgb8")
    message.data = message.data[:20]
    with pytest.raises(BagError, match="truncated"):
        m.decode_image(message, m.IMAGE, "/t")


def test_transforms_and_header_stamp_from_raw(rng):
    pose = Rigid3.from_rotvec(rng.normal(size=3), rng.normal(size=3))
    message = through_cdr(m.transform_stamped_msg(1_700_000_000_123_456_789, "a", "b", pose),
                          "geometry_msgs/msg/TransformStamped")
    assert m.rigid_from_transform(message.transform).is_close(pose, 1e-12, 1e-12)
    raw = m.typestore().serialize_cdr(m.image_msg(np.zeros((2, 2), np.uint8),
                                                  1_700_000_000_123_456_789, "f", "mono8"),
                                      m.IMAGE)
    assert m.header_stamp_from_raw(raw) == 1_700_000_000_123_456_789


def test_nan_and_non_unit_rotations_are_rejected():
    message = m.transform_msg(Rigid3.identity())
    message.rotation.w = 2.0
    with pytest.raises(BagError, match="non-unit quaternion"):
        m.rigid_from_transform(message, "/tf odom -> base_link")
    message.rotation.w = float("nan")
    with pytest.raises(BagError, match="/tf odom -> base_link contains NaN"):
        m.rigid_from_transform(message, "/tf odom -> base_link")
