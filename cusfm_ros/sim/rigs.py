"""Camera rig and camera-model presets of the simulator.

Mounting follows REP 105 for base_link (x forward, y left, z up) and REP 103 for the optical
frames (x right, y down, z forward). Stereo pairs are offset along the camera's x axis.
"""

from __future__ import annotations

import numpy as np

from cusfm_ros.core.cameras import CameraBase, FisheyeCamera, OpenCVCamera, PinholeCamera
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.rig import Rig, RigCamera
from cusfm_ros.errors import ConfigError

RIGS = ("mono", "stereo", "rig4", "stereo4")
CAMERA_MODELS = ("pinhole", "opencv", "fisheye")

# rotation taking optical-frame vectors into a forward-looking body frame
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def make_camera(model: str, width: int, height: int) -> CameraBase:
    """A camera of ``model`` with a ~90 degree (pinhole/opencv) or ~180 degree (fisheye) view."""
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    if model == "pinhole":
        f = width / 2.0
        return PinholeCamera(width, height, fx=f, fy=f, cx=cx, cy=cy)
    if model == "opencv":
        f = width / 2.0
        return OpenCVCamera(width, height, fx=f, fy=f * 1.002, cx=cx + 1.3, cy=cy - 0.8,
                            k1=-0.12, k2=0.025, p1=2e-4, p2=-3e-4, k3=0.0)
    if model == "fisheye":
        f = width / np.pi * 1.05
        return FisheyeCamera(width, height, fx=f, fy=f, cx=cx, cy=cy, k1=0.02, k2=-0.004,
                             k3=0.0005, k4=0.0)
    raise ConfigError(f"unknown camera model {model!r} (use {', '.join(CAMERA_MODELS)})")


def _mount(yaw_deg: float, pitch_deg: float, position_m, baseline_offset_m: float = 0.0
           ) -> Rigid3:
    """``base_link_from_cam`` for a camera looking along ``yaw`` and pitched down."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    rz = Rigid3.from_rotvec([0, 0, yaw], [0, 0, 0]).rotation
    ry = Rigid3.from_rotvec([0, pitch, 0], [0, 0, 0]).rotation  # +y pitch looks down
    rotation = rz @ ry @ BODY_FROM_OPTICAL
    position = np.asarray(position_m, float) + rotation @ np.array([baseline_offset_m, 0, 0])
    return Rigid3(rotation, position)


def make_rig(rig: str, scene: str, camera: CameraBase) -> Rig:
    """Rig preset; street rigs are larger and higher than indoor ones."""
    street = scene == "street"
    height = 1.6 if street else 1.0
    pitch = 4.0 if street else 2.0
    baseline = 0.54 if street and rig == "stereo" else (0.3 if street else 0.15)
    front_x, back_x, side_y = (1.6, -1.0, 0.85) if street else (0.3, -0.3, 0.25)
    directions = {"front": (0.0, [front_x, 0.0, height]), "back": (180.0, [back_x, 0, height]),
                  "left": (90.0, [0.0, side_y, height]), "right": (-90.0, [0.0, -side_y, height])}
    cameras: list[RigCamera] = []

    def add(name: str, yaw: float, position, offset: float = 0.0):
        cameras.append(RigCamera(name, camera, _mount(yaw, pitch, position, offset),
                                 f"{name}_optical_frame"))

    if rig == "mono":
        add("front", *directions["front"])
    elif rig == "stereo":
        add("front_stereo_left", *directions["front"], -baseline / 2)
        add("front_stereo_right", *directions["front"], baseline / 2)
    elif rig == "rig4":
        for name, (yaw, position) in directions.items():
            add(name, yaw, position)
    elif rig == "stereo4":
        for name, (yaw, position) in directions.items():
            add(f"{name}_stereo_left", yaw, position, -baseline / 2)
            add(f"{name}_stereo_right", yaw, position, baseline / 2)
    else:
        raise ConfigError(f"unknown rig {rig!r} (use {', '.join(RIGS)})")
    return Rig(tuple(cameras), "base_link")


def perturb_extrinsics(rig: Rig, translation_m: float, rotation_deg: float,
                       rng: np.random.Generator) -> Rig:
    """Each camera's ``rig_from_cam`` moved by exactly ``translation_m`` in a random direction
    and rotated by exactly ``rotation_deg`` about a random axis."""
    perturbed = {}
    for camera in rig.cameras:
        direction = rng.normal(size=3)
        axis = rng.normal(size=3)
        delta = Rigid3.from_axis_angle(axis, np.radians(rotation_deg),
                                       direction / np.linalg.norm(direction) * translation_m)
        perturbed[camera.name] = camera.rig_from_cam * delta
    return rig.with_extrinsics(perturbed)
