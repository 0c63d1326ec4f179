"""Conversions between ROS 2 Jazzy messages (rosbags' typestore) and the project's types.

Pure functions, no rclpy: the typestore builds the same message classes, and serializes the
same CDR bytes, as a real Jazzy node.
"""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np

from cusfm_ros.core.cameras import CameraBase, FisheyeCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import QUAT_NORM_TOLERANCE, Rigid3
from cusfm_ros.errors import BadFrameError, BagError, CalibrationError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)

# ROS Bayer encodings -> OpenCV demosaicing codes. OpenCV names a pattern by the second row's
# second and third pixels, so ROS "rggb" is OpenCV "BG" (as in cv_bridge).
_BAYER_TO_RGB = {
    "bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
    "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB,
    "bayer_rggb16": cv2.COLOR_BayerBG2RGB, "bayer_bggr16": cv2.COLOR_BayerRG2RGB,
    "bayer_gbrg16": cv2.COLOR_BayerGR2RGB, "bayer_grbg16": cv2.COLOR_BayerGB2RGB,
}
_PLAIN_ENCODINGS = {  # encoding -> (dtype, channels)
    "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3),
    "8UC3": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "8UC4": (np.uint8, 4), "rgb16": (np.uint16, 3), "bgr16": (np.uint16, 3),
}
SUPPORTED_ENCODINGS = tuple(_PLAIN_ENCODINGS) + tuple(_BAYER_TO_RGB)


@functools.lru_cache(maxsize=1)
def typestore():
    """The ROS 2 Jazzy typestore plus cusfm_ros_interfaces' messages and service types."""
    from rosbags.typesys import Stores, get_typestore

    from cusfm_ros.io.bags.interfaces import interface_types

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(interface_types())
    return store


def msg(name: str, **fields: Any) -> Any:
    return typestore().types[name](**fields)


# --------------------------------------------------------------------------- time and frames
def time_msg(stamp_ns: int) -> Any:
    seconds, nanos = divmod(int(stamp_ns), 1_000_000_000)
    return msg("builtin_interfaces/msg/Time", sec=seconds, nanosec=nanos)


def stamp_ns_of(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def header_msg(stamp_ns: int, frame_id: str) -> Any:
    return msg("std_msgs/msg/Header", stamp=time_msg(stamp_ns), frame_id=frame_id)


def _xyz(msgtype: str, values: np.ndarray) -> Any:
    return msg(msgtype, x=float(values[0]), y=float(values[1]), z=float(values[2]))


def _quaternion(pose: Rigid3) -> Any:
    qx, qy, qz, qw = pose.quat_xyzw()
    return msg("geometry_msgs/msg/Quaternion", x=qx, y=qy, z=qz, w=qw)


def transform_msg(pose: Rigid3) -> Any:
    return msg("geometry_msgs/msg/Transform",
               translation=_xyz("geometry_msgs/msg/Vector3", pose.translation),
               rotation=_quaternion(pose))


def pose_msg(pose: Rigid3) -> Any:
    return msg("geometry_msgs/msg/Pose", position=_xyz("geometry_msgs/msg/Point",
                                                       pose.translation),
               orientation=_quaternion(pose))


def _rigid(translation: Any, rotation: Any, what: str,
           fix: str = "filter it out, or choose another pose source") -> Rigid3:
    t = np.array([translation.x, translation.y, translation.z], dtype=np.float64)
    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], dtype=np.float64)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise BagError(f"{what} contains NaN or inf; the recording is corrupt at that message "
                       f"({fix})")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        raise BagError(f"{what} has a non-unit quaternion (norm {norm:.4g}); the publisher "
                       "must send normalized rotations")
    return Rigid3.from_quat_xyzw(q / norm, t)


def rigid_from_transform(transform: Any, what: str = "transform", static: bool = False
                         ) -> Rigid3:
    """``static``: a /tf_static transform (an extrinsic, whose fix is another source of
    extrinsics, not another pose source)."""
    return _rigid(transform.translation, transform.rotation, what,
                  "record the static transforms again or pass --extrinsics FILE" if static
                  else "filter it out, or choose another pose source")


def rigid_from_pose(pose: Any, what: str = "pose") -> Rigid3:
    return _rigid(pose.position, pose.orientation, what)


def transform_stamped_msg(stamp_ns: int, parent: str, child: str, parent_from_child: Rigid3):
    return msg("geometry_msgs/msg/TransformStamped", header=header_msg(stamp_ns, parent),
               child_frame_id=child, transform=transform_msg(parent_from_child))


