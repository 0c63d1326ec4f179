"""Stereo relative pose (paper section 4.1) vs the triangulate + PnP baseline.

Random map/stereo configurations with 3D points 5-25 m away, 0.5 px noise at a 500 px focal
length and 15 % outlier matches. The baseline triangulates the points from the stereo pair and
solves PnP (OpenCV SQPnP + RANSAC) against the map view. The stereo relative pose runs both
ways of its step 2: the scale from the right pair given the left pair's rotation (the
default) and the right pair's own essential matrix (the paper's). Prints error
distributions; asserts nothing. Usage: python bench/stereo_pose.py [--trials 200]
"""

from __future__ import annotations

import argparse

import cv2
import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.relpose.stereo import StereoPoseOptions, stereo_relative_pose
from cusfm_ros.errors import GeometryError

FOCAL_PX = 500.0


def trial(rng: np.random.Generator, baseline_m: float):
    left_from_right = Rigid3.from_rotvec(rng.normal(scale=0.005, size=3), [baseline_m, 0, 0])
    truth = Rigid3.from_rotvec(rng.normal(scale=0.15, size=3),
                               rng.normal(scale=[1.5, 0.2, 1.5]))
    count = 250
    points = np.c_[rng.uniform(-6, 6, (count, 2)), rng.uniform(5, 25, count)]

    def observe(cam_from_map):
        p = cam_from_map.transform_points(points)
        return p[:, :2] / p[:, 2:] + rng.normal(scale=0.5 / FOCAL_PX, size=(count, 2))

    left = observe(truth.inverse())
    right = observe((truth * left_from_right).inverse())
    in_map = observe(Rigid3.identity())
    outliers = rng.random(count) < 0.15
    left[outliers] = rng.uniform(-0.5, 0.5, (outliers.sum(), 2))
    return truth, left, right, in_map, left_from_right


def pnp_baseline(left, right, in_map, left_from_right: Rigid3) -> Rigid3:
    right_from_left = left_from_right.inverse()
    p_left = np.eye(3, 4)
    p_right = right_from_left.matrix()[:3]
    homogeneous = cv2.triangulatePoints(p_left, p_right, left.T, right.T)
    points_left = (homogeneous[:3] / homogeneous[3]).T
    ok, rvec, tvec, _ = cv2.solvePnPRansac(points_left, in_map, np.eye(3), None,
                                           reprojectionError=2.0 / FOCAL_PX,
                                           flags=cv2.SOLVEPNP_SQPNP, iterationsCount=1000)
    if not ok:
        raise GeometryError("PnP failed")
    return Rigid3.from_rotvec(rvec.ravel(), tvec.ravel())  # map_from_left


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trials", type=int, default=200)
    args = parser.parse_args()
    print("| baseline m | method | rot err median deg | rot p90 | trans err median m | "
          "trans p90 | failures |\n|---|---|---|---|---|---|---|")
    for baseline in (0.12, 0.3, 0.54):
        rng = np.random.default_rng(0)
        errors = {"stereo relative pose (scale from right)": [],
                  "stereo relative pose (two essentials)": [], "triangulate + PnP": []}
        failures = dict.fromkeys(errors, 0)
        for _ in range(args.trials):
            truth, left, right, in_map, left_from_right = trial(rng, baseline)
            for name in errors:
                try:
                    if name.startswith("stereo relative pose"):
                        estimate = stereo_relative_pose(
                            left, in_map, right, in_map, left_from_right, StereoPoseOptions(
                                ransac_threshold=1.0 / FOCAL_PX,
                                right_pair="scale" if "scale" in name else "essential")
                        ).map_from_left
                    else:
                        estimate = pnp_baseline(left, right, in_map, left_from_right)
                except GeometryError:
                    failures[name] += 1
                    continue
                delta = truth.inverse() * estimate
                errors[name].append((delta.rotation_angle_deg(),
                                     float(np.linalg.norm(delta.translation))))
        for name, values in errors.items():
            e = np.array(values)
            print(f"| {baseline} | {name} | {np.median(e[:, 0]):.3f} | "
                  f"{np.percentile(e[:, 0], 90):.3f} | {np.median(e[:, 1]):.3f} | "
                  f"{np.percentile(e[:, 1], 90):.3f} | {failures[name]} |")


if __name__ == "__main__":
    main()
