"""Frame-to-frame visual odometry, the initializer for bags without a pose source.

Stereo (a rig with a calibrated stereo pair): at each frame the left/right matches are
triangulated with the calibrated extrinsic (metric), the next frame's left and right images
are matched against those points, and absolute-pose RANSAC (OpenCV ``solvePnPRansac``, SQPnP)
followed by Levenberg-Marquardt refinement over both images' inliers gives the metric motion.

Monocular: the first two frames give the relative pose by the essential matrix (unit scale),
their matches are triangulated, and each later frame is registered by absolute pose against the
points of the previous frame (triangulated afresh from the last two frames): a path of
arbitrary, slowly drifting scale, for the mapper to refine.

Both work on normalized camera coordinates, so every camera model works through
``normalized``; a step with too few inliers raises ``MappingError`` naming the stamps.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cusfm_ros.core.features.types import Features
from cusfm_ros.core.relpose.two_view import TwoViewOptions, estimate_two_view, usac_params
from cusfm_ros.core.rig import Rig
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError, MappingError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class VisualOdometryOptions:
    ransac_threshold_px: float = 1.5
    min_inliers: int = 15
    """A step registered with fewer inliers fails (too little texture or overlap)."""
    max_depth_baselines: float = 150.0
    """Stereo points farther than this many baselines carry no metric depth; left out."""
    min_parallax_deg: float = 1.0
    """Monocular: the first two frames need this much median parallax."""
    max_keypoints: int = 2000
    """SIFT keypoints per image (the initializer's own features)."""
    max_rate_hz: float = 10.0
    """Frames faster than this are skipped (their poses are interpolated)."""
    max_skipped_start_frames: int = 5
    """Leading frames that cannot start a track (dark, featureless) are left out, this many
    at most."""

    def __post_init__(self) -> None:
        if self.max_keypoints < 100 or self.max_rate_hz <= 0:
            raise ConfigError("visual odometry: max_keypoints >= 100 and max_rate_hz > 0")
        if self.ransac_threshold_px <= 0 or self.min_inliers < 6:
            raise ConfigError("visual odometry: ransac_threshold_px > 0 and min_inliers >= 6")
        if self.max_depth_baselines <= 0 or self.min_parallax_deg < 0:
            raise ConfigError("visual odometry: max_depth_baselines > 0, min_parallax_deg >= 0")


@dataclass
class VisualOdometryResult:
    world_from_rig: Trajectory
    """world = the rig at the first frame."""
    inliers: list[int]
    """Inliers of each step."""
    method: str
    """``stereo`` (metric) or ``monocular`` (scale arbitrary)."""


def _transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _triangulate(x0: np.ndarray, x1: np.ndarray, cam1_from_cam0: np.ndarray) -> np.ndarray:
    """Points in camera 0 from normalized matches (linear triangulation)."""
    if len(x0) == 0:
        return np.zeros((0, 3))
    p0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    p1 = cam1_from_cam0[:3]
    points = cv2.triangulatePoints(p0, p1, x0.T.astype(np.float64), x1.T.astype(np.float64))
    return (points[:3] / points[3]).T


def _pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(rvec)[0]
    out[:3, 3] = tvec.ravel()
    return out


class VisualOdometry:
    """``solve(stamps_ns, load)``: ``load(i)`` returns {camera name: Features} of frame i."""

    def __init__(self, rig: Rig, matcher, options: VisualOdometryOptions = VisualOdometryOptions(),
                 seed: int = 0) -> None:
        self.rig, self.matcher, self.options, self.seed = rig, matcher, options, seed
        left = next((n for n in rig.names if (p := rig.stereo_partner(n)) and n < p), None)
        self.left = left or rig.names[0]
        self.right = rig.stereo_partner(self.left) if left else None

    # ------------------------------------------------------------------------------ helpers
    def _normalized(self, name: str, features: Features, indices: np.ndarray):
        return self.rig[name].camera.normalized(features.keypoints_px[indices])

    def _threshold(self, name: str) -> float:
        return self.options.ransac_threshold_px / self.rig[name].camera.focal_px

    def _register(self, points: np.ndarray, x: np.ndarray, name: str, what: str
                  ) -> tuple[np.ndarray, np.ndarray]:
        """cam_from_points pose (4x4) and inlier mask by PnP RANSAC + LM refinement."""
        if len(points) < self.options.min_inliers:
            raise MappingError(f"visual odometry lost track {what}: {len(points)} matched "
                               f"points (need {self.options.min_inliers}); the images lack "
                               "texture or overlap, or the camera barely moved")
        params = usac_params(TwoViewOptions(self._threshold(name), confidence=0.9999,
                                            max_iterations=1000, seed=self.seed))
        # MSAC scoring with inner local optimization: MAGSAC's sigma-consensus is tuned for
        # epipolar geometry and fails on some well-posed PnP problems
        params.score = cv2.SCORE_METHOD_MSAC
        params.loMethod = cv2.LOCAL_OPTIM_INNER_LO
        params.final_polisher = cv2.LSQ_POLISHER
        ok, _, rvec, tvec, inliers = cv2.solvePnPRansac(
            points.astype(np.float64), x.astype(np.float64), np.eye(3), np.zeros((1, 5)),
            params=params)
        if not ok or inliers is None or len(inliers) < self.options.min_inliers:
            count = 0 if inliers is None else len(inliers)
            raise MappingError(f"visual odometry lost track {what}: {count} inliers of "
                               f"{len(points)} matched points (need "
                               f"{self.options.min_inliers})")
        index = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(points[index], x[index], np.eye(3), None, rvec, tvec)
        mask = np.zeros(len(points), bool)
        mask[index] = True
        return _pose_matrix(rvec, tvec), mask

    @property
    def cameras(self) -> list[str]:
        """The cameras the odometry reads: the stereo pair, or one camera."""
        return [self.left] + ([self.right] if self.right else [])

    # -------------------------------------------------------------------------------- solve
    def solve(self, stamps_ns: Sequence[int], load: Callable[[int], dict[str, Features]]
              ) -> VisualOdometryResult:
        """Poses from the first frame that starts a track (leading frames that cannot, e.g.
        dark or featureless ones, are left out, at most ``max_skipped_start_frames``)."""
        if len(stamps_ns) < 2:
            raise MappingError("visual odometry needs at least two frames")
        frames = _FrameCache(load)
        method = self._stereo if self.right is not None else self._monocular
        first_error = None
        for start in range(min(self.options.max_skipped_start_frames + 1,
                               len(stamps_ns) - 1)):
            try:
                return method(list(stamps_ns[start:]), frames.offset(start))
            except MappingError as exc:
                if frames.loaded > start + 3:  # failed later on: a lost track, not the start
                    raise
                first_error = first_error or exc
                logger.warning("visual odometry: cannot start at frame %d (%s); trying the "
                               "next", start, exc)
        raise first_error

    def _stereo_points(self, frame: dict[str, Features]):
        """Metric points in the left camera from the left/right matches of one frame."""
        left, right = frame[self.left], frame[self.right]
        matches = self.matcher.match(left, right).indices
        xl, fl = self._normalized(self.left, left, matches[:, 0])
        xr, fr = self._normalized(self.right, right, matches[:, 1])
        rig = self.rig
        right_from_left = (rig[self.right].rig_from_cam.inverse()
                           * rig[self.left].rig_from_cam).matrix()
        points = _triangulate(xl, xr, right_from_left)
        baseline = float(np.linalg.norm(right_from_left[:3, 3]))
        in_right = _transform(right_from_left, points)
        reprojection = np.maximum(
            np.linalg.norm(points[:, :2] / points[:, 2:] - xl, axis=1),
            np.linalg.norm(in_right[:, :2] / in_right[:, 2:] - xr, axis=1))
        keep = (fl & fr & (points[:, 2] > 0) & (in_right[:, 2] > 0)
                & (points[:, 2] < self.options.max_depth_baselines * baseline)
                & (reprojection < self._threshold(self.left)))
        return matches[keep, 0], points[keep]

    def _stereo(self, stamps_ns, load) -> VisualOdometryResult:
        world_from_left = [np.eye(4)]
        inliers = []
        frame = load(0)
        for i in range(1, len(stamps_ns)):
            keypoints, points = self._stereo_points(frame)
            following = load(i)
            what = f"between {stamps_ns[i - 1]} and {stamps_ns[i]} ns"
            matches = self.matcher.match(Features(
                frame[self.left].keypoints_px[keypoints], frame[self.left].scores[keypoints],
                frame[self.left].descriptors[keypoints], frame[self.left].image_size),
                following[self.left]).indices
            x, front = self._normalized(self.left, following[self.left], matches[:, 1])
            cam_from_prev, mask = self._register(points[matches[front, 0]], x[front],
                                                 self.left, what)
            inliers.append(int(mask.sum()))
            world_from_left.append(world_from_left[-1] @ np.linalg.inv(cam_from_prev))
            frame = following
        return self._result(stamps_ns, world_from_left, inliers, "stereo")

    def _monocular(self, stamps_ns, load) -> VisualOdometryResult:
        name = self.left
        frames = [load(0), load(1)]
        matches = self.matcher.match(frames[0][name], frames[1][name]).indices
        x0, f0 = self._normalized(name, frames[0][name], matches[:, 0])
        x1, f1 = self._normalized(name, frames[1][name], matches[:, 1])
        ok = f0 & f1
        result = estimate_two_view(x0[ok], x1[ok], TwoViewOptions(
            self._threshold(name), seed=self.seed))
        what = f"between {stamps_ns[0]} and {stamps_ns[1]} ns"
        if not result.success or result.num_inliers < self.options.min_inliers:
            raise MappingError(f"visual odometry cannot initialize {what}: "
                               f"{result.num_inliers} two-view inliers (need "
                               f"{self.options.min_inliers})")
        cam1_from_cam0 = np.eye(4)
        cam1_from_cam0[:3, :3], cam1_from_cam0[:3, 3] = (result.rotation,
                                                         result.translation_direction)
        parallax = np.degrees(np.arccos(np.clip(np.sum(
            _unit(x0[ok][result.inlier_mask]) * (_unit(x1[ok][result.inlier_mask])
                                                @ result.rotation), axis=1), -1, 1)))
        if np.median(parallax) < self.options.min_parallax_deg:
            raise MappingError(f"visual odometry cannot initialize {what}: median parallax "
                               f"{np.median(parallax):.2f} deg (need "
                               f"{self.options.min_parallax_deg}); the camera barely moved")
        world_from_cam = [np.eye(4), np.linalg.inv(cam1_from_cam0)]
        inliers = [result.num_inliers]
        for i in range(2, len(stamps_ns)):
            previous, current = frames[-2][name], frames[-1][name]
            pair = self.matcher.match(previous, current).indices
            xa, fa = self._normalized(name, previous, pair[:, 0])
            xb, fb = self._normalized(name, current, pair[:, 1])
            # points of the last two frames, in the last frame's camera
            b_from_a = np.linalg.inv(world_from_cam[-1]) @ world_from_cam[-2]
            points_a = _triangulate(xa, xb, b_from_a)
            points_b = _transform(b_from_a, points_a)
            good = fa & fb & (points_a[:, 2] > 0) & (points_b[:, 2] > 0)
            following = load(i)
            onward = self.matcher.match(Features(
                current.keypoints_px[pair[good, 1]], current.scores[pair[good, 1]],
                current.descriptors[pair[good, 1]], current.image_size),
                following[name]).indices
            x, front = self._normalized(name, following[name], onward[:, 1])
            what = f"between {stamps_ns[i - 1]} and {stamps_ns[i]} ns"
            cam_from_prev, mask = self._register(points_b[good][onward[front, 0]], x[front],
                                                 name, what)
            inliers.append(int(mask.sum()))
            world_from_cam.append(world_from_cam[-1] @ np.linalg.inv(cam_from_prev))
            frames = [frames[-1], following]
        return self._result(stamps_ns, world_from_cam, inliers, "monocular")

    def _result(self, stamps_ns, world_from_cam, inliers, method) -> VisualOdometryResult:
        rig_from_cam = self.rig[self.left].rig_from_cam.matrix()
        cam_from_rig = np.linalg.inv(rig_from_cam)
        world_from_rig = np.stack([rig_from_cam @ w @ cam_from_rig for w in world_from_cam])
        logger.info("visual odometry (%s): %d frames, inliers per step median %d, min %d",
                    method, len(world_from_rig), int(np.median(inliers)), int(min(inliers)))
        return VisualOdometryResult(Trajectory(np.asarray(stamps_ns, np.int64),
                                               world_from_rig), inliers, method)


class _FrameCache:
    """Sequential frame loading with the last few frames kept, so a failed start can be
    retried from the next frame without reading the stream again."""

    def __init__(self, load: Callable[[int], dict[str, Features]], keep: int = 8) -> None:
        self._load, self._keep, self._frames, self.loaded = load, keep, {}, 0

    def get(self, index: int) -> dict[str, Features]:
        while self.loaded <= index:
            self._frames[self.loaded] = self._load(self.loaded)
            self._frames.pop(self.loaded - self._keep, None)
            self.loaded += 1
        return self._frames[index]

    def offset(self, start: int) -> Callable[[int], dict[str, Features]]:
        return lambda index: self.get(start + index)


def _unit(x: np.ndarray) -> np.ndarray:
    rays = np.c_[x, np.ones(len(x))]
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)
