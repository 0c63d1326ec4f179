"""Fleet mapping on a local Ray instance: SESSIONS simulated drives over one area (seed 0,
each starting elsewhere on the route, in its own light), mapped with ``cusfm fleet`` using
each worker count in turn, and one more drive kept back as the query.

Reports, per worker count, the fleet's wall time and the peak resident memory of its
workers; per drive, the ATE of its trajectory in the merged map against mapping it alone;
and how well the held-back drive localizes (``cusfm localize --bag``) against the merged
map versus each single-drive map.

    python bench/fleet.py --out /tmp/fleet [--sessions 8] [--workers 1 2 0] [--frames 40]
                          [--scene indoor|street] [--image-size 320x240]

(``--workers 0``: all cores.) Writes ``OUT/fleet.md``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

from cusfm_ros.cli.main import main as cusfm
from cusfm_ros.core.evaluation import absolute_trajectory_error
from cusfm_ros.io.tum import read_tum
from cusfm_ros.pipeline.fleet import session_names

FAST = ["--min-translation-m", "0.3", "--max-keypoints", "1024", "--seed", "0"]


def _truth(sim: Path, k: int) -> Path:
    return sim / ("ground_truth.tum" if k == 0 else f"ground_truth_session{k + 1}.tum")


def _bag(sim: Path, k: int) -> Path:
    return sim / ("bag" if k == 0 else f"bag_session{k + 1}")


def _localize(map_dir: Path, bag: Path, out: Path, truth: Path) -> tuple[int, int, float]:
    """(localized, queries, ATE after an SE(3) fit) of a bag's samples against a map."""
    if cusfm(["-q", "localize", str(map_dir), "--bag", str(bag), "--out", str(out)]) != 0:
        return 0, 0, float("nan")
    report = json.loads((out / "report.json").read_text())
    localized = read_tum(out / "localized.tum")
    error = (absolute_trajectory_error(read_tum(truth), localized).rmse
             if len(localized) >= 3 else float("nan"))
    return report["summary"]["localized"], report["summary"]["queries"], error


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", required=True)
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--scene", choices=("indoor", "street"), default="indoor")
    parser.add_argument("--image-size", default="320x240")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    out = Path(args.out)
    sim = out / "sim"
    if not (sim / "scene.json").is_file():
        cusfm(["-q", "simulate", "--scene", args.scene, "--rig", "stereo", "--frames",
               str(args.frames), "--image-size", args.image_size, "--sessions",
               str(args.sessions + 1), str(sim)])
    bags = [str(_bag(sim, k)) for k in range(args.sessions)]
    names = session_names(bags)
    lines = [f"{time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores; `python bench/fleet.py "
             f"{' '.join(argv if argv is not None else sys.argv[1:])}`", "",
             "| workers | wall s | peak RSS per worker MB (max) |", "|---|---|---|"]
    last = None
    for workers in args.workers:
        fleet = out / f"fleet_w{workers}"
        if not (fleet / "report.json").is_file():  # a finished fleet run is reused
            code = cusfm(["-q", "fleet", *bags, "--out", str(fleet), "--workers",
                          str(workers), *FAST])
            if code != 0:
                lines.append(f"| {workers or os.cpu_count()} | failed (exit {code}) | — |")
                continue
        report = json.loads((fleet / "report.json").read_text())
        seconds = report["seconds"]
        peak = max(s["worker_peak_rss_mb"] for s in report["sessions"].values())
        lines.append(f"| {workers or os.cpu_count()} | {seconds:.1f} | {peak:.0f} |")
        last = (fleet, report)
        print("\n".join(lines), flush=True)
    if last is None:
        raise SystemExit("no fleet run finished")
    fleet, report = last
    lines += ["", "| drive | ATE alone m | ATE in the merged map m |", "|---|---|---|"]
    for k, name in enumerate(names):
        if name not in report["trajectories"]:
            lines.append(f"| {name} | — | dropped |")
            continue
        truth = read_tum(_truth(sim, k))
        alone = absolute_trajectory_error(truth, read_tum(fleet / "sessions" / name /
                                                          "poses.tum")).rmse
        merged = absolute_trajectory_error(truth, read_tum(report["trajectories"][name])).rmse
        lines.append(f"| {name} | {alone:.4f} | {merged:.4f} |")
    query = args.sessions
    lines += ["", f"Held-back drive {query + 1} localized against:", "",
              "| map | localized | ATE m |", "|---|---|---|"]
    maps = [("merged", Path(report["map"]))] + [(name, fleet / "sessions" / name)
                                                for name in names if name in report["sessions"]]
    for label, map_dir in maps:
        found, total, error = _localize(map_dir, _bag(sim, query), out / "query" / label,
                                        _truth(sim, query))
        lines.append(f"| {label} | {found} of {total} | {error:.4f} |")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    (out / "fleet.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
