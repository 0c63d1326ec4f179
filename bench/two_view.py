"""Two-view benchmark: relative-pose AUC on simulator pairs, homography AUC on real photographs,
time per pair, and ALIKED / LightGlue timings (ONNX Runtime vs torch).

Usage: python bench/two_view.py [--pairs 24] [--skip-timing]
Prints tables; asserts nothing. Needs the ONNX models (``make models``); torch only for the
timing comparison.
"""

from __future__ import annotations

import argparse
import logging
import time

import cv2
import numpy as np

from cusfm_ros.core.features.aliked import AlikedExtractor, AlikedOptions
from cusfm_ros.core.features.knn import KnnMatcher, KnnOptions
from cusfm_ros.core.features.lightglue import LightGlueMatcher
from cusfm_ros.core.features.sift import SiftExtractor, SiftOptions
from cusfm_ros.core.geometry import invert_matrices
from cusfm_ros.models.store import ensure_models
from cusfm_ros.sim.render import CameraRays, Lighting, Renderer
from cusfm_ros.sim.rigs import make_camera, make_rig
from cusfm_ros.sim.route import Motion, Route
from cusfm_ros.sim.textures import build_texture_library
from cusfm_ros.sim.world import build_street

PHOTOS = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "hubble_deep_field",
          "stereo_motorcycle", "retina")


def pose_auc(errors_deg: np.ndarray, thresholds=(5, 10, 20)) -> list[float]:
    """Area under the recall curve up to each threshold (as in SuperGlue/LightGlue papers)."""
    errors = np.sort(np.r_[0.0, errors_deg])
    recall = np.r_[0.0, (np.arange(len(errors_deg)) + 1) / len(errors_deg)]
    out = []
    for threshold in thresholds:
        last = np.searchsorted(errors, threshold)
        e = np.r_[errors[:last], threshold]
        r = np.r_[recall[:last], recall[last - 1]]
        out.append(float(np.trapezoid(r, x=e) / threshold))
    return out


def simulator_pairs(count: int, seed: int = 0):
    """Rendered front-camera pairs of a street drive with exact relative poses."""
    textures = build_texture_library(seed)
    route = Route.for_perimeter(160.0, 8.0)
    renderer = Renderer(build_street(route, textures, seed), textures)
    camera = make_camera("pinhole", 640, 480)
    rig = make_rig("mono", "street", camera)
    rays = CameraRays.for_camera(camera)
    motion = Motion(route, 8.0)
    rng = np.random.default_rng(seed)
    pairs = []
    for _ in range(count):
        t0 = rng.uniform(0, 18)
        t1 = t0 + rng.uniform(0.25, 0.9)
        poses = motion.world_from_body(np.array([t0, t1])) @ rig.cameras[0].rig_from_cam.matrix()
        images = [renderer.render(camera, rays, p, Lighting(exposure=e),
                                  np.random.default_rng(int(rng.integers(1 << 30))))[0]
                  for p, e in zip(poses, (1.0, rng.uniform(0.85, 1.15)))]
        cam1_from_cam0 = invert_matrices(poses[1]) @ poses[0]
        pairs.append((images[0], images[1], cam1_from_cam0, camera.K))
    return pairs


def homography_pairs(count: int, seed: int = 0):
    import skimage.data

    rng = np.random.default_rng(seed)
    pairs = []
    for i in range(count):
        name = PHOTOS[i % len(PHOTOS)]
        image = getattr(skimage.data, name)()
        image = image[0] if name == "stereo_motorcycle" else image
        image = cv2.resize(image, (640, 480), interpolation=cv2.INTER_AREA)
        h, w = image.shape[:2]
        corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
        moved = (corners + rng.uniform(-0.18, 0.18, (4, 2)) * [w, h]).astype(np.float32)
        homography = cv2.getPerspectiveTransform(corners, moved)
        warped = cv2.warpPerspective(image, homography, (w, h))
        gain = rng.uniform(0.7, 1.3)
        warped = np.clip(warped.astype(np.float32) * gain + rng.normal(0, 3, warped.shape),
                         0, 255).astype(np.uint8)
        pairs.append((image, warped, homography))
    return pairs


def relative_pose_error(f0, f1, matches, cam1_from_cam0, k) -> float:
    if len(matches) < 5:
        return 180.0
    p0 = f0.keypoints_px[matches.indices[:, 0]].astype(np.float64)
    p1 = f1.keypoints_px[matches.indices[:, 1]].astype(np.float64)
    e, inliers = cv2.findEssentialMat(p0, p1, k, method=cv2.USAC_MAGSAC, prob=0.9999,
                                      threshold=1.0)
    if e is None or e.shape != (3, 3):
        return 180.0
    _, rotation, t, _ = cv2.recoverPose(e, p0, p1, k, mask=inliers)
    rot_err = np.degrees(np.arccos(np.clip((np.trace(rotation.T @ cam1_from_cam0[:3, :3]) - 1)
                                           / 2, -1, 1)))
    t_true = cam1_from_cam0[:3, 3] / np.linalg.norm(cam1_from_cam0[:3, 3])
    t_est = t.ravel() / np.linalg.norm(t)
    t_err = np.degrees(np.arccos(np.clip(abs(t_true @ t_est), -1, 1)))
    return float(max(rot_err, t_err))


