"""``cusfm simulate``: render a rig driving through a textured world and record it as a bag.

Outputs (all in ``OUT_DIR``, which appears only when everything is written):
- ``bag/``: rosbag2 (mcap or sqlite3) with per camera ``/<cam>/image_raw`` (or
  ``/<cam>/image_raw/compressed``) and ``/<cam>/camera_info``, ``/odom`` (odom -> base_link,
  drifting), ``/tf`` (the same transform) and ``/tf_static`` (base_link -> optical frames,
  perturbed by ``extrinsic_noise``);
- ``ground_truth.tum``: true ``world_from_base_link`` at every rig sample stamp;
- ``extrinsics_gt.yaml``: true ``base_link_from_cam``;
- ``scene.json``: every parameter, including the seed;
- with ``second_session`` or ``sessions`` N: ``bag_session<k>/`` and
  ``ground_truth_session<k>.tum`` for k = 2..N.
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import multiprocessing
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from cusfm_ros import __version__
from cusfm_ros.core.geometry import Rigid3, invert_matrices, se3_log
from cusfm_ros.core.rig import Rig
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.errors import ConfigError
from cusfm_ros.io.atomic import atomic_directory
from cusfm_ros.io.bags import messages as m
from cusfm_ros.io.bags.writer import STORAGES, BagWriter
from cusfm_ros.io.extrinsics_yaml import CameraExtrinsics, Extrinsics, write_extrinsics
from cusfm_ros.io.tum import write_tum
from cusfm_ros.core.odometry_drift import OdometryDriftOptions, drift_odometry
from cusfm_ros.sim.render import CameraRays, Lighting, Renderer
from cusfm_ros.sim.rigs import CAMERA_MODELS, RIGS, make_camera, make_rig, perturb_extrinsics
from cusfm_ros.sim.route import Motion, Route
from cusfm_ros.sim.textures import build_texture_library
from cusfm_ros.sim.world import build_indoor, build_street

logger = logging.getLogger(__name__)

SCENES = ("street", "indoor")
START_STAMP_NS = 1_700_000_000_000_000_000
_SCENE_DEFAULTS = {  # rate_hz, speed_mps, minimum perimeter, corner radius, vehicle height
    "street": (10.0, 8.0, 100.0, 8.0, 0.0),
    "indoor": (3.0, 1.2, 24.0, 2.5, 0.0),
}


@dataclass(frozen=True)
class SimulationOptions:
    scene: str = "street"
    rig: str = "stereo"
    frames: int = 100
    """Rig samples in session one."""
    rate_hz: float | None = None
    """Camera rate; None: 10 Hz street, 3 Hz indoor."""
    image_width: int = 640
    image_height: int = 480
    camera_model: str = "pinhole"
    loops: int = 1
    """Laps of the closed route in session one; every lap after the first revisits (the route
    shrinks to fit, down to a minimum size per scene)."""
    odom_yaw_drift_deg_per_m: float = 0.05
    odom_scale_error: float = 0.01
    pose_noise_m: tuple[float, float] = (0.0, 0.0)
    """(horizontal, vertical): Gaussian noise (sigma = limit / 3, clipped at the limit) added
    to every odometry pose, the paper's protocol for noisy initial poses."""
    extrinsic_noise: tuple[float, float] = (0.0, 0.0)
    """(metres, degrees) by which /tf_static extrinsics are perturbed; GT stays exact."""
    rolling_shutter_line_delay_s: float = 0.0
    second_session: bool = False
    sessions: int = 1
    """Drives over the same world (``second_session`` asks for 2): session k > 1 goes to
    ``bag_session<k>/`` and ``ground_truth_session<k>.tum``."""
    storage: str = "mcap"
    compressed: bool = False
    sensor_noise: bool = True
    odom_rate_factor: int = 5
    """Odometry messages per camera frame."""
    seed: int = 0
    workers: int = 0
    """Rendering processes; 0 = all cores."""

    def __post_init__(self) -> None:
        checks = [
            (self.scene in SCENES, f"unknown scene {self.scene!r} (use {', '.join(SCENES)})"),
            (self.rig in RIGS, f"unknown rig {self.rig!r} (use {', '.join(RIGS)})"),
            (self.camera_model in CAMERA_MODELS,
             f"unknown camera model {self.camera_model!r} (use {', '.join(CAMERA_MODELS)})"),
            (self.frames >= 2, f"--frames must be at least 2, got {self.frames}"),
            (self.loops >= 1, f"--loops must be at least 1, got {self.loops}"),
            (self.rate_hz is None or self.rate_hz > 0, "--rate-hz must be positive"),
            (self.image_width >= 32 and self.image_height >= 32,
             "--image-size must be at least 32x32"),
            (self.storage in STORAGES, f"unknown storage {self.storage!r}"),
            (self.rolling_shutter_line_delay_s >= 0, "--rolling-shutter must be >= 0"),
            (min(self.pose_noise_m) >= 0 and min(self.extrinsic_noise) >= 0,
             "noise magnitudes must be >= 0"),
            (self.odom_rate_factor >= 1, "odom_rate_factor must be >= 1"),
            (self.sessions >= 1, f"--sessions must be at least 1, got {self.sessions}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)
        rate = self.rate_hz or _SCENE_DEFAULTS[self.scene][0]
        readout = self.rolling_shutter_line_delay_s * self.image_height
        if readout >= 1.0 / rate:
            raise ConfigError(f"rolling-shutter readout {readout:.3f} s is longer than the "
                              f"frame period {1.0 / rate:.3f} s")


@dataclass
class SessionPlan:
    name: str
    motion: Motion
    frames: int
    odom_from_world: Rigid3
    lighting_phase: float
    seed: int
    start_offset_s: float = 0.0
    """Clock of this session's first frame after session one's (sessions are recorded apart:
    their stamps never overlap)."""
    ground_truth: Trajectory = field(init=False)


# ------------------------------------------------------------------------- worker processes
_WORKER: dict = {}


def _init_worker(renderer: Renderer, cameras: list, rays: list) -> None:
    # The renderer's matrix products are small: BLAS threads in every worker only fight over
    # the cores the pool already fills (measured: 2x slower on 2 cores).
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    _WORKER.update(renderer=renderer, cameras=cameras, rays=rays)


def _render_task(task: tuple) -> np.ndarray:
    camera_index, world_from_cam, lighting, noise_seed = task
    rng = None if noise_seed is None else np.random.default_rng(noise_seed)
    image, _ = _WORKER["renderer"].render(_WORKER["cameras"][camera_index],
                                          _WORKER["rays"][camera_index], world_from_cam,
                                          lighting, rng)
    return image


class Simulator:
    def __init__(self, options: SimulationOptions) -> None:
        self.options = options
        o = options
        self.rate_hz, speed, min_perimeter, corner, self.height = _SCENE_DEFAULTS[o.scene]
        self.rate_hz = o.rate_hz or self.rate_hz
        # The route is sized so that the drive covers `loops` laps at the scene's usual speed;
        # below the scene's minimum route size the drive is shorter than the laps asked for.
        distance = o.frames * speed / self.rate_hz
        perimeter = max(min_perimeter, distance / o.loops)
        self.speed_mps = speed
        self.laps = distance / perimeter
        self.num_sessions = max(o.sessions, 2 if o.second_session else 1)
        if self.laps < o.loops - 1e-9:
            # a partial single lap is ordinary; missing revisits that were asked for is not
            logger.log(logging.WARNING if o.loops > 1 else logging.INFO,
                       "simulate: %d frames at %.1f m/s cover %.0f m, %.2f laps of the "
                           "smallest %s route (%.0f m), not the %d asked for; raise --frames "
                           "for revisits", o.frames, speed, distance, self.laps, o.scene,
                           perimeter, o.loops)
        self.route = Route.for_perimeter(perimeter, corner)
        rng = np.random.default_rng(o.seed)
        self.camera = make_camera(o.camera_model, o.image_width, o.image_height)
        self.rig_true = make_rig(o.rig, o.scene, self.camera)
        t_m, r_deg = o.extrinsic_noise
        self.rig_recorded = (perturb_extrinsics(self.rig_true, t_m, r_deg, rng)
                             if t_m or r_deg else self.rig_true)

    # ------------------------------------------------------------------------------- timing
    def _session_plans(self) -> list[SessionPlan]:
        o = self.options
        start = Motion(self.route, self.speed_mps, 0.0, self.height, phase=0.0)
        plans = [SessionPlan("session1", start, o.frames, Rigid3.identity(), 0.0, o.seed)]
        frames = max(int(round(o.frames / self.laps)), 2) if self.laps >= 1 else o.frames
        for k in range(1, self.num_sessions):
            # session 2 starts half a route ahead; later ones spread around the route, each
            # recorded a minute after the one before, in its own light
            along_m = self.route.perimeter_m * (0.5 if k == 1 else k / self.num_sessions
                                                 + 0.25 / self.num_sessions) + 3.0
            motion = Motion(self.route, self.speed_mps, along_m, self.height,
                            phase=1.3 + 0.9 * (k - 1))
            first_pose = Rigid3.from_matrix(motion.world_from_body(np.array([0.0]))[0])
            plans.append(SessionPlan(f"session{k + 1}", motion, frames, first_pose.inverse(),
                                     0.5 + 0.3 * (k - 1), o.seed + 1000 * k,
                                     k * (o.frames / self.rate_hz + 60.0)))
        for plan in plans:
            times = np.arange(plan.frames) / self.rate_hz
            plan.ground_truth = Trajectory(self._stamps(times + plan.start_offset_s),
                                           plan.motion.world_from_body(times))
        return plans

    def _stamps(self, times_s: np.ndarray) -> np.ndarray:
        return START_STAMP_NS + np.round(np.asarray(times_s) * 1e9).astype(np.int64)

    def _lighting(self, plan: SessionPlan, t_s: float) -> Lighting:
        """Sun and exposure change per lap and per session (revisits look different)."""
        lap = int(plan.motion.arc_length(np.array([t_s]))[0] // self.route.perimeter_m)
        phase = plan.lighting_phase + 0.35 * lap
        azimuth = 0.6 + 1.3 * phase
        elevation = 1.05 - 0.25 * np.sin(3 * phase)
        sun = (np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
               np.sin(elevation))
        exposure = 1.0 + 0.12 * np.sin(2.1 * phase + 0.4) if phase else 1.0
        return Lighting(sun_direction=tuple(sun), ambient=0.42 + 0.08 * np.cos(phase),
                        exposure=float(exposure))

    def _camera_poses(self, plan: SessionPlan, t_s: float, rig_from_cam: Rigid3) -> np.ndarray:
        delay = self.options.rolling_shutter_line_delay_s
        if delay > 0:
            rows = t_s + np.arange(self.camera.height) * delay
            return plan.motion.world_from_body(rows) @ rig_from_cam.matrix()
        return plan.motion.world_from_body(np.array([t_s]))[0] @ rig_from_cam.matrix()

    def _odometry(self, plan: SessionPlan) -> tuple[Trajectory, np.ndarray]:
        """Odometry poses ``odom_from_base_link`` at the odometry rate, and twists."""
        o = self.options
        step = 1.0 / (self.rate_hz * o.odom_rate_factor)
        count = (plan.frames - 1) * o.odom_rate_factor + 1
        times = np.arange(count) * step
        truth = Trajectory(self._stamps(times + plan.start_offset_s),
                           plan.motion.world_from_body(times))
        drift = OdometryDriftOptions(o.odom_yaw_drift_deg_per_m, o.odom_scale_error,
                                     seed=plan.seed + 7)
        odom = drift_odometry(truth, drift).world_from_body
        odom = plan.odom_from_world.matrix() @ odom
        horizontal, vertical = o.pose_noise_m
        if horizontal or vertical:
            rng = np.random.default_rng(plan.seed + 11)
            noise = rng.normal(size=(count, 3)) * np.array([horizontal, horizontal, vertical]) / 3
            limit = np.array([horizontal, horizontal, vertical])
            odom[:, :3, 3] += np.clip(noise, -limit, limit)
        # body-frame twist from the odometry itself (finite differences)
        relative = invert_matrices(odom[:-1]) @ odom[1:]
        twist = se3_log(relative) / step
        twist = np.vstack([twist, twist[-1:]])
        return Trajectory(truth.stamps_ns, odom), twist

    # ------------------------------------------------------------------------------- output
    def generate(self, out_dir: str | os.PathLike) -> Path:
        out_dir = Path(out_dir)
        if out_dir.exists() and any(out_dir.iterdir()):
            raise ConfigError(f"{out_dir} exists and is not empty; choose a new directory")
        o = self.options
        started = time.perf_counter()
        logger.info("simulate: %s scene, %s rig (%d cameras, %s %dx%d), %d frames at %.1f Hz, "
                    "%d loop(s) of %.0f m at %.1f m/s", o.scene, o.rig, len(self.rig_true),
                    o.camera_model, o.image_width, o.image_height, o.frames, self.rate_hz,
                    o.loops, self.route.perimeter_m, self.speed_mps)
        textures = build_texture_library(o.seed)
        build = build_street if o.scene == "street" else build_indoor
        world = build(self.route, textures, o.seed)
        renderer = Renderer(world, textures)
        rays = [CameraRays.for_camera(self.camera)]
        plans = self._session_plans()
        stats = {"render_s": 0.0, "images": 0}
        with atomic_directory(out_dir) as tmp:
            workers = o.workers or os.cpu_count() or 1
            context = multiprocessing.get_context("fork")
            with concurrent.futures.ProcessPoolExecutor(
                    workers, mp_context=context, initializer=_init_worker,
                    initargs=(renderer, [self.camera], rays)) as pool:
                for plan in plans:
                    suffix = "" if plan.name == "session1" else f"_{plan.name}"
                    self._write_session(plan, tmp / f"bag{suffix}", pool, stats)
                    write_tum(tmp / f"ground_truth{suffix}.tum", plan.ground_truth)
            write_extrinsics(tmp / "extrinsics_gt.yaml", Extrinsics(
                self.rig_true.base_frame_id,
                {c.name: CameraExtrinsics(c.frame_id, c.rig_from_cam)
                 for c in self.rig_true.cameras}))
            (tmp / "scene.json").write_text(json.dumps(self._scene_description(plans), indent=2))
        elapsed = time.perf_counter() - started
        logger.info("simulate: %d images rendered in %.1f s (%.3f s/image), total %.1f s -> %s",
                    stats["images"], stats["render_s"],
                    stats["render_s"] / max(stats["images"], 1), elapsed, out_dir)
        return out_dir

    def _write_session(self, plan: SessionPlan, bag_path: Path, pool, stats: dict) -> None:
        o = self.options
        odom, twist = self._odometry(plan)
        cameras = self.rig_recorded.cameras
        image_type = m.COMPRESSED_IMAGE if o.compressed else m.IMAGE
        image_suffix = "/image_raw/compressed" if o.compressed else "/image_raw"
        batch = max(1, 8 // len(cameras)) * 2
        with BagWriter(bag_path, o.storage) as bag:
            bag.add_topic("/tf_static", m.TF_MESSAGE, latched=True)
            start = int(plan.ground_truth.stamps_ns[0])
            bag.write("/tf_static", m.TF_MESSAGE, start, m.tf_message([
                m.transform_stamped_msg(start, self.rig_recorded.base_frame_id, c.frame_id,
                                        c.rig_from_cam) for c in cameras]))
            for first in range(0, plan.frames, batch):
                samples = range(first, min(first + batch, plan.frames))
                tasks = []
                for k in samples:
                    t_s = k / self.rate_hz
                    lighting = self._lighting(plan, t_s)
                    for index, camera in enumerate(cameras):
                        pose = self._camera_poses(plan, t_s, self.rig_true[camera.name]
                                                  .rig_from_cam)
                        noise_seed = (plan.seed * 1_000_003 + k * 101 + index
                                      if o.sensor_noise else None)
                        tasks.append((0, pose, lighting, noise_seed))
                tick = time.perf_counter()
                images = list(pool.map(_render_task, tasks))
                stats["render_s"] += time.perf_counter() - tick
                stats["images"] += len(images)
                for offset, k in enumerate(samples):
                    stamp = int(plan.ground_truth.stamps_ns[k])
                    for j in range(o.odom_rate_factor if k < plan.frames - 1 else 1):
                        self._write_odometry(bag, odom, twist, k * o.odom_rate_factor + j)
                        if j == 0:
                            for index, camera in enumerate(cameras):
                                image = images[offset * len(cameras) + index]
                                self._write_image(bag, camera.name, camera.frame_id, image,
                                                  stamp, image_type, image_suffix)
                logger.info("simulate %s: %d/%d samples rendered (%.2f s/image)", plan.name,
                            samples[-1] + 1, plan.frames,
                            stats["render_s"] / max(stats["images"], 1))

    def _write_odometry(self, bag: BagWriter, odom: Trajectory, twist: np.ndarray, i: int):
        stamp = int(odom.stamps_ns[i])
        pose = Rigid3.from_matrix(odom.world_from_body[i])
        receive = stamp + 1_000_000
        bag.write("/odom", m.ODOMETRY, receive,
                  m.odometry_msg(stamp, "odom", "base_link", pose, twist[i, 3:], twist[i, :3]))
        bag.write("/tf", m.TF_MESSAGE, receive, m.tf_message(
            [m.transform_stamped_msg(stamp, "odom", "base_link", pose)]))

    def _write_image(self, bag: BagWriter, name: str, frame_id: str, image: np.ndarray,
                     stamp: int, image_type: str, image_suffix: str) -> None:
        receive = stamp + 3_000_000
        if image_type == m.COMPRESSED_IMAGE:
            message = m.compressed_image_msg(image, stamp, frame_id)
        else:
            message = m.image_msg(image, stamp, frame_id, "rgb8")
        bag.write(f"/{name}{image_suffix}", image_type, receive, message)
        bag.write(f"/{name}/camera_info", m.CAMERA_INFO, receive,
                  m.camera_info_msg(self.camera, stamp, frame_id))

    def _scene_description(self, plans: list[SessionPlan]) -> dict:
        def rig_dict(rig: Rig) -> dict:
            return {c.name: {"frame_id": c.frame_id, "camera": c.camera.to_dict(),
                             "rig_from_cam": {"translation_m": c.rig_from_cam.translation.tolist(),
                                              "quat_xyzw": c.rig_from_cam.quat_xyzw().tolist()}}
                    for c in rig.cameras}

        return {
            "generator": f"cusfm_ros {__version__}",
            "options": asdict(self.options),
            "rate_hz": self.rate_hz,
            "speed_mps": self.speed_mps,
            "laps": self.laps,
            "route": {"perimeter_m": self.route.perimeter_m, **asdict(self.route)},
            "frames": {p.name: p.frames for p in plans},
            "start_stamp_ns": START_STAMP_NS,
            "rig_true": rig_dict(self.rig_true),
            "rig_recorded": rig_dict(self.rig_recorded),
            "topics": {
                "images": [f"/{c.name}/image_raw" + ("/compressed" if self.options.compressed
                                                     else "") for c in self.rig_true.cameras],
                "camera_info": [f"/{c.name}/camera_info" for c in self.rig_true.cameras],
                "odometry": "/odom", "tf": "/tf", "tf_static": "/tf_static"},
            "frames_ids": {"odom": "odom", "base": "base_link", "world": "world (= odom of "
                           "session 1 at its first stamp)"},
        }
