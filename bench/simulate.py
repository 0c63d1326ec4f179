"""Benchmark the bag generator: 100 rig samples x 4 cameras at 640x480 (target < 60 s, 2 cores).

Usage: python bench/simulate.py [--frames 100] [--rig rig4] [--scene street] [--workers 0]
Prints wall time per phase, seconds per image and peak memory; asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import resource
import tempfile
import time
from pathlib import Path

from cusfm_ros.sim.generator import SimulationOptions, Simulator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--rig", default="rig4")
    parser.add_argument("--scene", default="street")
    parser.add_argument("--camera-model", default="pinhole")
    parser.add_argument("--workers", type=int, default=0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    options = SimulationOptions(scene=args.scene, rig=args.rig, frames=args.frames,
                                camera_model=args.camera_model, workers=args.workers)
    with tempfile.TemporaryDirectory() as tmp:
        simulator = Simulator(options)
        started = time.perf_counter()
        out = simulator.generate(Path(tmp) / "sim")
        total = time.perf_counter() - started
        images = args.frames * len(simulator.rig_true)
        size_mb = sum(p.stat().st_size for p in (out / "bag").iterdir()) / 1e6
    peak_mb = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                  resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024
    print("| scene | rig | model | samples | images | total s | s/image | s per 100 samples "
          "| bag MB | peak RSS MB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(f"| {args.scene} | {args.rig} | {args.camera_model} | {args.frames} | {images} | "
          f"{total:.1f} | {total / images:.3f} | {100 * total / args.frames:.1f} | "
          f"{size_mb:.0f} | {peak_mb:.0f} |")


if __name__ == "__main__":
    main()