def tf_message(transforms: list[Any]) -> Any:
    return msg(TF_MESSAGE, transforms=transforms)


def odometry_msg(stamp_ns: int, frame_id: str, child_frame_id: str, odom_from_body: Rigid3,
                 linear_mps: np.ndarray, angular_radps: np.ndarray,
                 pose_sigma_m: float = 0.05, twist_sigma: float = 0.05) -> Any:
    covariance = np.diag([pose_sigma_m**2] * 3 + [(pose_sigma_m / 5) ** 2] * 3).ravel()
    twist_cov = np.diag([twist_sigma**2] * 6).ravel()
    vector = "geometry_msgs/msg/Vector3"
    return msg(ODOMETRY, header=header_msg(stamp_ns, frame_id), child_frame_id=child_frame_id,
               pose=msg("geometry_msgs/msg/PoseWithCovariance", pose=pose_msg(odom_from_body),
                        covariance=covariance),
               twist=msg("geometry_msgs/msg/TwistWithCovariance",
                         twist=msg("geometry_msgs/msg/Twist", linear=_xyz(vector, linear_mps),
                                   angular=_xyz(vector, angular_radps)),
                         covariance=twist_cov))


# ----------------------------------------------------------------------------- camera info
def camera_info_msg(camera: CameraBase, stamp_ns: int, frame_id: str) -> Any:
    """CameraInfo for PINHOLE/OPENCV (plumb_bob or rational_polynomial) and OPENCV_FISHEYE
    (equidistant). The projection matrix is that of the unrectified camera (R = identity)."""
    if isinstance(camera, FisheyeCamera):
        model, d = "equidistant", [camera.k1, camera.k2, camera.k3, camera.k4]
    elif isinstance(camera, OpenCVCamera):
        model = "rational_polynomial" if camera.is_rational else "plumb_bob"
        d = list(camera.coefficients)
    elif isinstance(camera, PinholeCamera):
        model, d = "plumb_bob", [0.0] * 5
    else:
        raise CalibrationError(f"{camera.model_name} cameras have no sensor_msgs/CameraInfo "
                               "distortion model")
    k = camera.K
    p = np.hstack([k, np.zeros((3, 1))])
    roi = msg("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
              do_rectify=False)
    return msg(CAMERA_INFO, header=header_msg(stamp_ns, frame_id), height=camera.height,
               width=camera.width, distortion_model=model,
               d=np.asarray(d, dtype=np.float64), k=k.ravel(), r=np.eye(3).ravel(),
               p=p.ravel(), binning_x=0, binning_y=0, roi=roi)


def camera_from_camera_info(info: Any, topic: str) -> CameraBase:
    """Our camera model for a CameraInfo message; errors name the topic and the fix."""
    width, height = int(info.width), int(info.height)
    # ROS 2 names the arrays k, d; ROS 1 bags (decoded with their own definitions) K, D
    k = np.asarray(info.k if hasattr(info, "k") else info.K, dtype=np.float64)
    d = np.asarray(info.d if hasattr(info, "d") else info.D, dtype=np.float64)
    if width <= 0 or height <= 0 or not np.any(k):
        raise CalibrationError(f"{topic}: CameraInfo is uncalibrated (size {width}x{height}, "
                               "K all zero); calibrate the camera (ROS camera_calibration) "
                               "and publish its CameraInfo with the images")
    if int(info.binning_x) > 1 or int(info.binning_y) > 1 or int(info.roi.width) not in (
            0, width):
        raise CalibrationError(f"{topic}: binned or ROI-cropped CameraInfo is not supported; "
                               "record full-resolution images")
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    model = info.distortion_model
    try:
        if model in ("plumb_bob", "rational_polynomial", ""):
            if not np.any(d):
                return PinholeCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy)
            limit = 8 if model == "rational_polynomial" else 5
            if len(d) > limit:
                raise CalibrationError(f"{topic}: {model} takes at most {limit} coefficients, "
                                       f"got {len(d)}")
            padded = np.zeros(8)
            padded[:len(d)] = d
            names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
            return OpenCVCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy,
                                **dict(zip(names, padded)))
        if model == "equidistant":
            if len(d) != 4:
                raise CalibrationError(f"{topic}: equidistant needs 4 coefficients, "
                                       f"got {len(d)}")
            return FisheyeCamera(width, height, fx=fx, fy=fy, cx=cx, cy=cy, k1=d[0], k2=d[1],
                                 k3=d[2], k4=d[3])
    except CalibrationError as exc:
        if str(exc).startswith(topic):
            raise
        raise CalibrationError(f"{topic}: {exc}") from None
    raise CalibrationError(f"{topic}: unsupported distortion model {model!r} (supported: "
                           "plumb_bob, rational_polynomial, equidistant)")


