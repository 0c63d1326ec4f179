"""Inputs of ``bench/compare.py``: a bag for us and, from the same bag, image folders for the
peers, with the ground truth and the cameras they need.

- ``kitti``: the real KITTI 06 clip (../shared/realdata/kitti06_stereo_51) through
  ``cusfm convert kitti`` with drifting odometry (2 % scale, 0.1 deg/m yaw, seeded);
- ``street`` / ``indoor``: the simulator (street stereo, indoor stereo4), 1241x376, 2 laps,
  ``frames`` rig samples, seed 0.

Each input becomes ``ROOT/<name>/`` with ``bag/``, ``ground_truth.tum``, ``images/<camera>/
<stamp_ns>.png`` (every rig sample, every camera: the peers' images), ``odometry.tum`` (the
bag's odometry: the peers' pose priors) and ``input.json``
(written last: its presence means the input is complete).
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np

from cusfm_ros.cli.main import main as cusfm
from cusfm_ros.core.trajectory import Trajectory
from cusfm_ros.io.bags.messages import rigid_from_pose
from cusfm_ros.io.bags.reader import BagReader
from cusfm_ros.io.bags.rig_samples import iter_rig_samples, scan_cameras
from cusfm_ros.io.tum import read_tum, write_tum

from compare_names import SCENES  # run as a script: its folder is on the path

KITTI = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "kitti06_stereo_51"
logger = logging.getLogger("compare")


def _bag_of(name: str, frames: int, width: int, height: int, folder: Path) -> None:
    if name == "kitti":
        if not KITTI.is_dir():
            raise SystemExit(f"{KITTI} is absent: the kitti input needs ../shared/realdata")
        if cusfm(["convert", "kitti", str(KITTI), str(folder / "bag"),
                  "--odom-drift", "0.1,0.02"]) != 0:
            raise SystemExit("cusfm convert kitti failed")
        return
    from cusfm_ros.sim.generator import SimulationOptions, Simulator

    scene, rig = SCENES[name]
    Simulator(SimulationOptions(scene=scene, rig=rig, frames=frames, image_width=width,
                                image_height=height, loops=2, seed=0)).generate(folder)


def _extract_images(bag: Path, out: Path) -> dict:
    """Every rig sample's images as PNG, named by stamp, and the cameras (pinhole intrinsics,
    ``rig_from_cam``) the peers are given."""
    cameras = {}
    with BagReader(bag) as reader:
        scanned = scan_cameras(reader)
        for sample, images in iter_rig_samples(reader, scanned):
            for name, image in images.items():
                folder = out / name
                folder.mkdir(parents=True, exist_ok=True)
                bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
                cv2.imwrite(str(folder / f"{sample.image_stamps_ns[name]}.png"), bgr)
        for name, camera in scanned.cameras.items():
            k = camera.K
            rig_from_cam = scanned.rig_from_cam("base_link", name)
            cameras[name] = {
                "width": camera.width, "height": camera.height,
                "pinhole": [float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])],
                "rig_from_cam": None if rig_from_cam is None else rig_from_cam.matrix().tolist()}
    return cameras


def _odometry(bag: Path) -> Trajectory | None:
    """The bag's nav_msgs/Odometry as a trajectory (the peers' pose priors), None without."""
    with BagReader(bag) as reader:
        topics = [t.name for t in reader.topics().values() if t.msgtype.endswith("Odometry")]
        if not topics:
            return None
        stamps, poses = [], []
        for message in reader.messages(topics[:1]):
            odometry = reader.deserialize(message)
            stamps.append(reader.header_stamp_ns(message))
            poses.append(rigid_from_pose(odometry.pose.pose).matrix())
    return Trajectory(np.asarray(stamps, np.int64), np.stack(poses))


def prepare(name: str, root: Path, frames: int, width: int = 1241, height: int = 376) -> dict:
    """The input ``name`` under ``root`` (reused when complete)."""
    folder = root / (name if name == "kitti" else f"{name}_{frames}")
    spec_path = folder / "input.json"
    if spec_path.is_file():
        return json.loads(spec_path.read_text())
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    logger.info("compare: preparing input %s in %s", name, folder)
    _bag_of(name, frames, width, height, folder)
    cameras = _extract_images(folder / "bag", folder / "images")
    truth = read_tum(folder / "ground_truth.tum")
    odometry = _odometry(folder / "bag")
    if odometry is not None:
        write_tum(folder / "odometry.tum", odometry)
    first = sorted(cameras)[0]
    spec = {"name": name, "bag": str(folder / "bag"), "truth": str(folder / "ground_truth.tum"),
            "images": str(folder / "images"),
            "odometry": None if odometry is None else str(folder / "odometry.tum"),
            "cameras": cameras, "reference_camera": first,
            "frames": len(truth), "path_m": float(np.linalg.norm(
                np.diff(truth.positions_m, axis=0), axis=1).sum())}
    spec_path.write_text(json.dumps(spec, indent=1) + "\n")
    return spec


if __name__ == "__main__":  # bench/compare.py: NAME ROOT FRAMES WIDTH HEIGHT -> input.json path
    import sys

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s",
                        datefmt="%H:%M:%S")
    name, root, frames, width, height = sys.argv[1:6]
    spec = prepare(name, Path(root), int(frames), int(width), int(height))
    print(Path(spec["bag"]).parent / "input.json")