def homography_error(f0, f1, matches, homography, size) -> float:
    if len(matches) < 4:
        return 1e3
    p0 = f0.keypoints_px[matches.indices[:, 0]]
    p1 = f1.keypoints_px[matches.indices[:, 1]]
    estimate, _ = cv2.findHomography(p0, p1, cv2.USAC_MAGSAC, 3.0)
    if estimate is None:
        return 1e3
    w, h = size
    corners = np.float32([[0, 0], [w, 0], [w, h], [0, h]])[None]
    return float(np.mean(np.linalg.norm(cv2.perspectiveTransform(corners, estimate)
                                        - cv2.perspectiveTransform(corners, homography), axis=2)))


def timing(model_dir) -> None:
    """ALIKED 1241x376 and LightGlue 2x1024: onnxruntime vs torch, median of 5."""
    import skimage.data

    image = cv2.resize(skimage.data.stereo_motorcycle()[0], (1241, 376))
    rows = []
    ort = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=1024, detection_threshold=-1))
    feats = ort.extract(image)
    other = ort.extract(cv2.resize(skimage.data.stereo_motorcycle()[1], (1241, 376)))
    lightglue = LightGlueMatcher(model_dir)

    def median_time(fn):
        fn()
        times = []
        for _ in range(5):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return float(np.median(times))

    rows.append(("ALIKED-n16 1241x376", "onnxruntime", median_time(lambda: ort.extract(image))))
    rows.append(("LightGlue 2x1024", "onnxruntime (all 9 layers)",
                 median_time(lambda: lightglue.match(feats, other))))
    try:
        import torch

        from cusfm_ros.models.torch_backend import TorchAlikedExtractor, TorchLightGlueMatcher
        torch.set_num_threads(2)
        torch_aliked = TorchAlikedExtractor(AlikedOptions(max_keypoints=1024,
                                                          detection_threshold=-1, device="cpu"))
        torch_lg = TorchLightGlueMatcher()
        rows.append(("ALIKED-n16 1241x376", "torch CPU",
                     median_time(lambda: torch_aliked.extract(image))))
        rows.append(("LightGlue 2x1024", "torch CPU (all 9 layers)",
                     median_time(lambda: torch_lg.match(feats, other))))
    except ImportError:
        pass
    print("\n| stage | backend | median s |\n|---|---|---|")
    for stage, backend, seconds in rows:
        print(f"| {stage} | {backend} | {seconds:.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--pairs", type=int, default=24)
    parser.add_argument("--skip-timing", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    model_dir = ensure_models()
    aliked = AlikedExtractor(model_dir, AlikedOptions(max_keypoints=2048))
    sift = SiftExtractor(SiftOptions(max_keypoints=2048))
    methods = {"SIFT+NN": (sift, KnnMatcher(KnnOptions(ratio=0.8))),
               "ALIKED+kNN": (aliked, KnnMatcher(KnnOptions(ratio=0.95))),
               "ALIKED+LightGlue": (aliked, LightGlueMatcher(model_dir))}
    sim, photos = simulator_pairs(args.pairs), homography_pairs(args.pairs)
    print("| method | sim pose AUC@5 | @10 | @20 | photo H AUC@3px | @5px | @10px | "
          "matches/pair | s/pair |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (extractor, matcher) in methods.items():
        pose_errors, h_errors, counts, seconds = [], [], [], []
        for image0, image1, cam1_from_cam0, k in sim:
            start = time.perf_counter()
            f0, f1 = extractor.extract(image0), extractor.extract(image1)
            matches = matcher.match(f0, f1)
            seconds.append(time.perf_counter() - start)
            counts.append(len(matches))
            pose_errors.append(relative_pose_error(f0, f1, matches, cam1_from_cam0, k))
        for image0, image1, homography in photos:
            start = time.perf_counter()
            f0, f1 = extractor.extract(image0), extractor.extract(image1)
            matches = matcher.match(f0, f1)
            seconds.append(time.perf_counter() - start)
            counts.append(len(matches))
            h_errors.append(homography_error(f0, f1, matches, homography, (640, 480)))
        pose = pose_auc(np.array(pose_errors))
        hom = pose_auc(np.array(h_errors), (3, 5, 10))
        print(f"| {name} | {100 * pose[0]:.1f} | {100 * pose[1]:.1f} | {100 * pose[2]:.1f} | "
              f"{100 * hom[0]:.1f} | {100 * hom[1]:.1f} | {100 * hom[2]:.1f} | "
              f"{np.mean(counts):.0f} | {np.mean(seconds):.2f} |")
    if not args.skip_timing:
        timing(model_dir)


if __name__ == "__main__":
    main()