# --------------------------------------------------------------------------------- images
def image_msg(image: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "rgb8") -> Any:
    image = np.ascontiguousarray(image)
    channels = 1 if image.ndim == 2 else image.shape[2]
    return msg(IMAGE, header=header_msg(stamp_ns, frame_id), height=image.shape[0],
               width=image.shape[1], encoding=encoding, is_bigendian=0,
               step=image.shape[1] * channels * image.itemsize,
               data=np.frombuffer(image.tobytes(), dtype=np.uint8))


def compressed_image_msg(rgb: np.ndarray, stamp_ns: int, frame_id: str, quality: int = 90
                         ) -> Any:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise BagError("JPEG encoding failed")
    # image_transport's compressed format string
    return msg(COMPRESSED_IMAGE, header=header_msg(stamp_ns, frame_id),
               format="rgb8; jpeg compressed bgr8", data=data.ravel())


def decode_image(message: Any, msgtype: str, topic: str) -> np.ndarray:
    """Image or CompressedImage -> (H, W) mono or (H, W, 3) RGB array (uint8 or uint16)."""
    if msgtype == COMPRESSED_IMAGE:
        data = np.asarray(message.data, dtype=np.uint8)
        if not len(data):
            raise BadFrameError(f"{topic}: empty CompressedImage (0 bytes of data)")
        try:
            image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        except cv2.error:  # OpenCV asserts on some malformed headers instead of returning None
            image = None
        if image is None or image.size == 0:
            raise BadFrameError(f"{topic}: cannot decode CompressedImage ({len(data)} bytes, "
                                f"format {message.format!r}): corrupt or not jpeg/png")
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4
                                 else cv2.COLOR_BGR2RGB)
        return image
    encoding = message.encoding
    height, width, step = int(message.height), int(message.width), int(message.step)
    data = np.asarray(message.data, dtype=np.uint8)
    if encoding in _BAYER_TO_RGB:
        dtype, channels = (np.uint16 if encoding.endswith("16") else np.uint8), 1
    elif encoding in _PLAIN_ENCODINGS:
        dtype, channels = _PLAIN_ENCODINGS[encoding]
    else:
        raise BagError(f"{topic}: unsupported image encoding {encoding!r} (supported: "
                       f"{', '.join(SUPPORTED_ENCODINGS)}); convert the topic first, e.g. with "
                       "image_proc")
    if height <= 0 or width <= 0:
        raise BadFrameError(f"{topic}: image of size {width}x{height} (the message's width "
                            "and height must be positive)")
    row_bytes = width * channels * np.dtype(dtype).itemsize
    if step < row_bytes or len(data) < step * height:
        raise BadFrameError(f"{topic}: image data is truncated ({len(data)} bytes for "
                            f"{width}x{height} {encoding}, step {step})")
    rows = data[:step * height].reshape(height, step)[:, :row_bytes]
    big_endian = bool(message.is_bigendian)
    pixel_dtype = np.dtype(dtype).newbyteorder(">" if big_endian else "<")
    image = np.ascontiguousarray(rows).view(pixel_dtype).astype(dtype)
    image = image.reshape(height, width, channels) if channels > 1 else image.reshape(height,
                                                                                      width)
    if encoding in _BAYER_TO_RGB:
        return cv2.cvtColor(image, _BAYER_TO_RGB[encoding])
    if encoding in ("bgr8", "bgr16"):
        return image[..., ::-1].copy()
    if encoding in ("rgba8", "8UC4"):
        return image[..., :3].copy()
    if encoding == "bgra8":
        return image[..., 2::-1].copy()
    return image


def header_stamp_from_raw(raw: bytes | memoryview, cdr: bool = True) -> int:
    """Header stamp of a serialized message whose first field is a std_msgs/Header, without
    deserializing the rest (an image stays undecoded). CDR puts the 4-byte encapsulation first
    (byte 1 = 0 means big-endian), ROS 1 the 4-byte seq; both put sec, nanosec at byte 4."""
    head = bytes(raw[:12])
    if len(head) < 12:
        raise BagError("message too short to hold a header")
    byteorder = "big" if cdr and head[1] == 0 else "little"
    seconds = int.from_bytes(head[4:8], byteorder, signed=True)
    nanos = int.from_bytes(head[8:12], byteorder)
    return seconds * 1_000_000_000 + nanos
