"""LightGlue's passes replayed as CUDA graphs against launched kernel by kernel, over a run's
own pairs, with and without other Python threads holding the GIL (the stages verify pairs on
CPU threads while the main thread launches the next pass).

Usage (on a GPU machine, after a run): ``python bench/gpu_lightglue_graphs.py RUN_DIR
[--pairs 1024] [--busy-threads 0 15] [--switch-interval-ms 5 1] [--graphs on off]``

The pairs of ``RUN_DIR/pairs/pairs.txt`` in order, 16 a pass, launched as the stages do (one
pass in flight while the next is prepared: ``submit_many``). Prints per variant: wall ms
per pass (CUDA-synchronized at the end), the main thread's ms per pass inside
``submit_many`` (reading, padding, launching), graphs captured and replays, and the share
of the matches of the uncaptured passes that the graphed ones give (padded to other sizes:
fp16 rounding may move a few). The first sweep over the pairs (captures, first shapes) is
not timed. Asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np


def _busy(stop: threading.Event, seed: int) -> None:
    """Small numpy work in a loop, as a verification thread does (each call holds the GIL)."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(500, 3))
    while not stop.is_set():
        rays = points / np.linalg.norm(points, axis=1, keepdims=True)
        _ = rays[:, :2] / np.where(rays[:, 2] > 0.1, rays[:, 2], 1.0)[:, None]


def _sweep(matcher, batches) -> tuple[list, float, float]:
    """All passes, one in flight: (matches, wall s, s inside submit_many)."""
    import torch

    torch.cuda.synchronize()
    started, host = time.perf_counter(), 0.0
    found, in_flight = [], None
    for batch in batches:
        before = time.perf_counter()
        launched = matcher.submit_many(batch)
        host += time.perf_counter() - before
        if in_flight is not None:
            found += in_flight()
        in_flight = launched
    found += in_flight()
    torch.cuda.synchronize()
    return found, time.perf_counter() - started, host


def main() -> None:
    import torch

    from cusfm_ros.core.features.lightglue import LightGlueOptions
    from cusfm_ros.io.feature_store import FeatureStore
    from cusfm_ros.models.torch_backend import TorchLightGlueMatcher

    parser = argparse.ArgumentParser()
    parser.add_argument("run", type=Path)
    parser.add_argument("--pairs", type=int, default=1024)
    parser.add_argument("--busy-threads", type=int, nargs="+", default=[0, 15])
    parser.add_argument("--switch-interval-ms", type=float, nargs="+", default=[5.0],
                        help="Python's GIL switch interval while the threads run")
    parser.add_argument("--graphs", nargs="+", choices=("off", "on"), default=["off", "on"])
    args = parser.parse_args()
    assert torch.cuda.is_available(), "needs a CUDA GPU"
    pairs = [line.split() for line in (args.run / "pairs" / "pairs.txt").read_text().splitlines()
             if line.strip()][:args.pairs]
    with FeatureStore(args.run / "features" / "features.h5", {}, read_only=True) as store:
        features = {name: store.features(name) for pair in pairs for name in pair}
    batch_pairs = LightGlueOptions().batch_pairs
    batches = [[(features[a], features[b]) for a, b in pairs[start:start + batch_pairs]]
               for start in range(0, len(pairs), batch_pairs)]
    print(f"device: {torch.cuda.get_device_name()} torch {torch.__version__}; {len(pairs)} "
          f"pairs, {len(batches)} passes of {batch_pairs}")
    print("| graphs | busy threads | switch interval ms | ms per pass | main thread ms per pass "
          "| graphs | replays | matches as uncaptured |\n|---|---|---|---|---|---|---|---|",
          flush=True)
    reference = None
    variants = [(busy, interval, graphs == "on") for busy in args.busy_threads
                for interval in (args.switch_interval_ms if busy else [5.0])
                for graphs in args.graphs]
    for busy_threads, interval_ms, graphs in variants:
        matcher = TorchLightGlueMatcher(LightGlueOptions(device="cuda", cuda_graphs=graphs))
        _sweep(matcher, batches)  # first shapes, captures
        stop = threading.Event()
        threads = [threading.Thread(target=_busy, args=(stop, seed), daemon=True)
                   for seed in range(busy_threads)]
        for thread in threads:
            thread.start()
        previous = sys.getswitchinterval()
        sys.setswitchinterval(interval_ms / 1000)
        try:
            found, wall, host = _sweep(matcher, batches)
        finally:
            sys.setswitchinterval(previous)
            stop.set()
            for thread in threads:
                thread.join()
        if reference is None:
            reference = found
        same = sum(len({tuple(m) for m in a.indices} & {tuple(m) for m in b.indices})
                   for a, b in zip(found, reference))
        total = sum(len(m) for m in reference)
        graphed = matcher.graphed
        print(f"| {'on' if graphs else 'off'} | {busy_threads} | {interval_ms:g} | "
              f"{1000 * wall / len(batches):.2f} | {1000 * host / len(batches):.2f} | "
              f"{len(graphed) if graphed else '-'} | {graphed.replays if graphed else '-'} "
              f"| {same / max(total, 1):.4f} |", flush=True)


if __name__ == "__main__":
    main()
