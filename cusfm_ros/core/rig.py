"""A camera rig: named cameras with intrinsics and ``rig_from_cam`` extrinsics.

The rig frame is the vehicle body (``base_link`` by REP 105); camera frames are REP 103
optical frames. ``world_from_cam = world_from_rig * rig_from_cam``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cusfm_ros.core.cameras import CameraBase
from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.errors import CalibrationError


@dataclass(frozen=True)
class RigCamera:
    name: str
    camera: CameraBase
    rig_from_cam: Rigid3
    frame_id: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            raise CalibrationError("a rig camera needs a non-empty name")
        if not self.frame_id:
            object.__setattr__(self, "frame_id", f"{self.name}_optical_frame")


@dataclass(frozen=True)
class Rig:
    cameras: tuple[RigCamera, ...]
    base_frame_id: str = "base_link"
    _by_name: dict[str, RigCamera] = field(init=False, repr=False, compare=False)
    _partners: dict = field(init=False, repr=False, compare=False)
    """``stereo_partner``'s answers (the pose graph asks once per loop)."""

    def __post_init__(self) -> None:
        cameras = tuple(self.cameras)
        object.__setattr__(self, "cameras", cameras)
        if not cameras:
            raise CalibrationError("a rig needs at least one camera")
        names = [c.name for c in cameras]
        frames = [c.frame_id for c in cameras]
        for what, values in (("name", names), ("frame id", frames)):
            duplicates = sorted({v for v in values if values.count(v) > 1})
            if duplicates:
                raise CalibrationError(f"rig cameras share the {what} {duplicates}")
        object.__setattr__(self, "_by_name", {c.name: c for c in cameras})
        object.__setattr__(self, "_partners", {})

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def __getitem__(self, name: str) -> RigCamera:
        try:
            return self._by_name[name]
        except KeyError:
            raise CalibrationError(
                f"rig has no camera named {name!r} (cameras: {', '.join(self.names)})") from None

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def world_from_cam(self, world_from_rig: Rigid3, name: str) -> Rigid3:
        return world_from_rig * self[name].rig_from_cam

    def stereo_partner(self, name: str, max_angle_deg: float = 5.0) -> str | None:
        """The camera forming a stereo pair with ``name``: parallel optical axes (within
        ``max_angle_deg``) and the shortest baseline above 2 cm; None if there is none."""
        key = (name, max_angle_deg)
        if key not in self._partners:
            self._partners[key] = self._stereo_partner(name, max_angle_deg)
        return self._partners[key]

    def _stereo_partner(self, name: str, max_angle_deg: float) -> str | None:
        own = self[name].rig_from_cam
        best, best_distance = None, float("inf")
        for camera in self.cameras:
            if camera.name == name:
                continue
            relative = own.inverse() * camera.rig_from_cam
            distance = float(np.linalg.norm(relative.translation))
            if relative.rotation_angle_deg() < max_angle_deg and 0.02 < distance < best_distance:
                best, best_distance = camera.name, distance
        return best

    def with_extrinsics(self, rig_from_cams: dict[str, Rigid3]) -> Rig:
        """A copy with some cameras' extrinsics replaced (unknown names raise)."""
        for name in rig_from_cams:
            self[name]
        cameras = tuple(
            RigCamera(c.name, c.camera, rig_from_cams.get(c.name, c.rig_from_cam), c.frame_id)
            for c in self.cameras)
        return Rig(cameras, self.base_frame_id)
