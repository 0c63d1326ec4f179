"""Latency of single-image localization against a map, on CPU or GPU, for the same queries.

    python bench/localization_latency.py MAP_DIR IMAGE_DIR CAMERA_YAML [--device cpu|cuda]
        [--reference POSES.json] [--out POSES.json]

Every image of IMAGE_DIR (sorted) is one query (no prior). After two warm-up queries, prints
the median and p90 wall time per query, the feature-extraction share of it, and, with
``--reference``, how far each pose is from the reference run's (e.g. CPU against GPU).
Needs no bag libraries: it runs where only torch/onnxruntime and the core are installed.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from cusfm_ros.core.geometry import Rigid3
from cusfm_ros.core.localization.localizer import QueryImage
from cusfm_ros.io.camera_yaml import read_camera_yaml
from cusfm_ros.pipeline.localization import latency_stats, load_localizer
from cusfm_ros.pipeline.stages.features import read_image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map_dir")
    parser.add_argument("image_dir", type=Path)
    parser.add_argument("camera")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--reference", type=Path)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    started = time.perf_counter()
    localizer = load_localizer(args.map_dir, device=args.device)
    print(f"localizer ready in {time.perf_counter() - started:.2f} s "
          f"({type(localizer.extractor).__name__}, device {args.device})")
    camera = read_camera_yaml(args.camera)
    images = [(p.name, read_image(p)) for p in sorted(args.image_dir.glob("*.png"))]
    for _, image in images[:2]:  # warm-up (CUDA kernels, ORT arenas)
        localizer.localize([QueryImage(image, camera)])
    poses, total, extract = {}, [], []
    for name, image in images:
        tick = time.perf_counter()
        localizer.extractor.extract(image)
        extract.append(time.perf_counter() - tick)
        result = localizer.localize([QueryImage(image, camera)])
        total.append(result.seconds)
        poses[name] = {"success": result.success, "inliers": result.num_inliers,
                       "map_from_cam": result.map_from_cam["query"].matrix().tolist()
                       if result.success else None}
    t, e = latency_stats(total), latency_stats(extract)
    print(f"{len(images)} queries, {sum(p['success'] for p in poses.values())} localized; "
          f"per query median {1000 * t['median_s']:.1f} ms, p90 {1000 * t['p90_s']:.1f} ms; "
          f"feature extraction median {1000 * e['median_s']:.1f} ms")
    if args.reference:
        reference = json.loads(args.reference.read_text())
        worst_m = worst_deg = 0.0
        for name, pose in poses.items():
            other = reference.get(name, {})
            if pose["success"] and other.get("success"):
                d = (Rigid3.from_matrix(np.array(pose["map_from_cam"])).inverse()
                     * Rigid3.from_matrix(np.array(other["map_from_cam"])))
                worst_m = max(worst_m, float(np.linalg.norm(d.translation)))
                worst_deg = max(worst_deg, d.rotation_angle_deg())
        print(f"largest difference from the reference poses: {worst_m:.4f} m, "
              f"{worst_deg:.3f} deg")
    if args.out:
        args.out.write_text(json.dumps(poses, indent=1))


if __name__ == "__main__":
    main()
