"""The closed route the rig drives and its exact ground-truth motion ``world_from_base_link``.

The route's centre line is a rounded rectangle (two straights of length ``straight_x_m``, two
of ``straight_y_m``, four quarter circles of ``corner_radius_m``), parametrized by arc length.
The vehicle follows it with a smoothly varying speed, a small lateral wander and gentle
pitch/roll, all analytic functions of time so that the pose at *any* stamp is exact (rolling
shutter rows included). World frame: REP 105, z up; body frame: x forward, y left, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cusfm_ros.core.geometry import se3_exp


@dataclass(frozen=True)
class Route:
    straight_x_m: float
    straight_y_m: float
    corner_radius_m: float

    @property
    def perimeter_m(self) -> float:
        return 2 * self.straight_x_m + 2 * self.straight_y_m + 2 * np.pi * self.corner_radius_m

    @property
    def half_extent_m(self) -> tuple[float, float]:
        """Half sizes of the centre line's bounding box."""
        return (self.straight_x_m / 2 + self.corner_radius_m,
                self.straight_y_m / 2 + self.corner_radius_m)

    @classmethod
    def for_perimeter(cls, perimeter_m: float, corner_radius_m: float, aspect: float = 2.0
                      ) -> Route:
        """A route with straights in ratio ``aspect`` and the given perimeter."""
        straight_y = max((perimeter_m - 2 * np.pi * corner_radius_m) / (2 * (1 + aspect)), 1.0)
        return cls(aspect * straight_y, straight_y, corner_radius_m)

    def segments(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """The four straights as (start xy, unit direction, length), counter-clockwise."""
        hx, hy = self.straight_x_m / 2, self.straight_y_m / 2
        r = self.corner_radius_m
        return [(np.array([-hx, -hy - r]), np.array([1.0, 0.0]), self.straight_x_m),
                (np.array([hx + r, -hy]), np.array([0.0, 1.0]), self.straight_y_m),
                (np.array([hx, hy + r]), np.array([-1.0, 0.0]), self.straight_x_m),
                (np.array([-hx - r, hy]), np.array([0.0, -1.0]), self.straight_y_m)]

    def centerline(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (N, 2) and headings (N,) [rad] at arc lengths ``s_m`` (wrapping)."""
        s = np.mod(np.asarray(s_m, dtype=np.float64), self.perimeter_m)
        r = self.corner_radius_m
        hx, hy = self.straight_x_m / 2, self.straight_y_m / 2
        corners = [np.array([hx, -hy]), np.array([hx, hy]), np.array([-hx, hy]),
                   np.array([-hx, -hy])]
        xy = np.zeros((len(s), 2))
        heading = np.zeros(len(s))
        start = 0.0
        for index, (origin, direction, length) in enumerate(self.segments()):
            on_straight = (s >= start) & (s < start + length)
            local = s[on_straight] - start
            xy[on_straight] = origin + local[:, None] * direction
            heading[on_straight] = np.arctan2(direction[1], direction[0])
            start += length
            arc = 0.5 * np.pi * r
            on_arc = (s >= start) & (s < start + arc)
            angle0 = np.arctan2(direction[1], direction[0]) - np.pi / 2
            phi = angle0 + (s[on_arc] - start) / r
            xy[on_arc] = corners[index] + r * np.stack([np.cos(phi), np.sin(phi)], axis=1)
            heading[on_arc] = phi + np.pi / 2
            start += arc
        return xy, heading


@dataclass(frozen=True)
class Motion:
    """Time -> pose along a route, with analytic speed, wander, height and attitude."""

    route: Route
    speed_mps: float
    start_s_m: float = 0.0
    height_m: float = 0.0
    speed_variation: float = 0.15
    wander_m: float = 0.3
    attitude_deg: float = 0.6
    phase: float = 0.0

    def arc_length(self, t_s: np.ndarray) -> np.ndarray:
        # speed(t) = v (1 + a sin(w t + phase)); integrated in closed form
        w = 2 * np.pi / 9.0
        a = self.speed_variation
        return self.start_s_m + self.speed_mps * (
            t_s - a / w * (np.cos(w * t_s + self.phase) - np.cos(self.phase)))

    def _position(self, t_s: np.ndarray) -> np.ndarray:
        xy, heading = self.route.centerline(self.arc_length(t_s))
        lateral = self.wander_m * np.sin(2 * np.pi * t_s / 13.0 + self.phase)
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
        z = self.height_m + 0.05 * np.sin(2 * np.pi * t_s / 7.0 + 2 * self.phase)
        return np.column_stack([xy + lateral[:, None] * normal, z])

    def world_from_body(self, t_s: np.ndarray) -> np.ndarray:
        """Exact poses (N, 4, 4) at times ``t_s`` (seconds since the session start)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        dt = 1e-4
        position = self._position(t)
        velocity = (self._position(t + dt) - self._position(t - dt)) / (2 * dt)
        yaw = np.arctan2(velocity[:, 1], velocity[:, 0])
        amp = np.radians(self.attitude_deg)
        roll = amp * np.sin(2 * np.pi * t / 5.0 + self.phase)
        pitch = amp * np.sin(2 * np.pi * t / 6.5 + 1.0 + self.phase)
        # yaw (z) * pitch (y) * roll (x), each as an exponential of one axis
        zeros = np.zeros_like(t)
        rz = se3_exp(np.column_stack([zeros, zeros, yaw, zeros, zeros, zeros]))
        ry = se3_exp(np.column_stack([zeros, pitch, zeros, zeros, zeros, zeros]))
        rx = se3_exp(np.column_stack([roll, zeros, zeros, zeros, zeros, zeros]))
        poses = rz @ ry @ rx
        poses[:, :3, 3] = position
        return poses
