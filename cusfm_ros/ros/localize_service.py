"""The logic of the ``~/localize`` service (``cusfm_ros_interfaces/srv/LocalizeImage``), with
no rclpy: the node hands each request here and copies the answer into its response.

A request carries ``images`` (sensor_msgs/Image, one per camera), ``camera_names`` (cameras
of the map's rig: their intrinsics and extrinsics come from the map), an optional ``prior``
(geometry_msgs/PoseStamped of base_link in the map frame; empty frame_id = none) and
``prior_radius_m`` (0 = the localizer's default). Every problem with a request -- no image,
names and images that do not pair up, a camera the map does not know, an encoding we cannot
decode, an image whose size is not its camera's -- becomes ``success=False`` and a message;
nothing raises, so the node keeps serving.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.localization.localizer import LocalizationResult, Localizer, QueryImage
from cusfm_ros.errors import CusfmError
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.ros_conversions import pose_with_covariance_stamped_msg

logger = logging.getLogger(__name__)


@dataclass
class LocalizeAnswer:
    success: bool
    message: str
    map_from_base_link: Rigid3 | None = None
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    num_inliers: int = 0
    mean_reprojection_error_px: float = float("nan")
    stamp_ns: int = 0
    seconds: float = 0.0


class LocalizeService:
    def __init__(self, localizer: Localizer, map_frame: str = "map") -> None:
        self.localizer = localizer
        self.map_frame = map_frame
        self.rig = localizer.map.keyframes.rig

    def _queries(self, request: Any) -> tuple[list[QueryImage], int]:
        images, names = list(request.images), list(request.camera_names)
        if not images:
            raise CusfmError("the request has no image")
        if len(names) != len(images):
            raise CusfmError(f"{len(images)} images but {len(names)} camera names; name the "
                             "camera of every image")
        queries, stamps = [], []
        for image, name in zip(images, names):
            if name not in self.rig:
                raise CusfmError(f"camera {name!r} is not in the map (its cameras: "
                                 f"{', '.join(self.rig.names)})")
            if int(image.width) == 0 or int(image.height) == 0 or len(image.data) == 0:
                raise CusfmError(f"the image of camera {name} is empty")
            pixels = m.decode_image(image, m.IMAGE, f"image of camera {name}")
            camera = self.rig[name]
            queries.append(QueryImage(pixels, camera.camera, camera.rig_from_cam, name))
            stamps.append(m.stamp_ns_of(image.header))
        return queries, min(stamps)

    def _prior(self, request: Any) -> Rigid3 | None:
        prior = getattr(request, "prior", None)
        if prior is None or not prior.header.frame_id:
            return None
        if prior.header.frame_id != self.map_frame:
            raise CusfmError(f"the prior is in frame {prior.header.frame_id!r}; give it in the "
                             f"map frame {self.map_frame!r}")
        return m.rigid_from_pose(prior.pose, "the prior pose")

    def handle(self, request: Any) -> LocalizeAnswer:
        try:
            queries, stamp = self._queries(request)
            radius = float(getattr(request, "prior_radius_m", 0.0) or 0.0)
            result: LocalizationResult = self.localizer.localize(
                queries, self._prior(request), radius if radius > 0 else None)
        except CusfmError as exc:
            logger.warning("localize: %s", exc)
            return LocalizeAnswer(False, str(exc))
        except Exception as exc:  # a bug must not take the service down with it
            logger.exception("localize: unexpected error")
            return LocalizeAnswer(False, f"internal error: {type(exc).__name__}: {exc}")
        return LocalizeAnswer(result.success, result.message, result.map_from_base_link,
                              result.covariance, result.num_inliers,
                              result.mean_reprojection_error_px, stamp, result.seconds)

    def response_pose(self, answer: LocalizeAnswer) -> Any:
        """The answer's pose as a (rosbags) PoseWithCovarianceStamped in the map frame."""
        pose = answer.map_from_base_link or Rigid3.identity()
        return pose_with_covariance_stamped_msg(pose, answer.covariance, self.map_frame,
                                                answer.stamp_ns)
